"""The pieces of a fit that are not NFQ's own: network modes, mini-batch epochs, taking rows of a batch."""

import contextlib
from collections.abc import Iterator
from typing import Any

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples


@contextlib.contextmanager
def eval_mode(module: th.nn.Module) -> Iterator[None]:
    """Put ``module`` in eval mode for the block, then back in the mode it was in."""
    was_training = module.training
    module.train(False)
    try:
        yield
    finally:
        module.train(was_training)


def has_mode_dependent_layers(module: th.nn.Module) -> bool:
    """:return: whether ``module`` holds layers that compute differently in training mode (BatchNorm, Dropout)"""
    mode_dependent = (th.nn.modules.batchnorm._NormBase, th.nn.modules.dropout._DropoutNd)
    return any(isinstance(layer, mode_dependent) for layer in module.modules())


def minibatch_indices(n_transitions: int, batch_size: int | None, device: th.device) -> Iterator[th.Tensor | None]:
    """
    :param n_transitions: number of transitions in the memory
    :param batch_size: ``None`` for the whole memory at once, else the mini-batch size
    :param device: device of the index tensors
    :return: ``None`` (the whole memory) once, or the indices of one shuffled epoch of mini-batches
        that covers every transition exactly once.
    """
    if batch_size is None or batch_size >= n_transitions:
        yield None
        return
    yield from th.randperm(n_transitions, device=device).split(batch_size)


def take_rows(observations: Any, rows: th.Tensor | slice) -> Any:
    """:return: the given rows of observations (a tensor, or a dict of tensors)"""
    if isinstance(observations, dict):
        return {key: value[rows] for key, value in observations.items()}
    return observations[rows]


def take_obs(observations: Any, indices: th.Tensor | None) -> Any:
    """:return: the observations at ``indices`` (``None``: all of them)"""
    return observations if indices is None else take_rows(observations, indices)


def take(batch: ReplayBufferSamples, indices: th.Tensor | None) -> ReplayBufferSamples:
    """
    :param batch: transitions
    :param indices: which ones (``None``: all)
    :return: the selected transitions (``discounts``, unused by NFQ, stays ``None``)
    """
    if indices is None:
        return batch
    return ReplayBufferSamples(
        observations=take_obs(batch.observations, indices),
        actions=batch.actions[indices],
        next_observations=take_obs(batch.next_observations, indices),
        dones=batch.dones[indices],
        rewards=batch.rewards[indices],
    )
