"""
How the growing memory's fitting cost scales: fit seconds per 1,000 env steps against the memory's size, for fixed
rounds (``nfq-shared``: a refit every 256 steps) and for rounds that lengthen with the memory (``round_fraction``).

    python -m benchmarks.scaling [--env CartPole-v1] [--max-steps 200000] [--configs nfq-shared ...]
        [--round-fraction 0.1] [--seed 0] [--out benchmarks/results/scaling.json]

Modes: each shipped config named by ``--configs`` (default ``nfq-shared``), and with ``--round-fraction f`` the first
of them with rounds of ``f`` x the memory; each with a memory as large as the run, so that it never drops a transition.
One run per mode, one after the other in this process (1 torch thread). Every fit is timed; the fits are then
grouped by the memory size they ran at (bins ending at 10k, 20k, 50k, 100k, 200k transitions) and each bin reports
its fit seconds per 1,000 env steps collected in it. A mode whose cost per collected step stays flat as the memory
grows has a total cost linear in the steps; with fixed rounds it grows with the memory.
"""

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch as th

from sb3_nfq import NFQ
from sb3_nfq.configs import nfq_kwargs

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_OUT = REPO_ROOT / "benchmarks" / "results" / "scaling.json"
#: Upper ends of the memory-size bins, in transitions.
BINS = (10_000, 20_000, 50_000, 100_000, 200_000)


def timed_run(env_id: str, kwargs: dict[str, Any], max_steps: int, seed: int) -> list[dict[str, float]]:
    """
    :param env_id: gymnasium env id (made with no render mode)
    :param kwargs: NFQ's keyword arguments
    :param max_steps: env steps to train
    :param seed: seed
    :return: one record per fit: env steps and memory size when it ran, its seconds
    """
    model = NFQ("MlpPolicy", gym.make(env_id), seed=seed, device="cpu", **kwargs)
    fits: list[dict[str, float]] = []
    fit = model.train

    def timed_fit(gradient_steps: int, batch_size: int | None = None) -> None:
        start = time.perf_counter()
        fit(gradient_steps, batch_size)
        fits.append(
            {
                "steps": model.num_timesteps,
                "memory": model.replay_buffer.size() * model.n_envs,
                "seconds": time.perf_counter() - start,
            }
        )

    model.train = timed_fit  # type: ignore[method-assign]  # time each fit of this one model
    model.learn(max_steps)
    return fits


def per_bin(fits: Sequence[dict[str, float]], bins: Sequence[int] = BINS) -> list[dict[str, float]]:
    """
    :param fits: the fits of one run, in order
    :param bins: upper ends of the memory-size bins
    :return: for each bin with fits: env steps collected and fit seconds spent while the memory was in it, and
        their ratio per 1,000 steps
    """
    rows, low = [], 0
    for high in bins:
        inside = [fit for fit in fits if low < fit["memory"] <= high]
        if inside:
            first = fits.index(inside[0])
            start = fits[first - 1]["steps"] if first > 0 else 0.0
            steps = inside[-1]["steps"] - start
            seconds = sum(fit["seconds"] for fit in inside)
            rows.append(
                {"memory_up_to": high, "steps": steps, "seconds": seconds, "per_1000_steps": 1000 * seconds / steps}
            )
        low = high
    return rows


def spread(rows: Sequence[dict[str, float]]) -> float:
    """
    :param rows: one mode's bins (see :func:`per_bin`)
    :return: the largest relative departure of a bin's fit seconds per 1,000 steps from the mean over the bins (0:
        flat; 0.3: some bin is 30% above or below the mean)
    """
    values = [row["per_1000_steps"] for row in rows]
    mean = sum(values) / len(values)
    return max(abs(value / mean - 1) for value in values)


