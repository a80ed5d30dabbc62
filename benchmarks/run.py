"""
Benchmark runner: train (algorithm config x env x seed) jobs and append one JSON line per finished job.

    python -m benchmarks.run [--algos nfq-book reference-nfq dqn-zoo] [--envs CartPole-v1 ...] [--seeds 0-4]
        [--budget N] [--eval-every N] [--stop-at-solve] [--protocol rounds|book] [--workers 2]
        [--results benchmarks/results/runs.jsonl] [--ray-address local|auto|ray://host:10001] [--dry-run]

Criterion, the same for every algorithm: after each NFQ round (each reference round; for DQN at the first rollout
start at or after each multiple of ``eval_every`` env steps), the greedy policy plays ``N_EVAL_EPISODES`` = 100
episodes on separate envs (fixed episode seeds, the same at every evaluation of a job), all in lockstep with one
batched forward pass per step. The job is "solved" at the first evaluation whose mean return reaches the env's
threshold; training goes on to the budget (unless ``--stop-at-solve``), then 100 new greedy episodes give the
final score.

``--protocol book`` uses the criterion of the book's own code instead (:class:`sb3_nfq.BookCriterion`): after every
training episode the greedy policy plays one episode on a separate env (its first reset seeded with
``CURVE_SEED_BASE + 1000 * seed``); the job is solved, and stops, when the mean of the last 100 of those returns
reaches the threshold. Its records go to ``benchmarks/results/book_protocol.jsonl`` by default.

Timing: each job runs in its own process (spawned; or as a Ray task with ``num_cpus=1``) with
``torch.set_num_threads(1)``, and at most as many jobs run at once as there are cores. ``train_seconds`` is the
time spent in ``learn()`` minus the time spent evaluating inside it.

Resumable: a job whose key (algo, env, seed, budget, config hash) is already in the results file is skipped.
"""

import argparse
import concurrent.futures
import contextlib
import datetime
import enum
import hashlib
import importlib.metadata
import json
import multiprocessing
import os
import platform
import shlex
import socket
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import torch as th

from benchmarks import configs
from sb3_nfq.callbacks import StopTrainingOnBookCriterion
from sb3_nfq.configs import vec_normalize_kwargs, zoo_to_kwargs

if TYPE_CHECKING:
    from stable_baselines3.common.vec_env import VecEnv

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_RESULTS = REPO_ROOT / "benchmarks" / "results" / "runs.jsonl"
DEFAULT_BOOK_RESULTS = REPO_ROOT / "benchmarks" / "results" / "book_protocol.jsonl"
#: Evaluation protocols: "rounds" (100 greedy episodes after each round, the benchmark's), "book" (one greedy
#: episode after each training episode, solved at the mean of the last BOOK_WINDOW, the book's code).
PROTOCOLS = ("rounds", "book")
BOOK_WINDOW = 100
#: Bumped when the evaluation protocol changes, so that old results do not count as done.
PROTOCOL_VERSION = 1
#: Episode seeds: the learning-curve evaluations of seed s use CURVE_SEED_BASE + 1000 * s + i for episode i,
#: the final evaluation FINAL_SEED_BASE + 1000 * s + i (episodes never seen during training).
CURVE_SEED_BASE = 1_000_000
FINAL_SEED_BASE = 2_000_000

Actor = Callable[[np.ndarray], np.ndarray]


# --- machine and versions ---------------------------------------------------------------------------------------


def usable_cores() -> int:
    """:return: the number of CPU cores this process may run on"""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def machine_line() -> str:
    """:return: one line describing this machine: CPU model, cores, memory, OS"""
    model = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    memory = ""
    with contextlib.suppress(ValueError, OSError, AttributeError):
        memory = f", {os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB RAM"
    return f"{model}, {usable_cores()} cores ({platform.machine()}){memory}, {platform.system()} {platform.release()}"


def package_versions() -> dict[str, str]:
    """:return: versions of the packages a result depends on"""
    import stable_baselines3

    import sb3_nfq

    versions = {
        "sb3_nfq": sb3_nfq.__version__,
        "stable_baselines3": stable_baselines3.__version__,
        "torch": th.__version__,
        "gymnasium": gym.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }
    with contextlib.suppress(importlib.metadata.PackageNotFoundError):
        versions["rl_zoo3"] = importlib.metadata.version("rl_zoo3")
    return versions


def git_revision() -> str | None:
    """:return: the repository's commit (with ``+dirty`` if sb3_nfq/ or benchmarks/ have local changes), if known"""
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "sb3_nfq", "benchmarks"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return commit + ("+dirty" if dirty else "")


