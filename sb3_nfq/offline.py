"""Fixed datasets of transitions for fitting NFQ offline (``NFQ.fit_offline``), validated on creation."""

import pathlib
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.save_util import load_from_pkl
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import get_device

from sb3_nfq.memory import flatten

__all__ = ["TransitionDataset"]


@dataclass(frozen=True)
class TransitionDataset:
    """
    A fixed set of transitions ``(s, a, r, s', terminated, truncated)``, one row each, with the spaces they live in.

    Build it with :meth:`from_arrays`, :meth:`from_replay_buffer` or :meth:`from_minari`; it is checked on
    creation (non-empty, matching lengths and shapes, actions inside the action space, finite values),
    and every problem raises a ``ValueError`` that names the field.
    ``terminated`` transitions bootstrap on 0; ``truncated`` ones (time limits) bootstrap on ``Q(s', .)``.

    :param observations: states ``s``, shape ``(n, *observation_space.shape)``
    :param actions: actions ``a``, integers in ``[0, action_space.n)``, shape ``(n,)``
    :param rewards: rewards ``r``, shape ``(n,)``
    :param next_observations: next states ``s'``, same shape as ``observations``
    :param terminated: whether the episode truly ended at ``s'``, shape ``(n,)``
    :param truncated: whether the episode was cut (time limit) at ``s'``, shape ``(n,)``
    :param observation_space: a ``Box`` observation space
    :param action_space: a ``Discrete`` action space starting at 0
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_observations: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    observation_space: spaces.Box
    action_space: spaces.Discrete

    def __post_init__(self) -> None:
        _validate(self)

    def __len__(self) -> int:
        return len(self.rewards)

    @classmethod
    def from_arrays(
        cls,
        observations: Any,
        actions: Any,
        rewards: Any,
        next_observations: Any,
        terminated: Any,
        truncated: Any,
        action_space: spaces.Discrete,
        observation_space: spaces.Box | None = None,
    ) -> "TransitionDataset":
        """
        Build a dataset from plain arrays (anything ``np.asarray`` takes), one row per transition.

        :param observations: states ``s``, shape ``(n, *obs_shape)``
        :param actions: integer actions, shape ``(n,)`` (or ``(n, 1)``)
        :param rewards: rewards, shape ``(n,)``
        :param next_observations: next states ``s'``, shape ``(n, *obs_shape)``
        :param terminated: 0/1 or bool, shape ``(n,)``
        :param truncated: 0/1 or bool, shape ``(n,)``
        :param action_space: the ``Discrete`` action space (not guessed from the data: an action that never
            occurs would be lost)
        :param observation_space: the observation space; default: an unbounded ``Box`` of the observations' shape.
            Pass the env's own space to continue online on that env later (SB3 requires equal spaces).
        :return: the validated dataset
        """
        observations = np.asarray(observations)
        if observation_space is None:
            if observations.ndim < 1:
                raise ValueError(f"observations must have one row per transition, got shape {observations.shape}")
            observation_space = spaces.Box(-np.inf, np.inf, shape=observations.shape[1:], dtype=np.float32)
        actions = np.asarray(actions)
        if actions.ndim == 2 and actions.shape[1] == 1:
            actions = actions[:, 0]
        return cls(
            observations=observations,
            actions=actions,
            rewards=np.asarray(rewards),
            next_observations=np.asarray(next_observations),
            terminated=np.asarray(terminated),
            truncated=np.asarray(truncated),
            observation_space=observation_space,
            action_space=action_space,
        )

    @classmethod
    def from_replay_buffer(cls, buffer: ReplayBuffer | str | pathlib.Path) -> "TransitionDataset":
        """
        Build a dataset from an SB3 replay buffer, or the file written by ``model.save_replay_buffer(path)``.

        :param buffer: the replay buffer or the path of its pickle
        :return: every stored transition, in storage order (step-major, then env)
        """
        if isinstance(buffer, (str, pathlib.Path)):
            path = buffer
            try:
                buffer = load_from_pkl(path)
            except Exception as error:
                raise ValueError(f"{path} is not a replay buffer saved with save_replay_buffer: {error}") from error
        if isinstance(buffer, DictReplayBuffer) or not isinstance(buffer, ReplayBuffer):
            raise ValueError(
                f"from_replay_buffer needs an SB3 ReplayBuffer of array observations, got {type(buffer).__name__}"
            )
        if buffer.optimize_memory_usage:
            raise ValueError("replay buffers saved with optimize_memory_usage=True are not supported: no next_obs")
        dones = flatten(buffer, buffer.dones).astype(bool)
        timeouts = flatten(buffer, buffer.timeouts).astype(bool)
        return cls.from_arrays(
            observations=flatten(buffer, buffer.observations),
            actions=flatten(buffer, buffer.actions),
            rewards=flatten(buffer, buffer.rewards),
            next_observations=flatten(buffer, buffer.next_observations),
            terminated=dones & ~timeouts,
            truncated=dones & timeouts,
            action_space=buffer.action_space,  # type: ignore[arg-type]  # checked by the validation
            observation_space=buffer.observation_space,  # type: ignore[arg-type]
        )

    @classmethod
    def from_minari(cls, dataset: Any) -> "TransitionDataset":
        """
        Build a dataset from a Minari dataset: a ``MinariDataset`` or the id of one stored locally
        (under ``MINARI_DATASETS_PATH``); nothing is downloaded. Needs the ``offline`` extra
        (``pip install ".[offline]"`` in a checkout).

        :param dataset: a ``minari.MinariDataset`` or a local dataset id such as ``"cartpole/random-v0"``
        :return: every transition of every episode
        """
        try:
            import minari
        except ImportError as error:
            raise ImportError(
                'from_minari needs Minari: the offline extra, pip install ".[offline]" in a checkout'
            ) from error
        if isinstance(dataset, str):
            dataset = minari.load_dataset(dataset, download=False)
        columns: dict[str, list[np.ndarray]] = {
            name: [] for name in ("obs", "actions", "rewards", "next", "term", "trunc")
        }
        for episode in dataset.iterate_episodes():
            if isinstance(episode.observations, dict):
                raise ValueError("from_minari supports array observations, not Dict observations")
            columns["obs"].append(episode.observations[:-1])
            columns["next"].append(episode.observations[1:])
            columns["actions"].append(episode.actions)
            columns["rewards"].append(episode.rewards)
            columns["term"].append(episode.terminations)
            columns["trunc"].append(episode.truncations)
        if not columns["obs"]:
            raise ValueError(f"the Minari dataset {dataset.id} has no episodes: the dataset is empty")
        stacked = {name: np.concatenate(parts) for name, parts in columns.items()}
        return cls.from_arrays(
            observations=stacked["obs"],
            actions=stacked["actions"],
            rewards=stacked["rewards"],
            next_observations=stacked["next"],
            terminated=stacked["term"],
            truncated=stacked["trunc"],
            action_space=dataset.action_space,
            observation_space=dataset.observation_space,
        )

    def check_spaces(self, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        """
        Raise a ``ValueError`` unless the dataset fits a model with these spaces.

        :param observation_space: the model's observation space
        :param action_space: the model's action space
        """
        if not isinstance(observation_space, spaces.Box) or observation_space.shape != self.observation_space.shape:
            raise ValueError(
                f"the dataset's observations have shape {self.observation_space.shape}, "
                f"the model expects {observation_space}"
            )
        if not isinstance(action_space, spaces.Discrete) or action_space.n != self.action_space.n:
            raise ValueError(f"the dataset's actions are {self.action_space}, the model expects {action_space}")

    def samples(self, device: th.device | str = "auto") -> ReplayBufferSamples:
        """
        :param device: device of the tensors
        :return: the transitions as the batch NFQ fits, one row each in order, with the dtypes of SB3's replay
            buffer; ``dones`` is 1 only for true terminations (time-limit truncations bootstrap)
        """
        device = get_device(device)
        observation_dtype = self.observation_space.dtype

        def column(array: np.ndarray, dtype: Any = np.float32) -> th.Tensor:
            return th.as_tensor(np.asarray(array, dtype=dtype), device=device)

        return ReplayBufferSamples(
            observations=column(self.observations, observation_dtype),
            actions=column(self.actions.reshape(-1, 1), self.action_space.dtype),
            next_observations=column(self.next_observations, observation_dtype),
            dones=column(self.terminated.reshape(-1, 1)),
            rewards=column(self.rewards.reshape(-1, 1)),
        )

    def to_replay_buffer(self, device: th.device | str = "auto") -> ReplayBuffer:
        """
        :param device: device of the tensors the buffer hands out
        :return: an SB3 replay buffer (one env) holding exactly these transitions, in order
        """
        n = len(self)
        buffer = ReplayBuffer(n, self.observation_space, self.action_space, device=device, n_envs=1)
        buffer.observations[:, 0] = self.observations
        buffer.next_observations[:, 0] = self.next_observations
        buffer.actions[:, 0, 0] = self.actions
        buffer.rewards[:, 0] = self.rewards
        buffer.dones[:, 0] = self.terminated | self.truncated
        buffer.timeouts[:, 0] = self.truncated & ~self.terminated
        buffer.pos, buffer.full = 0, True
        return buffer


def _validate(dataset: TransitionDataset) -> None:
    """Check a dataset, raising a ``ValueError`` that names the field at fault."""
    if not isinstance(dataset.action_space, spaces.Discrete) or int(dataset.action_space.start) != 0:
        raise ValueError(f"action_space must be a Discrete space starting at 0, got {dataset.action_space}")
    if not isinstance(dataset.observation_space, spaces.Box):
        raise ValueError(f"observation_space must be a Box (array observations), got {dataset.observation_space}")
    n = len(dataset.rewards)
    if n == 0:
        raise ValueError("the dataset is empty: it needs at least one transition")
    for name in ("observations", "actions", "rewards", "next_observations", "terminated", "truncated"):
        length = len(getattr(dataset, name))
        if length != n:
            raise ValueError(f"all fields need one row per transition: rewards has {n} rows, {name} has {length}")
    obs_shape = (n, *dataset.observation_space.shape)
    for name in ("observations", "next_observations"):
        array = getattr(dataset, name)
        if array.shape != obs_shape:
            raise ValueError(f"{name} must have shape {obs_shape} for {dataset.observation_space}, got {array.shape}")
        if np.issubdtype(array.dtype, np.floating) and not np.isfinite(array).all():
            raise ValueError(f"{name} holds {int((~np.isfinite(array)).sum())} NaN/inf values")
    for name in ("actions", "rewards", "terminated", "truncated"):
        if getattr(dataset, name).shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), got {getattr(dataset, name).shape}")
    rewards = dataset.rewards
    if not np.issubdtype(rewards.dtype, np.number):
        raise ValueError(f"rewards must be numbers, got dtype {rewards.dtype}")
    if not np.isfinite(rewards).all():
        raise ValueError(f"rewards holds {int((~np.isfinite(rewards)).sum())} NaN/inf values")
    actions = dataset.actions
    n_actions = int(dataset.action_space.n)
    integral = np.issubdtype(actions.dtype, np.integer) or (
        np.issubdtype(actions.dtype, np.floating)
        and np.isfinite(actions).all()
        and (actions == np.round(actions)).all()
    )
    if not integral:
        raise ValueError(f"actions must be integers in [0, {n_actions}), got dtype {actions.dtype} with fractions")
    outside = (actions < 0) | (actions >= n_actions)
    if outside.any():
        raise ValueError(
            f"{int(outside.sum())} actions lie outside {dataset.action_space} (allowed: 0..{n_actions - 1}), "
            f"e.g. {actions[outside][:5].tolist()}"
        )
    for name in ("terminated", "truncated"):
        flags = getattr(dataset, name)
        if not np.isin(flags, (0, 1)).all():
            raise ValueError(f"{name} must hold booleans (0/1), got values {np.unique(flags)[:5].tolist()}")
    object.__setattr__(dataset, "actions", actions.astype(np.int64))
    object.__setattr__(dataset, "terminated", dataset.terminated.astype(bool))
    object.__setattr__(dataset, "truncated", dataset.truncated.astype(bool))
