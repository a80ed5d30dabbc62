"""
Plot NFQ's learning curve to a PNG: training episode returns (SB3's Monitor) and greedy evaluations
(SB3's EvalCallback) against environment steps.

    python examples/plot_learning_curve.py [--total-timesteps 100000] [--log-dir logs/nfq_curve]
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # no display needed
import matplotlib.pyplot as plt
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.results_plotter import load_results, ts2xy

from sb3_nfq import NFQ


def main(argv: list[str] | None = None) -> Path:
    """
    Train NFQ on CartPole-v1 with a Monitor log and per-round greedy evaluations, then plot both.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: the path of the PNG
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--total-timesteps", type=int, default=100_000)
    parser.add_argument("--log-dir", type=Path, default=Path("logs/nfq_curve"))
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: see README)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    log_dir: Path = args.log_dir
    log_dir.mkdir(parents=True, exist_ok=True)

    env = make_vec_env("CartPole-v1", n_envs=1, seed=0, monitor_dir=str(log_dir / "monitor"))
    evaluation = EvalCallback(
        make_vec_env("CartPole-v1", n_envs=20, seed=1),
        n_eval_episodes=20,
        eval_freq=1024,  # after every round of 1024 transitions
        log_path=str(log_dir),
        deterministic=True,
        verbose=0,
    )
    NFQ("MlpPolicy", env, seed=0).learn(args.total_timesteps, callback=evaluation, progress_bar=True)

    steps, returns = ts2xy(load_results(str(log_dir / "monitor")), "timesteps")
    evaluations = np.load(log_dir / "evaluations.npz")
    figure, axes = plt.subplots(figsize=(8, 4.5))
    axes.plot(steps, returns, ".", markersize=2, alpha=0.4, label="training episodes (epsilon-greedy, eps=0.5)")
    mean, std = evaluations["results"].mean(axis=1), evaluations["results"].std(axis=1)
    axes.plot(evaluations["timesteps"], mean, color="C1", label="greedy evaluation (20 episodes)")
    axes.fill_between(evaluations["timesteps"], mean - std, mean + std, color="C1", alpha=0.2)
    axes.axhline(475, color="gray", linestyle="--", linewidth=1, label="solved (475)")
    axes.set(xlabel="environment steps", ylabel="episode return", title="NFQ (textbook defaults) on CartPole-v1")
    axes.legend(loc="upper left")
    figure.tight_layout()
    path = log_dir / "learning_curve.png"
    figure.savefig(path, dpi=120)
    print(f"Learning curve saved to {path}")
    return path


if __name__ == "__main__":
    main()
