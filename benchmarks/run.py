"""
Benchmark runner: train (algorithm config x env x seed) jobs and append one JSON line per finished job.

    python -m benchmarks.run --algos nfq-book reference-nfq dqn-zoo [--envs CartPole-v1 ...] [--seeds 0-4]
        [--budget N] [--eval-every N] [--stop-at-solve] [--protocol rounds|book] [--workers 2]
        [--results benchmarks/results/runs.jsonl] [--ray-address local|auto|ray://host:10001]

The criterion, the timing and the record fields: benchmarks/README.md ("What is measured").
"""

import argparse
import concurrent.futures
import contextlib
import datetime
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
import time
import traceback
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv

from benchmarks import configs
from sb3_nfq.callbacks import StopTrainingOnBookCriterion
from sb3_nfq.configs import zoo_to_kwargs

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_RESULTS = REPO_ROOT / "benchmarks" / "results" / "runs.jsonl"
DEFAULT_BOOK_RESULTS = REPO_ROOT / "benchmarks" / "results" / "book_protocol.jsonl"
DEFAULT_HELD_OUT = REPO_ROOT / "benchmarks" / "results" / "held_out.jsonl"
PROTOCOLS = ("rounds", "book")
BOOK_WINDOW = 100
#: Bumped when the evaluation protocol changes, so that old results do not count as done.
PROTOCOL_VERSION = 1
CURVE_SEED_BASE = 1_000_000
FINAL_SEED_BASE = 2_000_000
Key = tuple[str, str, int, int, str]


def usable_cores() -> int:
    """:return: the number of CPU cores this process may run on"""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def machine_line() -> str:
    """:return: one line describing this machine: CPU model, cores, memory, OS"""
    model = platform.processor() or platform.machine()
    with contextlib.suppress(OSError, StopIteration):
        cpuinfo = Path("/proc/cpuinfo").read_text().splitlines()
        model = next(line for line in cpuinfo if line.startswith("model name")).split(":", 1)[1].strip()
    memory = ""
    with contextlib.suppress(ValueError, OSError, AttributeError):
        memory = f", {os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB RAM"
    return f"{model}, {usable_cores()} cores ({platform.machine()}){memory}, {platform.system()} {platform.release()}"


def hardware(machine: str) -> str:
    """
    :param machine: a :func:`machine_line`
    :return: its hardware (CPU model, cores, memory), without the OS release, which alike machines change between boots
    """
    return machine.rsplit(", ", 1)[0]


def package_versions() -> dict[str, str]:
    """:return: versions of the packages a result depends on"""
    versions = {"python": platform.python_version()}
    for name in ("sb3_nfq", "stable_baselines3", "sb3_contrib", "torch", "gymnasium", "numpy", "rl_zoo3"):
        with contextlib.suppress(importlib.metadata.PackageNotFoundError):
            versions[name] = importlib.metadata.version(name.replace("_", "-"))
    return versions


