"""
The pieces of NFQ's fit: TD targets, the loss and its gradient over a batch of any size, network modes, mini-batch
epochs, taking rows of a batch.
"""

import contextlib
import math
import warnings
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_nfq.memory import rows_per_chunk
from sb3_nfq.policies import critic_q_values, n_critics

if TYPE_CHECKING:
    from sb3_nfq.nfq import NFQ


class NFQDivergenceError(FloatingPointError, ValueError):
    """
    The fitting loss became NaN or infinite. A ``FloatingPointError``, and also a ``ValueError`` so that
    RL Zoo / Optuna tuning prunes the diverging trial instead of stopping the whole study.

    Before that, with ``gamma < 1``, :func:`check_q_values_bounded` warns (once per ``learn()``) when the fitted
    Q-values go far past the largest value the rewards seen allow, and logs ``train/q_bound_exceeded``.
    """


def check_loss_is_finite(loss_value: float, round_number: int, iteration: int, iterations: int, timesteps: int) -> None:
    """
    Raise :class:`NFQDivergenceError` if the loss of a gradient step is NaN or infinite, before the step is applied.

    :param loss_value: the step's loss
    :param round_number: the round being fitted (from 1)
    :param iteration: the fitted iteration (from 1)
    :param iterations: the fitted iterations of the round
    :param timesteps: env steps taken so far
    """
    if not math.isfinite(loss_value):
        raise NFQDivergenceError(
            f"NFQ loss became {loss_value} in round {round_number} (fitted iteration {iteration}/{iterations}, "
            f"after {timesteps} env steps); training stopped before that step was applied. Check the rewards and "
            "observations for NaN/inf, or lower learning_rate, use loss='huber' or set max_grad_norm."
        )


#: How far above the largest value the rewards allow the fitted Q-values may go before :func:`check_q_values_bounded`
#: warns. Targets ``r + gamma * max Q(s', .)`` carry the max's overestimation into every round, so healthy training
#: (a growing memory on CartPole, say) can overshoot the bound several times over before its values settle; a
#: divergence multiplies them by orders of magnitude from one round to the next, so a factor of 100 delays the warning
#: by a round or two and stays clear of that overshoot.
Q_BOUND_MARGIN = 100.0


def q_value_bound(max_abs_reward: float, gamma: float) -> float | None:
    """
    :param max_abs_reward: the largest ``|r|`` seen so far
    :param gamma: the discount factor
    :return: the largest ``|Q(s, a)|`` these rewards allow, ``max |r| / (1 - gamma)``; ``None`` for ``gamma = 1``,
        where no such bound exists (undiscounted returns grow with the episode's length)
    """
    return None if gamma >= 1 else max_abs_reward / (1 - gamma)


def check_q_values_bounded(model: "NFQ", q_abs_max: float, rewards: th.Tensor) -> bool:
    """
    Divergence before it reaches NaN: with ``gamma < 1``, no return exceeds ``max |r| / (1 - gamma)``, so fitted
    Q-values far above it (:data:`Q_BOUND_MARGIN` times it; for rewards near 0, :data:`Q_BOUND_MARGIN` times 1, the
    scale of a network's first outputs) are bootstrapping on their own errors, which a loss that stays finite does
    not show. With ``gamma = 1`` there is no such bound and nothing is checked. Warns (``UserWarning``) once per
    ``learn()``: the model's ``_max_abs_reward`` and ``_q_bound_warned`` keep what this has seen.

    :param model: the model whose round (or dataset) was just fitted
    :param q_abs_max: the largest ``|Q(s, a)|`` of the fitted batch
    :param rewards: the fitted batch's rewards
    :return: whether the bound is exceeded
    """
    model._max_abs_reward = max(model._max_abs_reward, rewards.abs().max().item())
    max_abs_reward, gamma = model._max_abs_reward, model.gamma
    bound = q_value_bound(max_abs_reward, gamma)
    if bound is None or q_abs_max <= Q_BOUND_MARGIN * max(bound, 1.0):
        return False
    if not model._q_bound_warned:
        warnings.warn(
            f"NFQ's Q-values look divergent: after round {model._n_rounds} ({model.num_timesteps} env steps) the "
            f"largest |Q(s, a)| of the fitted batch is {q_abs_max:.4g}, but rewards of at most {max_abs_reward:.4g} "
            f"in size with gamma={gamma} bound every value by {bound:.4g} (warned above {Q_BOUND_MARGIN:g} times "
            "that). Lower learning_rate, use loss='huber' or set max_grad_norm; train/q_bound_exceeded logs each "
            "round.",
            UserWarning,
            stacklevel=2,
        )
        model._q_bound_warned = True
    return True


