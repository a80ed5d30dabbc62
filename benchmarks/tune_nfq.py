"""
Tune NFQ per env: run a few candidate configs on tuning seeds, under the benchmark runner's own protocol, and rank
them. The winner of an env becomes ``nfq-tuned``'s entry for it in ``benchmarks/configs.py``, which the runner then
measures on the benchmark seeds (0-4), which tuning never sees.

    python -m benchmarks.tune_nfq --envs CartPole-v1 [Acrobot-v1 ...] [--candidates NAME ...] [--seeds 100-101]
        [--workers 2] [--results benchmarks/results/tuning_per_env.jsonl] [--list] [--summary-only]
        [--budget N --eval-episodes N: smoke tests only]

Protocol: each (candidate, env, seed) is one job of ``benchmarks/run.py`` (same greedy evaluations of 100 episodes
every ``eval_every`` steps, on CartPole every 256 (see ``TUNING_EVAL_EVERY``), same threshold, one torch thread, one
spawned process per job), run with ``--stop-at-solve``: tuning looks for the fewest env steps to reach the criterion,
not for the final score. Results are appended to their own JSON-lines file (``algo`` = ``tune:<candidate>``),
resumable like the runner's.

Ranking, per env: most seeds solved, then the lowest median steps to solve (an unsolved seed counts as the steps it
trained), then the lowest median training seconds.

The candidates are a handful of hand-picked variations of the configs already benchmarked (the book's settings and
the CartPole-tuned growing-memory config), each changing what the env's difficulty suggests: exploration and discount
on Acrobot, the Zoo DQN's memory size and discount on MountainCar, and on LunarLander memory size, refit rate,
network, loss and the Zoo DQN's exploration. On CartPole, where the shared config solves at about twice the steps of
DQN's first touch of 475, discount, refit rate, exploration length and the Zoo DQN's network and learning rate, in
two rounds (the second combining the first round's best with the others). A search this small is affordable on 2
cores (the shared growing-memory config ran 9-27 minutes to the Zoo's budget off CartPole); the RL Zoo's Optuna
(``python -m sb3_nfq.zoo train --algo nfq --env ENV -optimize``) searches wider where more CPU is available.
"""

import argparse
import shlex
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks import configs
from benchmarks.run import REPO_ROOT, Job, git_revision, parse_seeds, read_results, run_jobs

DEFAULT_RESULTS = REPO_ROOT / "benchmarks" / "results" / "tuning_per_env.jsonl"
#: Seeds for tuning; the benchmark's are 0-4.
DEFAULT_TUNING_SEEDS = "100-101"
#: Prefix of a candidate's ``algo`` in the results file.
ALGO_PREFIX = "tune:"

_SHARED = configs.GROWING_MEMORY_CONFIG
#: Exploration of the Zoo's DQN on LunarLander-v3 (rl_zoo3 hyperparams/dqn.yml): 1 -> 0.1 over 12% of the budget.
_ZOO_LUNAR_EXPLORATION = {"exploration_final_eps": 0.1, "exploration_fraction": 0.12}

#: Evaluation period of the tuning jobs where it differs from the benchmark's (``configs.ENVS``). CartPole's
#: sample-efficiency target is also judged on runs evaluated every 256 steps (the shared config's round length, and
#: the period at which DQN's early peaks show), the stricter of its two readings: tune for that one.
TUNING_EVAL_EVERY: dict[str, int] = {"CartPole-v1": 256}

_CARTPOLE_BUDGET = {"n_timesteps": configs.ZOO_DQN_BUDGETS["CartPole-v1"]}
#: The Zoo DQN's CartPole network and learning rate (rl_zoo3 hyperparams/dqn.yml), fitted with Adam.
_CARTPOLE_ZOO_NET = {
    "learning_rate": 2.3e-3,
    "policy_kwargs": "dict(net_arch=[256, 256], optimizer_class=th.optim.Adam)",
}