# --- jobs -------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Job:
    """
    One training run: an algorithm config on one env with one seed.

    :param algo: algorithm config name
    :param kind: ``nfq``, ``reference`` or ``dqn``
    :param env_id: gymnasium env id
    :param seed: random seed (model, training env, evaluation episodes)
    :param budget: env-step budget
    :param kwargs: the config's constructor kwargs (plain data)
    :param threshold: solve threshold (mean greedy return)
    :param eval_every: evaluation period in env steps
    :param n_eval_episodes: greedy episodes per evaluation
    :param stop_at_solve: stop training at the first solved evaluation
    :param protocol: ``"rounds"`` or ``"book"`` (see :data:`PROTOCOLS`; the book's protocol always stops at solve)
    :param source: where the config comes from
    :param command: the runner command that created the job
    :param git: the repository revision of the driver
    """

    algo: str
    kind: configs.AlgoKind
    env_id: str
    seed: int
    budget: int
    kwargs: dict[str, Any] = field(hash=False)
    threshold: float
    eval_every: int
    n_eval_episodes: int = configs.N_EVAL_EPISODES
    stop_at_solve: bool = False
    protocol: str = "rounds"
    source: str = ""
    command: str = ""
    git: str | None = None

    @property
    def config_hash(self) -> str:
        """:return: a short hash of everything but the seed and budget that changes what the job measures"""
        payload: dict[str, Any] = {
            "kind": self.kind,
            "kwargs": self.kwargs,
            "threshold": self.threshold,
            "eval_every": self.eval_every,
            "n_eval_episodes": self.n_eval_episodes,
            "stop_at_solve": self.stop_at_solve,
            "protocol": PROTOCOL_VERSION,
        }
        if self.protocol != "rounds":  # the benchmark's own protocol keeps the hashes of the runs it has recorded
            payload["criterion"] = self.protocol
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:12]

    @property
    def key(self) -> tuple[str, str, int, int, str]:
        """:return: the resumability key (algo, env, seed, budget, config hash)"""
        return (self.algo, self.env_id, self.seed, self.budget, self.config_hash)


def make_jobs(
    algos: Sequence[str],
    envs: Sequence[str],
    seeds: Sequence[int],
    budget: int | None = None,
    eval_every: int | None = None,
    n_eval_episodes: int = configs.N_EVAL_EPISODES,
    stop_at_solve: bool = False,
    command: str = "",
    protocol: str = "rounds",
) -> list[Job]:
    """
    :param algos: algorithm config names
    :param envs: env ids
    :param seeds: seeds
    :param budget: env-step budget for every job (default: each config's budget on each env)
    :param eval_every: evaluation period for every job (default: each env's)
    :param n_eval_episodes: greedy episodes per evaluation
    :param stop_at_solve: stop each job at its first solved evaluation
    :param command: the command line, recorded with each result
    :param protocol: ``"rounds"`` or ``"book"`` (then every job stops at its solve)
    :return: the jobs, algorithm-major
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {list(PROTOCOLS)}, got {protocol!r}")
    git = git_revision()
    jobs = []
    for algo in algos:
        for env_id in envs:
            config = configs.resolve(algo, env_id)
            for seed in seeds:
                jobs.append(
                    Job(
                        algo=algo,
                        kind=config.kind,
                        env_id=env_id,
                        seed=seed,
                        budget=budget if budget is not None else config.budget,
                        kwargs=config.kwargs,
                        threshold=config.threshold,
                        eval_every=eval_every if eval_every is not None else config.eval_every,
                        n_eval_episodes=n_eval_episodes,
                        stop_at_solve=stop_at_solve or protocol == "book",
                        protocol=protocol,
                        source=config.source,
                        command=command,
                        git=git,
                    )
                )
    return jobs


def result_key(record: dict[str, Any]) -> tuple[str, str, int, int, str]:
    """:return: the resumability key of a result line"""
    return (record["algo"], record["env"], int(record["seed"]), int(record["budget"]), record["config_hash"])


def read_results(path: Path) -> list[dict[str, Any]]:
    """
    :param path: a results file (JSON lines); missing means empty
    :return: its records (a line that is not valid JSON, e.g. cut by a crash, is skipped with a warning)
    """
    if not path.exists():
        return []
    records = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            print(f"warning: {path}:{number} is not valid JSON, ignored", file=sys.stderr)
    return records


def append_result(path: Path, record: dict[str, Any]) -> None:
    """Append one JSON line (only the driver process writes, so lines never interleave)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as file:
        file.write(json.dumps(record) + "\n")
        file.flush()
        os.fsync(file.fileno())