def flushes_denormals() -> bool:
    """:return: whether this thread's CPU now flushes denormal floats to zero (``torch.set_flush_denormal``)"""
    # 1e-40 is denormal in float32 whatever torch's default dtype (in float64 it is a normal number).
    return (th.full((), 1e-30, dtype=th.float32) * 1e-10).item() == 0.0


@contextlib.contextmanager
def denormals_flushed(device: th.device) -> Iterator[None]:
    """
    On a CPU, flush denormal floats (below ``1.2e-38`` in float32) to zero for the block, in this thread (with one
    torch thread, the whole computation), then restore the mode found. Adam's and RMSprop's running averages for a
    weight whose gradient stays zero (a ReLU unit that no longer fires) decay through the denormal range, where a CPU
    computes many times slower than on other floats; flushed, they are zero. The update a denormal average makes is far
    below a float32 weight's precision and is rounded away, so the weights come out the same unless the network's own
    activations or gradients reach that range.

    :param device: the fit's device; on any other than a CPU the block runs as it is
    """
    if device.type != "cpu":
        yield
        return
    was_flushing = flushes_denormals()
    th.set_flush_denormal(True)
    try:
        yield
    finally:
        th.set_flush_denormal(was_flushing)


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
        that covers every transition exactly once. A last mini-batch of one row (``n_transitions % batch_size ==
        1``, ``batch_size`` above 1) joins the one before it, which then holds ``batch_size + 1`` rows: a BatchNorm
        layer in training mode cannot normalise one row, and one row's gradient step would be the noisiest of all.
    """
    if batch_size is None or batch_size >= n_transitions:
        yield None
        return
    batches = list(th.randperm(n_transitions, device=device).split(batch_size))
    if batch_size > 1 and len(batches[-1]) == 1:
        batches[-2:] = [th.cat(batches[-2:])]
    yield from batches


def iteration_rows(n_transitions: int, iteration_transitions: int | None, device: th.device) -> th.Tensor | None:
    """
    :param n_transitions: number of transitions in the memory
    :param iteration_transitions: NFQ's ``iteration_transitions``
    :param device: device of the index tensor
    :return: ``None`` (the whole memory: no random number is drawn), or the rows of ``iteration_transitions``
        transitions drawn at random without replacement, when the memory holds more
    """
    if iteration_transitions is None or iteration_transitions >= n_transitions:
        return None
    return th.randperm(n_transitions, device=device)[:iteration_transitions]


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
    :return: the selected transitions
    """
    if indices is None:
        return batch
    return ReplayBufferSamples(
        observations=take_obs(batch.observations, indices),
        actions=batch.actions[indices],
        next_observations=take_obs(batch.next_observations, indices),
        dones=batch.dones[indices],
        rewards=batch.rewards[indices],
        discounts=None if batch.discounts is None else batch.discounts[indices],
    )


#: Most rows of one target pass over the memory on a CPU (for an ensemble, divided among its critics, each of which
#: computes its own activations). A pass over tens of thousands of rows at once moves activations too large for the
#: CPU's caches through memory, layer after layer; passes over pieces this size compute the same rows with the
#: activations in cache. Not measured on a GPU, where passes stay as large as memory allows.
TARGET_CHUNK_ROWS = 2048


