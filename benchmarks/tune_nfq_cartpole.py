"""
Tune NFQ's sample efficiency on CartPole-v1: run candidate configs x seeds and measure how many env steps each
needs to reach the solve criterion, and whether it stays solved.

Protocol (one run = one config and one seed):

- ``learn()`` is called once with the whole budget (50k env steps by default) as ``total_timesteps``, so the
  exploration and learning-rate schedules are computed on that budget.
- After every NFQ round (at the next rollout start, i.e. right after the previous round's fit), the greedy policy
  plays 100 episodes on a separate 100-env vectorised env (``make_vec_env(..., seed=seed + 10_000)``, SB3's
  ``evaluate_policy`` with ``deterministic=True``). The run is "solved" at the first evaluation whose mean
  return reaches 475; ``steps_to_solve`` is the env steps trained at that evaluation. ``steps_to_solve_1024``
  is the same read on the coarser grid of ``benchmarks/run.py`` (first round end at or after each multiple of
  1024 steps), to compare with DQN results measured that way.
- After the solve, training goes on to the budget without per-round evaluations (only every
  ``--post-solve-eval-every`` steps), then 100 new greedy episodes on another env (``seed + 20_000``) give the
  final score.
- CPU seconds are the process's CPU time for the run (``time.process_time``), with ``torch.set_num_threads(1)``;
  ``eval_cpu_seconds`` is the part spent in the evaluations.

    python benchmarks/tune_nfq_cartpole.py --configs NAME [NAME ...] --seeds 0 1 [--budget 50000]
        [--results benchmarks/results/tuning_cartpole.jsonl] [--list]

Each run appends one JSON line to the results file; a summary per config is printed at the end.
"""

import argparse
import json
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from sb3_nfq import NFQ

ENV_ID = "CartPole-v1"
SOLVED_AT = 475.0
N_EVAL_EPISODES = 100
DEFAULT_BUDGET = 50_000
#: Grid of benchmarks/run.py's evaluations (``EnvSpec.eval_every``), for ``steps_to_solve_1024``.
RUN_PY_EVAL_EVERY = 1024
DEFAULT_RESULTS = Path(__file__).resolve().parent / "results" / "tuning_cartpole.jsonl"


def _adam(net_arch: list[int], **optimizer_kwargs: Any) -> dict[str, Any]:
    """
    :param net_arch: hidden layer sizes
    :param optimizer_kwargs: extra kwargs of ``th.optim.Adam`` (besides the learning rate)
    :return: ``policy_kwargs`` for an Adam-fitted ReLU network
    """
    policy_kwargs: dict[str, Any] = {"net_arch": net_arch, "optimizer_class": th.optim.Adam}
    if optimizer_kwargs:
        policy_kwargs["optimizer_kwargs"] = optimizer_kwargs
    return policy_kwargs


class LinearSchedule:
    """
    Learning rate going linearly from ``initial`` to 0 over the ``learn()`` budget (the RL Zoo's ``lin_<x>``).

    :param initial: learning rate at the start
    """

    def __init__(self, initial: float) -> None:
        self.initial = initial

    def __call__(self, progress_remaining: float) -> float:
        return progress_remaining * self.initial

    def __repr__(self) -> str:
        return f"lin_{self.initial:g}"


#: The 2005 paper's data-efficient variant: a growing memory, fitted in shuffled mini-batch epochs, small rounds,
#: classic fitted Q-iteration targets (frozen for each fitted iteration). MSE: with Huber (and 1 epoch per iteration)
#: the Q-values diverged in screening; a small [64, 64] net is ~4-10x cheaper per sample than [256, 256] on CPU.
_GROWING_BASE: dict[str, Any] = {
    "memory": "growing",
    "target_mode": "fixed_per_iteration",
    "gamma": 0.99,
    "loss": "mse",
    "max_grad_norm": 10.0,
    "learning_rate": 1e-3,
    "train_freq": 256,
    "batch_size": 256,
    "exploration_initial_eps": 1.0,
    "exploration_final_eps": 0.04,
    "exploration_fraction": 0.16,
    "policy_kwargs": _adam([64, 64]),
}

