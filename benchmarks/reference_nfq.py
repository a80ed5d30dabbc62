"""
Textbook Neural Fitted Q-Iteration in plain PyTorch: no Stable-Baselines3, one file, read top to bottom.

It is the yardstick of the benchmark suite: ``sb3_nfq.NFQ`` with its defaults should learn as fast (in env steps)
and run at least as fast (in seconds) as this. The algorithm is chapter 8 of "Grokking Deep Reinforcement
Learning":

1. collect ``transitions_per_round`` = 1024 fresh transitions (s, a, r, s', terminated) with an
   epsilon-greedy policy (epsilon = 0.5, constant);
2. ``fitting_iterations`` = 40 times: compute the TD targets ``r + gamma * max_a' Q(s', a')`` with the current
   network under ``torch.no_grad()`` (the target is a constant), then take one full-batch gradient step of the
   MSE between ``Q(s, a)`` and the targets;
3. throw the transitions away and go back to 1.

A true termination bootstraps on 0; a time-limit truncation bootstraps on ``Q(s', .)`` like any other step.
The network is ``obs -> 512 -> 128 -> n_actions`` with ReLU, fitted with RMSprop (lr 5e-4), and gamma = 1.
Episodes run on across rounds: a round ends after 1024 steps, not at an episode boundary.
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from torch import nn
from torch.nn import functional as F

RoundCallback = Callable[["ReferenceNFQ"], bool]
#: Called after each training episode ends, with the agent; returning False stops training there (the book's loop).
EpisodeCallback = Callable[["ReferenceNFQ"], bool]


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
    layers: list[nn.Module] = []
    width = obs_dim
    for size in hidden_sizes:
        layers += [nn.Linear(width, size), nn.ReLU()]
        width = size
    layers.append(nn.Linear(width, n_actions))
    return nn.Sequential(*layers)


def td_targets(q_net: nn.Module, batch: Transitions, gamma: float) -> th.Tensor:
    """
    :param q_net: the network being fitted
    :param batch: the round's transitions
    :param gamma: discount factor
    :return: ``r + gamma * max_a' Q(s', a')``, with 0 in place of the max after a true termination;
        computed without a graph, so no gradient flows through the targets.
    """
    with th.no_grad():
        max_next_q = q_net(batch.next_observations).max(dim=1, keepdim=True).values
        return batch.rewards + gamma * (1.0 - batch.terminated) * max_next_q


def fit_q_network(
    q_net: nn.Module, optimizer: th.optim.Optimizer, batch: Transitions, gamma: float, iterations: int
) -> th.Tensor:
    """
    The fitting phase of one round: ``iterations`` full-batch steps, each with freshly computed targets.

    :param q_net: the network being fitted
    :param optimizer: its optimizer
    :param batch: the round's transitions
    :param gamma: discount factor
    :param iterations: number of fitted iterations (the book's K)
    :return: the loss of each iteration (a detached tensor of shape ``(iterations,)``)
    """
    losses = []
    for _ in range(iterations):
        targets = td_targets(q_net, batch, gamma)
        q_taken = q_net(batch.observations).gather(1, batch.actions)
        loss = F.mse_loss(q_taken, targets)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.detach())
    return th.stack(losses) if losses else th.zeros(0)


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
        self.gamma = gamma
        self.epsilon = epsilon
        self.transitions_per_round = transitions_per_round
        self.fitting_iterations = fitting_iterations

        th.manual_seed(seed)
        self.rng = np.random.default_rng(seed)
        self.q_net = make_q_network(obs_shape[0], self.n_actions, hidden_sizes)
        self.optimizer = th.optim.RMSprop(self.q_net.parameters(), lr=learning_rate)

        self.num_timesteps = 0
        self.n_rounds = 0
        self.n_episodes = 0
        #: Set when an episode callback asked to stop training.
        self.stop_requested = False
        self.last_losses = th.zeros(0)
        self._obs, _ = self.env.reset(seed=seed)

    # --- acting ---------------------------------------------------------------------------------------------

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
        SB3's ``predict``, so that SB3's ``evaluate_policy`` can play it: greedy (or epsilon-greedy) action(s) for one
        observation or a batch.

        :param observation: one observation ``(obs_dim,)`` or a batch ``(n, obs_dim)``
        :param state: unused (no recurrent state)
        :param episode_start: unused (no recurrent state)
        :param deterministic: greedy if True, epsilon-greedy otherwise
        :return: the action(s) and ``None`` (no recurrent state)
        """
        batch = np.atleast_2d(observation)
        actions = self.act(batch)
        if not deterministic:
            explore = self.rng.random(len(batch)) < self.epsilon
            actions = np.where(explore, self.rng.integers(self.n_actions, size=len(batch)), actions)
        return (actions if np.ndim(observation) > 1 else actions[0]), None

    def _epsilon_greedy(self, observation: np.ndarray) -> int:
        if self.rng.random() < self.epsilon:
            return int(self.rng.integers(self.n_actions))
        return int(self.act(observation[None])[0])  # the network is only run when acting greedily

    # --- one round --------------------------------------------------------------------------------------------

    def collect_round(self, episode_callback: EpisodeCallback | None = None) -> Transitions:
        """
        Step the environment ``transitions_per_round`` times with the epsilon-greedy policy.

        :param episode_callback: called after each episode that ends; returning False stops collecting
        :return: the transitions, in collection order (fewer if ``episode_callback`` stopped the round: then
            ``stop_requested`` is set)
        """
        obs, actions, rewards, next_obs, terminated = [], [], [], [], []
        for _ in range(self.transitions_per_round):
            action = self._epsilon_greedy(self._obs)
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
                self.n_episodes += 1
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

    def fit(self, batch: Transitions) -> th.Tensor:
        """
        :param batch: the round's transitions
        :return: the loss of each fitted iteration
        """
        self.last_losses = fit_q_network(self.q_net, self.optimizer, batch, self.gamma, self.fitting_iterations)
        self.n_rounds += 1
        return self.last_losses

    def learn(
        self,
        total_timesteps: int,
        callback: RoundCallback | None = None,
        episode_callback: EpisodeCallback | None = None,
    ) -> "ReferenceNFQ":
        """
        Train in whole rounds until at least ``total_timesteps`` environment steps were taken.

        :param total_timesteps: environment-step budget (the last round is completed, so it may be exceeded)
        :param callback: called after each round (collect then fit) with this agent; returning False stops training
        :param episode_callback: called after each training episode ends, with this agent; returning False stops
            training at once (the round under way is not fitted)
        :return: this agent
        """
        while self.num_timesteps < total_timesteps:
            batch = self.collect_round(episode_callback)
            if self.stop_requested:  # the book stops at an episode's end, leaving the unfinished round unfitted
                break
            self.fit(batch)
            if callback is not None and not callback(self):
                break
        return self
