"""
NFQ's memory: building it, what it costs in RAM, and how much of it one forward pass may take (both in bytes, so that
a memory of images is bounded like a memory of vectors), and reading it whole.
"""

import contextlib
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import BaseBuffer, DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.vec_env import VecNormalize

from sb3_nfq.rounds import round_length

#: Most bytes of float32 network input in one forward pass over the memory (target passes, and the chunks a
#: full-batch gradient is accumulated over): a whole CartPole memory of millions of rows, a few hundred 84x84x4 frames.
CHUNK_BYTES = 64 * 2**20


def _space_bytes(space: spaces.Space) -> int:
    """:return: bytes one observation of ``space`` takes in SB3's replay buffer"""
    if isinstance(space, spaces.Dict):
        return sum(_space_bytes(subspace) for subspace in space.spaces.values())
    if isinstance(space, spaces.Discrete):
        return np.dtype(space.dtype).itemsize
    shape = space.shape or ()
    return int(np.prod(shape)) * np.dtype(space.dtype).itemsize


def memory_bytes(observation_space: spaces.Space, capacity: int) -> int:
    """
    :param observation_space: the observations stored
    :param capacity: transitions the memory holds (all envs together)
    :return: bytes SB3's replay buffer takes for them: observation and next observation, action, reward, done and
        timeout flags
    """
    per_transition = 2 * _space_bytes(observation_space) + 8 + 4 + 4 + 4
    return capacity * per_transition


def available_memory_bytes() -> int | None:
    """:return: the RAM available to a new allocation (Linux's MemAvailable, else physical RAM), if known"""
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    with contextlib.suppress(ValueError, OSError, AttributeError):
        import os

        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    return None


