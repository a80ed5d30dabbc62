"""
Offline NFQ from a Minari dataset: record episodes of a uniformly random policy on CartPole-v1 into a
local Minari dataset, fit NFQ on it without touching the env again, then evaluate the greedy policy.
This is the 2005 paper's experiment in miniature (it learned pole balancing from random episodes).

Needs ``pip install "minari[create,hdf5]"`` (DataCollector uses JAX). Nothing is downloaded: the dataset
is written under ``--minari-dir``.

    python examples/offline_minari.py [--episodes 200] [--iterations 25] [--minari-dir data/minari]
"""

import argparse
import os
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_nfq import NFQ, TransitionDataset

DATASET_ID = "cartpole/uniform-random-v0"

#: Offline settings used by this example (the measured study: benchmarks/results/offline_random_cartpole.md).
OFFLINE_NFQ = {
    "gamma": 0.99,
    "target_mode": "fixed_per_iteration",
    "fit_epochs": 10,
    "learning_rate": 1e-3,
    "policy_kwargs": {"optimizer_class": th.optim.Adam},
}


def record_random_episodes(n_episodes: int, seed: int) -> None:
    """
    Write ``n_episodes`` episodes of a uniformly random policy to the local Minari dataset ``DATASET_ID``.

    :param n_episodes: number of episodes
    :param seed: seed of the env resets and of the random actions
    """
    import minari

    if DATASET_ID in minari.list_local_datasets():
        minari.delete_dataset(DATASET_ID)
    env = minari.DataCollector(gym.make("CartPole-v1"))
    env.action_space.seed(seed)
    for episode in range(n_episodes):
        env.reset(seed=seed * 100_000 + episode)
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            done = terminated or truncated
    env.create_dataset(dataset_id=DATASET_ID, algorithm_name="uniform random policy")


def main(argv: list[str] | None = None) -> float:
    """
    Record, fit offline, evaluate.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: the mean greedy episode length over 20 episodes
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--iterations", type=int, default=25, help="fitted iterations")
    parser.add_argument("--minari-dir", type=Path, default=Path("data/minari"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: see README)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    os.environ["MINARI_DATASETS_PATH"] = str(args.minari_dir.resolve())

    record_random_episodes(args.episodes, args.seed)
    dataset = TransitionDataset.from_minari(DATASET_ID)
    print(f"Dataset {DATASET_ID}: {len(dataset)} transitions from {args.episodes} random episodes")

    model = NFQ.for_dataset("MlpPolicy", dataset, seed=args.seed, **OFFLINE_NFQ)
    model.fit_offline(dataset, iterations=args.iterations)

    # 20 episodes from seeded start states (env i's from seed args.seed + 20_000 + i)
    eval_env = make_vec_env("CartPole-v1", n_envs=20, seed=args.seed + 20_000)
    _, lengths = evaluate_policy(model, eval_env, n_eval_episodes=20, return_episode_rewards=True)
    assert isinstance(lengths, list)
    print(
        f"Greedy policy fitted offline: mean episode length {np.mean(lengths):.0f} over 20 episodes "
        f"({sum(length == 500 for length in lengths)} balanced the full 500 steps; random policy: about 22)"
    )
    return float(np.mean(lengths))


if __name__ == "__main__":
    main()
