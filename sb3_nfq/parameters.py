"""NFQ's parameters: their allowed values, and the checks that refuse anything else early, naming the parameter."""

import functools
import inspect
import math
import numbers
import warnings
from collections.abc import Callable
from typing import Any, Literal, NamedTuple

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule
from torch.nn import functional as F

#: Regression losses NFQ can fit its Q-values with (the textbook uses MSE).
LOSSES = ("huber", "mse")
LossName = Literal["mse", "huber"]
#: "fresh": the textbook's batch of one round, discarded after fitting; "growing": the 2005 paper's memory of
#: every transition so far (up to ``buffer_size``, then the oldest go first).
MEMORIES = ("fresh", "growing")
MemoryName = Literal["fresh", "growing"]
#: "recompute_every_step": the textbook's targets, recomputed before every gradient step;
#: "fixed_per_iteration": classic fitted Q-iteration, targets computed once per iteration then regressed on.
TARGET_MODES = ("recompute_every_step", "fixed_per_iteration")
TargetModeName = Literal["recompute_every_step", "fixed_per_iteration"]
#: When epsilon's schedule starts: "first_step" (SB3 DQN's), or "first_termination": at the first transition into a
#: terminal state (not a time-limit truncation) that NFQ collects, epsilon held at its initial value until then.
EXPLORATION_STARTS = ("first_step", "first_termination")
ExplorationStartName = Literal["first_step", "first_termination"]


#: NFQ's (and DQN's) default ``exploration_fraction``: only another value is known to be chosen, and refused when it
#: has no effect.
DEFAULT_EXPLORATION_FRACTION = 0.1


#: ``learn()``'s default budget: the textbook's CartPole-v1 budget, in env steps.
DEFAULT_TOTAL_TIMESTEPS = 300_000


#: DQN's parameters that NFQ has no counterpart for, and what NFQ does instead.
DQN_ONLY_PARAMETERS = {
    "learning_starts": "NFQ has no warm-up: it fits each round as soon as its train_freq transitions are collected",
    "target_update_interval": (
        "NFQ has no target network: its TD targets come from the network being fitted, recomputed before every "
        "step (target_mode='recompute_every_step', the textbook) or once per fitted iteration "
        "(target_mode='fixed_per_iteration')"
    ),
    "tau": "NFQ has no target network to update softly (see target_mode for how its targets are held still)",
    "optimize_memory_usage": "NFQ's memory keeps next observations explicitly; bound it with buffer_size instead",
    "replay_buffer_class": "NFQ builds its own memory: choose memory='fresh' (textbook) or 'growing', and buffer_size",
    "replay_buffer_kwargs": "NFQ builds its own memory: choose memory='fresh' (textbook) or 'growing', and buffer_size",
    "action_noise": "NFQ acts on Discrete actions, epsilon-greedy (exploration_initial_eps, exploration_final_eps)",
}


class RetiredParameter(NamedTuple):
    """An NFQ parameter that earlier versions had."""

    #: its value that did what NFQ does now
    default: object
    #: what else an earlier version saved with a model for it: attributes and networks
    saved: tuple[str, ...]
    #: what NFQ does instead
    instead: str


#: NFQ parameters that earlier versions had, and what NFQ does instead (a model loaded from an earlier version's zip
#: too: see :func:`~sb3_nfq.checkpoints.drop_retired`).
RETIRED_PARAMETERS = {
    "double_q": RetiredParameter(False, ("q_net_lagged",), "NFQ's targets bootstrap on max_a' Q(s', a')"),
    "round_step_size": RetiredParameter(1.0, (), "each round's fit is kept whole"),
    "keep_best": RetiredParameter(
        False,
        ("_best_score", "_returns_since_fit", "q_net_best"),
        "learn() ends with the last fit's weights; pass callback=sb3_nfq.KeepBestCallback() to learn() to end it "
        "with the best-scoring ones",
    ),
}


