"""
Turn the runner's JSON lines into ``benchmarks/results/README.md`` and learning-curve PNGs.

    python -m benchmarks.report [--results benchmarks/results/runs.jsonl] [--out-dir benchmarks/results]

With the default results file, it also writes the short summary table into the top-level README (between its
markers).

Per env and algorithm: seeds, success rate, steps to solve (median and IQR; IQM with a 95% stratified-bootstrap
CI from ``rliable``), final greedy score at the budget, training seconds. Runs that never solved count as their
number of trained steps (censored): a statistic that reaches a censored value is a lower bound, shown as ``≥``.
Then the project's targets, each "met", "not met" or "not enough data" (staying solved is judged only on runs trained
on to the budget), and one PNG of learning curves per env (mean greedy return over seeds with a 95% bootstrap band).
The targets are data (``benchmarks/targets.yml``). Runs whose recorded settings are no longer what their config
name holds (recorded before configs became files that are never edited) get a table of their own under their env,
and are left out of the targets and the plots. Runs of the runner's ``--protocol book`` (``--book-results``) get a
table of their own beside the book's printed numbers, with the ratio of medians and a Mann-Whitney test between
implementations.
"""

import argparse
import functools
import json
import math
import shlex
import sys
import warnings
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import yaml

from benchmarks import configs, readme_blocks
from benchmarks.run import DEFAULT_BOOK_RESULTS, DEFAULT_RESULTS, REPO_ROOT, jobs_at_once, read_results
from benchmarks.scaling import DEFAULT_OUT as DEFAULT_SCALING
from benchmarks.scaling import spread as scaling_spread
from benchmarks.scaling import table as scaling_table

BOOTSTRAP_REPS = 2000
#: A config "solves" an env when at least this fraction of its seeds solved it (4/5).
SOLVE_FRACTION = 0.8
#: Seeds needed before a target is judged.
MIN_SEEDS = 5
#: The targets, as data.
TARGETS_FILE = REPO_ROOT / "benchmarks" / "targets.yml"
#: The book's own NFQ table on CartPole-v1 ("Grokking Deep Reinforcement Learning", chapter 8): its seeds and the
#: means it prints over them, under its own criterion (the runner's ``--protocol book``).
BOOK_SEEDS = (12, 34, 56, 78, 90)
BOOK_MEAN_STEPS = 233_918
BOOK_MEAN_EPISODES = 2_344
#: The two implementations the book-protocol table compares: the ratio is ``BOOK_PAIR[0] / BOOK_PAIR[1]``.
BOOK_PAIR = ("nfq-book", "reference-nfq")
#: Significance level of the Mann-Whitney test between them.
BOOK_ALPHA = 0.05
#: Seeds per implementation before the test is judged.
BOOK_MIN_SEEDS = 15


# --- statistics -------------------------------------------------------------------------------------------------


@functools.cache
def _rliable_library() -> ModuleType | str:
    """:return: ``rliable.library``, or why it cannot be imported (it needs ``arch``, whose 7.x breaks on pandas 3)"""
    try:
        from rliable import library

        return library
    except Exception as error:
        return f"{type(error).__name__}: {error}"


def iqm_with_ci(values: np.ndarray, seed: int = 0) -> tuple[float, float, float]:
    """
    :param values: one value per run
    :param seed: bootstrap seed
    :return: the interquartile mean (``rliable.metrics.aggregate_iqm``) and its 95% percentile-bootstrap CI
        (``rliable.library.get_interval_estimates``, runs resampled with replacement; if ``rliable.library`` cannot
        be imported, the same bootstrap done here with ``aggregate_iqm``)
    """
    from rliable import metrics

    scores = np.asarray(values, dtype=float).reshape(-1, 1)  # (runs, tasks=1), rliable's layout
    point = float(metrics.aggregate_iqm(scores))
    if len(scores) < 2:
        return point, point, point
    library = _rliable_library()
    if isinstance(library, ModuleType):
        # rliable 1.2's StratifiedBootstrap draws its resamples with the global np.random.choice, whatever
        # random_state says: without seeding the global generator here, a cell's CI depended on what the report
        # had computed before it (the row order of the results file). Seed it per call, then restore it.
        global_state = np.random.get_state()
        np.random.seed(seed)
        try:
            with warnings.catch_warnings():  # arch deprecates random_state; rliable 1.2 still passes it
                warnings.simplefilter("ignore", FutureWarning)
                _, intervals = library.get_interval_estimates(
                    {"x": scores},
                    lambda x: np.array([metrics.aggregate_iqm(x)]),
                    reps=BOOTSTRAP_REPS,
                    random_state=np.random.RandomState(seed),
                )
        finally:
            np.random.set_state(global_state)
        return point, float(intervals["x"][0, 0]), float(intervals["x"][1, 0])
    rng = np.random.default_rng(seed)
    resampled = [
        metrics.aggregate_iqm(scores[rng.integers(len(scores), size=len(scores))]) for _ in range(BOOTSTRAP_REPS)
    ]
    low, high = np.percentile(resampled, [2.5, 97.5])
    return point, float(low), float(high)


def ci_method() -> str:
    """:return: how the IQM confidence intervals are computed, for the report"""
    library = _rliable_library()
    if isinstance(library, ModuleType):
        return f"rliable `get_interval_estimates` (percentile bootstrap over runs, {BOOTSTRAP_REPS} resamples)"
    return (
        f"percentile bootstrap over runs with rliable's `aggregate_iqm`, {BOOTSTRAP_REPS} resamples "
        f"(rliable.library could not be imported: {library})"
    )


