"""
NFQ's rounds: how much each collects before it is fitted, and collecting them through SB3's ``collect_rollouts``.
"""

import math
import warnings
from typing import Any

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit


def round_length(train_freq: TrainFreq | int | tuple[int, str], n_envs: int) -> TrainFreq:
    """
    :param train_freq: NFQ's ``train_freq`` once the model has set up (a ``TrainFreq``): transitions over all envs,
        or episodes
    :param n_envs: number of envs
    :return: how much one round collects, in ``env.step()`` calls (each gives ``n_envs`` transitions: ``train_freq``
        rounded up to a multiple of ``n_envs``) or in episodes
    """
    assert isinstance(train_freq, TrainFreq), "round_length needs the train_freq of a model that has set up"
    if train_freq.unit == TrainFrequencyUnit.EPISODE:
        return train_freq
    return TrainFreq(math.ceil(train_freq.frequency / n_envs), TrainFrequencyUnit.STEP)


def fresh_round_transitions(train_freq: TrainFreq | int | tuple[int, str], n_envs: int, memory: str) -> int | None:
    """
    :param train_freq: NFQ's ``train_freq`` (see :func:`round_length`)
    :param n_envs: number of envs
    :param memory: NFQ's ``memory``
    :return: the transitions every round's fit covers when that is known in advance: a fresh memory of rounds
        counted in steps; else ``None`` (a growing memory, episode rounds)
    """
    length = round_length(train_freq, n_envs)
    if memory == "fresh" and length.unit == TrainFrequencyUnit.STEP:
        return length.frequency * n_envs
    return None


def round_size(
    length: TrainFreq, round_fraction: float | None, held_transitions: int, n_envs: int, offset: int = 0
) -> int:
    """
    :param length: the round length ``train_freq`` asks for (:func:`round_length`)
    :param round_fraction: NFQ's ``round_fraction``, or ``None``
    :param held_transitions: transitions the memory holds as the round starts (all envs together)
    :param n_envs: number of envs
    :param offset: NFQ's ``round_fraction_offset``: transitions of the memory that ``round_fraction`` does not count
    :return: how long the round is, in episodes or ``env.step()`` calls: ``length``, or with ``round_fraction``
        (rounds counted in steps) the larger of ``length`` and ``round_fraction * (held_transitions - offset)``
        transitions, so that the fit per transition collected tends to about ``gradient_steps / round_fraction``
    """
    if round_fraction is None or length.unit == TrainFrequencyUnit.EPISODE:
        return length.frequency
    return max(length.frequency, math.ceil(round_fraction * (held_transitions - offset) / n_envs))


def check_round_fits(round_steps: int, memory: ReplayBuffer, buffer_size: int | None, round_number: int) -> None:
    """
    Refuse a round that has collected more than the memory holds (an episode round can): its first transitions
    were overwritten before they were fitted.

    :param round_steps: ``env.step()`` calls the round has collected so far
    :param memory: NFQ's memory
    :param buffer_size: NFQ's ``buffer_size`` (named in the error)
    :param round_number: the round (from 1)
    """
    if round_steps > memory.buffer_size:
        raise ValueError(
            f"Round {round_number} collected {round_steps * memory.n_envs} transitions, more than "
            f"buffer_size={buffer_size} holds; raise buffer_size."
        )


def missing_from_memory(round_steps: int, memory: ReplayBuffer, round_number: int) -> bool:
    """
    A model saved partway through a round and loaded without its replay buffer counts a partly collected round that
    its memory does not hold: fitting it would fit a short round of the transitions still to come. Say so with a
    warning, so that the round starts over.

    :param round_steps: ``env.step()`` calls the model counts into the current round
    :param memory: NFQ's memory
    :param round_number: the current round (from 1)
    :return: whether the round is missing from the memory, and must start over
    """
    if round_steps <= memory.size():
        return False
    warnings.warn(
        f"This model was saved {round_steps} env.step() calls into round {round_number}, but its "
        f"memory holds {memory.size()}: it was loaded without its replay buffer. The round starts "
        "over as a whole round; to go on with the collected transitions instead, call "
        "model.load_replay_buffer(path) (of a buffer saved with save_replay_buffer) before learn().",
        UserWarning,
        stacklevel=3,
    )
    return True


def store_interrupted_step(model: OffPolicyAlgorithm, callback: BaseCallback) -> None:
    """
    SB3's ``collect_rollouts`` returns as soon as a callback's ``on_step`` says stop, before it stores that step's
    transition and moves ``_last_obs`` on. Finish the step from the callback's view of ``collect_rollouts``' locals,
    so that nothing collected is lost and the next ``learn()`` goes on from the env's real state.

    :param model: the model collecting
    :param callback: the callback ``learn()`` passed to ``collect_rollouts``
    """
    assert model.replay_buffer is not None
    step: dict[str, Any] = callback.locals
    dones = np.asarray(step["dones"])
    model._update_info_buffer(step["infos"], dones)
    model._store_transition(
        model.replay_buffer, step["buffer_actions"], step["new_obs"], step["rewards"], dones, step["infos"]
    )
    model._update_current_progress_remaining(model.num_timesteps, model._total_timesteps)
    model._on_step()
    model._episode_num += int(dones.sum())