def git_revision() -> str | None:
    """
    :return: the repository's commit (with ``+dirty`` if the code or configs of sb3_nfq/ or benchmarks/ have local
        changes; the results files, which runs append to, do not count), if known
    """
    git = ["git", "-C", str(REPO_ROOT)]
    try:
        commit = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True)
        status = [*git, "status", "--porcelain", "--", "sb3_nfq", "benchmarks", ":!benchmarks/results"]
        dirty = subprocess.run(status, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return commit.stdout.strip() + ("+dirty" if dirty else "")


def relative_command(module: str, argv: Sequence[str]) -> str:
    """:return: the command line, with the paths inside the repository written relative to its root"""
    paths = [Path(argument).resolve() for argument in argv]
    inside = [Path(a).is_absolute() and p.is_relative_to(REPO_ROOT) for a, p in zip(argv, paths, strict=True)]
    shown = [str(p.relative_to(REPO_ROOT)) if i else a for a, p, i in zip(argv, paths, inside, strict=True)]
    return shlex.join(["python", "-m", module, *shown])


def script_result(
    command: Sequence[str], check: bool = True, cwd: Path | None = None
) -> tuple[dict[str, Any], list[str]]:
    """
    :param command: a script that ends by printing ``RESULT <json>``
    :param check: also require exit status 0
    :param cwd: where it runs (default: here)
    :return: the JSON of its last ``RESULT`` line, and every line it printed
    """
    done = subprocess.run(command, capture_output=True, text=True, check=False, cwd=cwd)
    printed = done.stdout.splitlines()
    lines = [line for line in printed if line.startswith("RESULT ")]
    if not lines or (check and done.returncode != 0):
        raise RuntimeError(
            f"{shlex.join(command)} failed (exit status {done.returncode}):\n{done.stdout}\n{done.stderr}"
        )
    return dict(json.loads(lines[-1].removeprefix("RESULT "))), printed


@dataclass(frozen=True)
class Job:
    """
    One training run: an algorithm config on one env with one seed.

    :param config: the algorithm config on the env
    :param seed: random seed (model, training env, evaluation episodes)
    :param budget: env-step budget
    :param eval_every: evaluation period in env steps
    :param n_eval_episodes: greedy episodes per evaluation
    :param stop_at_solve: stop training at the first solved evaluation
    :param protocol: ``"rounds"`` or ``"book"`` (the book's protocol always stops at solve)
    :param command: the runner command that created the job
    :param git: the repository revision of the driver
    """

    config: configs.ResolvedConfig
    seed: int
    budget: int
    eval_every: int
    n_eval_episodes: int = configs.N_EVAL_EPISODES
    stop_at_solve: bool = False
    protocol: str = "rounds"
    command: str = ""
    git: str | None = None

    def __post_init__(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {list(PROTOCOLS)}, got {self.protocol!r}")
        if self.protocol == "book":  # the book's criterion stops at the solve
            object.__setattr__(self, "stop_at_solve", True)

    @property
    def threshold(self) -> float:
        """:return: the env's solve threshold (mean greedy return)"""
        return configs.ENVS[self.config.env_id].threshold

    @property
    def config_hash(self) -> str:
        """:return: a short hash of everything but the seed and budget that changes what the job measures"""
        payload: dict[str, Any] = {
            "kind": self.config.kind,
            "kwargs": self.config.kwargs,
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
    def key(self) -> Key:
        """:return: the resumability key (algo, env, seed, budget, config hash)"""
        return (self.config.algo, self.config.env_id, self.seed, self.budget, self.config_hash)

    def __str__(self) -> str:
        return f"{self.config.algo} {self.config.env_id} seed {self.seed}"


def make_jobs(
    algos: Sequence[str],
    envs: Sequence[str],
    seeds: Sequence[int],
    budget: int | None = None,
    eval_every: int | None = None,
    **fields: Any,
) -> list[Job]:
    """
    :param algos: algorithm config names
    :param envs: env ids
    :param seeds: seeds
    :param budget: env-step budget for every job (default: each config's budget on each env)
    :param eval_every: evaluation period for every job (default: each env's)
    :param fields: the jobs' other :class:`Job` fields (default ``git``: this checkout's revision)
    :return: the jobs, seed-major: each seed's algorithms one after the other, so that every algorithm shares the
        cores with a like mix of jobs (algorithm-major, each would run mostly beside itself)
    """
    resolved = [configs.resolve(algo, env_id) for env_id in envs for algo in algos]
    fields = {"git": git_revision(), **fields}
    return [
        Job(
            config,
            seed,
            config.budget if budget is None else budget,
            configs.ENVS[config.env_id].eval_every if eval_every is None else eval_every,
            **fields,
        )
        for seed in seeds
        for config in resolved
    ]


def read_results(path: Path) -> list[dict[str, Any]]:
    """:return: the records of a results file (JSON lines; missing means empty; a line cut by a crash is skipped)"""
    records = []
    for number, line in enumerate(path.read_text().splitlines() if path.exists() else [], start=1):
        try:
            records += [json.loads(line)] if line.strip() else []
        except json.JSONDecodeError:
            print(f"warning: {path}:{number} is not valid JSON, ignored", file=sys.stderr)
    return records


def result_key(record: dict[str, Any]) -> Key:
    """:return: the resumability key of a result line"""
    return (record["algo"], record["env"], int(record["seed"]), int(record["budget"]), record["config_hash"])


# --- evaluation -------------------------------------------------------------------------------------------------


def make_env(env_id: str, n_envs: int, seed: int | None = None) -> VecEnv:
    """
    SB3's ``make_vec_env`` with no render mode (SB3 asks for ``rgb_array``, which makes LunarLander draw particles).

    :param env_id: gymnasium env id
    :param n_envs: number of envs
    :param seed: seed of the first env (env ``i`` gets ``seed + i``)
    """
    return make_vec_env(env_id, n_envs=n_envs, seed=seed, env_kwargs={"render_mode": None})


class Evaluations(BaseCallback):
    """
    The greedy evaluations of one job: ``n_eval_episodes`` episodes with ``evaluate_policy`` on as many envs, episode
    ``i`` from ``reset(seed=seed_base + i)``, at the first call of :meth:`maybe_evaluate` at or after each multiple of
    ``eval_every``. As an SB3 callback, it evaluates at rollout starts (for NFQ: right after the previous round's fit;
    SB3's ``EvalCallback`` evaluates inside a round) and at the end of training.

    :param job: the job (env, episodes per evaluation, threshold, evaluation period, whether to stop at the solve)
    :param seed_base: the learning curve's first episode seed
    """

    def __init__(self, job: Job, seed_base: int) -> None:
        super().__init__()
        self.job, self.seed_base, self.env = job, seed_base, make_env(job.config.env_id, job.n_eval_episodes)
        self.curve: list[list[float]] = []
        self.steps_to_solve: int | None = None
        #: Training seconds from ``started`` (training's start) to the evaluation that solved, evaluations left out.
        self.seconds_to_solve: float | None = None
        self.started = time.perf_counter()
        self.eval_seconds, self.stopped, self.keep_training = 0.0, False, True
        self._next_eval = 0

    def returns(self, model: Any, seed_base: int) -> np.ndarray:
        """:return: the returns of ``model``'s greedy episodes, the first from ``reset(seed=seed_base)``"""
        self.env.seed(seed_base)
        n_episodes = self.job.n_eval_episodes
        returns, _ = evaluate_policy(model, self.env, n_episodes, deterministic=True, return_episode_rewards=True)
        return np.asarray(returns, dtype=float)

    def evaluate(self, steps: int, model: Any) -> None:
        """Add a point to the learning curve: ``model`` after ``steps`` env steps."""
        start = time.perf_counter()
        mean = float(np.mean(self.returns(model, self.seed_base)))
        if mean >= self.job.threshold and self.steps_to_solve is None:
            self.steps_to_solve, self.seconds_to_solve = steps, start - self.started - self.eval_seconds
        self.eval_seconds += time.perf_counter() - start
        self.curve.append([steps, mean])
        self._next_eval = (steps // self.job.eval_every + 1) * self.job.eval_every

    def maybe_evaluate(self, steps: int, model: Any) -> bool:
        """Evaluate if a multiple of ``eval_every`` was reached. :return: whether training should go on"""
        if steps >= self._next_eval:
            self.evaluate(steps, model)
        self.stopped = self.job.stop_at_solve and self.steps_to_solve is not None
        return not self.stopped

    def finish(self, steps: int, model: Any) -> None:
        """Evaluate the final policy unless it was just evaluated or training stopped at the solve."""
        if not self.stopped and (not self.curve or self.curve[-1][0] != steps):
            self.evaluate(steps, model)

    def _on_rollout_start(self) -> None:
        self.keep_training = self.maybe_evaluate(self.num_timesteps, self.model)

    def _on_step(self) -> bool:
        return self.keep_training

    def _on_training_end(self) -> None:
        self.finish(self.num_timesteps, self.model)


# --- training ---------------------------------------------------------------------------------------------------


def build_sb3_model(job: Job) -> tuple[Any, list[BaseCallback]]:
    """
    :param job: an NFQ, DQN or QR-DQN job
    :return: its model on its training envs and the callbacks its config asks for (``keep_best``:
        ``sb3_nfq.KeepBestCallback`` with its defaults)
    """
    from sb3_contrib import QRDQN
    from stable_baselines3 import DQN

    from sb3_nfq import NFQ, KeepBestCallback

    kwargs = dict(job.config.kwargs)
    n_envs, policy = int(kwargs.pop("n_envs", 1)), kwargs.pop("policy", "MlpPolicy")
    callbacks: list[BaseCallback] = [KeepBestCallback()] if kwargs.pop("keep_best", False) else []
    algorithm_class: Any = {"nfq": NFQ, "dqn": DQN, "qrdqn": QRDQN}[job.config.kind]
    env = make_env(job.config.env_id, n_envs, job.seed)
    return algorithm_class(policy, env, seed=job.seed, device="cpu", verbose=0, **zoo_to_kwargs(kwargs)), callbacks


def train(job: Job, tracker: BaseCallback) -> tuple[Any, str | None]:
    """
    :param job: the job
    :param tracker: its :class:`Evaluations` (``--protocol rounds``) or the book's criterion
    :return: the trained model (what ``evaluate_policy`` plays) and the divergence error, if training diverged
    """
    from benchmarks.reference_nfq import ReferenceNFQ
    from sb3_nfq import NFQDivergenceError

    if job.config.kind == "reference":
        model: Any = ReferenceNFQ(job.config.env_id, seed=job.seed, **job.config.kwargs)
        if isinstance(tracker, StopTrainingOnBookCriterion):
            criterion = tracker.criterion

            def after_episode(agent: ReferenceNFQ) -> bool:
                return not criterion.on_training_episode_end(agent.num_timesteps, lambda o: int(agent.act(o[None])[0]))

            model.learn(job.budget, episode_callback=after_episode)
        elif isinstance(tracker, Evaluations):  # evaluated at step 0, as SB3's learn() does at its first rollout start
            tracker.maybe_evaluate(0, model)
            model.learn(job.budget, callback=lambda agent: tracker.maybe_evaluate(agent.num_timesteps, agent))
            tracker.finish(model.num_timesteps, model)
        return model, None
    model, callbacks = build_sb3_model(job)
    try:  # keep_best restores its weights before the last evaluation, at the end of learn()
        model.learn(job.budget, callback=CallbackList([*callbacks, tracker]))
    except NFQDivergenceError as error:  # a result like any other: recorded, not retried
        return model, str(error)
    return model, None


def run_job(job: Job) -> dict[str, Any]:
    """Train one job and evaluate it, with one torch thread. :return: its result record (one JSON line)"""
    wall_start = time.perf_counter()
    th.set_num_threads(1)
    config, curve_seed, final_seed = job.config, CURVE_SEED_BASE + 1000 * job.seed, FINAL_SEED_BASE + 1000 * job.seed
    evaluations = Evaluations(job, curve_seed)
    book = (
        StopTrainingOnBookCriterion(config.env_id, job.threshold, BOOK_WINDOW, seed=curve_seed)
        if job.protocol == "book"
        else None
    )
    evaluations.started = start = time.perf_counter()
    model, diverged = train(job, book or evaluations)
    learn_seconds = time.perf_counter() - start
    final_returns, solve_seconds = evaluations.returns(model, final_seed), evaluations.seconds_to_solve
    outcome: dict[str, Any] = {
        "solved": evaluations.steps_to_solve is not None,
        "steps_to_solve": evaluations.steps_to_solve,
        "train_seconds_to_solve": None if solve_seconds is None else round(solve_seconds, 3),
        "stopped_at_solve": evaluations.stopped,
    }
    eval_seconds, curve = evaluations.eval_seconds, evaluations.curve
    if book is not None:
        criterion = book.criterion
        outcome = {
            "protocol": "book",
            "book_window": criterion.window,
            "solved": criterion.solved,
            "steps_to_solve": criterion.steps_to_solve,
            "episodes_to_solve": criterion.episodes_to_solve,
            "episodes_trained": len(criterion.evaluation_returns),
            "train_seconds_to_solve": None,  # not measured under the book's criterion
            "stopped_at_solve": criterion.solved,
        }
        eval_seconds, curve = criterion.eval_seconds, []  # its evaluations are single episodes: no curve
    return {
        "algo": config.algo,
        "env": config.env_id,
        "seed": job.seed,
        "budget": job.budget,
        "config_hash": job.config_hash,
        "kind": config.kind,
        "config": config.kwargs,
        "config_source": config.source,
        "threshold": job.threshold,
        "n_eval_episodes": job.n_eval_episodes,
        "eval_every": job.eval_every,
        "eval_seeds": {"curve": curve_seed, "final": final_seed},
        "stop_at_solve": job.stop_at_solve,
        **outcome,
        "steps_trained": model.num_timesteps,
        "diverged": diverged,
        "final_score": float(np.mean(final_returns)),
        "final_score_std": float(np.std(final_returns)),
        "final_n_episodes": len(final_returns),
        "train_seconds": round(learn_seconds - eval_seconds, 3),
        "eval_seconds": round(eval_seconds, 3),
        "wall_seconds": round(time.perf_counter() - wall_start, 3),
        "curve": [[int(steps), round(mean, 3)] for steps, mean in curve],
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


def submit(jobs: Sequence[Job], workers: int, ray_address: str | None, stack: contextlib.ExitStack) -> dict[Any, Job]:
    """
    :param jobs: the jobs
    :param workers: local worker processes (0: one job after the other in this process)
    :param ray_address: run the jobs as Ray tasks (``num_cpus=1``) on this cluster instead
    :param stack: where what has to be shut down afterwards goes
    :return: a future of each job's record
    """
    if ray_address:
        try:
            import ray
        except ImportError as error:
            raise SystemExit("--ray-address needs Ray: the dev group of pyproject.toml, or 'ray>=2.9'") from error
        if not ray.is_initialized():  # ship this checkout's code to the workers (the nodes need the packages installed)
            runtime_env = {"py_modules": [str(REPO_ROOT / "benchmarks"), str(REPO_ROOT / "sb3_nfq")]}
            if ray_address == "local":
                ray.init(num_cpus=max(workers, 1), include_dashboard=False, runtime_env=runtime_env)
            else:
                ray.init(address=ray_address, runtime_env=runtime_env)
            stack.callback(ray.shutdown)
        remote = ray.remote(num_cpus=1, max_retries=0, max_calls=1)(run_job)  # a fresh process per job
        return {remote.remote(job).future(): job for job in jobs}
    if workers == 0:  # one after the other in this process (debugging, tests)
        pool: concurrent.futures.Executor = concurrent.futures.ThreadPoolExecutor(1)
    else:  # a fresh process per job: no state leaks between jobs
        context = multiprocessing.get_context("spawn")
        pool = concurrent.futures.ProcessPoolExecutor(workers, mp_context=context, max_tasks_per_child=1)
    stack.enter_context(pool)
    return {pool.submit(run_job, job): job for job in jobs}


def run_jobs(
    jobs: Sequence[Job], results: Path, workers: int, ray_address: str | None = None, rerun: bool = False
) -> tuple[int, int, int]:
    """
    Run the jobs not yet in ``results``, appending one line per finished job (only this process writes).

    :param jobs: the jobs
    :param results: the results file (JSON lines)
    :param workers: local worker processes (0: run in this process); at most the number of cores
    :param ray_address: run as Ray tasks on this cluster (``local``, ``auto`` or an address) instead
    :param rerun: skip only the jobs this same command line has recorded on this hardware (:func:`hardware`): to run
        a baseline side by side again, or the whole run again on other hardware, whose seconds do not compare
    :return: (jobs run, jobs skipped as already done, jobs failed)
    """
    commands, here = {job.command for job in jobs}, hardware(machine_line())

    def recorded_alike(record: dict[str, Any]) -> bool:
        return record["command"] in commands and hardware(record.get("machine", "")) == here

    done = {result_key(record) for record in read_results(results) if not rerun or recorded_alike(record)}
    todo = [job for job in jobs if job.key not in done]
    if workers > usable_cores():
        print(f"warning: {workers} workers on {usable_cores()} cores would distort timings", file=sys.stderr)
        workers = usable_cores()
    print(f"{len(jobs)} jobs: {len(jobs) - len(todo)} already in {results}, {len(todo)} to run")
    finished = failures = 0
    pool = f"local pool ({workers} spawned workers)" if workers else "in-process"
    launched = f"ray ({ray_address})" if ray_address else pool
    with contextlib.ExitStack() as stack:
        futures = submit(todo, workers, ray_address, stack) if todo else {}
        for future in concurrent.futures.as_completed(futures):
            job = futures[future]
            try:
                record = future.result()
            except Exception as error:
                failures += 1
                print(f"FAILED {job}: {''.join(traceback.format_exception(error))}", file=sys.stderr)
                continue
            record["launcher"] = launched
            results.parent.mkdir(parents=True, exist_ok=True)
            with results.open("a") as file:
                file.write(json.dumps(record) + "\n")
            finished += 1
            solved = f"solved at {record['steps_to_solve']}" if record["solved"] else "not solved"
            score, seconds = record["final_score"], record["train_seconds"]
            print(f"[{finished}/{len(todo)}] {job}: {solved}, final {score:.1f}, train {seconds:.1f}s", flush=True)
    return finished, len(jobs) - len(todo), failures


def parse_seeds(values: Iterable[str]) -> list[int]:
    """:return: the seeds of ``values`` such as ``["0-4"]`` or ``["0", "3,7-9"]``, in order, without duplicates"""
    seeds: list[int] = []
    for part in (part for value in values for part in value.split(",") if part):
        low, _, high = part.partition("-")
        seeds.extend(range(int(low), int(high or low) + 1))
    return list(dict.fromkeys(seeds))


def main(argv: Sequence[str] | None = None) -> int:
    """:param argv: arguments (default: ``sys.argv[1:]``) :return: exit status (1 if a job failed)"""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    names, seeds = configs.algorithm_names(), f"{configs.SEEDS[0]}-{configs.SEEDS[-1]}"
    parser.add_argument("--algos", nargs="+", required=True, choices=names)
    parser.add_argument("--envs", nargs="+", default=list(configs.ENVS), choices=list(configs.ENVS))
    parser.add_argument("--seeds", nargs="+", default=[seeds], help=f"seeds or ranges (default {seeds})")
    parser.add_argument("--budget", type=int, help="env-step budget of every job (default: per config and env)")
    parser.add_argument("--eval-every", type=int, help="evaluation period in env steps (default: per env)")
    parser.add_argument("--eval-episodes", type=int, default=configs.N_EVAL_EPISODES, help="fewer: smoke tests")
    parser.add_argument("--stop-at-solve", action="store_true", help="stop each job when solved (quick runs)")
    parser.add_argument("--protocol", choices=PROTOCOLS, default="rounds", help="book: the book's criterion")
    parser.add_argument("--workers", type=int, default=min(2, usable_cores()), help="processes (0: this one)")
    parser.add_argument("--results", type=Path, help="JSON-lines file (default: runs.jsonl or book_protocol.jsonl)")
    parser.add_argument("--ray-address", help="run the jobs as Ray tasks: 'local', 'auto' or a cluster address")
    parser.add_argument(
        "--rerun", action="store_true", help="skip only the jobs this exact command has recorded on this hardware"
    )
    args = parser.parse_args(argv)
    if args.workers < 0:
        parser.error(f"--workers must be >= 0, got {args.workers}")
    results = args.results or (DEFAULT_BOOK_RESULTS if args.protocol == "book" else DEFAULT_RESULTS)
    command = relative_command("benchmarks.run", argv)
    jobs = make_jobs(
        args.algos, args.envs, parse_seeds(args.seeds), args.budget, args.eval_every,
        n_eval_episodes=args.eval_episodes, stop_at_solve=args.stop_at_solve, command=command, protocol=args.protocol,
    )  # fmt: skip
    print(f"machine: {machine_line()}; torch threads per job: 1")
    return 1 if run_jobs(jobs, results, args.workers, args.ray_address, args.rerun)[2] else 0


if __name__ == "__main__":
    sys.exit(main())