#: Candidate NFQ kwargs (for ``NFQ("MlpPolicy", env, seed=seed, **kwargs)``), by name. Measured results
#: (50k budget, seeds 0-4 unless said; solve steps with an evaluation after every 256-step round) in the comments.
CANDIDATES: dict[str, dict[str, Any]] = {
    # Best: solved at 12800/13056/14336/14848/14336 (median 14336), final 500/500/500/500/489, ~145 s CPU per run.
    "k8": {**_GROWING_BASE, "gradient_steps": 8},
    # Runner-up, half the CPU (~76 s): median 14080 but final 500/500/138/500/454 (3/5 stay solved).
    "k8-b512-cap20k": {**_GROWING_BASE, "gradient_steps": 8, "batch_size": 512, "buffer_size": 20_000},
    # Seeds 0-1: solved at 15360/19968, final 500/500, ~82 s CPU.
    "k4": {**_GROWING_BASE, "gradient_steps": 4},
    # Seeds 0-1: solved at 18176/12800 but final 133/237: decaying the learning rate did not stabilise the end.
    "k8-b512-lin": {**_GROWING_BASE, "gradient_steps": 8, "batch_size": 512, "learning_rate": LinearSchedule(1e-3)},
    # Not measured to the end (screening stopped to save CPU).
    "k4-e2": {**_GROWING_BASE, "gradient_steps": 4, "fit_epochs": 2},
    "k16": {**_GROWING_BASE, "gradient_steps": 16},
    "k8-lr5e-4": {**_GROWING_BASE, "gradient_steps": 8, "learning_rate": 5e-4},
    "k4-f128": {**_GROWING_BASE, "gradient_steps": 4, "train_freq": 128},
    "k8-x10": {**_GROWING_BASE, "gradient_steps": 8, "exploration_fraction": 0.1},
    "k4-b512": {**_GROWING_BASE, "gradient_steps": 4, "batch_size": 512},
}


@dataclass
class RunResult:
    """
    What one run measured.

    :param config: candidate name
    :param seed: random seed (model, training env; evaluation envs use ``seed + 10_000`` and ``seed + 20_000``)
    :param budget: env-step budget (``total_timesteps`` of ``learn()``)
    :param steps_to_solve: env steps at the first per-round evaluation with mean >= 475 (``None``: never)
    :param steps_to_solve_1024: the same on benchmarks/run.py's grid of evaluations every 1024 steps
    :param final_mean: mean return of 100 new greedy episodes after the budget
    :param final_std: their standard deviation
    :param steps: env steps trained in all (the last round is completed, so it may pass the budget)
    :param cpu_seconds: CPU time of the run, evaluations included
    :param eval_cpu_seconds: CPU time of the evaluations alone
    :param wall_seconds: wall-clock time of the run
    :param curve: ``[steps, mean greedy return]`` of every evaluation
    :param kwargs: the NFQ kwargs, as plain data
    """

    config: str
    seed: int
    budget: int
    steps_to_solve: int | None
    steps_to_solve_1024: int | None
    final_mean: float
    final_std: float
    steps: int
    cpu_seconds: float
    eval_cpu_seconds: float
    wall_seconds: float
    curve: list[list[float]] = field(default_factory=list)
    kwargs: dict[str, Any] = field(default_factory=dict)


