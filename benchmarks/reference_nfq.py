"""
Textbook Neural Fitted Q-Iteration in plain PyTorch, no Stable-Baselines3 ("Grokking Deep Reinforcement Learning",
chapter 8): the yardstick ``sb3_nfq.NFQ`` with its defaults is measured against. Each round collects
``transitions_per_round`` fresh epsilon-greedy transitions, fits the network ``fitting_iterations`` times on them
(full batch, MSE to ``r + gamma * max_a' Q(s', a')`` recomputed each time, 0 after a true termination, ``Q(s', .)``
after a time-limit truncation), then throws them away. Episodes run on across rounds.
"""

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from torch import nn
from torch.nn import functional as F

#: Called with the agent after each round (``learn``'s ``callback``) or each training episode (``episode_callback``);
#: returning False stops training.
Callback = Callable[["ReferenceNFQ"], bool]


@dataclass(frozen=True)
class Transitions:
    """One round of transitions, as float32/int64 tensors with one row per transition."""

    observations: th.Tensor  # (n, obs_dim)
    actions: th.Tensor  # (n, 1), int64
    rewards: th.Tensor  # (n, 1)
    next_observations: th.Tensor  # (n, obs_dim)
    terminated: th.Tensor  # (n, 1), 1.0 only for true terminations (not time-limit truncations)


def make_q_network(obs_dim: int, n_actions: int, hidden_sizes: Sequence[int] = (512, 128)) -> nn.Sequential:
    """
    :param obs_dim: size of the (flat) observation
    :param n_actions: number of discrete actions
    :param hidden_sizes: widths of the hidden layers
    :return: the MLP ``obs -> hidden... -> n_actions`` with ReLU between layers (the textbook's Q-network)
    """
    widths = [obs_dim, *hidden_sizes]
    hidden = [layer for n_in, n_out in itertools.pairwise(widths) for layer in (nn.Linear(n_in, n_out), nn.ReLU())]
    return nn.Sequential(*hidden, nn.Linear(widths[-1], n_actions))


def td_targets(q_net: nn.Module, batch: Transitions, gamma: float) -> th.Tensor:
    """
    :param q_net: the network being fitted
    :param batch: the round's transitions
    :param gamma: discount factor
    :return: ``r + gamma * max_a' Q(s', a')``, 0 in place of the max after a true termination; no gradient flows
    """
    with th.no_grad():
        max_next_q = q_net(batch.next_observations).max(dim=1, keepdim=True).values
        return batch.rewards + gamma * (1.0 - batch.terminated) * max_next_q


def fit_q_network(
    q_net: nn.Module, optimizer: th.optim.Optimizer, batch: Transitions, gamma: float, iterations: int
) -> None:
    """
    The fitting phase of one round: ``iterations`` full-batch steps, each with freshly computed targets.

    :param q_net: the network being fitted
    :param optimizer: its optimizer
    :param batch: the round's transitions
    :param gamma: discount factor
    :param iterations: number of fitted iterations (the book's K)
    """
    for _ in range(iterations):
        targets = td_targets(q_net, batch, gamma)
        loss = F.mse_loss(q_net(batch.observations).gather(1, batch.actions), targets)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


