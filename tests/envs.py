"""Small real gymnasium environments for the tests (image and Dict observations, broken rewards, Atari-sized frames),
and random CartPole transitions."""

from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class LineWorld(gym.Env):
    """
    A walk on a line of ``size`` cells: start in the middle, reach the right end (+1) or fall off the left (-1).
    Actions: 0 = left, 1 = right. Observations come as an image or a Dict, to exercise the policy aliases.

    :param observation: ``"image"`` (36x36x1 uint8, the position as a bright column) or ``"dict"``
        (``{"position": one-hot Box, "steps": Discrete}``)
    :param size: number of cells
    :param max_steps: episode length at which the episode is truncated
    """

    def __init__(self, observation: str = "image", size: int = 6, max_steps: int = 20) -> None:
        self.kind = observation
        self.size = size
        self.max_steps = max_steps
        self.action_space = spaces.Discrete(2)
        if observation == "image":
            self.observation_space: spaces.Space = spaces.Box(0, 255, shape=(36, 36, 1), dtype=np.uint8)
        elif observation == "dict":
            self.observation_space = spaces.Dict(
                {
                    "position": spaces.Box(0.0, 1.0, shape=(size,), dtype=np.float32),
                    "steps": spaces.Discrete(max_steps + 1),
                }
            )
        else:
            raise ValueError(f"observation must be 'image' or 'dict', got {observation!r}")
        self.position = size // 2
        self.steps = 0

    def _observation(self) -> Any:
        if self.kind == "image":
            image = np.zeros((36, 36, 1), dtype=np.uint8)
            column = self.position * 36 // self.size
            image[:, column : column + 36 // self.size] = 255
            return image
        one_hot = np.zeros(self.size, dtype=np.float32)
        one_hot[self.position] = 1.0
        return {"position": one_hot, "steps": self.steps}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        self.position = self.size // 2
        self.steps = 0
        return self._observation(), {}

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        self.position += 1 if int(action) == 1 else -1
        self.steps += 1
        terminated = self.position in (0, self.size - 1)
        reward = 0.0
        if self.position == self.size - 1:
            reward = 1.0
        elif self.position == 0:
            reward = -1.0
        truncated = not terminated and self.steps >= self.max_steps
        return self._observation(), reward, terminated, truncated, {}


class NaNRewardAfter(gym.Wrapper):
    """
    Return NaN rewards after ``n_steps`` steps, to check that NFQ stops on a non-finite loss.

    :param env: the environment to wrap
    :param n_steps: number of finite-reward steps before the NaNs start
    """

    def __init__(self, env: gym.Env, n_steps: int) -> None:
        super().__init__(env)
        self.n_steps = n_steps
        self.steps_taken = 0

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps_taken += 1
        if self.steps_taken > self.n_steps:
            reward = float("nan")
        return obs, reward, terminated, truncated, info


class SpaceEnv(gym.Env):
    """
    Observations drawn from any ``observation_space`` (Discrete, MultiDiscrete, MultiBinary, ...); the reward is 1
    for action 1; episodes are truncated after ``length`` steps.

    :param observation_space: the space observations are sampled from (seeded by ``reset(seed=...)``)
    :param length: episode length
    """

    def __init__(self, observation_space: spaces.Space, length: int = 10) -> None:
        self.observation_space = observation_space
        self.action_space = spaces.Discrete(2)
        self.length = length
        self.t = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            self.observation_space.seed(seed)
        self.t = 0
        return self.observation_space.sample(), {}

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        self.t += 1
        return self.observation_space.sample(), float(action), False, self.t >= self.length, {}


class SplitObservation(gym.ObservationWrapper):
    """CartPole's observation as a Dict of two Boxes: ``{"cart": x, x_dot; "pole": theta, theta_dot}``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        box = spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32)
        self.observation_space = spaces.Dict({"cart": box, "pole": box})

    def observation(self, observation: Any) -> dict[str, np.ndarray]:
        return {"cart": observation[:2], "pole": observation[2:]}


class ChannelFirst(gym.ObservationWrapper):
    """An image env's ``(H, W, C)`` frames as ``(C, H, W)``, as PyTorch-style envs give them."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        space = env.observation_space
        assert isinstance(space, spaces.Box) and space.shape is not None
        height, width, channels = space.shape
        self.observation_space = spaces.Box(0, 255, shape=(channels, height, width), dtype=np.uint8)

    def observation(self, observation: Any) -> np.ndarray:
        return np.ascontiguousarray(np.transpose(observation, (2, 0, 1)))


class Frames(gym.Env):
    """
    Episodes of random 84x84x4 uint8 frames; action 1 ends an episode after its 5th step, else it is truncated at
    ``length`` steps. Its observations cost what Atari's stacked frames cost; there is nothing to learn.

    :param length: steps before truncation
    """

    def __init__(self, length: int = 50) -> None:
        self.observation_space = gym.spaces.Box(0, 255, shape=(84, 84, 4), dtype=np.uint8)
        self.action_space = gym.spaces.Discrete(2)
        self.length = length
        self.t = 0

    def _frame(self) -> np.ndarray:
        return self.np_random.integers(0, 256, size=(84, 84, 4), dtype=np.uint8)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self._frame(), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.t += 1
        return self._frame(), float(action), int(action) == 1 and self.t > 5, self.t >= self.length, {}


def random_cartpole_arrays(n_episodes: int, seed: int, max_episode_steps: int = 500) -> dict[str, np.ndarray]:
    """
    :param n_episodes: number of episodes of a uniformly random policy on CartPole-v1
    :param seed: seed of the actions; episode ``i`` starts from ``reset(seed=seed * 100_000 + i)``
    :param max_episode_steps: the time limit (episodes cut there are truncated, not terminated)
    :return: the transitions in collection order, keys ``obs``, ``act``, ``rew``, ``next``, ``term``, ``trunc``,
        with the episode ends as gymnasium reports them
    """
    env = gym.make("CartPole-v1", max_episode_steps=max_episode_steps)
    rng = np.random.default_rng(seed)
    rows: dict[str, list[Any]] = {key: [] for key in ("obs", "act", "rew", "next", "term", "trunc")}
    for episode in range(n_episodes):
        obs, _ = env.reset(seed=seed * 100_000 + episode)
        done = False
        while not done:
            action = int(rng.integers(2))
            next_obs, reward, terminated, truncated, _ = env.step(action)
            for key, value in zip(rows, (obs, action, reward, next_obs, terminated, truncated), strict=True):
                rows[key].append(value)
            obs, done = next_obs, terminated or truncated
    return {key: np.array(values) for key, values in rows.items()}
