"""
NFQ on your own gymnasium env: a small grid world whose observation is a ``Dict``
(the agent's cell and the goal's cell), solved with ``MultiInputPolicy``.

    python examples/custom_env_gridworld.py [--total-timesteps 30000]
"""

import argparse
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_nfq import NFQ


class GridWorld(gym.Env):
    """
    Reach a goal on a ``size`` x ``size`` grid. Both the start and the goal are drawn at random each episode.

    Observation: ``{"agent": Discrete(size*size), "goal": Discrete(size*size)}`` (cells as indices; SB3 one-hot
    encodes them). Actions: 0 up, 1 right, 2 down, 3 left. Reward: -0.05 per step, +1 on reaching the goal
    (terminated); episodes are truncated after ``max_steps``.

    :param size: side of the grid
    :param max_steps: time limit of an episode
    """

    MOVES = ((-1, 0), (0, 1), (1, 0), (0, -1))

    def __init__(self, size: int = 5, max_steps: int = 30) -> None:
        self.size = size
        self.max_steps = max_steps
        self.observation_space = spaces.Dict(
            {"agent": spaces.Discrete(size * size), "goal": spaces.Discrete(size * size)}
        )
        self.action_space = spaces.Discrete(4)
        self.agent = np.zeros(2, dtype=int)
        self.goal = np.zeros(2, dtype=int)
        self.steps = 0

    def _observation(self) -> dict[str, int]:
        return {
            "agent": int(self.agent[0] * self.size + self.agent[1]),
            "goal": int(self.goal[0] * self.size + self.goal[1]),
        }

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, int], dict]:
        super().reset(seed=seed)
        self.agent = self.np_random.integers(self.size, size=2)
        self.goal = self.agent
        while np.array_equal(self.goal, self.agent):
            self.goal = self.np_random.integers(self.size, size=2)
        self.steps = 0
        return self._observation(), {}

    def step(self, action: Any) -> tuple[dict[str, int], SupportsFloat, bool, bool, dict]:
        self.agent = np.clip(self.agent + self.MOVES[int(action)], 0, self.size - 1)
        self.steps += 1
        terminated = bool(np.array_equal(self.agent, self.goal))
        reward = 1.0 if terminated else -0.05
        truncated = not terminated and self.steps >= self.max_steps
        return self._observation(), reward, terminated, truncated, {}


def main(argv: list[str] | None = None) -> float:
    """
    Train NFQ with ``MultiInputPolicy`` on the grid world and report the greedy success rate.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: the greedy success rate over 100 episodes
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--total-timesteps", type=int, default=30_000)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: see README)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)

    check_env(GridWorld())  # SB3's checker: the env follows the gymnasium API
    model = NFQ(
        "MultiInputPolicy",  # Dict observations; "CnnPolicy" for image observations, "MlpPolicy" for vectors
        GridWorld(),
        gamma=0.95,  # the book's gamma=1 suits CartPole's +1 per step, not a goal task with a step cost
        exploration_initial_eps=1.0,
        exploration_final_eps=0.1,
        exploration_fraction=0.5,
        seed=0,
    )
    model.learn(args.total_timesteps, progress_bar=True)

    _, episode_lengths = evaluate_policy(
        model, make_vec_env(GridWorld, seed=20_000), 100, deterministic=True, return_episode_rewards=True
    )
    assert isinstance(episode_lengths, list)
    success_rate = float(np.mean([length < GridWorld().max_steps for length in episode_lengths]))
    print(
        f"After {model.num_timesteps} steps: greedy success rate {success_rate:.0%} over 100 random start/goal pairs, "
        f"mean episode length {np.mean(episode_lengths):.1f} (a shortest path is at most {2 * (GridWorld().size - 1)})"
    )
    return success_rate


if __name__ == "__main__":
    main()
