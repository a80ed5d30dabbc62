"""
Quickstart: NFQ is used exactly like SB3's DQN. It trains the growing-memory NFQ of the 2005 paper on CartPole-v1
with the package's settings for it (nfq.yml's CartPole-v1 entry), evaluates it greedily and watches one episode.

The textbook's own NFQ (fresh batches of 1024 transitions, the defaults of ``NFQ("MlpPolicy", "CartPole-v1")``)
needs ten times the steps: ``examples/solve_cartpole.py`` (``make solve``) runs it until solved.

    python examples/quickstart.py [--total-timesteps 20000] [--threads 1]
"""

import argparse

import gymnasium as gym
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_nfq import NFQ
from sb3_nfq.configs import nfq_callbacks, nfq_kwargs


def main(argv: list[str] | None = None) -> float:
    """
    Train NFQ on CartPole-v1, evaluate it greedily and watch one episode.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: the mean greedy return over 20 evaluation episodes
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--total-timesteps", type=int, default=20_000)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: see README)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)

    # sb3_nfq/hyperparams/nfq.yml's CartPole-v1 entry: memory="growing" keeps every transition and refits on all of
    # them, in rounds that lengthen as the memory grows; its callback ends training on the best-scoring fit.
    model = NFQ("MlpPolicy", gym.make("CartPole-v1"), seed=0, **nfq_kwargs("CartPole-v1"))
    model.learn(total_timesteps=args.total_timesteps, callback=nfq_callbacks("CartPole-v1"), progress_bar=True)

    # 20 episodes from seeded start states (env i's from seed 20_000 + i): the same model gets the same figure on
    # every run.
    eval_env = make_vec_env("CartPole-v1", n_envs=20, seed=20_000)
    mean_return, std_return = evaluate_policy(model, eval_env, n_eval_episodes=20, deterministic=True)
    assert isinstance(mean_return, float)
    print(f"Greedy return over 20 episodes after {model.num_timesteps} steps: {mean_return:.1f} +/- {std_return:.1f}")

    env = gym.make("CartPole-v1")
    obs, _ = env.reset(seed=0)
    done, steps = False, 0
    while not done:
        action, _ = model.predict(obs, deterministic=True)  # greedy: argmax_a Q(s, a)
        obs, _, terminated, truncated, _ = env.step(int(action))
        done, steps = terminated or truncated, steps + 1
    print(f"One greedy episode lasted {steps} steps (500 is CartPole-v1's limit)")
    return mean_return


if __name__ == "__main__":
    main()