#: env id -> candidate name -> NFQ kwargs (with ``n_timesteps``, the step budget, where not the env's default).
CANDIDATES: dict[str, dict[str, dict[str, Any]]] = {
    # The shared config solves in ~14k steps, where the Zoo's DQN first touches 475 at ~7k. Each candidate changes
    # one thing: the discount (a shorter horizon propagates values in fewer fitted iterations), how much is refitted
    # per env step (more fitted iterations per round, or shorter rounds), how long epsilon decays, or the network
    # and learning rate (the Zoo DQN's: 256-256, 2.3e-3); the last two of the first round combine the first ones.
    "CartPole-v1": {
        "shared": {**_SHARED, **_CARTPOLE_BUDGET},
        # A shorter horizon: values propagate in fewer fitted iterations.
        "shared-gamma-0.98": {**_SHARED, "gamma": 0.98, **_CARTPOLE_BUDGET},
        # Twice the fitted iterations per round (16 instead of 8).
        "shared-k16": {**_SHARED, "gradient_steps": 16, **_CARTPOLE_BUDGET},
        # Rounds of 128 steps: the memory is refitted twice as often.
        "shared-rounds-128": {**_SHARED, "train_freq": 128, **_CARTPOLE_BUDGET},
        # Epsilon reaches its floor after 4k steps instead of 8k.
        "shared-eps-4k": {**_SHARED, "exploration_fraction": 0.08, **_CARTPOLE_BUDGET},
        # The Zoo DQN's network and learning rate.
        "shared-256x256-lr-2.3e-3": {**_SHARED, **_CARTPOLE_ZOO_NET, **_CARTPOLE_BUDGET},
        "shared-gamma-0.98-k16": {**_SHARED, "gamma": 0.98, "gradient_steps": 16, **_CARTPOLE_BUDGET},
        "shared-gamma-0.98-k16-rounds-128": {
            **_SHARED,
            "gamma": 0.98,
            "gradient_steps": 16,
            "train_freq": 128,
            **_CARTPOLE_BUDGET,
        },
        # Second round: the Zoo DQN's network and learning rate gave the largest gain of the first round (median
        # 7,168 steps against the shared config's 13,056); each of these adds one more lever of the first round.
        "shared-256x256-lr-2.3e-3-k16": {**_SHARED, **_CARTPOLE_ZOO_NET, "gradient_steps": 16, **_CARTPOLE_BUDGET},
        "shared-256x256-lr-2.3e-3-rounds-128": {**_SHARED, **_CARTPOLE_ZOO_NET, "train_freq": 128, **_CARTPOLE_BUDGET},
        "shared-256x256-lr-2.3e-3-eps-4k": {
            **_SHARED,
            **_CARTPOLE_ZOO_NET,
            "exploration_fraction": 0.08,
            **_CARTPOLE_BUDGET,
        },
        "shared-256x256-lr-2.3e-3-gamma-0.98": {**_SHARED, **_CARTPOLE_ZOO_NET, "gamma": 0.98, **_CARTPOLE_BUDGET},
    },
    "Acrobot-v1": {
        "book": {},
        "book-gamma-0.99": {"gamma": 0.99},
        "book-eps-1-to-0.05": {
            "exploration_initial_eps": 1.0,
            "exploration_final_eps": 0.05,
            "exploration_fraction": 0.1,
        },
        "shared": {**_SHARED, "n_timesteps": configs.ZOO_DQN_BUDGETS["Acrobot-v1"]},
    },
    "MountainCar-v0": {
        "shared": {**_SHARED, "n_timesteps": configs.ZOO_DQN_BUDGETS["MountainCar-v0"]},
        # The Zoo DQN's MountainCar memory and discount (buffer_size 10000, gamma 0.98); the small memory also
        # makes each round's fit cheaper.
        "shared-memory-10k-gamma-0.98": {
            **_SHARED,
            "buffer_size": 10_000,
            "gamma": 0.98,
            "n_timesteps": configs.ZOO_DQN_BUDGETS["MountainCar-v0"],
        },
    },
    "LunarLander-v3": {
        "shared": {**_SHARED, "n_timesteps": configs.ZOO_DQN_BUDGETS["LunarLander-v3"]},
        "shared-memory-50k-zoo-eps": {
            **_SHARED,
            **_ZOO_LUNAR_EXPLORATION,
            "buffer_size": 50_000,
            "n_timesteps": configs.ZOO_DQN_BUDGETS["LunarLander-v3"],
        },
        "shared-128x128-memory-50k-zoo-eps": {
            **_SHARED,
            **_ZOO_LUNAR_EXPLORATION,
            "buffer_size": 50_000,
            "policy_kwargs": "dict(net_arch=[128, 128], optimizer_class=th.optim.Adam)",
            "n_timesteps": configs.ZOO_DQN_BUDGETS["LunarLander-v3"],
        },
        # Second round, after the three above solved no tuning seed and swung by hundreds between evaluations:
        # the shared config refits the whole memory 8 times every 256 steps (at 50k transitions, ~12 mini-batch
        # steps per env step, against the Zoo DQN's one). These refit it 4 times every 1024 steps (16x fewer).
        "low-replay-memory-50k-zoo-eps": {
            **_SHARED,
            **_ZOO_LUNAR_EXPLORATION,
            "train_freq": 1024,
            "gradient_steps": 4,
            "buffer_size": 50_000,
            "n_timesteps": configs.ZOO_DQN_BUDGETS["LunarLander-v3"],
        },
        # ... with the Zoo DQN's network (256-256) and a smaller, Huber-loss step.
        "low-replay-256x256-huber-lr-5e-4-memory-50k-zoo-eps": {
            **_SHARED,
            **_ZOO_LUNAR_EXPLORATION,
            "train_freq": 1024,
            "gradient_steps": 4,
            "buffer_size": 50_000,
            "loss": "huber",
            "learning_rate": 5e-4,
            "policy_kwargs": "dict(net_arch=[256, 256], optimizer_class=th.optim.Adam)",
            "n_timesteps": configs.ZOO_DQN_BUDGETS["LunarLander-v3"],
        },
        # Third round: low-replay-memory-50k-zoo-eps was still climbing at 100k steps (greedy mean 152 and 106 at
        # the end), and a run costs about a minute of training per 100k steps now: twice the Zoo DQN's budget.
        "low-replay-memory-50k-zoo-eps-200k-steps": {
            **_SHARED,
            **_ZOO_LUNAR_EXPLORATION,
            "train_freq": 1024,
            "gradient_steps": 4,
            "buffer_size": 50_000,
            "n_timesteps": 2 * configs.ZOO_DQN_BUDGETS["LunarLander-v3"],
        },
    },
}