class ReferenceNFQ:
    """
    Textbook NFQ on one gymnasium environment with a ``Discrete`` action space and a flat ``Box`` observation.

    :param env_id: gymnasium environment id (e.g. ``"CartPole-v1"``)
    :param seed: seeds torch's global generator (network initialisation), the exploration generator and the env
    :param hidden_sizes: hidden layer widths of the Q-network
    :param learning_rate: RMSprop learning rate
    :param gamma: discount factor (the book's CartPole code uses 1.0)
    :param epsilon: probability of a random action while collecting (constant)
    :param transitions_per_round: fresh transitions collected per round (the book's E)
    :param fitting_iterations: fitted iterations per round (the book's K)
    :param env_kwargs: extra keyword arguments for ``gymnasium.make`` (e.g. ``max_episode_steps``)
    """

    def __init__(
        self,
        env_id: str,
        seed: int = 0,
        hidden_sizes: Sequence[int] = (512, 128),
        learning_rate: float = 5e-4,
        gamma: float = 1.0,
        epsilon: float = 0.5,
        transitions_per_round: int = 1024,
        fitting_iterations: int = 40,
        env_kwargs: dict[str, Any] | None = None,
    ) -> None:
        self.env = gym.make(env_id, **(env_kwargs or {}))
        if not isinstance(self.env.action_space, spaces.Discrete):
            raise ValueError(f"ReferenceNFQ needs a Discrete action space, {env_id} has {self.env.action_space}")
        obs_shape = self.env.observation_space.shape
        if obs_shape is None or len(obs_shape) != 1:
            raise ValueError(f"ReferenceNFQ needs flat vector observations, {env_id} has {self.env.observation_space}")
        self.n_actions = int(self.env.action_space.n)
        self.gamma, self.epsilon = gamma, epsilon
        self.transitions_per_round, self.fitting_iterations = transitions_per_round, fitting_iterations
        th.manual_seed(seed)
        self.rng = np.random.default_rng(seed)
        self.q_net = make_q_network(obs_shape[0], self.n_actions, hidden_sizes)
        self.optimizer = th.optim.RMSprop(self.q_net.parameters(), lr=learning_rate)
        self.num_timesteps = 0
        #: Set when an episode callback asked to stop training.
        self.stop_requested = False
        self._obs, _ = self.env.reset(seed=seed)

    def act(self, observations: np.ndarray) -> np.ndarray:
        """
        :param observations: a batch of observations, shape ``(n, obs_dim)``
        :return: the greedy actions ``argmax_a Q(s, a)``, shape ``(n,)``
        """
        with th.no_grad():
            q_values = self.q_net(th.as_tensor(np.asarray(observations, dtype=np.float32)))
        return q_values.argmax(dim=1).numpy()

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: Any = None, deterministic: bool = True
    ) -> tuple[np.ndarray, None]:
        """
        SB3's ``predict``, so that SB3's ``evaluate_policy`` can play the greedy policy on a ``VecEnv``.

        :param observation: a batch of observations ``(n, obs_dim)``
        :param state: unused (no recurrent state)
        :param episode_start: unused (no recurrent state)
        :param deterministic: must be True: only the greedy policy is played
        :return: the greedy actions and ``None`` (no recurrent state)
        """
        if not deterministic:
            raise ValueError("ReferenceNFQ.predict plays the greedy policy only: deterministic must be True")
        return self.act(observation), None

    def collect_round(self, episode_callback: Callback | None = None) -> Transitions:
        """
        Step the environment ``transitions_per_round`` times with the epsilon-greedy policy.

        :param episode_callback: called after each episode that ends; returning False stops collecting
        :return: the transitions, in collection order (fewer if ``episode_callback`` stopped the round: then
            ``stop_requested`` is set)
        """
        obs, actions, rewards, next_obs, terminated = [], [], [], [], []
        for _ in range(self.transitions_per_round):
            if self.rng.random() < self.epsilon:
                action = int(self.rng.integers(self.n_actions))
            else:  # the network is only run when acting greedily
                action = int(self.act(self._obs[None])[0])
            next_observation, reward, is_terminated, is_truncated, _ = self.env.step(action)
            obs.append(self._obs)
            actions.append(action)
            rewards.append(float(reward))
            next_obs.append(next_observation)  # the true s', also at a truncation
            terminated.append(float(is_terminated))
            self._obs = next_observation
            self.num_timesteps += 1
            if is_terminated or is_truncated:
                self._obs, _ = self.env.reset()
                if episode_callback is not None and not episode_callback(self):
                    self.stop_requested = True
                    break
        # th.tensor copies into torch-allocated memory, as SB3's buffer.to_torch does: both fit on alike tensors.
        return Transitions(
            observations=th.tensor(np.asarray(obs, dtype=np.float32)),
            actions=th.tensor(actions, dtype=th.int64).reshape(-1, 1),
            rewards=th.tensor(rewards, dtype=th.float32).reshape(-1, 1),
            next_observations=th.tensor(np.asarray(next_obs, dtype=np.float32)),
            terminated=th.tensor(terminated, dtype=th.float32).reshape(-1, 1),
        )

    def learn(
        self, total_timesteps: int, callback: Callback | None = None, episode_callback: Callback | None = None
    ) -> "ReferenceNFQ":
        """
        Train in whole rounds until at least ``total_timesteps`` environment steps were taken.

        :param total_timesteps: environment-step budget (the last round is completed, so it may be exceeded)
        :param callback: called after each round (collect then fit); returning False stops training
        :param episode_callback: called after each training episode; returning False stops training at once (the
            round under way is not fitted, as in the book)
        :return: this agent
        """
        while self.num_timesteps < total_timesteps:
            batch = self.collect_round(episode_callback)
            if self.stop_requested:
                break
            fit_q_network(self.q_net, self.optimizer, batch, self.gamma, self.fitting_iterations)
            if callback is not None and not callback(self):
                break
        return self