def check_memory_fits(observation_space: spaces.Space, capacity: int, memory: str) -> None:
    """
    Refuse a memory that cannot fit in this machine's RAM: SB3's buffer allocates it lazily, so it would otherwise
    fail (or swap) only once it fills, maybe hours into training.

    :param observation_space: the observations stored
    :param capacity: transitions the memory holds
    :param memory: ``"fresh"`` or ``"growing"`` (named in the error)
    """
    needed, available = memory_bytes(observation_space, capacity), available_memory_bytes()
    if available is None or needed <= available:
        return
    per_transition = needed / capacity
    fits = int(available // per_transition)
    raise ValueError(
        f"buffer_size={capacity:,} transitions of these observations need {needed / 2**30:.1f} GiB "
        f"({per_transition / 1024:,.1f} KiB each, observation and next observation) for memory={memory!r}, "
        f"but only {available / 2**30:.1f} GiB of RAM is available. Pass a smaller buffer_size "
        f"(at most about {fits:,} here; the memory then keeps the newest transitions)."
    )


#: Capacity of a growing memory when ``buffer_size`` is not given (SB3's replay buffer default).
DEFAULT_GROWING_CAPACITY = 1_000_000


def make_memory(
    observation_space: spaces.Space,
    action_space: spaces.Space,
    train_freq: TrainFreq | int | tuple[int, str],
    n_envs: int,
    buffer_size: int | None,
    memory: str,
    device: th.device | str,
) -> ReplayBuffer:
    """
    Create the transition memory: SB3's replay buffer, read whole, never sampled with replacement. It keeps
    ``terminated`` and time-limit truncation apart (``handle_timeout_termination``).

    :param observation_space: the observations stored
    :param action_space: the actions stored
    :param train_freq: NFQ's ``train_freq`` (a ``TrainFreq``, once the model has set up)
    :param n_envs: number of envs
    :param buffer_size: NFQ's ``buffer_size``
    :param memory: ``"fresh"`` or ``"growing"``
    :param device: where the buffer hands its samples
    :return: an empty replay buffer (a ``DictReplayBuffer`` for ``Dict`` observations) for ``n_envs`` environments
    """
    length = round_length(train_freq, n_envs)
    assert isinstance(train_freq, TrainFreq)
    asked = f"train_freq=({train_freq.frequency}, {train_freq.unit.value!r})"
    if length.unit == TrainFrequencyUnit.EPISODE:
        if n_envs > 1:
            raise ValueError(
                f"{asked} counts episodes, which needs a single environment; "
                f"got n_envs={n_envs}. Count transitions instead, e.g. train_freq=1024."
            )
        if buffer_size is None and memory == "fresh":
            raise ValueError(
                f"{asked} counts episodes, so NFQ cannot know how many transitions a round "
                "holds: pass buffer_size, the most transitions one round may hold (e.g. buffer_size=100_000)."
            )
        capacity = buffer_size or DEFAULT_GROWING_CAPACITY
    else:
        round_transitions = length.frequency * n_envs
        if buffer_size is not None and buffer_size < round_transitions:
            raise ValueError(
                f"buffer_size={buffer_size} is smaller than one round of {round_transitions} transitions "
                f"({asked} with n_envs={n_envs}); use buffer_size=None or a larger value."
            )
        capacity = buffer_size or (round_transitions if memory == "fresh" else DEFAULT_GROWING_CAPACITY)
    check_memory_fits(observation_space, capacity, memory)
    buffer_class: type[ReplayBuffer] = DictReplayBuffer if isinstance(observation_space, spaces.Dict) else ReplayBuffer
    return buffer_class(
        capacity, observation_space, action_space, device=device, n_envs=n_envs, handle_timeout_termination=True
    )


def rows_per_chunk(observations: Any) -> int:
    """
    :param observations: the memory's observations (a tensor, or a dict of tensors), one row per transition
    :return: how many rows one forward pass may take: :data:`CHUNK_BYTES` of float32 input
    """
    tensors = observations.values() if isinstance(observations, dict) else [observations]
    row_bytes = sum(4 * math.prod(tensor.shape[1:]) for tensor in tensors)
    return max(1, CHUNK_BYTES // max(1, row_bytes))


def flatten(buffer: BaseBuffer, array: np.ndarray) -> np.ndarray:
    """
    :param buffer: an SB3 buffer
    :param array: one of its arrays, ``(rows, n_envs, ...)``
    :return: its stored rows, one row per transition (step-major, then env); a view, not a copy
    """
    n_rows = buffer.buffer_size if buffer.full else buffer.pos
    return array[:n_rows].reshape(n_rows * buffer.n_envs, *array.shape[2:])


def stored_transitions(
    buffer: ReplayBuffer, vec_normalize_env: VecNormalize | None = None, n_steps: int = 1, gamma: float = 1.0
) -> ReplayBufferSamples:
    """
    :param buffer: NFQ's memory (or a dataset's buffer)
    :param vec_normalize_env: normalises observations and rewards for the fit, as SB3's ``sample`` does
    :param n_steps: above 1, each transition with its ``n_steps``-step return instead (:func:`n_step_transitions`)
    :param gamma: with ``n_steps`` above 1, the discount factor
    :return: every transition in the buffer, in its row order (step-major, then env: collection order until a
        growing memory is full, after which new rows overwrite the oldest in place), as tensors that share the
        buffer's memory on the CPU (no copy of the memory per round). ``dones`` is 1 only for true terminations:
        time-limit truncations bootstrap.
    """
    if n_steps > 1:
        return n_step_transitions(buffer, vec_normalize_env, n_steps, gamma)

    def flat_obs(obs: np.ndarray | dict[str, np.ndarray]) -> Any:
        if isinstance(obs, dict):
            normalized = buffer._normalize_obs(
                {key: flatten(buffer, value) for key, value in obs.items()}, vec_normalize_env
            )
            assert isinstance(normalized, dict)
            return {key: buffer.to_torch(value, copy=False) for key, value in normalized.items()}
        return buffer.to_torch(buffer._normalize_obs(flatten(buffer, obs), vec_normalize_env), copy=False)  # type: ignore[arg-type]

    terminated = flatten(buffer, buffer.dones) * (1 - flatten(buffer, buffer.timeouts))
    rewards = buffer._normalize_reward(flatten(buffer, buffer.rewards).reshape(-1, 1), vec_normalize_env)
    return ReplayBufferSamples(
        observations=flat_obs(buffer.observations),
        actions=buffer.to_torch(flatten(buffer, buffer.actions)),
        next_observations=flat_obs(buffer.next_observations),
        dones=buffer.to_torch(terminated.reshape(-1, 1)),
        rewards=buffer.to_torch(rewards),
    )


def n_step_transitions(
    buffer: ReplayBuffer, vec_normalize_env: VecNormalize | None, n_steps: int, gamma: float
) -> ReplayBufferSamples:
    """
    Every transition of the memory with its n-step return, as SB3's ``NStepReplayBuffer`` samples them: from step
    ``t`` of an env, ``r_t + gamma r_(t+1) + ... + gamma^(k-1) r_(t+k-1)``, the state after step ``t+k-1`` and
    ``discounts`` ``gamma^k``, where ``k`` is ``n_steps`` or less when the env's episode ends first (a termination then
    bootstraps on 0, a truncation on the state it left) or the memory's newest step comes first (bootstrapped on).

    :param buffer: NFQ's memory
    :param vec_normalize_env: normalises observations and rewards for the fit, as SB3's ``sample`` does
    :param n_steps: steps per return, more than 1
    :param gamma: the discount factor
    :return: the transitions in the order of :func:`stored_transitions` (the next observations are copies)
    """
    n_rows = buffer.buffer_size if buffer.full else buffer.pos
    steps = np.arange(n_steps)
    window = (np.arange(n_rows)[:, None] + steps) % n_rows  # (rows, n_steps): a step's next steps, in its env
    stops = buffer.dones[:n_rows].astype(bool)
    stops[(buffer.pos - 1) % n_rows] = True  # the newest step: past it lie older steps (or nothing yet)
    ends = stops[window]  # (rows, n_steps, n_envs)
    last = np.where(ends.any(axis=1), ends.argmax(axis=1), n_steps - 1)  # (rows, n_envs): k - 1
    within = steps[None, :, None] <= last[:, None, :]
    rewards = buffer._normalize_reward(buffer.rewards[:n_rows], vec_normalize_env)
    returns = (rewards[window] * (gamma**steps)[None, :, None] * within).sum(axis=1).astype(np.float32)
    rows, envs = (np.arange(n_rows)[:, None] + last) % n_rows, np.arange(buffer.n_envs)[None, :]
    terminated = buffer.dones[rows, envs] * (1 - buffer.timeouts[rows, envs])

    def next_obs(obs: np.ndarray) -> np.ndarray:
        return obs[rows, envs].reshape(n_rows * buffer.n_envs, *obs.shape[2:])

    successors = buffer.next_observations
    if isinstance(successors, dict):
        raw = {key: next_obs(value) for key, value in successors.items()}
        normalized: Any = buffer._normalize_obs(raw, vec_normalize_env)
        next_observations: Any = {key: buffer.to_torch(value) for key, value in normalized.items()}
    else:
        next_observations = buffer.to_torch(buffer._normalize_obs(next_obs(successors), vec_normalize_env))  # type: ignore[arg-type]
    one_step = stored_transitions(buffer, vec_normalize_env)
    return one_step._replace(
        next_observations=next_observations,
        dones=buffer.to_torch(terminated.reshape(-1, 1)),
        rewards=buffer.to_torch(returns.reshape(-1, 1)),
        discounts=buffer.to_torch((gamma ** (last + 1)).astype(np.float32).reshape(-1, 1)),
    )