def discount(data: ReplayBufferSamples, gamma: float) -> th.Tensor | float:
    """:return: what the transitions' bootstrapped values are discounted by: ``discounts`` (n-step), else ``gamma``"""
    return gamma if data.discounts is None else data.discounts


def td_targets(q_net: th.nn.Module, data: ReplayBufferSamples, gamma: float) -> th.Tensor:
    """
    :param q_net: the Q-network
    :param data: transitions
    :param gamma: the discount factor (n-step transitions carry their own, ``discounts``)
    :return: ``r + gamma * (1 - terminated) * max_a' Q(s', a')`` with the network in eval mode (no Dropout,
        BatchNorm's running statistics used and left as they are), as a constant (no graph), shape ``(n, critics)``
        (each critic's own targets; one critic for a plain ``QNetwork``); computed in chunks so that a large memory
        fits in memory (on a CPU, of at most :data:`TARGET_CHUNK_ROWS` rows)
    """
    with th.no_grad(), eval_mode(q_net):
        n_transitions, chunk_rows = len(data.rewards), rows_per_chunk(data.next_observations)
        if data.rewards.device.type == "cpu":
            chunk_rows = min(chunk_rows, max(1, TARGET_CHUNK_ROWS // n_critics(q_net)))
        if n_transitions <= chunk_rows:
            next_q_values = critic_q_values(q_net, data.next_observations).max(dim=2).values
        else:
            chunks = (slice(start, start + chunk_rows) for start in range(0, n_transitions, chunk_rows))
            next_q_values = th.cat(
                [critic_q_values(q_net, take_rows(data.next_observations, rows)).max(dim=2).values for rows in chunks]
            )
        return data.rewards + (1 - data.dones) * discount(data, gamma) * next_q_values


def states_and_successors(batch: ReplayBufferSamples, n_envs: int) -> tuple[th.Tensor, th.Tensor] | None:
    """
    In a round, the next state of a transition is usually the state of the same env's next transition (``n_envs``
    rows later): only episode ends and the last steps bring new states. So the targets need a forward pass over those
    few new states only, the rest of ``Q(s', .)`` being rows of ``Q(s, .)``: the same numbers as a pass over every
    ``s'``, for about half the work.

    :param batch: the whole memory
    :param n_envs: how many envs the rows interleave
    :return: ``(new_next_observations, next_rows)``: the ``s'`` not found among the ``s``, and for each transition
        ``i`` the row of ``cat([Q(s, .), Q(new_next_observations, .)])`` holding ``Q(s'_i, .)``. ``None`` for ``Dict``
        observations.
    """
    observations, next_observations = batch.observations, batch.next_observations
    if isinstance(observations, dict) or isinstance(next_observations, dict):
        return None
    n_transitions, offset = len(observations), n_envs
    is_next_state = th.zeros(n_transitions, dtype=th.bool, device=observations.device)
    if n_transitions > offset:
        successors = next_observations[:-offset] == observations[offset:]
        is_next_state[:-offset] = successors.reshape(n_transitions - offset, -1).all(dim=1)
    new_rows = th.nonzero(~is_next_state).flatten()
    next_rows = th.arange(n_transitions, device=observations.device) + offset
    next_rows[new_rows] = n_transitions + th.arange(len(new_rows), device=observations.device)
    return next_observations[new_rows], next_rows


def shared_successor_states(
    q_net: th.nn.Module, batch: ReplayBufferSamples, n_envs: int, batch_size: int | None
) -> tuple[th.Tensor, th.Tensor] | None:
    """
    :param q_net: the Q-network
    :param batch: the whole memory
    :param n_envs: how many envs the rows interleave
    :param batch_size: NFQ's ``batch_size``
    :return: :func:`states_and_successors` where ``Q(s', .)`` can be read off the ``Q(s, .)`` pass: full-batch steps
        whose pass covers the whole memory at once, with a network that computes the same in training and eval mode,
        on one-step transitions (an n-step ``s'`` is seldom the next row's ``s``); else ``None``
    """
    if batch.discounts is not None:
        return None
    n_transitions = len(batch.rewards)
    full_batch = batch_size is None or batch_size >= n_transitions
    one_pass = n_transitions <= rows_per_chunk(batch.observations)
    if full_batch and one_pass and not has_mode_dependent_layers(q_net):
        return states_and_successors(batch, n_envs)
    return None


def taken_q_values(q_values: th.Tensor, actions: th.Tensor) -> th.Tensor:
    """
    :param q_values: each critic's Q-values, ``(n, critics, n_actions)``
    :param actions: the actions taken, ``(n, 1)``
    :return: each critic's ``Q(s, a)`` of the actions taken, ``(n, critics)``
    """
    n_critics = q_values.shape[1]
    return th.gather(q_values, 2, actions.long().unsqueeze(1).expand(-1, n_critics, 1)).squeeze(2)


def loss_and_gradient(
    q_net: th.nn.Module,
    loss_fn: Callable[..., th.Tensor],
    gamma: float,
    data: ReplayBufferSamples,
    targets: th.Tensor | None,
    shared_states: tuple[th.Tensor, th.Tensor] | None,
) -> tuple[float, th.Tensor, th.Tensor]:
    """
    The loss of one gradient step over ``data``, and its gradient (``backward``). When ``data`` holds more rows than
    one forward pass may take (:func:`~sb3_nfq.memory.rows_per_chunk`: a large memory of images), the gradient is
    accumulated over chunks of rows: the same full-batch gradient, in bounded memory (a BatchNorm layer then
    normalises each chunk on its own).

    :param q_net: the Q-network
    :param loss_fn: the regression loss (``torch.nn.functional``'s signature)
    :param gamma: the discount factor
    :param data: the transitions of this gradient step
    :param targets: their TD targets if already known (fixed for the iteration), else ``None``: computed now
    :param shared_states: from :func:`states_and_successors` (``data`` is then the whole memory, in one pass: its
        ``Q(s', .)`` are read off the pass that computes ``Q(s, a)``), else ``None``
    :return: the loss, and ``Q(s, a)`` and the targets (of the last chunk), for logging
    """
    n_transitions, chunk_rows = len(data.rewards), rows_per_chunk(data.observations)
    if targets is None and shared_states is not None:
        new_next_observations, next_rows = shared_states
        all_q_values = critic_q_values(q_net, data.observations)
        with th.no_grad():
            q_candidates = th.cat([all_q_values.detach(), critic_q_values(q_net, new_next_observations)])
            next_q_values = q_candidates[next_rows].max(dim=2).values
            targets = data.rewards + (1 - data.dones) * discount(data, gamma) * next_q_values
        q_values = taken_q_values(all_q_values, data.actions)
    elif n_transitions <= chunk_rows:
        targets = td_targets(q_net, data, gamma) if targets is None else targets
        q_values = taken_q_values(critic_q_values(q_net, data.observations), data.actions)
    else:
        targets = td_targets(q_net, data, gamma) if targets is None else targets
        loss_value = 0.0
        for rows in th.arange(n_transitions, device=targets.device).split(chunk_rows):
            q_values = taken_q_values(critic_q_values(q_net, take_rows(data.observations, rows)), data.actions[rows])
            chunk_targets = targets[rows]
            loss = loss_fn(q_values, chunk_targets, reduction="sum") / targets.numel()
            loss.backward()
            loss_value += loss.item()
        return loss_value, q_values, chunk_targets
    loss = loss_fn(q_values, targets)
    loss.backward()
    return loss.item(), q_values, targets