def reject_unknown_parameters(kwargs: dict[str, Any]) -> None:
    """
    :param kwargs: keyword arguments NFQ's constructor does not take
    :raises TypeError: naming the first one, and, for a DQN parameter or one NFQ no longer has, what NFQ does instead
    """
    for name in kwargs:
        if name in RETIRED_PARAMETERS:
            raise TypeError(f"NFQ no longer has the parameter {name!r}: {RETIRED_PARAMETERS[name].instead}.")
        if name in DQN_ONLY_PARAMETERS:
            raise TypeError(
                f"NFQ got DQN's parameter {name!r}, which it does not have: {DQN_ONLY_PARAMETERS[name]}. "
                "See 'Coming from DQN' in the README."
            )
        raise TypeError(f"NFQ.__init__() got an unexpected keyword argument {name!r}")


def check_action_space(action_space: spaces.Space | None) -> None:
    """Refuse action spaces NFQ's network cannot output a Q-value for each action of."""
    if not isinstance(action_space, spaces.Discrete):
        raise ValueError(
            "NFQ supports only Discrete action spaces (its network outputs one Q-value per action), "
            f"got {action_space}. For Box action spaces use SAC or TD3; "
            "for MultiDiscrete, wrap the env to flatten its actions."
        )
    if int(action_space.start) != 0:
        raise ValueError(
            f"NFQ supports Discrete action spaces that start at 0, got {action_space} (start={action_space.start}). "
            "Wrap the env so that its actions are 0..n-1."
        )


def _is_positive_number(value: object) -> bool:
    """:return: whether ``value`` is an int or float (not a bool) above 0"""
    return not isinstance(value, bool) and isinstance(value, int | float) and value > 0


def _is_finite_non_negative(value: object) -> bool:
    """:return: whether ``value`` is an int or float (not a bool) in ``[0, inf)``"""
    return not isinstance(value, bool) and isinstance(value, int | float) and 0 <= value < math.inf


def is_positive_int(value: object) -> bool:
    """:return: whether ``value`` is an int (not a bool) above 0"""
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


def check_total_timesteps(total_timesteps: int | None) -> int:
    """
    :param total_timesteps: ``learn()``'s budget in env steps, or ``None``
    :return: the budget: ``None`` gives :data:`DEFAULT_TOTAL_TIMESTEPS`, with a ``UserWarning`` saying how to watch
        the minutes it takes (at ``verbose=0`` nothing is printed); anything but a positive number is refused
    """
    if total_timesteps is None:
        warnings.warn(
            f"learn() was called without total_timesteps: NFQ trains for its default budget of "
            f"{DEFAULT_TOTAL_TIMESTEPS:,} env steps (the textbook's CartPole-v1 budget), which takes minutes. "
            "Pass progress_bar=True (or verbose=1) to watch the progress, or total_timesteps to choose the budget.",
            UserWarning,
            stacklevel=3,
        )
        total_timesteps = DEFAULT_TOTAL_TIMESTEPS
    if isinstance(total_timesteps, bool) or not isinstance(total_timesteps, numbers.Real) or not total_timesteps > 0:
        raise ValueError(f"total_timesteps (env steps to train for) must be a positive number, got {total_timesteps!r}")
    return total_timesteps