# --- evaluation -------------------------------------------------------------------------------------------------


class GreedyEvaluator:
    """
    Plays ``n_episodes`` episodes at once, one per env, with a batched greedy policy: each step, one call of
    ``act`` on the observations of the episodes still running. Episode ``i`` always starts from
    ``reset(seed=seed_base + i)``, so every evaluation of a job uses the same start states.

    :param env_id: gymnasium env id
    :param n_episodes: episodes per evaluation
    :param seed_base: seed of the first episode
    """

    def __init__(self, env_id: str, n_episodes: int, seed_base: int) -> None:
        self.envs = [gym.make(env_id) for _ in range(n_episodes)]
        self.seeds = [seed_base + i for i in range(n_episodes)]

    def evaluate(self, act: Actor) -> np.ndarray:
        """
        :param act: greedy policy on a batch of observations ``(k, obs_dim) -> (k,)``
        :return: the return of each episode
        """
        observations = np.stack([env.reset(seed=seed)[0] for env, seed in zip(self.envs, self.seeds, strict=True)])
        returns = np.zeros(len(self.envs))
        running = np.arange(len(self.envs))
        while running.size:
            actions = np.asarray(act(observations[running])).reshape(-1)
            still_running = []
            for index, action in zip(running, actions, strict=True):
                obs, reward, terminated, truncated, _ = self.envs[index].step(int(action))
                returns[index] += float(reward)
                observations[index] = obs
                if not (terminated or truncated):
                    still_running.append(index)
            running = np.asarray(still_running, dtype=int)
        return returns


