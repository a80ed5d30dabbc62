"""
How NFQ acts: epsilon-greedy, with one coin flip per observation, or its temporally-extended form while collecting
(a random action repeated for a random number of steps); and the greedy action of the Q-network (or, optimistic, of
an ensemble's).
"""

from collections.abc import Callable
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space

from sb3_nfq.policies import NFQPolicy, critic_q_values


def reject_obs_info_pair(observation: Any) -> None:
    """Raise a ``ValueError`` if ``observation`` is the ``(obs, info)`` pair of a Gymnasium ``reset()``/``step()``."""
    if isinstance(observation, tuple) and len(observation) == 2 and isinstance(observation[1], dict):
        raise ValueError(
            "You have passed a tuple to predict() instead of a NumPy array or a Dict: probably the (obs, info) "
            "pair of a Gymnasium env's reset() or step(). Pass the observation alone: `obs, info = env.reset()` "
            "then `model.predict(obs)` (an SB3 VecEnv's reset() returns the observations alone)."
        )


def epsilon_greedy(
    epsilon: float, action_space: spaces.Space, n_obs: int, greedy: Callable[[], np.ndarray]
) -> np.ndarray:
    """
    :param epsilon: probability of a random action, for each observation independently
    :param action_space: a ``Discrete`` action space
    :param n_obs: number of observations acting at once
    :param greedy: gives the greedy actions of the observations (called only if one of them acts greedily)
    :return: one action per observation
    """
    assert isinstance(action_space, spaces.Discrete)
    explore = np.random.rand(n_obs) < epsilon
    actions = np.random.randint(int(action_space.n), size=n_obs)
    if explore.all():  # the network is only needed where some observation acts greedily
        return actions
    return np.where(explore, actions, np.reshape(greedy(), n_obs))


def repeated_epsilon_greedy(
    epsilon: float,
    action_space: spaces.Space,
    repeat_mu: float,
    steps_left: np.ndarray,
    repeated: np.ndarray,
    greedy: Callable[[], np.ndarray],
) -> np.ndarray:
    """
    Temporally-extended epsilon-greedy ("ez-greedy": W. Dabney, G. Ostrovski, A. Barreto, ICLR 2021). An env that is
    not repeating an action flips the epsilon coin; on heads it draws a random action and a duration
    ``n ~ Zeta(repeat_mu)`` (``P(n) ~ n^-repeat_mu``, ``n >= 1``), and takes that action for the next ``n`` steps.

    :param epsilon: probability that an env which is not repeating an action starts a random one
    :param action_space: a ``Discrete`` action space
    :param repeat_mu: the exponent of the durations' zeta distribution, > 1 (smaller: longer repeats)
    :param steps_left: for each env, the steps its random action still lasts (0: none); updated in place
    :param repeated: for each env, the random action it repeats; updated in place
    :param greedy: gives the greedy actions of the envs' observations (called only if one of them acts greedily)
    :return: one action per env
    """
    assert isinstance(action_space, spaces.Discrete)
    n_envs = len(steps_left)
    start = (steps_left == 0) & (np.random.rand(n_envs) < epsilon)
    steps_left[start] = np.random.zipf(repeat_mu, int(start.sum()))
    repeated[start] = np.random.randint(int(action_space.n), size=int(start.sum()))
    repeating = steps_left > 0
    steps_left[repeating] -= 1
    if repeating.all():
        return repeated.copy()
    return np.where(repeating, repeated, np.reshape(greedy(), n_envs))


def epsilon_greedy_predict(
    policy: NFQPolicy, observation: np.ndarray | dict[str, np.ndarray], epsilon: float
) -> np.ndarray:
    """
    ``predict(deterministic=False)``: epsilon-greedy, with an independent coin flip for each observation of a batch.

    :param policy: the NFQ policy
    :param observation: one observation or a batch of them (arrays, or lists and tuples of numbers as SB3's
        ``predict`` takes them)
    :param epsilon: probability of a random action
    :return: the action(s): one per observation of a batch, or a 0-d array for one observation
    """
    if isinstance(observation, dict):
        observation = {key: np.asarray(value) for key, value in observation.items()}
    else:
        observation = np.asarray(observation)
    vectorized = policy.is_vectorized_observation(observation)
    first = next(iter(observation.values())) if isinstance(observation, dict) else observation
    actions = epsilon_greedy(
        epsilon,
        policy.action_space,
        len(first) if vectorized else 1,
        lambda: policy.predict(observation, deterministic=True)[0],
    )
    return actions if vectorized else np.asarray(actions[0])


def greedy_actions(
    policy: NFQPolicy, observation: np.ndarray | dict[str, np.ndarray], ucb: float | None = None
) -> np.ndarray:
    """
    The greedy actions while collecting. ``collect_rollouts`` has already put the policy in eval mode, so plain
    vector observations (a non-image ``Box``) go straight to the Q-network: SB3's ``policy.predict`` would set the
    mode and convert the observation again at every step.

    :param policy: the NFQ policy
    :param observation: the current observations of the envs
    :param ucb: ``None``: the actions greedy on the Q-values (the critics' mean). A number ``c``: SUNRISE's optimistic
        actions, greedy on the critics' mean plus ``c`` times their standard deviation
    :return: one action per env
    """
    space = policy.observation_space
    plain_vectors = isinstance(observation, np.ndarray) and isinstance(space, spaces.Box) and not is_image_space(space)
    if ucb is None and not plain_vectors:
        return policy.predict(observation, deterministic=True)[0]
    obs = th.as_tensor(observation, device=policy.device) if plain_vectors else policy.obs_to_tensor(observation)[0]
    with th.no_grad():
        if ucb is None:
            q_values = policy.q_net(obs)
        else:
            per_critic = critic_q_values(policy.q_net, obs)
            q_values = per_critic.mean(dim=1) + ucb * per_critic.std(dim=1)
    return q_values.argmax(dim=1).cpu().numpy()