def check_hyperparameters(
    learning_rate: float | Schedule,
    train_freq: int | tuple[int, str],
    gradient_steps: int,
    batch_size: int | None,
    buffer_size: int | None,
    memory: str,
    round_fraction: float | None,
    round_fraction_offset: int,
    target_mode: str,
    fit_epochs: int,
    iteration_transitions: int | None,
    gamma: float,
    n_steps: int,
    loss: str,
    huber_delta: float,
    exploration_fraction: float,
    exploration_initial_eps: float,
    exploration_final_eps: float,
    exploration_repeat_mu: float | None,
    exploration_start: str,
    exploration_ucb: float | None,
    max_grad_norm: float | None,
) -> None:
    """Fail early, naming the parameter and its allowed values."""
    if not callable(learning_rate) and not learning_rate > 0:
        raise ValueError(f"learning_rate must be a positive number or a schedule, got {learning_rate!r}")
    frequency, unit = train_freq if isinstance(train_freq, tuple) else (train_freq, "step")
    if not is_positive_int(frequency):
        raise ValueError(f"train_freq (transitions per round) must be a positive integer, got {frequency!r}")
    if unit not in ("step", "episode"):
        raise ValueError(f"the unit of train_freq must be 'step' or 'episode', got {unit!r}")
    for name, value in (
        ("gradient_steps", gradient_steps),
        ("fit_epochs", fit_epochs),
        ("n_steps", n_steps),
        ("batch_size", batch_size),
        ("buffer_size", buffer_size),
        ("iteration_transitions", iteration_transitions),
    ):
        nullable = name in ("batch_size", "buffer_size", "iteration_transitions")
        if value is None and nullable:
            continue
        if not is_positive_int(value):
            raise ValueError(f"{name} must be a positive integer{' or None' if nullable else ''}, got {value!r}")
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"gamma must be in [0, 1], got {gamma!r}")
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {sorted(LOSSES)}, got {loss!r}")
    if not _is_positive_number(huber_delta):
        raise ValueError(f"huber_delta must be a positive number, got {huber_delta!r}")
    if loss != "huber" and huber_delta != 1.0:
        raise ValueError(
            f"huber_delta={huber_delta} sets the Huber loss's threshold, which needs loss='huber' (got loss={loss!r})"
        )
    if memory not in MEMORIES:
        raise ValueError(f"memory must be one of {list(MEMORIES)}, got {memory!r}")
    if buffer_size is not None and memory == "fresh" and unit == "step":
        raise ValueError(
            f"buffer_size={buffer_size} has no effect with memory='fresh' and train_freq counted in steps: the memory "
            "holds one round of train_freq transitions and is discarded once it is fitted. For a memory that keeps "
            "transitions across rounds, as DQN's replay buffer does, pass memory='growing'; else drop buffer_size."
        )
    if round_fraction is not None:
        if not _is_positive_number(round_fraction):
            raise ValueError(f"round_fraction must be a positive number or None, got {round_fraction!r}")
        if memory != "growing":
            raise ValueError(
                f"round_fraction={round_fraction} sizes rounds by the memory, which needs memory='growing' "
                f"(got memory={memory!r}: a fresh memory holds one round)"
            )
        if unit != "step":
            raise ValueError(f"round_fraction needs train_freq counted in steps, got train_freq={train_freq!r}")
    if type(round_fraction_offset) is not int or round_fraction_offset < 0:  # a bool is not an offset
        raise ValueError(f"round_fraction_offset must be an integer >= 0, got {round_fraction_offset!r}")
    if round_fraction_offset and round_fraction is None:
        raise ValueError(
            f"round_fraction_offset={round_fraction_offset} sets which transitions round_fraction counts, which "
            "needs round_fraction (got None)"
        )
    if target_mode not in TARGET_MODES:
        raise ValueError(f"target_mode must be one of {list(TARGET_MODES)}, got {target_mode!r}")
    if fit_epochs != 1 and target_mode != "fixed_per_iteration":
        raise ValueError(
            f"fit_epochs={fit_epochs} needs target_mode='fixed_per_iteration': with 'recompute_every_step' "
            "every step already uses fresh targets, so raise gradient_steps instead"
        )
    if not 0.0 < exploration_fraction <= 1.0:
        raise ValueError(f"exploration_fraction must be in (0, 1], got {exploration_fraction!r}")
    for name, eps in (
        ("exploration_initial_eps", exploration_initial_eps),
        ("exploration_final_eps", exploration_final_eps),
    ):
        if not 0.0 <= eps <= 1.0:
            raise ValueError(f"{name} must be a probability in [0, 1], got {eps!r}")
    if exploration_initial_eps == exploration_final_eps and exploration_fraction != DEFAULT_EXPLORATION_FRACTION:
        raise ValueError(
            f"exploration_fraction={exploration_fraction} sets how long epsilon takes to go from "
            f"exploration_initial_eps to exploration_final_eps, but both are {exploration_final_eps} (NFQ's default "
            "is the textbook's constant 0.5): set them apart (DQN's are 1.0 and 0.05) or drop exploration_fraction"
        )
    if exploration_repeat_mu is not None and not (
        _is_positive_number(exploration_repeat_mu) and exploration_repeat_mu > 1
    ):
        raise ValueError(
            "exploration_repeat_mu must be None (random actions of one step) or a number > 1 (the exponent of the "
            f"zeta distribution of their durations; 2.0 is the ez-greedy paper's), got {exploration_repeat_mu!r}"
        )
    if exploration_start not in EXPLORATION_STARTS:
        raise ValueError(f"exploration_start must be one of {list(EXPLORATION_STARTS)}, got {exploration_start!r}")
    if exploration_start != "first_step" and exploration_initial_eps == exploration_final_eps:
        raise ValueError(
            f"exploration_start={exploration_start!r} sets when epsilon starts to go from exploration_initial_eps to "
            f"exploration_final_eps, but both are {exploration_final_eps}: set them apart or drop exploration_start"
        )
    if exploration_ucb is not None and not _is_finite_non_negative(exploration_ucb):
        raise ValueError(
            "exploration_ucb must be None (greedy on the Q-values) or a number >= 0 (the weight of the critics' "
            f"standard deviation in the optimistic actions), got {exploration_ucb!r}"
        )
    if max_grad_norm is not None and not max_grad_norm > 0:
        raise ValueError(f"max_grad_norm must be positive or None (no clipping), got {max_grad_norm!r}")