@dataclass
class Cell:
    """The runs of one algorithm config on one env (one budget, one config hash), one per seed."""

    env: str
    algo: str
    budget: int
    config_hash: str
    runs: list[dict[str, Any]]
    label: str = ""
    #: The runs' recorded settings are not what the config name holds today.
    superseded: bool = False

    @property
    def n(self) -> int:
        """:return: number of runs (seeds)"""
        return len(self.runs)

    def steps(self) -> tuple[np.ndarray, np.ndarray]:
        """:return: steps to solve per run (unsolved: steps trained) and whether each is censored (unsolved)"""
        censored = np.array([run["steps_to_solve"] is None for run in self.runs])
        steps = np.array(
            [run["steps_trained"] if run["steps_to_solve"] is None else run["steps_to_solve"] for run in self.runs],
            dtype=float,
        )
        return steps, censored

    def steps_quantile(self, q: float) -> tuple[float, bool]:
        """
        :param q: quantile in [0, 100]
        :return: the quantile of the steps to solve, and whether it is only a lower bound (reaches an unsolved run)
        """
        steps, censored = self.steps()
        value = float(np.percentile(steps, q))
        return value, bool(censored.any() and value >= steps[censored].min())

    def success_rate(self) -> float:
        """:return: fraction of runs that solved"""
        return float(np.mean([run["steps_to_solve"] is not None for run in self.runs]))

    def n_diverged(self) -> int:
        """:return: how many runs stopped on a diverged (non-finite) loss"""
        return sum(bool(run.get("diverged")) for run in self.runs)

    def final_scores(self) -> np.ndarray:
        """:return: final greedy score of each run"""
        return np.array([run["final_score"] for run in self.runs], dtype=float)

    def protocol(self) -> str:
        """:return: the evaluation period, and whether the runs stopped at the solve (final score at the solve)"""
        periods = ", ".join(f"{period:,}" for period in sorted({int(run["eval_every"]) for run in self.runs}))
        return f"{periods} steps" + (" (stopped at solve)" if self.stop_at_solve else "")

    @property
    def stop_at_solve(self) -> bool:
        """:return: whether the runs stopped at their solve"""
        return any(run.get("stop_at_solve") for run in self.runs)

    @property
    def eval_every(self) -> int:
        """:return: the evaluation period of the runs (the largest, should they differ)"""
        return max(int(run["eval_every"]) for run in self.runs)

    def train_seconds(self) -> np.ndarray:
        """:return: training seconds (evaluation excluded) of each run"""
        return np.array([run["train_seconds"] for run in self.runs], dtype=float)


def current_config(algo: str, env: str) -> dict[str, Any] | None:
    """
    :return: the kwargs ``algo`` runs with on ``env`` today, as recorded in a result line's ``config``; ``None`` when
        the runner has no such config (a tuning candidate, an env without an entry, ``dqn-zoo`` without rl_zoo3)
    """
    try:
        kwargs = configs.resolve(algo, env).kwargs
    except (KeyError, ModuleNotFoundError):
        return None
    return dict(json.loads(json.dumps(kwargs)))


def build_cells(records: Sequence[dict[str, Any]]) -> dict[str, list[Cell]]:
    """
    :param records: result lines
    :return: env -> cells, in :data:`configs.ENVS` then algorithm order, superseded cells (whose recorded settings
        are not what their config name holds today) last; within a (env, algo), the cell with the most seeds first
        (the one targets use). A seed that appears twice in a cell keeps its last line.
    """
    grouped: dict[tuple[str, str, int, str], dict[int, dict[str, Any]]] = defaultdict(dict)
    for record in records:
        grouped[(record["env"], record["algo"], int(record["budget"]), record["config_hash"])][record["seed"]] = record
    by_env: dict[str, list[Cell]] = defaultdict(list)
    current_by_env: dict[str, dict[str, dict[str, Any] | None]] = {}  # env -> algo -> its current config there
    for (env, algo, budget, config_hash), runs in grouped.items():
        cell = Cell(env, algo, budget, config_hash, [runs[seed] for seed in sorted(runs)])
        if env not in current_by_env:
            current_by_env[env] = {name: current_config(name, env) for name in configs.algorithm_names()}
        current = current_by_env[env].get(algo)
        recorded = cell.runs[0].get("config")
        cell.superseded = current is not None and recorded != current
        by_env[env].append(cell)
    env_order: dict[str, int] = {}
    for env in [*configs.ENVS, *sorted(by_env)]:
        env_order.setdefault(env, len(env_order))
    algo_order = {algo: index for index, algo in enumerate(configs.algorithm_names())}
    result = {}
    for env in sorted(by_env, key=lambda name: env_order[name]):
        cells = sorted(
            by_env[env],
            key=lambda cell: (cell.superseded, algo_order.get(cell.algo, len(algo_order)), cell.algo, -cell.n),
        )
        for cell in cells:
            same_algo = [other for other in cells if other.algo == cell.algo and other.superseded == cell.superseded]
            cell.label = _distinct_label(cell, same_algo)
        result[env] = cells
    return result


def _distinct_label(cell: Cell, same_algo: Sequence[Cell]) -> str:
    """
    :param same_algo: the cells of the same algorithm on the env, superseded or not like ``cell``
    :return: the algorithm name, plus what tells this cell apart from the algorithm's other cells on the env
    """
    details = []
    if cell.superseded:
        details.append(f"config {cell.config_hash}, since changed")
    if len(same_algo) == 1:
        return f"{cell.algo} ({details[0]})" if details else cell.algo
    if len({other.budget for other in same_algo}) > 1:
        details.append(f"budget {cell.budget:,}")
    if len({other.eval_every for other in same_algo}) > 1:
        details.append(f"evaluated every {cell.eval_every:,}")
    if len({other.stop_at_solve for other in same_algo}) > 1:
        details.append("stopped at solve" if cell.stop_at_solve else "to the budget")
    if len({(other.budget, other.eval_every, other.stop_at_solve) for other in same_algo}) < len(same_algo):
        details.append(f"config {cell.config_hash}")
    return f"{cell.algo} ({', '.join(details)})"