def plot(runs: dict[str, list[dict[str, float]]], path: Path, title: str) -> None:
    """
    Write the scaling figure: fit seconds per 1,000 env steps against the memory's size, one line per mode.

    :param runs: mode -> its bins
    :param path: the PNG
    :param title: the figure's title
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7, 4))
    for name, rows in runs.items():
        axes.plot([row["memory_up_to"] for row in rows], [row["per_1000_steps"] for row in rows], "o-", label=name)
    axes.set_xscale("log")
    axes.set_xlabel("transitions in the memory (upper end of the bin)")
    axes.set_ylabel("fit seconds per 1,000 env steps")
    axes.set_title(title, fontsize="medium")
    axes.legend(fontsize="small")
    axes.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def table(runs: dict[str, list[dict[str, float]]]) -> str:
    """:return: the markdown table: one row per bin, one column per mode"""
    names = list(runs)
    header = "| memory (transitions) | " + " | ".join(f"{name}: fit s per 1,000 steps" for name in names) + " |"
    lines = [header, "|---|" + "---|" * len(names)]
    by_bin: dict[int, dict[str, float]] = {}
    for name, rows in runs.items():
        for row in rows:
            by_bin.setdefault(int(row["memory_up_to"]), {})[name] = row["per_1000_steps"]
    low = 0
    for high in sorted(by_bin):
        cells = [f"{by_bin[high][name]:.2f}" if name in by_bin[high] else "—" for name in names]
        lines.append(f"| {low:,}-{high:,} | " + " | ".join(cells) + " |")
        low = high
    return "\n".join(lines)


def merged(earlier: dict[str, Any], later: dict[str, Any]) -> dict[str, Any]:
    """
    :param earlier: a scaling run's payload (as written; one from before ``commands`` had a single ``command``)
    :param later: the payload of more modes, on the same env, seed and step count
    :return: one payload with the modes of both (the later run's where a mode is in both)
    """
    for key in ("env", "seed", "max_steps", "torch_threads"):
        if earlier[key] != later[key]:
            raise ValueError(f"--add: the run in the file has {key}={earlier[key]!r}, this one {later[key]!r}")
    listed = {"commands": "command", "machines": "machine"}
    out = dict(later)
    for key, single in listed.items():
        before = earlier.get(key, [earlier[single]] if single in earlier else [])
        out[key] = list(dict.fromkeys([*before, *later[key]]))
    out["bins"] = {**earlier["bins"], **later["bins"]}
    out["fits"] = {**earlier["fits"], **later["fits"]}
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """
    Command-line entry point.

    :param argv: arguments (default: ``sys.argv[1:]``)
    :return: exit status
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--max-steps", type=int, default=BINS[-1])
    parser.add_argument("--configs", nargs="+", default=["nfq-shared"], help="shipped config names")
    parser.add_argument("--round-fraction", type=float, help="also run the first config with this round_fraction")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--add", action="store_true", help="add these modes to the run already in --out")
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    modes = {name: {**nfq_kwargs(name, args.env), "buffer_size": args.max_steps} for name in args.configs}
    if args.round_fraction is not None:
        first = args.configs[0]
        modes[f"{first}, round_fraction={args.round_fraction:g}"] = {
            **modes[first],
            "round_fraction": args.round_fraction,
        }
    runs: dict[str, list[dict[str, float]]] = {}
    raw: dict[str, list[dict[str, float]]] = {}
    for name, kwargs in modes.items():
        raw[name] = timed_run(args.env, kwargs, args.max_steps, args.seed)
        runs[name] = per_bin(raw[name])
        print(f"{name}: {len(raw[name])} fits, {sum(fit['seconds'] for fit in raw[name]):.1f} s", flush=True)
    from benchmarks.run import machine_line, package_versions

    command = " ".join(["python -m benchmarks.scaling", *(argv if argv is not None else sys.argv[1:])])
    payload = {
        "commands": [command],
        "env": args.env,
        "max_steps": args.max_steps,
        "seed": args.seed,
        "torch_threads": th.get_num_threads(),
        "machines": [machine_line()],
        "versions": package_versions(),
        "bins": runs,
        "fits": raw,
    }
    if args.add:
        payload = merged(json.loads(args.out.read_text()), payload)
        runs = payload["bins"]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(payload, indent=1) + "\n")
    block = table(runs)
    args.out.with_suffix(".md").write_text(block + "\n")
    plot(runs, args.out.with_suffix(".png"), f"{args.env}, seed {args.seed}, 1 torch thread")
    print(block)
    return 0


if __name__ == "__main__":
    sys.exit(main())