def candidate_jobs(
    env_id: str,
    names: Sequence[str],
    seeds: Sequence[int],
    budget: int | None = None,
    n_eval_episodes: int = configs.N_EVAL_EPISODES,
    command: str = "",
) -> list[Job]:
    """
    :param env_id: one of :data:`CANDIDATES`' envs
    :param names: candidate names for that env
    :param seeds: tuning seeds
    :param budget: env-step budget of every job (default: each candidate's; smaller only for smoke tests)
    :param n_eval_episodes: greedy episodes per evaluation (fewer only for smoke tests)
    :param command: the command line, recorded with each result
    :return: one runner job per candidate and seed, stopped at solve
    """
    if env_id not in CANDIDATES:
        raise KeyError(f"no tuning candidates for {env_id!r}; envs with candidates: {sorted(CANDIDATES)}")
    unknown = [name for name in names if name not in CANDIDATES[env_id]]
    if unknown:
        raise KeyError(f"unknown candidates {unknown} for {env_id}; known: {sorted(CANDIDATES[env_id])}")
    spec = configs.ENVS[env_id]
    git = git_revision()
    jobs = []
    for name in names:
        kwargs = dict(CANDIDATES[env_id][name])
        candidate_budget = int(kwargs.pop("n_timesteps", spec.budget))
        for seed in seeds:
            jobs.append(
                Job(
                    algo=ALGO_PREFIX + name,
                    kind="nfq",
                    env_id=env_id,
                    seed=seed,
                    budget=budget if budget is not None else candidate_budget,
                    kwargs=kwargs,
                    threshold=spec.threshold,
                    eval_every=TUNING_EVAL_EVERY.get(env_id, spec.eval_every),
                    n_eval_episodes=n_eval_episodes,
                    stop_at_solve=True,
                    source="benchmarks/tune_nfq.py",
                    command=command,
                    git=git,
                )
            )
    return jobs