def primary_cell(
    cells_by_env: dict[str, list[Cell]],
    env: str,
    algo: str,
    eval_every: int | None = None,
    to_the_budget: bool = False,
) -> Cell | None:
    """
    :param eval_every: only cells evaluated with this period (default: any)
    :param to_the_budget: only cells whose runs trained on to the budget (not stopped at the solve)
    :return: the cell of ``algo`` on ``env`` with the most seeds, if any
    """
    cells = [
        cell
        for cell in current_cells(cells_by_env, env)
        if cell.algo == algo
        and (eval_every is None or cell.eval_every == eval_every)
        and not (to_the_budget and cell.stop_at_solve)
    ]
    return max(cells, key=lambda cell: cell.n) if cells else None


def current_cells(cells_by_env: dict[str, list[Cell]], env: str) -> list[Cell]:
    """:return: the env's cells that ran the algorithms' current configs (the ones targets and plots use)"""
    return [cell for cell in cells_by_env.get(env, []) if not cell.superseded]


# --- formatting -------------------------------------------------------------------------------------------------


def _steps(value: float, lower_bound: bool) -> str:
    return f"{'≥' if lower_bound else ''}{value:,.0f}"


def table_rows(cells: Sequence[Cell]) -> list[str]:
    """:return: the markdown table of one env"""
    rows = [
        "| algorithm | seeds | budget | evaluated every | success | steps to solve: median [IQR] | IQM [95% CI] | "
        "final score: mean ± sd (≥ threshold) | train s: median [IQR] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for cell in cells:
        median, median_bound = cell.steps_quantile(50)
        q1, q1_bound = cell.steps_quantile(25)
        q3, q3_bound = cell.steps_quantile(75)
        steps, censored = cell.steps()
        iqm, low, high = iqm_with_ci(steps)
        iqm_bound = int(censored.sum()) > math.floor(0.25 * cell.n)
        scores = cell.final_scores()
        threshold = cell.runs[0]["threshold"]
        seconds = cell.train_seconds()
        s1, s2, s3 = np.percentile(seconds, [25, 50, 75])
        diverged = f" ({cell.n_diverged()} diverged)" if cell.n_diverged() else ""
        rows.append(
            f"| {cell.label} | {cell.n} | {cell.budget:,} | {cell.protocol()} | {cell.success_rate():.0%}{diverged} "
            f"| {_steps(median, median_bound)} [{_steps(q1, q1_bound)}, {_steps(q3, q3_bound)}] "
            f"| {_steps(iqm, iqm_bound)} [{low:,.0f}, {high:,.0f}] "
            f"| {scores.mean():.1f} ± {scores.std():.1f} ({int((scores >= threshold).sum())}/{cell.n}) "
            f"| {s2:.1f} [{s1:.1f}, {s3:.1f}] |"
        )
    return rows


#: The top-level README's markers around the summary table.
SUMMARY_MARKERS = (
    "<!-- results-summary:start (generated by python -m benchmarks.report) -->",
    "<!-- results-summary:end -->",
)


def summary_cell(cells_by_env: dict[str, list[Cell]], env: str, algo: str) -> Cell | None:
    """
    :return: the cell that stands for ``algo`` on ``env`` in the summary: evaluated at the env's own period if any
        is, then the one with the most seeds, then one trained to the budget
    """
    cells = [cell for cell in current_cells(cells_by_env, env) if cell.algo == algo]
    if not cells:
        return None
    own_period = configs.ENVS[env].eval_every if env in configs.ENVS else None
    return max(cells, key=lambda cell: (cell.eval_every == own_period, cell.n, not cell.stop_at_solve))


def summary_table(cells_by_env: dict[str, list[Cell]]) -> str:
    """:return: the README's short results table: one row per env and config (see :func:`summary_cell`)"""
    lines = [
        "| env | config | seeds | evaluated every | trained | solved | steps to solve: median "
        "| final score ≥ threshold | train s: median |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for env in cells_by_env:
        for algo in configs.algorithm_names():
            cell = summary_cell(cells_by_env, env, algo)
            if cell is None:
                continue
            median, bound = cell.steps_quantile(50)
            solved = sum(run["steps_to_solve"] is not None for run in cell.runs)
            final = int((cell.final_scores() >= cell.runs[0]["threshold"]).sum())
            trained = "to the solve" if cell.stop_at_solve else f"to {cell.budget:,} steps"
            lines.append(
                f"| {env} | {algo} | {cell.n} | {cell.eval_every:,} | {trained} | {solved}/{cell.n} "
                f"| {_steps(median, bound)} | {final}/{cell.n} | {float(np.median(cell.train_seconds())):.0f} |"
            )
    return "\n".join(lines)


# --- targets ----------------------------------------------------------------------------------------------------


def _median_interval(cell: Cell) -> tuple[float, float]:
    """:return: the range the true median steps to solve lies in (upper end inf when censored)"""
    value, bound = cell.steps_quantile(50)
    return value, math.inf if bound else value


def common_eval_periods(cells_by_env: dict[str, list[Cell]], env: str, algos: Sequence[str]) -> list[int | None]:
    """
    :return: the evaluation periods at which every one of ``algos`` has runs on ``env`` (steps to solve are only
        comparable at the same period: a finer grid catches earlier, possibly transient, solves); ``[None]`` if none
    """
    periods = [{cell.eval_every for cell in current_cells(cells_by_env, env) if cell.algo == algo} for algo in algos]
    common = sorted(set.intersection(*periods)) if periods else []
    return [*common] if common else [None]


def median_ratio_ci(num: Cell, den: Cell, seed: int = 0, n_resamples: int = 10_000) -> tuple[float, float]:
    """
    Percentile bootstrap of ``median steps(num) / median steps(den)``: the runs of each cell are resampled with
    replacement, independently (censored runs count as the steps they trained).

    :return: the 95% confidence interval of the ratio
    """
    rng = np.random.default_rng(seed)
    num_steps, den_steps = num.steps()[0], den.steps()[0]
    num_medians = np.median(rng.choice(num_steps, (n_resamples, len(num_steps))), axis=1)
    den_medians = np.median(rng.choice(den_steps, (n_resamples, len(den_steps))), axis=1)
    low, high = np.percentile(num_medians / den_medians, [2.5, 97.5])
    return float(low), float(high)


def ratio_target(
    cells_by_env: dict[str, list[Cell]],
    env: str,
    numerator: str,
    denominator: str,
    low: float,
    high: float,
    eval_every: int | None = None,
) -> tuple[str, str]:
    """
    Judge ``median steps(numerator) / median steps(denominator)`` against ``[low, high]``. Censored medians make the
    ratio an interval; the target is met/not met only when the whole interval is inside/outside the range.

    :param eval_every: compare the cells evaluated with this period (default: the cells with the most seeds)
    :return: (verdict, the ratio as text)
    """
    num = primary_cell(cells_by_env, env, numerator, eval_every)
    den = primary_cell(cells_by_env, env, denominator, eval_every)
    if num is None or den is None or num.n < MIN_SEEDS or den.n < MIN_SEEDS:
        have = f"{numerator}: {num.n if num else 0} seeds, {denominator}: {den.n if den else 0} seeds"
        return "not enough data", f"needs {MIN_SEEDS} seeds each ({have})"
    num_low, num_high = _median_interval(num)
    den_low, den_high = _median_interval(den)
    ratio_low = num_low / den_high if den_high < math.inf else 0.0
    ratio_high = num_high / den_low
    if ratio_low == ratio_high:
        ci_low, ci_high = median_ratio_ci(num, den)
        text = (
            f"{ratio_low:.2f} ({num_low:,.0f} / {den_low:,.0f}; 95% bootstrap CI of the ratio "
            f"{ci_low:.2f}-{ci_high:.2f})"
        )
    elif ratio_high == math.inf and ratio_low > 0:
        text = f"≥ {ratio_low:.2f} (median of {numerator} did not solve)"
    elif ratio_low == 0 and ratio_high < math.inf:
        text = f"≤ {ratio_high:.2f} (median of {denominator} did not solve)"
    else:
        text = "unknown: neither median solved"
    if low <= ratio_low and ratio_high <= high:
        return "met", text
    if ratio_high < low or ratio_low > high:
        return "not met", text
    return "not enough data", text


def solved_envs_target(cells_by_env: dict[str, list[Cell]], algo: str, at_least: int) -> tuple[str, str]:
    """:return: (verdict, text) for "``algo`` solves at least ``at_least`` envs, each in >= 4/5 seeds" """
    solved, unknown, parts = 0, 0, []
    for env in configs.ENVS:
        cell = primary_cell(cells_by_env, env, algo)
        if cell is None or cell.n < MIN_SEEDS:
            unknown += 1
            parts.append(f"{env}: {cell.n if cell else 0} seeds")
        else:
            ok = cell.success_rate() >= SOLVE_FRACTION
            solved += ok
            parts.append(f"{env}: {sum(run['solved'] for run in cell.runs)}/{cell.n}")
    text = f"{solved} of {len(configs.ENVS)} envs solved in ≥ 4/5 seeds ({'; '.join(parts)})"
    if solved >= at_least:
        return "met", text
    if solved + unknown < at_least:
        return "not met", text
    return "not enough data", text


def final_score_target(
    cells_by_env: dict[str, list[Cell]], env: str, algo: str, eval_every: int | None = None
) -> tuple[str, str]:
    """
    :return: (verdict, text) for "final score at the budget >= threshold in >= 4/5 seeds", judged on runs that
        trained on to the budget (a run stopped at its solve says nothing of staying solved)
    """
    cell = primary_cell(cells_by_env, env, algo, eval_every, to_the_budget=True)
    if cell is None or cell.n < MIN_SEEDS:
        return "not enough data", f"needs {MIN_SEEDS} seeds run to the budget ({cell.n if cell else 0})"
    scores = cell.final_scores()
    threshold = cell.runs[0]["threshold"]
    passed = int((scores >= threshold).sum())
    text = f"{passed}/{cell.n} seeds with final score ≥ {threshold:g} (scores {', '.join(f'{s:.0f}' for s in scores)})"
    return ("met" if passed / cell.n >= SOLVE_FRACTION else "not met"), text


def _period_note(eval_every: int | None) -> str:
    return "" if eval_every is None else f" (runs evaluated every {eval_every:,} steps)"


def read_targets(path: Path = TARGETS_FILE) -> list[dict[str, Any]]:
    """
    :param path: the targets file: targets, and groups ``{algos: [...], targets: [...]}`` that state targets once for
        several algorithms (each of the group's targets, without ``algo``, is judged for each algorithm in turn)
    :return: its targets, groups expanded in order, each checked to be of a known kind with the keys that kind needs
    """
    needs = {
        "steps_ratio": {"algo", "baseline", "env", "high"},
        "final_score": {"algo", "env"},
        "solved_envs": {"algo", "at_least"},
        "flat_fit_cost": {"mode", "tolerance"},
        "seconds_ratio": {"algo", "baseline", "envs", "high"},
    }
    optional = {"steps_ratio": {"low"}}
    targets: list[dict[str, Any]] = []
    for entry in yaml.safe_load(path.read_text()):
        if "kind" in entry:
            targets.append(entry)
            continue
        if set(entry) != {"algos", "targets"} or not entry["algos"] or not entry["targets"]:
            raise ValueError(
                f"{path}: an entry without 'kind' is a group, which takes a non-empty 'algos' list and 'targets' list, "
                f"got {sorted(entry)}"
            )
        for target in entry["targets"]:
            if "algo" in target:
                raise ValueError(f"{path}: a group's target takes its 'algo' from the group's 'algos', got {target}")
        targets.extend({**target, "algo": algo} for algo in entry["algos"] for target in entry["targets"])
    for target in targets:
        kind = target.get("kind")
        if kind not in needs:
            raise ValueError(f"{path}: unknown target kind {kind!r}; known: {sorted(needs)}")
        keys = set(target) - {"kind"}
        if not needs[kind] <= keys <= needs[kind] | optional.get(kind, set()):
            raise ValueError(
                f"{path}: a {kind} target takes {sorted(needs[kind])} (optional: {sorted(optional.get(kind, []))}), "
                f"got {sorted(keys)}"
            )
    return targets


def side_by_side(records: Sequence[dict[str, Any]], env: str, algo: str, baseline: str) -> tuple[Cell, Cell] | None:
    """
    :param records: result lines
    :param env: env id
    :param algo: the config measured
    :param baseline: the config it is compared with
    :return: the runs of ``algo`` and ``baseline`` on ``env`` trained to the budget by one runner command (so on the
        same machine in the same session), the command with the most seeds of both and, among those, the fewest
        worker processes (jobs sharing the cores slow NFQ's full-memory fits more than DQN's small batches, and one
        job at a time is how a user trains); ``None`` if no command ran both
    """
    by_command: dict[str, dict[str, list[dict[str, Any]]]] = defaultdict(lambda: defaultdict(list))
    for record in records:
        if record["env"] == env and record["algo"] in (algo, baseline) and not record.get("stop_at_solve"):
            by_command[record["command"]][record["algo"]].append(record)
    both = [runs for runs in by_command.values() if runs[algo] and runs[baseline]]
    if not both:
        return None
    runs = max(
        both,
        key=lambda runs: (min(len(runs[algo]), len(runs[baseline])), -_workers([*runs[algo], *runs[baseline]])),
    )
    num, den = (
        Cell(env, name, runs[name][0]["budget"], runs[name][0]["config_hash"], runs[name]) for name in (algo, baseline)
    )
    return num, den


def _workers(records: Sequence[dict[str, Any]]) -> int:
    """
    :param records: result lines of one runner command
    :return: the most jobs that ran at once for them (see :func:`benchmarks.run.jobs_at_once`); a Ray cluster's
        count is unknown and counts as the most
    """
    return max(sys.maxsize if (jobs := jobs_at_once(record)) is None else jobs for record in records)


def seconds_ratio_target(
    records: Sequence[dict[str, Any]], envs: Sequence[str], algo: str, baseline: str, high: float
) -> tuple[str, str]:
    """
    :param records: result lines
    :param envs: env ids
    :param algo: the config measured
    :param baseline: the config it is compared with
    :param high: the largest ratio that meets the target
    :return: (verdict, text) for "median training seconds to the budget of ``algo`` / of ``baseline`` <= ``high`` on
        every env of ``envs``", each pair run side by side (see :func:`side_by_side`)
    """
    parts, verdicts = [], []
    for env in envs:
        pair = side_by_side(records, env, algo, baseline)
        if pair is None or min(pair[0].n, pair[1].n) < MIN_SEEDS:
            have = f"{min(pair[0].n, pair[1].n)} seeds" if pair else "none"
            parts.append(f"{env}: needs {MIN_SEEDS} seeds of both run to the budget by one command ({have})")
            verdicts.append("not enough data")
            continue
        num, den = (float(np.median(cell.train_seconds())) for cell in pair)
        workers = _workers([*pair[0].runs, *pair[1].runs])
        ran = "on a Ray cluster" if workers == sys.maxsize else f"{workers} job{'s' if workers > 1 else ''} at a time"
        parts.append(f"{env}: {num / den:.2f} ({num:.0f} s / {den:.0f} s, {pair[0].n} seeds, {ran})")
        verdicts.append("met" if num / den <= high else "not met")
    verdict = "not met" if "not met" in verdicts else "not enough data" if "not enough data" in verdicts else "met"
    return verdict, "; ".join(parts)


def flat_fit_cost_target(scaling: dict[str, Any] | None, mode: str, tolerance: float) -> tuple[str, str]:
    """
    :param scaling: the scaling run (``benchmarks.scaling``'s JSON), if any
    :param mode: a mode of that run
    :param tolerance: the largest relative departure from the mean that meets the target
    :return: (verdict, text) for "the mode's fit seconds per 1,000 steps stay within ``tolerance`` of their mean"
    """
    if scaling is None or mode not in scaling["bins"]:
        return "not enough data", f"no scaling run of {mode}"
    rows = scaling["bins"][mode]
    if rows[-1]["memory_up_to"] < 200_000:
        return "not enough data", f"the run reached {rows[-1]['memory_up_to']:,} transitions, not 200,000"
    spread = scaling_spread(rows)
    values = ", ".join(f"{row['per_1000_steps']:.2f}" for row in rows)
    text = f"largest departure from the mean {spread:.0%} (bins: {values})"
    return ("met" if spread <= tolerance else "not met"), text


def judge(
    cells_by_env: dict[str, list[Cell]],
    target: dict[str, Any],
    scaling: dict[str, Any] | None = None,
    records: Sequence[dict[str, Any]] = (),
) -> list[tuple[str, tuple[str, str]]]:
    """
    :param target: one target of the targets file
    :param scaling: the scaling run, for ``flat_fit_cost`` targets
    :param records: the result lines, for ``seconds_ratio`` targets
    :return: (what the target says, (verdict, measured)) for each reading of it (one per evaluation period)
    """
    if target["kind"] == "seconds_ratio":
        envs = list(configs.ENVS) if target["envs"] == "all" else list(target["envs"])
        name = (
            f"{target['algo']} / {target['baseline']} median training seconds to the budget ≤ {target['high']:g}, "
            f"run side by side, on {', '.join(envs)}"
        )
        return [(name, seconds_ratio_target(records, envs, target["algo"], target["baseline"], target["high"]))]
    if target["kind"] == "flat_fit_cost":
        name = (
            f"{target['mode']}: fit seconds per 1,000 env steps within ±{target['tolerance']:.0%} of their mean, "
            "memory 10k-200k"
        )
        return [(name, flat_fit_cost_target(scaling, target["mode"], float(target["tolerance"])))]
    algo = target["algo"]
    if target["kind"] == "solved_envs":
        name = f"{algo} (one config) solves ≥ {target['at_least']} of the {len(configs.ENVS)} envs in ≥ 4/5 seeds"
        return [(name, solved_envs_target(cells_by_env, algo, target["at_least"]))]
    env = target["env"]
    if target["kind"] == "final_score":
        threshold = configs.ENVS[env].threshold
        return [
            (
                f"{algo} final score at budget ≥ {threshold:g} on {env} in ≥ 4/5 seeds" + _period_note(period),
                final_score_target(cells_by_env, env, algo, period),
            )
            for period in common_eval_periods(cells_by_env, env, [algo])
        ]
    baseline, low, high = target["baseline"], float(target.get("low", 0.0)), float(target["high"])
    bound = f"within {low:g} to {high:g}" if low > 0 else f"≤ {high:g}"
    return [
        (
            f"{algo} / {baseline} median steps to solve on {env} {bound}" + _period_note(period),
            ratio_target(cells_by_env, env, algo, baseline, low, high, period),
        )
        for period in common_eval_periods(cells_by_env, env, [algo, baseline])
    ]


def target_lines(
    cells_by_env: dict[str, list[Cell]],
    targets: Sequence[dict[str, Any]],
    scaling: dict[str, Any] | None = None,
    records: Sequence[dict[str, Any]] = (),
) -> list[str]:
    """:return: the markdown lines of the targets section"""
    lines = ["| target | verdict | measured |", "|---|---|---|"]
    for target in targets:
        for name, (verdict, text) in judge(cells_by_env, target, scaling, records):
            lines.append(f"| {name} | **{verdict}** | {text} |")
    return lines


# --- learning curves --------------------------------------------------------------------------------------------


def plot_curves(env: str, cells: Sequence[Cell], path: Path, seed: int = 0) -> None:
    """
    One PNG: per cell, the mean greedy return over seeds (curves interpolated on a common step grid, each run only
    up to its last evaluation) with a 95% bootstrap band over seeds; the threshold as a dashed line. The mean is
    drawn while at least half of the cell's runs are still training: past that (runs stopped at their solve) it
    would average the few runs left, the slowest, and fall.

    :param env: env id (title)
    :param cells: the env's cells
    :param path: where to write the PNG
    :param seed: bootstrap seed
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(seed)
    figure, axes = plt.subplots(figsize=(8, 4.5))
    for cell in cells:
        curves = [np.asarray(run["curve"], dtype=float) for run in cell.runs if run["curve"]]
        if not curves:
            continue
        last = max(curve[-1, 0] for curve in curves)
        grid = np.linspace(0, last, 200)
        values = np.full((len(curves), len(grid)), np.nan)
        for row, curve in zip(values, curves, strict=True):
            inside = grid <= curve[-1, 0]
            row[inside] = np.interp(grid[inside], curve[:, 0], curve[:, 1])
        counts = np.sum(~np.isnan(values), axis=0)
        keep = counts >= len(curves) / 2
        mean = np.nanmean(values[:, keep], axis=0)
        resamples = values[rng.integers(len(curves), size=(BOOTSTRAP_REPS // 4, len(curves)))][:, :, keep]
        with warnings.catch_warnings():  # a resample may hold no run that reached a step: its mean is NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            means = np.nanmean(resamples, axis=1)
            low, high = np.nanpercentile(means, [2.5, 97.5], axis=0)
        (line,) = axes.plot(grid[keep], mean, label=f"{cell.label} (n={cell.n})")
        axes.fill_between(grid[keep], low, high, color=line.get_color(), alpha=0.2)
    threshold = cells[0].runs[0]["threshold"] if cells else None
    if threshold is not None:
        axes.axhline(threshold, color="black", linestyle="--", linewidth=1, label=f"threshold {threshold:g}")
    axes.set_title(f"{env}: mean greedy return over seeds, 95% bootstrap CI", fontsize="medium")
    axes.set_xlabel("environment steps")
    axes.set_ylabel("greedy return (mean of 100 episodes)")
    axes.legend(fontsize="small")
    axes.grid(alpha=0.3)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)


# --- the report -------------------------------------------------------------------------------------------------


def curve_filename(env: str) -> str:
    """:return: the PNG name of an env's learning curves"""
    return f"curves_{env}.png"


def _unique(records: Sequence[dict[str, Any]], key: str) -> list[Any]:
    seen: dict[str, Any] = {}
    for record in records:
        value = record.get(key)
        seen.setdefault(repr(value), value)
    return list(seen.values())


def book_cells(records: Sequence[dict[str, Any]]) -> list[Cell]:
    """
    :param records: result lines of the runner's ``--protocol book`` on CartPole-v1
    :return: one cell per algorithm, in :data:`BOOK_PAIR` order then others; each run once per seed (the latest)
    """
    by_algo: dict[str, dict[int, dict[str, Any]]] = defaultdict(dict)
    for record in records:
        if record.get("protocol") == "book" and record["env"] == "CartPole-v1":
            by_algo[record["algo"]][int(record["seed"])] = record
    order = [algo for algo in BOOK_PAIR if algo in by_algo] + sorted(set(by_algo) - set(BOOK_PAIR))
    cells = []
    for algo in order:
        runs = [by_algo[algo][seed] for seed in sorted(by_algo[algo])]
        cells.append(Cell("CartPole-v1", algo, int(runs[0]["budget"]), runs[0]["config_hash"], runs, label=algo))
    return cells


def _episodes(cell: Cell) -> np.ndarray:
    """:return: training episodes to solve per run (unsolved: episodes trained)"""
    return np.array(
        [run["episodes_to_solve"] or run["episodes_trained"] for run in cell.runs],
        dtype=float,
    )


def mann_whitney(num: Cell, den: Cell) -> float:
    """
    :return: the two-sided Mann-Whitney U test's p-value for the steps to solve of the two cells (an unsolved run
        counts as the steps it trained, i.e. more than any run that solved within a smaller budget)
    """
    from scipy.stats import mannwhitneyu

    return float(mannwhitneyu(num.steps()[0], den.steps()[0], alternative="two-sided").pvalue)


def book_protocol_lines(records: Sequence[dict[str, Any]]) -> list[str]:
    """:return: the report's section on the book's criterion (empty without such runs)"""
    cells = book_cells(records)
    if not cells:
        return []
    book_seeds = BOOK_SEEDS
    lines = [
        "## CartPole-v1 under the book's criterion",
        "",
        "The book's own protocol (`python -m benchmarks.run --protocol book`, `sb3_nfq.StopTrainingOnBookCriterion`): "
        "after every training episode the greedy policy plays one episode on a separate env; a run is solved, and "
        "stops, when the mean of the last 100 of those returns reaches 475. Steps and episodes are counted to that "
        "point; an unsolved run counts as what it trained (≥). Training seconds exclude the evaluation episodes; the "
        "final score is 100 new greedy episodes after training. Both implementations run the textbook settings.",
        "",
        "Runner command(s): "
        + "; ".join(f"`{command}`" for command in _unique(list(records), "command"))
        + ". Torch threads per job: "
        + ", ".join(str(threads) for threads in _unique(list(records), "torch_threads"))
        + "; launcher: "
        + ", ".join(str(launcher) for launcher in _unique(list(records), "launcher"))
        + ".",
        "",
        "| implementation | seeds | solved | env steps: mean | median [min, max] | episodes: mean | median "
        "| train s: median | final score: mean |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| the book, as printed (seeds {', '.join(map(str, book_seeds))}) | {len(book_seeds)} | — "
        f"| {BOOK_MEAN_STEPS:,} | — | {BOOK_MEAN_EPISODES:,} | — | — | — |",
    ]
    for subset_name, subset in (("the book's seeds", set(book_seeds)), ("all seeds", None)):
        for cell in cells:
            runs = [run for run in cell.runs if subset is None or int(run["seed"]) in subset]
            if not runs:
                continue
            part = Cell(cell.env, cell.algo, cell.budget, cell.config_hash, runs)
            steps, censored = part.steps()
            episodes = _episodes(part)
            bound = "≥" if censored.any() else ""
            seeds = ", ".join(str(run["seed"]) for run in runs) if subset is not None else f"{part.n} seeds"
            median, median_bound = part.steps_quantile(50)
            lines.append(
                f"| {cell.algo}, {subset_name} ({seeds}) | {part.n} | {int((~censored).sum())}/{part.n} "
                f"| {bound}{steps.mean():,.0f} | {_steps(median, median_bound)} [{steps.min():,.0f}, "
                f"{bound}{steps.max():,.0f}] | {bound}{episodes.mean():,.0f} | {bound}{np.median(episodes):,.0f} "
                f"| {np.median(part.train_seconds()):.1f} | {part.final_scores().mean():.1f} |"
            )
    against_book = []
    for cell in cells:
        runs = [run for run in cell.runs if int(run["seed"]) in set(book_seeds)]
        if len(runs) == len(book_seeds):
            part = Cell(cell.env, cell.algo, cell.budget, cell.config_hash, runs)
            steps_ratio = part.steps()[0].mean() / BOOK_MEAN_STEPS
            episodes_ratio = _episodes(part).mean() / BOOK_MEAN_EPISODES
            against_book.append(f"{cell.algo} {steps_ratio:.2f}x its steps and {episodes_ratio:.2f}x its episodes")
    if against_book:
        lines += [
            "",
            "Mean over the book's five seeds, against the book's printed means: " + "; ".join(against_book) + ".",
        ]
    by_algo = {cell.algo: cell for cell in cells}
    if all(algo in by_algo for algo in BOOK_PAIR):
        num, den = by_algo[BOOK_PAIR[0]], by_algo[BOOK_PAIR[1]]
        ratio = num.steps_quantile(50)[0] / den.steps_quantile(50)[0]
        low, high = median_ratio_ci(num, den)
        p_value = mann_whitney(num, den)
        n = min(num.n, den.n)
        if n < BOOK_MIN_SEEDS:
            verdict = f"not judged yet: {n} seeds, {BOOK_MIN_SEEDS} needed"
        elif p_value < BOOK_ALPHA:
            faster = BOOK_PAIR[0] if ratio < 1 else BOOK_PAIR[1]
            verdict = f"a difference (p < {BOOK_ALPHA}): {faster} needs fewer steps"
        else:
            verdict = f"no difference shown (p ≥ {BOOK_ALPHA})"
        lines += [
            "",
            f"Median env steps to solve, {BOOK_PAIR[0]} / {BOOK_PAIR[1]}: **{ratio:.2f}** (95% percentile-bootstrap CI "
            f"{low:.2f}-{high:.2f}, runs resampled per implementation); two-sided Mann-Whitney U test on the steps, "
            f"{num.n} vs {den.n} seeds: p = {p_value:.3f}, {verdict}.",
        ]
    return [*lines, ""]


def build_report(
    records: Sequence[dict[str, Any]],
    out_dir: Path,
    results_path: Path,
    command: str,
    book_records: Sequence[dict[str, Any]] = (),
    scaling: dict[str, Any] | None = None,
) -> str:
    """
    Write ``README.md`` and the learning-curve PNGs into ``out_dir``.

    :param records: result lines
    :param out_dir: output folder
    :param results_path: where the records came from (named in the report)
    :param command: the report command (printed in the report)
    :param book_records: result lines of the runner's ``--protocol book`` (their own section)
    :param scaling: the growing memory's scaling run (``benchmarks.scaling``'s JSON; its own section), if any
    :return: the markdown text
    """
    cells_by_env = build_cells(records)
    lines = [
        "# NFQ benchmark results",
        "",
        f"Generated by `{command}` from {len(records)} runs in `{results_path}`.",
        "",
        "## How the data was produced",
        "",
        "Runner command(s), exactly as recorded with the runs:",
        "",
        *[f"    {cmd}" for cmd in _unique(records, "command")],
        "",
        "Machine(s): " + "; ".join(f"`{machine}`" for machine in _unique(records, "machine")),
        "",
        "Torch threads per job: "
        + ", ".join(str(t) for t in _unique(records, "torch_threads"))
        + "; launcher: "
        + ", ".join(str(t) for t in _unique(records, "launcher")),
        "",
        "Versions: "
        + "; ".join(", ".join(f"{k} {v}" for k, v in (vs or {}).items()) for vs in _unique(records, "versions")),
        "",
        "Code revision(s): " + ", ".join(f"`{rev}`" for rev in _unique(records, "git")),
        "",
        "Criterion (every algorithm): after each NFQ/reference round, or for DQN at the first rollout start at or "
        "after each multiple of `eval_every` env steps, the greedy policy plays 100 episodes on separate envs; a run "
        "is solved at the first evaluation whose mean return reaches the threshold. Training goes on to the budget, "
        "then 100 new greedy episodes give the final score; runs marked (stopped at solve) ran with "
        "`--stop-at-solve`: their training stopped at the solve and their final score is taken there. A run whose "
        "loss became non-finite stops there (NFQ raises `NFQDivergenceError`); it counts as unsolved unless it had "
        "solved before, and the success column says how many diverged. Training seconds exclude evaluation time. "
        "Learning curves: mean over seeds with a 95% bootstrap band, drawn while at least half of a row's runs are "
        "still training (a row stopped at solve ends near its median steps to solve).",
        "",
        f"Steps to solve: unsolved runs count as the steps they trained (censored), so a value marked ≥ is a lower "
        f"bound. IQM and its 95% CI: {ci_method()}.",
        "",
        "## Targets",
        "",
        f"From `{TARGETS_FILE.relative_to(REPO_ROOT)}`.",
        "",
        *target_lines(cells_by_env, read_targets(), scaling, records),
        "",
    ]
    for env, cells in cells_by_env.items():
        eval_every = ", ".join(str(e) for e in _unique([run for cell in cells for run in cell.runs], "eval_every"))
        threshold = cells[0].runs[0]["threshold"]
        current = current_cells(cells_by_env, env)
        superseded = [cell for cell in cells if cell.superseded]
        lines += [f"## {env} (threshold {threshold:g}, evaluation every {eval_every} steps)", ""]
        if current:
            lines += [*table_rows(current), "", f"![{env} learning curves]({curve_filename(env)})", ""]
            plot_curves(env, current, out_dir / curve_filename(env))
        if superseded:
            lines += [
                "Runs whose recorded settings are not what their config name holds today (recorded before configs "
                "became files that are never edited; kept in the results file, not used for the targets or the plot):",
                "",
                *table_rows(superseded),
                "",
            ]
    lines += book_protocol_lines(book_records)
    lines += scaling_lines(scaling)
    text = "\n".join(lines)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "README.md").write_text(text)
    return text


def scaling_lines(scaling: dict[str, Any] | None) -> list[str]:
    """:return: the report's section on the growing memory's fit cost against its size (none without a run)"""
    if scaling is None:
        return []
    spreads = "; ".join(f"{name}: {scaling_spread(rows):.0%}" for name, rows in scaling["bins"].items())
    return [
        "## The growing memory's fit cost against its size",
        "",
        " and ".join(f"`{command}`" for command in scaling["commands"])
        + f" on {scaling['env']}, seed {scaling['seed']}, {scaling['torch_threads']} torch thread(s), on "
        + ", ".join(f"`{machine}`" for machine in scaling["machines"])
        + ": every fit timed, fits grouped by the memory's size when they ran, "
        "and each bin's fit seconds divided by the env steps collected in it. A mode whose cost per step stays flat "
        "has a total cost linear in the steps.",
        "",
        scaling_table(scaling["bins"]),
        "",
        f"Largest departure of a bin from the mode's mean: {spreads}.",
        "",
        f"![fit cost against memory size]({DEFAULT_SCALING.with_suffix('.png').name})",
        "",
    ]


def main(argv: Sequence[str] | None = None) -> int:
    """
    Command-line entry point.

    :param argv: arguments (default: ``sys.argv[1:]``)
    :return: exit status (1 when there are no results)
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS, help="the runner's JSON-lines file")
    parser.add_argument(
        "--book-results", type=Path, default=DEFAULT_BOOK_RESULTS, help="the runner's --protocol book results"
    )
    parser.add_argument("--scaling", type=Path, default=DEFAULT_SCALING, help="benchmarks.scaling's JSON, if run")
    parser.add_argument("--out-dir", type=Path, help="where README.md and the PNGs go (default: the results' folder)")
    args = parser.parse_args(argv)
    records = read_results(args.results)
    if not records:
        print(f"no results in {args.results}", file=sys.stderr)
        return 1
    out_dir = args.out_dir or args.results.parent
    command = shlex.join(["python", "-m", "benchmarks.report", *argv])
    results_path = args.results.resolve()
    shown_path = results_path.relative_to(REPO_ROOT) if results_path.is_relative_to(REPO_ROOT) else results_path
    scaling = json.loads(args.scaling.read_text()) if args.scaling.is_file() else None
    print(build_report(records, out_dir, shown_path, command, read_results(args.book_results), scaling))
    print(f"\nwrote {out_dir / 'README.md'} and {len(build_cells(records))} PNG(s)")
    if results_path == DEFAULT_RESULTS.resolve():  # the project's own results: their summary goes into its README
        readme = readme_blocks.README
        readme.write_text(
            readme_blocks.replace_block(readme.read_text(), SUMMARY_MARKERS, summary_table(build_cells(records)))
        )
        print(f"wrote the summary table into {readme}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