class SolveTracker:
    """
    Runs the periodic greedy evaluations of one job and keeps its learning curve and the time spent evaluating; fed
    the training steps' episode ends (:meth:`count_episode_ends`), it also keeps, per evaluation, how many training
    episodes ended since the previous one and how many of those by termination (on MountainCar: at the goal).

    :param evaluator: plays the evaluation episodes
    :param threshold: solved when the mean return reaches this
    :param eval_every: evaluate at the first call at or after each multiple of this many env steps
    :param stop_at_solve: ask training to stop at the first solved evaluation
    """

    def __init__(self, evaluator: GreedyEvaluator, threshold: float, eval_every: int, stop_at_solve: bool) -> None:
        self.evaluator = evaluator
        self.threshold = threshold
        self.eval_every = eval_every
        self.stop_at_solve = stop_at_solve
        self.curve: list[list[float]] = []
        self.steps_to_solve: int | None = None
        self.eval_seconds = 0.0
        self.stopped = False
        self._next_eval = 0
        self.episode_ends: list[list[int]] = []
        self.counts_episode_ends = False
        self._ended = self._terminated = 0

    def count_episode_ends(self, dones: np.ndarray, infos: Sequence[dict[str, Any]]) -> None:
        """
        :param dones: one training ``VecEnv.step()``'s done flags
        :param infos: its infos (a time-limit truncation sets ``TimeLimit.truncated``)
        """
        self.counts_episode_ends = True
        for done, info in zip(dones, infos, strict=True):
            if done:
                self._ended += 1
                self._terminated += int(not info.get("TimeLimit.truncated", False))

    def evaluate(self, steps: int, act: Actor) -> float:
        """
        :param steps: env steps trained so far
        :param act: greedy policy
        :return: the mean greedy return, also added to the curve
        """
        start = time.perf_counter()
        mean = float(np.mean(self.evaluator.evaluate(act)))
        self.eval_seconds += time.perf_counter() - start
        self.curve.append([steps, mean])
        self.episode_ends.append([steps, self._ended, self._terminated])
        self._ended = self._terminated = 0
        self._next_eval = (steps // self.eval_every + 1) * self.eval_every
        if mean >= self.threshold and self.steps_to_solve is None:
            self.steps_to_solve = steps
        return mean

    def maybe_evaluate(self, steps: int, act: Actor) -> bool:
        """
        :param steps: env steps trained so far
        :param act: greedy policy
        :return: whether training should go on
        """
        if steps >= self._next_eval:
            self.evaluate(steps, act)
        self.stopped = self.stop_at_solve and self.steps_to_solve is not None
        return not self.stopped

    def finish(self, steps: int, act: Actor) -> None:
        """Evaluate the final policy unless it was just evaluated or training stopped at the solve."""
        if not self.stopped and (not self.curve or self.curve[-1][0] != steps):
            self.evaluate(steps, act)


def _round_end_callback(tracker: SolveTracker, act: Actor) -> Any:
    """
    :param tracker: the job's evaluations
    :param act: the model's greedy policy
    :return: an SB3 callback that evaluates at rollout starts (for NFQ: right after the previous round's fit) and
        at the end of training
    """
    from stable_baselines3.common.callbacks import BaseCallback

    class RoundEndEvaluation(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.keep_training = True

        def _on_rollout_start(self) -> None:
            self.keep_training = tracker.maybe_evaluate(self.model.num_timesteps, act)

        def _on_step(self) -> bool:
            tracker.count_episode_ends(self.locals["dones"], self.locals["infos"])
            return self.keep_training

        def _on_training_end(self) -> None:
            tracker.finish(self.model.num_timesteps, act)

    return RoundEndEvaluation()


# --- training ---------------------------------------------------------------------------------------------------


@dataclass
class Trained:
    """
    What a trainer hands back: env steps trained, greedy policy, seconds in learn(), effective settings, and the
    divergence error if training stopped on a non-finite loss (then ``steps`` is where it stopped).
    """

    steps: int
    act: Actor
    learn_seconds: float
    effective: dict[str, Any]
    diverged: str | None = None


def _jsonable(value: Any) -> Any:
    if isinstance(value, type):
        return f"{value.__module__}.{value.__qualname__}"
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, list | tuple):
        return [_jsonable(item) for item in value]
    if isinstance(value, dict):
        return {str(key): _jsonable(item) for key, item in value.items()}
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return repr(value)


def make_training_env(env_id: str, n_envs: int, seed: int) -> "VecEnv":
    """
    The training envs of NFQ and DQN: SB3's ``make_vec_env``, but with no render mode, like the reference's
    ``gym.make(env_id)`` and the evaluation envs. Given an env id, SB3 asks for ``render_mode="rgb_array"``;
    LunarLander then simulates exhaust particles as Box2D bodies at every engine firing (for drawing only: they
    collide with the ground, never the lander). That slows SB3 algorithms' LunarLander steps against the
    reference's without changing a single observation.

    :param env_id: gymnasium env id
    :param n_envs: number of envs
    :param seed: seed of the first env (SB3's convention: env ``i`` gets ``seed + i``)
    :return: a ``DummyVecEnv`` of ``Monitor``-wrapped envs
    """
    from stable_baselines3.common.env_util import make_vec_env

    return make_vec_env(env_id, n_envs=n_envs, seed=seed, env_kwargs={"render_mode": None})


def book_curve(callback: StopTrainingOnBookCriterion, every: int) -> list[list[float]]:
    """
    :param callback: the book protocol's evaluations of one job
    :param every: keep the first evaluation at or after each multiple of this many env steps, and the last
    :return: ``[steps, mean of the last BOOK_WINDOW evaluation returns]`` at those evaluations
    """
    criterion, curve = callback.criterion, []
    next_point = 0
    for index, steps in enumerate(criterion.evaluation_steps):
        if steps >= next_point or index == len(criterion.evaluation_steps) - 1:
            window = criterion.evaluation_returns[max(0, index + 1 - criterion.window) : index + 1]
            curve.append([steps, float(np.mean(window))])
            next_point = (steps // every + 1) * every
    return curve


def build_sb3_model(job: Job) -> Any:
    """
    :param job: an NFQ or DQN job
    :return: its model (SB3's ``NFQ`` or ``DQN``) on its training envs (:func:`make_training_env`), wrapped in
        ``VecNormalize`` where the config's ``normalize`` key asks for it, as the RL Zoo does
    """
    from stable_baselines3 import DQN
    from stable_baselines3.common.vec_env import VecNormalize

    from sb3_nfq import NFQ

    kwargs = dict(job.kwargs)
    n_envs = int(kwargs.pop("n_envs", 1))
    policy = kwargs.pop("policy", "MlpPolicy")
    normalize = vec_normalize_kwargs(kwargs.pop("normalize", False), kwargs.get("gamma"))
    algorithm_class: Any = NFQ if job.kind == "nfq" else DQN
    env = make_training_env(job.env_id, n_envs=n_envs, seed=job.seed)
    if normalize is not None:
        env = VecNormalize(env, **normalize)
    return algorithm_class(policy, env, seed=job.seed, device="cpu", verbose=0, **zoo_to_kwargs(kwargs))


def _train_sb3(job: Job, tracker: SolveTracker | StopTrainingOnBookCriterion) -> Trained:
    from sb3_nfq import NFQDivergenceError

    model = build_sb3_model(job)
    vec_normalize = model.get_vec_normalize_env()

    def act(observations: np.ndarray) -> np.ndarray:
        # Evaluation episodes see the training env's running statistics as they are now, without updating them
        # (the RL Zoo's evaluation env: VecNormalize with training=False, synced before each evaluation).
        if vec_normalize is not None:
            observations = vec_normalize.normalize_obs(observations)
        return model.predict(observations, deterministic=True)[0]

    start = time.perf_counter()
    diverged = None
    try:
        callback = tracker if isinstance(tracker, StopTrainingOnBookCriterion) else _round_end_callback(tracker, act)
        model.learn(job.budget, callback=callback)
    except NFQDivergenceError as error:  # a result like any other: recorded, not retried
        diverged = str(error)
    learn_seconds = time.perf_counter() - start

    names = [
        "learning_rate",
        "gamma",
        "batch_size",
        "buffer_size",
        "learning_starts",
        "train_freq",
        "gradient_steps",
        "target_update_interval",
        "exploration_initial_eps",
        "exploration_final_eps",
        "exploration_fraction",
        "loss",
        "max_grad_norm",
        "n_envs",
    ]
    effective = {name: _jsonable(getattr(model, name)) for name in names if hasattr(model, name)}
    effective["policy"] = type(model.policy).__name__
    effective["net_arch"] = _jsonable(getattr(model.policy, "net_arch", None))
    effective["optimizer"] = type(model.policy.optimizer).__name__
    effective["q_net"] = str(model.q_net.q_net).replace("\n", "")
    if vec_normalize is not None:
        effective["vec_normalize"] = {"norm_obs": vec_normalize.norm_obs, "norm_reward": vec_normalize.norm_reward}
    return Trained(model.num_timesteps, act, learn_seconds, effective, diverged)


def _train_reference(job: Job, tracker: SolveTracker | StopTrainingOnBookCriterion) -> Trained:
    from benchmarks.reference_nfq import ReferenceNFQ

    agent = ReferenceNFQ(job.env_id, seed=job.seed, **job.kwargs)
    start = time.perf_counter()
    if isinstance(tracker, StopTrainingOnBookCriterion):
        criterion = tracker.criterion

        def after_episode(trained: ReferenceNFQ) -> bool:
            holds = criterion.on_training_episode_end(trained.num_timesteps, lambda obs: int(trained.act(obs[None])[0]))
            return not holds

        agent.learn(job.budget, episode_callback=after_episode)
    else:  # includes the evaluation at step 0, as SB3's learn() does
        tracker.maybe_evaluate(0, agent.act)
        agent.learn(job.budget, callback=lambda trained: tracker.maybe_evaluate(trained.num_timesteps, trained.act))
        tracker.finish(agent.num_timesteps, agent.act)
    learn_seconds = time.perf_counter() - start
    effective = {
        "gamma": agent.gamma,
        "epsilon": agent.epsilon,
        "transitions_per_round": agent.transitions_per_round,
        "fitting_iterations": agent.fitting_iterations,
        "learning_rate": agent.optimizer.param_groups[0]["lr"],
        "optimizer": type(agent.optimizer).__name__,
        "q_net": str(agent.q_net).replace("\n", ""),
    }
    return Trained(agent.num_timesteps, agent.act, learn_seconds, effective)


def run_job(job: Job) -> dict[str, Any]:
    """
    Train one job and evaluate it. Pins ``torch.set_num_threads(1)``. Top-level, so worker processes and Ray
    tasks can run it.

    :param job: the job
    :return: its result record (one JSON line)
    """
    wall_start = time.perf_counter()
    th.set_num_threads(1)
    curve_seed, final_seed = CURVE_SEED_BASE + 1000 * job.seed, FINAL_SEED_BASE + 1000 * job.seed
    tracker: SolveTracker | StopTrainingOnBookCriterion
    if job.protocol == "book":
        tracker = StopTrainingOnBookCriterion(
            gym.make(job.env_id), threshold=job.threshold, window=BOOK_WINDOW, seed=curve_seed
        )
    else:
        tracker = SolveTracker(
            GreedyEvaluator(job.env_id, job.n_eval_episodes, curve_seed),
            job.threshold,
            job.eval_every,
            job.stop_at_solve,
        )
    trained = (_train_reference if job.kind == "reference" else _train_sb3)(job, tracker)
    final_returns = GreedyEvaluator(job.env_id, job.n_eval_episodes, final_seed).evaluate(trained.act)
    if isinstance(tracker, StopTrainingOnBookCriterion):
        criterion = tracker.criterion
        outcome: dict[str, Any] = {
            "protocol": "book",
            "book_window": criterion.window,
            "solved": criterion.solved,
            "steps_to_solve": criterion.steps_to_solve,
            "episodes_to_solve": criterion.episodes_to_solve,
            "episodes_trained": len(criterion.evaluation_returns),
            "stopped_at_solve": criterion.solved,
            "eval_seconds": criterion.eval_seconds,
            "curve": book_curve(tracker, job.eval_every),
        }
    else:
        outcome = {
            "solved": tracker.steps_to_solve is not None,
            "steps_to_solve": tracker.steps_to_solve,
            "stopped_at_solve": tracker.stopped,
            "eval_seconds": tracker.eval_seconds,
            "curve": tracker.curve,
            # [steps, training episodes ended since the previous evaluation, how many of them by termination]
            "train_episode_ends": tracker.episode_ends if tracker.counts_episode_ends else None,
        }
    return {
        "algo": job.algo,
        "env": job.env_id,
        "seed": job.seed,
        "budget": job.budget,
        "config_hash": job.config_hash,
        "kind": job.kind,
        "config": job.kwargs,
        "config_source": job.source,
        "effective_hyperparams": trained.effective,
        "threshold": job.threshold,
        "n_eval_episodes": job.n_eval_episodes,
        "eval_every": job.eval_every,
        "eval_seeds": {"curve": curve_seed, "final": final_seed},
        "stop_at_solve": job.stop_at_solve,
        **{key: value for key, value in outcome.items() if key not in ("eval_seconds", "curve")},
        "steps_trained": trained.steps,
        "diverged": trained.diverged,
        "final_score": float(np.mean(final_returns)),
        "final_score_std": float(np.std(final_returns)),
        "final_n_episodes": len(final_returns),
        "train_seconds": round(trained.learn_seconds - outcome["eval_seconds"], 3),
        "eval_seconds": round(outcome["eval_seconds"], 3),
        "wall_seconds": round(time.perf_counter() - wall_start, 3),
        "curve": [[int(steps), round(mean, 3)] for steps, mean in outcome["curve"]],
        "torch_threads": th.get_num_threads(),
        "versions": package_versions(),
        "machine": machine_line(),
        "hostname": socket.gethostname(),
        "pid": os.getpid(),
        "git": job.git,
        "command": job.command,
        "finished_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


# --- execution --------------------------------------------------------------------------------------------------


def _describe(record: dict[str, Any]) -> str:
    solved = f"solved at {record['steps_to_solve']}" if record["solved"] else "not solved"
    if record.get("episodes_to_solve") is not None:
        solved += f" ({record['episodes_to_solve']} episodes)"
    if record.get("diverged"):
        solved += ", then the loss diverged" if record["solved"] else ", the loss diverged"
    return (
        f"{record['algo']} {record['env']} seed {record['seed']}: {solved}, final {record['final_score']:.1f} "
        f"at {record['steps_trained']} steps, train {record['train_seconds']:.1f}s, wall {record['wall_seconds']:.1f}s"
    )


def exit_with_parent(parent: int, poll_seconds: float = 1.0) -> None:
    """
    Pool-worker initializer: end this worker once the runner that spawned it is gone. A runner stopped by a signal
    (``kill``, ``pkill``: no ``finally`` runs) leaves its spawned workers training on, to compete for the cores with
    the next command's jobs and slow them; a worker whose parent is no longer the runner has been orphaned, so it
    exits.

    :param parent: the runner's pid, passed in rather than read here, since the runner may be gone before a
        starting worker has finished its imports
    :param poll_seconds: how often the parent is checked
    """

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_seconds)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def job_pool(workers: int) -> concurrent.futures.ProcessPoolExecutor:
    """
    :param workers: worker processes
    :return: the local pool jobs run in: one fresh spawned process per job, so that no state (threads, RNG, imports)
        leaks from one job to the next, each ending with its runner (:func:`exit_with_parent`)
    """
    pool_kwargs: dict[str, Any] = {"max_tasks_per_child": 1} if sys.version_info >= (3, 11) else {}
    return concurrent.futures.ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=exit_with_parent,
        initargs=(os.getpid(),),
        **pool_kwargs,
    )


def _run_local(jobs: Sequence[Job], workers: int, on_result: Callable[[Job, dict[str, Any]], None]) -> int:
    failures = 0
    if workers == 0:  # in this process, one after the other (debugging, tests)
        for job in jobs:
            try:
                on_result(job, run_job(job))
            except Exception:
                failures += 1
                print(f"FAILED {job.algo} {job.env_id} seed {job.seed}:\n{traceback.format_exc()}", file=sys.stderr)
        return failures
    with job_pool(workers) as pool:
        futures = {pool.submit(run_job, job): job for job in jobs}
        for future in concurrent.futures.as_completed(futures):
            job = futures[future]
            try:
                on_result(job, future.result())
            except Exception as error:
                failures += 1
                print(f"FAILED {job.algo} {job.env_id} seed {job.seed}: {error!r}", file=sys.stderr)
    return failures


def _run_ray(jobs: Sequence[Job], address: str, workers: int, on_result: Callable[[Job, dict[str, Any]], None]) -> int:
    try:
        import ray
    except ImportError as error:
        raise SystemExit(
            "--ray-address needs Ray, which is not installed: make setup (the dev group of pyproject.toml) or "
            "pip install 'ray>=2.9'"
        ) from error
    started_here = not ray.is_initialized()
    if started_here:
        # Ship this checkout's code to the workers (the cluster's nodes need torch, SB3, gymnasium, ... installed).
        runtime_env = {"py_modules": [str(REPO_ROOT / "benchmarks"), str(REPO_ROOT / "sb3_nfq")]}
        if address == "local":  # a Ray instance on this machine, as many CPUs as local workers
            ray.init(num_cpus=max(workers, 1), include_dashboard=False, runtime_env=runtime_env)
        else:  # "auto" (a running cluster this machine belongs to) or "ray://head:10001"
            ray.init(address=address, runtime_env=runtime_env)
    failures = 0
    try:
        remote_run_job = ray.remote(num_cpus=1, max_retries=0)(run_job)
        pending = {remote_run_job.remote(job): job for job in jobs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            job = pending.pop(done[0])
            try:
                on_result(job, ray.get(done[0]))
            except Exception as error:
                failures += 1
                print(f"FAILED {job.algo} {job.env_id} seed {job.seed}: {error!r}", file=sys.stderr)
    finally:
        if started_here:
            ray.shutdown()
    return failures


def done_keys(results: Path, jobs: Sequence[Job], rerun: bool = False) -> set[tuple[str, str, int, int, str]]:
    """
    :param results: the results file
    :param jobs: the jobs about to run
    :param rerun: count only the records of the jobs' own command line (see :func:`run_jobs`)
    :return: the keys of the jobs the file already holds
    """
    commands = {job.command for job in jobs}
    return {result_key(record) for record in read_results(results) if not rerun or record["command"] in commands}


def launcher(workers: int, ray_address: str | None = None) -> str:
    """
    :param workers: local worker processes (0: the runner's own process)
    :param ray_address: the Ray cluster the jobs ran on, if any
    :return: how the jobs ran, as recorded in each result line's ``launcher`` (read back by :func:`jobs_at_once`)
    """
    if ray_address:
        return f"ray ({ray_address})"
    return f"local pool ({workers} spawned workers)" if workers else "in-process"


def jobs_at_once(record: dict[str, Any]) -> int | None:
    """
    :param record: a result line
    :return: how many jobs ran at once, this one included: its local pool's worker count, 1 in the runner's own
        process (or for a line without a launcher on record), ``None`` on a Ray cluster (unknown)
    """
    name = str(record.get("launcher", launcher(0)))
    if name.startswith("ray ("):
        return None
    return int(name.removeprefix("local pool (").split()[0]) if name.startswith("local pool (") else 1


def run_jobs(
    jobs: Sequence[Job], results: Path, workers: int, ray_address: str | None = None, rerun: bool = False
) -> tuple[int, int, int]:
    """
    Run the jobs not yet in ``results``, appending one line per finished job.

    :param jobs: the jobs
    :param results: the results file (JSON lines)
    :param workers: local worker processes (0: run in this process); clamped to the number of cores
    :param ray_address: run as Ray tasks on this cluster (``local``, ``auto`` or an address) instead
    :param rerun: run the jobs again even where the file has them, skipping only those this same command line
        (the jobs' ``command``) has already recorded: for runs side by side with new ones
    :return: (jobs run, jobs skipped as already done, jobs failed)
    """
    done = done_keys(results, jobs, rerun)
    todo = [job for job in jobs if job.key not in done]
    skipped = len(jobs) - len(todo)
    cores = usable_cores()
    if workers > cores:
        print(f"warning: {workers} workers on {cores} cores would distort timings; using {cores}", file=sys.stderr)
        workers = cores
    print(f"{len(jobs)} jobs: {skipped} already in {results}, {len(todo)} to run")
    finished = 0

    def on_result(job: Job, record: dict[str, Any]) -> None:
        nonlocal finished
        record["launcher"] = launcher(workers, ray_address)
        append_result(results, record)
        finished += 1
        print(f"[{finished}/{len(todo)}] {_describe(record)}", flush=True)

    if not todo:
        return 0, skipped, 0
    if ray_address:
        failures = _run_ray(todo, ray_address, workers, on_result)
        return finished, skipped, failures
    failures = _run_local(todo, workers, on_result)
    return finished, skipped, failures


def parse_seeds(values: Iterable[str]) -> list[int]:
    """
    :param values: seeds and ranges, e.g. ``["0-4"]`` or ``["0", "3", "7-9"]``
    :return: the seeds, in order, without duplicates
    """
    seeds: list[int] = []
    for value in values:
        for part in value.split(","):
            if "-" in part.strip("-"):
                low, high = part.split("-")
                seeds.extend(range(int(low), int(high) + 1))
            elif part:
                seeds.append(int(part))
    return list(dict.fromkeys(seeds))


def _workers(value: str) -> int:
    workers = int(value)
    if workers < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {workers}")
    return workers


def add_job_arguments(parser: argparse.ArgumentParser, default_seeds: str) -> None:
    """
    Add the arguments every script that runs jobs takes: ``--seeds``, ``--budget``, ``--eval-episodes``,
    ``--workers``.

    :param parser: the script's parser
    :param default_seeds: the seeds it runs by default, e.g. ``"0-4"``
    """
    parser.add_argument(
        "--seeds",
        nargs="+",
        default=[default_seeds],
        help=f"seeds or ranges, e.g. 0-4 or 0 1 2 (default {default_seeds})",
    )
    parser.add_argument("--budget", type=int, help="env-step budget of every job (default: per config and env)")
    parser.add_argument(
        "--eval-episodes",
        type=int,
        default=configs.N_EVAL_EPISODES,
        help="greedy episodes per evaluation (default 100, the criterion; fewer only for smoke tests)",
    )
    parser.add_argument(
        "--workers",
        type=_workers,
        default=min(2, usable_cores()),
        help="local worker processes, one job each (default: min(2, cores); 0: run in this process)",
    )


def main(argv: Sequence[str] | None = None) -> int:
    """
    Command-line entry point.

    :param argv: arguments (default: ``sys.argv[1:]``)
    :return: exit status (1 if a job failed)
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algos", nargs="+", default=configs.algorithm_names(), choices=configs.algorithm_names())
    parser.add_argument("--envs", nargs="+", default=list(configs.ENVS), choices=list(configs.ENVS))
    add_job_arguments(parser, default_seeds="0-4")
    parser.add_argument("--eval-every", type=int, help="evaluation period in env steps (default: per env, 1024)")
    parser.add_argument("--stop-at-solve", action="store_true", help="stop each job when solved (quick runs)")
    parser.add_argument(
        "--protocol",
        choices=PROTOCOLS,
        default="rounds",
        help="rounds: 100 greedy episodes after each round (default); book: one greedy episode after each training "
        "episode, solved (and stopped) at the mean of the last 100 (the book's code)",
    )
    parser.add_argument(
        "--results",
        type=Path,
        help="JSON-lines results file (default: runs.jsonl; book_protocol.jsonl with --protocol book)",
    )
    parser.add_argument("--ray-address", help="run the jobs as Ray tasks: 'local', 'auto' or a cluster address")
    parser.add_argument(
        "--rerun",
        action="store_true",
        help="run jobs again even if the results file has them (only this exact command's own are skipped): to "
        "measure a baseline side by side with new runs",
    )
    parser.add_argument("--dry-run", action="store_true", help="list the jobs to run and exit")
    args = parser.parse_args(argv)
    if args.results is None:
        args.results = DEFAULT_BOOK_RESULTS if args.protocol == "book" else DEFAULT_RESULTS

    command = shlex.join(["python", "-m", "benchmarks.run", *argv])
    jobs = make_jobs(
        args.algos,
        args.envs,
        parse_seeds(args.seeds),
        budget=args.budget,
        eval_every=args.eval_every,
        n_eval_episodes=args.eval_episodes,
        stop_at_solve=args.stop_at_solve,
        command=command,
        protocol=args.protocol,
    )
    if args.dry_run:
        done = done_keys(args.results, jobs, args.rerun)
        for job in jobs:
            state = "done" if job.key in done else "todo"
            print(f"{state} {job.algo} {job.env_id} seed={job.seed} budget={job.budget} config={job.config_hash}")
        return 0
    print(f"machine: {machine_line()}; torch threads per job: 1")
    _, _, failures = run_jobs(jobs, args.results, args.workers, args.ray_address, args.rerun)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