@dataclass(frozen=True)
class CandidateSummary:
    """
    One candidate's tuning runs on one env.

    :param name: candidate name
    :param seeds: seeds run
    :param solved: seeds that reached the threshold
    :param median_steps: median env steps to solve (an unsolved seed counts as the steps it trained)
    :param steps: per seed, steps to solve (``None``: not solved)
    :param median_train_seconds: median training seconds (evaluations excluded)
    """

    name: str
    seeds: int
    solved: int
    median_steps: float
    steps: list[int | None]
    median_train_seconds: float

    @property
    def rank_key(self) -> tuple[float, float, float]:
        """:return: sort key of the ranking: most solved, fewest steps, fewest seconds"""
        return (-self.solved / self.seeds, self.median_steps, self.median_train_seconds)


def summarize(records: Sequence[dict[str, Any]], env_id: str) -> list[CandidateSummary]:
    """
    :param records: result lines of the tuning file
    :param env_id: env to summarize
    :return: the env's candidates that have results, best first (see the module's ranking)
    """
    by_name: dict[str, list[dict[str, Any]]] = {}
    for record in records:
        if record["env"] == env_id and record["algo"].startswith(ALGO_PREFIX):
            by_name.setdefault(record["algo"].removeprefix(ALGO_PREFIX), []).append(record)
    summaries = []
    for name, runs in by_name.items():
        runs.sort(key=lambda record: record["seed"])
        summaries.append(
            CandidateSummary(
                name=name,
                seeds=len(runs),
                solved=sum(bool(run["solved"]) for run in runs),
                median_steps=statistics.median(
                    run["steps_to_solve"] if run["solved"] else run["steps_trained"] for run in runs
                ),
                steps=[run["steps_to_solve"] for run in runs],
                median_train_seconds=statistics.median(run["train_seconds"] for run in runs),
            )
        )
    return sorted(summaries, key=lambda summary: summary.rank_key)


def summary_table(summaries: Sequence[CandidateSummary], env_id: str) -> str:
    """
    :param summaries: ranked candidates of one env
    :param env_id: the env
    :return: a markdown table, best candidate first
    """
    lines = [
        f"{env_id} (threshold {configs.ENVS[env_id].threshold:g})",
        "",
        "| rank | candidate | solved | median steps to solve | steps per seed | median train s |",
        "|---|---|---|---|---|---|",
    ]
    for rank, summary in enumerate(summaries, start=1):
        steps = ", ".join("-" if value is None else f"{value:,}" for value in summary.steps)
        lines.append(
            f"| {rank} | {summary.name} | {summary.solved}/{summary.seeds} | {summary.median_steps:,.0f} | {steps} "
            f"| {summary.median_train_seconds:.1f} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """
    Command-line entry point.

    :param argv: arguments (default: ``sys.argv[1:]``)
    :return: exit status (1 if a job failed)
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", required=True, choices=sorted(CANDIDATES))
    parser.add_argument("--candidates", nargs="+", help="candidate names (default: all of each env's)")
    parser.add_argument("--seeds", nargs="+", default=[DEFAULT_TUNING_SEEDS], help="tuning seeds (default 100-101)")
    parser.add_argument("--budget", type=int, help="env-step budget of every job (default: each candidate's)")
    parser.add_argument(
        "--eval-episodes",
        type=int,
        default=configs.N_EVAL_EPISODES,
        help="greedy episodes per evaluation (default 100, the criterion; fewer only for smoke tests)",
    )
    parser.add_argument("--workers", type=int, default=2, help="local worker processes (0: in this process)")
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS, help="JSON-lines results file")
    parser.add_argument("--list", action="store_true", help="list the candidates and exit")
    parser.add_argument("--summary-only", action="store_true", help="rank what the results file holds; run nothing")
    args = parser.parse_args(argv)
    if args.workers < 0:
        parser.error("--workers must be >= 0")

    if args.list:
        for env_id in args.envs:
            for name, kwargs in CANDIDATES[env_id].items():
                print(f"{env_id} {name}: {kwargs}")
        return 0
    failures = 0
    if not args.summary_only:
        command = shlex.join(["python", "-m", "benchmarks.tune_nfq", *argv])
        seeds = parse_seeds(args.seeds)
        jobs = [
            job
            for env_id in args.envs
            for job in candidate_jobs(
                env_id, args.candidates or list(CANDIDATES[env_id]), seeds, args.budget, args.eval_episodes, command
            )
        ]
        _, _, failures = run_jobs(jobs, args.results, args.workers)
    records = read_results(args.results)
    for env_id in args.envs:
        print()
        print(summary_table(summarize(records, env_id), env_id))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
