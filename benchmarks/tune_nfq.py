"""
Tune NFQ per env: run a few candidate configs on tuning seeds, under the benchmark runner's own protocol, and rank
them. A winner becomes an entry of a new named config in ``sb3_nfq/hyperparams/`` (such as ``nfq-tuned.yml``), which
the runner then measures on the benchmark seeds (0-4), which tuning never sees.

    python -m benchmarks.tune_nfq --envs CartPole-v1 [Acrobot-v1 ...] [--candidates NAME ...] [--seeds 100-101]
        [--to-budget] [--workers 2] [--results benchmarks/results/tuning_per_env.jsonl] [--list] [--summary-only]
        [--budget N --eval-episodes N: smoke tests only]

The candidates are data: ``benchmarks/tuning_candidates.yml`` (per env, a name -> a shipped config's entry plus the
keys that differ; its ``every-env`` section: candidates for one config, tried on every env; the file says why each
was tried).

Protocol: each (candidate, env, seed) is one job of ``benchmarks/run.py`` (same greedy evaluations of 100 episodes
every ``eval_every`` steps, on CartPole every 256 (see ``TUNING_EVAL_EVERY``), same threshold, one torch thread, one
spawned process per job). By default a job stops at the solve (the fewest env steps to reach the criterion);
``--to-budget`` trains on to the budget, so that the final score shows whether a candidate stays solved. Results are
appended to their own JSON-lines file (``algo`` = ``tune:<candidate>``), resumable like the runner's.

Ranking, per env: most seeds solved, then most seeds whose final score reaches the threshold, then the lowest median
steps to solve (an unsolved seed counts as the steps it trained), then the lowest median training seconds.
A search this small is affordable on 2 cores; the RL Zoo's Optuna
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

import yaml

from benchmarks import configs
from benchmarks.run import REPO_ROOT, Job, add_job_arguments, git_revision, parse_seeds, read_results, run_jobs
from sb3_nfq.configs import read_entry

DEFAULT_RESULTS = REPO_ROOT / "benchmarks" / "results" / "tuning_per_env.jsonl"
#: The candidates, as data.
CANDIDATES_FILE = REPO_ROOT / "benchmarks" / "tuning_candidates.yml"
#: The candidates file's section of candidates tried on every env of the benchmark, unchanged (one config for all).
EVERY_ENV = "every-env"
#: Seeds for tuning; the benchmark's are 0-4.
DEFAULT_TUNING_SEEDS = "100-101"
#: Prefix of a candidate's ``algo`` in the results file.
ALGO_PREFIX = "tune:"

#: Evaluation period of the tuning jobs where it differs from the benchmark's (``configs.ENVS``). CartPole's
#: sample-efficiency target is also judged on runs evaluated every 256 steps (the shared config's round length, and
#: the period at which DQN's early peaks show), the stricter of its two readings: tune for that one.
TUNING_EVAL_EVERY: dict[str, int] = {"CartPole-v1": 256}


def read_candidates(path: Path = CANDIDATES_FILE) -> dict[str, dict[str, dict[str, Any]]]:
    """
    :param path: the candidates file
    :return: env id -> candidate name -> its entry (``n_timesteps`` included): its ``base`` config's entry for that
        env, updated with the keys the candidate sets. The candidates of the file's :data:`EVERY_ENV` section are
        candidates of each of the benchmark's envs (``configs.ENVS``), as the same keys on each env's entry.
    """
    table = yaml.safe_load(path.read_text())
    every_env = table.pop(EVERY_ENV, None) or {}
    written_per_env = {env_id: dict(table.get(env_id) or {}) for env_id in [*table, *configs.ENVS]}
    candidates: dict[str, dict[str, dict[str, Any]]] = {}
    for env_id, named in written_per_env.items():
        clash = sorted(set(named) & set(every_env))
        if clash:
            raise ValueError(f"{path}: candidates {clash} are both in {EVERY_ENV!r} and under {env_id}")
        for name, written in {**named, **every_env}.items():
            overrides = dict(written)
            if "base" not in overrides:
                raise ValueError(f"{path}: candidate {name!r} of {env_id} names no 'base' config")
            candidates.setdefault(env_id, {})[name] = {**read_entry(overrides.pop("base"), env_id), **overrides}
    return candidates


CANDIDATES = read_candidates()


def candidate_jobs(
    env_id: str,
    names: Sequence[str],
    seeds: Sequence[int],
    budget: int | None = None,
    n_eval_episodes: int = configs.N_EVAL_EPISODES,
    command: str = "",
    stop_at_solve: bool = True,
) -> list[Job]:
    """
    :param env_id: one of :data:`CANDIDATES`' envs
    :param names: candidate names for that env
    :param seeds: tuning seeds
    :param budget: env-step budget of every job (default: each candidate's; smaller only for smoke tests)
    :param n_eval_episodes: greedy episodes per evaluation (fewer only for smoke tests)
    :param command: the command line, recorded with each result
    :param stop_at_solve: stop each job at the solve (otherwise it trains on to the budget)
    :return: one runner job per candidate and seed
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
        candidate_budget = int(kwargs.pop("n_timesteps"))
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
                    stop_at_solve=stop_at_solve,
                    source="benchmarks/tuning_candidates.yml",
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
    :param stayed: seeds whose final score (at the budget, or at the solve for a run stopped there) reaches the
        threshold
    :param median_steps: median env steps to solve (an unsolved seed counts as the steps it trained)
    :param steps: per seed, steps to solve (``None``: not solved)
    :param median_train_seconds: median training seconds (evaluations excluded)
    """

    name: str
    seeds: int
    solved: int
    stayed: int
    median_steps: float
    steps: list[int | None]
    median_train_seconds: float

    @property
    def rank_key(self) -> tuple[float, float, float, float]:
        """:return: sort key of the ranking: most solved, most solved at the end, fewest steps, fewest seconds"""
        return (-self.solved / self.seeds, -self.stayed / self.seeds, self.median_steps, self.median_train_seconds)


def summarize(records: Sequence[dict[str, Any]], env_id: str, to_budget: bool = False) -> list[CandidateSummary]:
    """
    :param records: result lines of the tuning file
    :param env_id: env to summarize
    :param to_budget: summarize the runs trained to the budget (otherwise those stopped at the solve)
    :return: the env's candidates that have results, best first (see the module's ranking)
    """
    by_name: dict[str, list[dict[str, Any]]] = {}
    for record in records:
        if record["env"] == env_id and record["algo"].startswith(ALGO_PREFIX) and record["stop_at_solve"] != to_budget:
            by_name.setdefault(record["algo"].removeprefix(ALGO_PREFIX), []).append(record)
    summaries = []
    for name, runs in by_name.items():
        runs.sort(key=lambda record: record["seed"])
        summaries.append(
            CandidateSummary(
                name=name,
                seeds=len(runs),
                solved=sum(bool(run["solved"]) for run in runs),
                stayed=sum(run["final_score"] >= run["threshold"] for run in runs),
                median_steps=statistics.median(
                    run["steps_to_solve"] if run["solved"] else run["steps_trained"] for run in runs
                ),
                steps=[run["steps_to_solve"] for run in runs],
                median_train_seconds=statistics.median(run["train_seconds"] for run in runs),
            )
        )
    return sorted(summaries, key=lambda summary: summary.rank_key)


def summary_table(summaries: Sequence[CandidateSummary], env_id: str, to_budget: bool = False) -> str:
    """
    :param summaries: ranked candidates of one env
    :param env_id: the env
    :param to_budget: whether the runs trained to the budget (otherwise they stopped at the solve)
    :return: a markdown table, best candidate first
    """
    lines = [
        f"{env_id} (threshold {configs.ENVS[env_id].threshold:g}; "
        + ("trained to the budget)" if to_budget else "stopped at the solve)"),
        "",
        "| rank | candidate | solved | final ≥ threshold | median steps to solve | steps per seed | median train s |",
        "|---|---|---|---|---|---|---|",
    ]
    for rank, summary in enumerate(summaries, start=1):
        steps = ", ".join("-" if value is None else f"{value:,}" for value in summary.steps)
        lines.append(
            f"| {rank} | {summary.name} | {summary.solved}/{summary.seeds} | {summary.stayed}/{summary.seeds} "
            f"| {summary.median_steps:,.0f} | {steps} "
            f"| {summary.median_train_seconds:.1f} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """:param argv: command-line arguments (default: ``sys.argv[1:]``) :return: exit status (1 if a job failed)"""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", required=True, choices=sorted(CANDIDATES))
    parser.add_argument("--candidates", nargs="+", help="candidate names (default: all of each env's)")
    add_job_arguments(parser, default_seeds=DEFAULT_TUNING_SEEDS)
    parser.add_argument(
        "--to-budget", action="store_true", help="train every job to its budget (default: to the solve)"
    )
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS, help="JSON-lines results file")
    parser.add_argument("--list", action="store_true", help="list the candidates and exit")
    parser.add_argument("--summary-only", action="store_true", help="rank what the results file holds; run nothing")
    args = parser.parse_args(argv)

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
                env_id,
                args.candidates or list(CANDIDATES[env_id]),
                seeds,
                args.budget,
                args.eval_episodes,
                command,
                stop_at_solve=not args.to_budget,
            )
        ]
        _, _, failures = run_jobs(jobs, args.results, args.workers)
    records = read_results(args.results)
    for env_id in args.envs:
        print()
        print(summary_table(summarize(records, env_id, args.to_budget), env_id, args.to_budget))
    summary = args.results.with_suffix(".md")
    summary.write_text(summary_file_text(records, args.results.name))
    print(f"\nwrote {summary}")
    return 1 if failures else 0


def summary_file_text(records: Sequence[dict[str, Any]], results_name: str) -> str:
    """
    :param records: result lines of the tuning file
    :param results_name: the tuning file's name
    :return: the ranking of every env and protocol the file holds (written next to it, linked from the README)
    """
    lines = [
        "# Tuning rankings",
        "",
        f"Generated by `python -m benchmarks.tune_nfq --envs ... --summary-only` from `{results_name}` (see "
        "benchmarks/README.md, Per-env tuning, for the ranking and the candidates). Steps per seed in seed order; "
        "training seconds, 1 torch thread per job, are only the last tie-break.",
    ]
    for env_id in CANDIDATES:
        for to_budget in (False, True):
            summaries = summarize(records, env_id, to_budget)
            if summaries:
                lines += ["", "## " + summary_table(summaries, env_id, to_budget)]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