def loss_function(loss: LossName, huber_delta: float) -> Callable[..., th.Tensor]:
    """
    :param loss: ``"mse"`` or ``"huber"``
    :param huber_delta: with ``"huber"``, the error at which the loss turns from squared to linear (at 1.0 it is
        ``F.smooth_l1_loss``, SB3 DQN's loss)
    :return: the regression loss, with ``torch.nn.functional``'s signature
    """
    if loss == "huber":
        return functools.partial(F.huber_loss, delta=float(huber_delta))
    return F.mse_loss


def check_full_batch_optimizer(
    optimizer: th.optim.Optimizer,
    batch_size: int | None,
    iteration_transitions: int | None,
    n_transitions: int | None,
    what: str,
) -> None:
    """
    Rprop adapts each weight's step from the signs of successive gradients: they must be full-batch, over the same
    transitions from one step to the next.

    :param optimizer: the policy's optimizer
    :param batch_size: NFQ's ``batch_size``
    :param iteration_transitions: NFQ's ``iteration_transitions``
    :param n_transitions: how many transitions a fit covers; ``None`` when it can grow past any bound
    :param what: what a fit covers, for the message
    """
    if not isinstance(optimizer, th.optim.Rprop):
        return
    use = "or another optimizer_class (RMSprop, Adam)"
    if batch_size is not None and (n_transitions is None or batch_size < n_transitions):
        raise ValueError(
            f"Rprop needs full-batch gradients, but batch_size={batch_size} would split {what} into mini-batches. "
            f"Use batch_size=None with Rprop, {use} for mini-batches."
        )
    if iteration_transitions is not None and (n_transitions is None or iteration_transitions < n_transitions):
        raise ValueError(
            f"Rprop needs full-batch gradients, but iteration_transitions={iteration_transitions} would fit a "
            f"different part of {what} in each iteration. Use iteration_transitions=None with Rprop, {use}."
        )


#: The NFQ parameters :func:`check_hyperparameters` checks (NFQ passes it those of its arguments).
HYPERPARAMETERS = frozenset(inspect.signature(check_hyperparameters).parameters)