class RoundEndEvaluation(BaseCallback):
    """
    Greedy evaluation after every NFQ round until the first solve, then every ``post_solve_eval_every`` steps.

    :param eval_env: vectorised env with one env per evaluation episode
    :param n_eval_episodes: greedy episodes per evaluation
    :param threshold: solved when the mean return reaches this
    :param post_solve_eval_every: evaluation period in env steps once solved (0: none until the final one)
    """

    def __init__(self, eval_env: VecEnv, n_eval_episodes: int, threshold: float, post_solve_eval_every: int) -> None:
        super().__init__()
        self.eval_env = eval_env
        self.n_eval_episodes = n_eval_episodes
        self.threshold = threshold
        self.post_solve_eval_every = post_solve_eval_every
        self.curve: list[list[float]] = []
        self.steps_to_solve: int | None = None
        self.eval_cpu_seconds = 0.0
        self._next_post_solve_eval = 0

    def evaluate(self) -> float:
        """:return: the mean greedy return now, also added to the curve"""
        start = time.process_time()
        mean, _ = evaluate_policy(self.model, self.eval_env, n_eval_episodes=self.n_eval_episodes, deterministic=True)
        self.eval_cpu_seconds += time.process_time() - start
        assert isinstance(mean, float)
        steps = self.model.num_timesteps
        self.curve.append([steps, round(float(mean), 1)])
        if mean >= self.threshold and self.steps_to_solve is None:
            self.steps_to_solve = steps
            if self.post_solve_eval_every > 0:
                self._next_post_solve_eval = (steps // self.post_solve_eval_every + 1) * self.post_solve_eval_every
        return mean

    def _on_rollout_start(self) -> None:
        steps = self.model.num_timesteps
        if steps == 0:
            return
        if self.steps_to_solve is None:
            self.evaluate()
        elif self.post_solve_eval_every > 0 and steps >= self._next_post_solve_eval:
            self.evaluate()
            self._next_post_solve_eval = (steps // self.post_solve_eval_every + 1) * self.post_solve_eval_every

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        if self.steps_to_solve is None and (not self.curve or self.curve[-1][0] != self.model.num_timesteps):
            self.evaluate()


def steps_on_grid(curve: list[list[float]], threshold: float, every: int) -> int | None:
    """
    :param curve: ``[steps, mean return]`` of evaluations after every round (in order)
    :param threshold: solve threshold
    :param every: evaluation period of the coarser grid
    :return: steps to solve when only the first evaluation at or after each multiple of ``every`` counts
    """
    next_eval = 0
    for steps, mean in curve:
        if steps < next_eval:
            continue
        if mean >= threshold:
            return int(steps)
        next_eval = (int(steps) // every + 1) * every
    return None


def plain(value: Any) -> Any:
    """
    :param value: NFQ kwargs (or a part of them)
    :return: the same as JSON-ready data, classes written as ``th.optim.Adam`` / ``nn.ReLU``
    """
    if isinstance(value, dict):
        return {key: plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [plain(item) for item in value]
    if isinstance(value, type):
        if issubclass(value, th.optim.Optimizer):
            return f"th.optim.{value.__name__}"
        if issubclass(value, nn.Module):
            return f"nn.{value.__name__}"
    if callable(value):
        return repr(value)
    return value


def run_one(name: str, kwargs: dict[str, Any], seed: int, budget: int, post_solve_eval_every: int) -> RunResult:
    """
    Train one config with one seed for ``budget`` env steps, evaluating after every round until solved.

    :param name: candidate name
    :param kwargs: NFQ kwargs
    :param seed: random seed
    :param budget: env-step budget
    :param post_solve_eval_every: evaluation period once solved (0: only the final evaluation)
    :return: what the run measured
    """
    cpu_start, wall_start = time.process_time(), time.perf_counter()
    model = NFQ("MlpPolicy", ENV_ID, seed=seed, verbose=0, **kwargs)
    eval_env = make_vec_env(ENV_ID, n_envs=N_EVAL_EPISODES, seed=seed + 10_000)
    tracker = RoundEndEvaluation(eval_env, N_EVAL_EPISODES, SOLVED_AT, post_solve_eval_every)
    model.learn(budget, callback=tracker)

    final_env = make_vec_env(ENV_ID, n_envs=N_EVAL_EPISODES, seed=seed + 20_000)
    eval_start = time.process_time()
    final_mean, final_std = evaluate_policy(model, final_env, n_eval_episodes=N_EVAL_EPISODES, deterministic=True)
    eval_cpu_seconds = tracker.eval_cpu_seconds + time.process_time() - eval_start
    assert isinstance(final_mean, float) and isinstance(final_std, float)
    eval_env.close()
    final_env.close()
    return RunResult(
        config=name,
        seed=seed,
        budget=budget,
        steps_to_solve=tracker.steps_to_solve,
        steps_to_solve_1024=steps_on_grid(tracker.curve, SOLVED_AT, RUN_PY_EVAL_EVERY),
        final_mean=round(float(final_mean), 1),
        final_std=round(float(final_std), 1),
        steps=model.num_timesteps,
        cpu_seconds=round(time.process_time() - cpu_start, 1),
        eval_cpu_seconds=round(eval_cpu_seconds, 1),
        wall_seconds=round(time.perf_counter() - wall_start, 1),
        curve=tracker.curve,
        kwargs=plain(kwargs),
    )


def summarize(name: str, results: list[RunResult]) -> str:
    """
    :param name: candidate name
    :param results: its runs
    :return: one line: steps to solve per seed and their median (unsolved runs count as never), final scores,
        how many runs stay solved, and the mean CPU seconds per run
    """
    never = float("inf")
    solve = [r.steps_to_solve if r.steps_to_solve is not None else never for r in results]
    solve_1024 = [r.steps_to_solve_1024 if r.steps_to_solve_1024 is not None else never for r in results]
    finals = [r.final_mean for r in results]
    stayed = sum(final >= SOLVED_AT for final in finals)
    cpu = statistics.mean(r.cpu_seconds for r in results)
    eval_cpu = statistics.mean(r.eval_cpu_seconds for r in results)

    def show(values: list[float]) -> str:
        return "[" + ", ".join("never" if v == never else str(int(v)) for v in values) + "]"

    return (
        f"{name}: seeds {[r.seed for r in results]} steps_to_solve {show(solve)} median {statistics.median(solve):g} "
        f"(1024-grid {show(solve_1024)} median {statistics.median(solve_1024):g}); final {finals} "
        f"({stayed}/{len(results)} >= {SOLVED_AT:g}); CPU {cpu:.0f} s/run ({eval_cpu:.0f} s evaluating)"
    )


def main(argv: list[str] | None = None) -> int:
    """
    Run the chosen candidates x seeds one after another (one thread), appending each run to the results file.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: exit status
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", nargs="+", default=list(CANDIDATES), choices=list(CANDIDATES), metavar="NAME")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--budget", type=int, default=DEFAULT_BUDGET, help="env steps (total_timesteps of learn)")
    parser.add_argument("--post-solve-eval-every", type=int, default=10_000, help="0: no evaluation after solving")
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS, help="JSON lines, appended")
    parser.add_argument("--list", action="store_true", help="print the candidates and exit")
    args = parser.parse_args(argv)

    if args.list:
        for name, kwargs in CANDIDATES.items():
            print(f"{name}: {json.dumps(plain(kwargs))}")
        return 0

    th.set_num_threads(1)
    args.results.parent.mkdir(parents=True, exist_ok=True)
    results: dict[str, list[RunResult]] = {}
    for name in args.configs:
        for seed in args.seeds:
            result = run_one(name, CANDIDATES[name], seed, args.budget, args.post_solve_eval_every)
            results.setdefault(name, []).append(result)
            print(
                f"{name} seed {seed}: solved at {result.steps_to_solve} (1024-grid {result.steps_to_solve_1024}), "
                f"final {result.final_mean} +/- {result.final_std}, CPU {result.cpu_seconds} s "
                f"({result.eval_cpu_seconds} s evaluating)",
                flush=True,
            )
            with args.results.open("a") as file:
                file.write(json.dumps(asdict(result)) + "\n")
    print("\nSummary")
    for name, runs in results.items():
        print(summarize(name, runs), flush=True)
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=1)
    sys.exit(main())
