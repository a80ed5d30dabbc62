"""
Quickstart: NFQ is used exactly like SB3's DQN.

    python examples/quickstart.py [--total-timesteps 150000]
"""

import argparse

import gymnasium as gym
import torch as th
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_nfq import NFQ


def main(argv: list[str] | None = None) -> float:
    """
    Train NFQ with the textbook defaults on CartPole-v1, evaluate it greedily and watch one episode.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: the mean greedy return over 20 evaluation episodes
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--total-timesteps", type=int, default=150_000)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: see README)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)

    # Textbook defaults: Q-network 4-512-128-2, RMSprop(lr=5e-4), rounds of 1024 fresh transitions with
    # epsilon=0.5, 40 fitted iterations per round, gamma=1.
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0, verbose=0)
    model.learn(total_timesteps=args.total_timesteps, progress_bar=True)

    env = Monitor(gym.make("CartPole-v1"))
    mean_return, std_return = evaluate_policy(model, env, n_eval_episodes=20, deterministic=True)
    assert isinstance(mean_return, float)
    print(f"Greedy return over 20 episodes after {model.num_timesteps} steps: {mean_return:.1f} +/- {std_return:.1f}")

    obs, _ = env.reset(seed=0)
    done, steps = False, 0
    while not done:
        action, _ = model.predict(obs, deterministic=True)  # greedy: argmax_a Q(s, a)
        obs, _, terminated, truncated, _ = env.step(int(action))
        done, steps = terminated or truncated, steps + 1
    print(f"One greedy episode lasted {steps} steps")
    return mean_return


if __name__ == "__main__":
    main()
