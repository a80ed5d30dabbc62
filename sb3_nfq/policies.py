"""Policies for NFQ: one Q-network (state in, one value per action out), or an ensemble of them; no target network."""

import itertools
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    CombinedExtractor,
    FlattenExtractor,
    NatureCNN,
)
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.dqn.policies import DQNPolicy, QNetwork
from torch import nn

from sb3_nfq.parameters import is_positive_int

#: The textbook's hidden layers: obs -> 512 -> 128 -> n_actions.
TEXTBOOK_NET_ARCH = [512, 128]

__all__ = [
    "TEXTBOOK_NET_ARCH",
    "CnnPolicy",
    "CriticsQNetwork",
    "MlpPolicy",
    "MultiInputPolicy",
    "NFQPolicy",
    "QNetwork",
    "critic_q_values",
    "n_critics",
]


class BatchedMLP(nn.Module):
    """
    ``n_members`` MLPs of the same shape, each with its own weights, computed together by batched matrix products (one
    forward pass for all of them instead of one per member). Each member starts as a ``torch.nn.Linear`` stack would.

    :param input_dim: size of the input
    :param output_dim: size of each member's output
    :param net_arch: hidden layer sizes
    :param activation_fn: activation after each hidden layer
    :param n_members: number of MLPs
    """

    def __init__(
        self, input_dim: int, output_dim: int, net_arch: list[int], activation_fn: type[nn.Module], n_members: int
    ) -> None:
        super().__init__()
        sizes = [input_dim, *net_arch, output_dim]
        members = [[nn.Linear(n_in, n_out) for n_in, n_out in itertools.pairwise(sizes)] for _ in range(n_members)]
        self.weights = nn.ParameterList(
            nn.Parameter(th.stack([layers[i].weight.detach().T for layers in members])) for i in range(len(sizes) - 1)
        )
        self.biases = nn.ParameterList(
            nn.Parameter(th.stack([layers[i].bias.detach() for layers in members]).unsqueeze(1))
            for i in range(len(sizes) - 1)
        )
        self.activation = activation_fn()
        self.n_members = n_members

    def forward(self, features: th.Tensor) -> th.Tensor:
        """:return: each member's output, shape ``(batch, n_members, output_dim)``"""
        hidden = features.unsqueeze(0).expand(self.n_members, -1, -1)
        for layer, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            hidden = th.baddbmm(bias, hidden, weight)
            if layer < len(self.weights) - 1:
                hidden = self.activation(hidden)
        return hidden.transpose(0, 1)


class CriticsQNetwork(QNetwork):
    """
    ``n_critics`` Q-networks on one features extractor (each its own MLP from its own initial weights), computed as one
    batched network. ``forward`` gives their mean Q-values, on which NFQ acts greedily and is evaluated;
    :meth:`critic_q_values` gives each critic's, which NFQ's fit regresses each on its own TD targets.

    :param observation_space: Observation space
    :param action_space: Action space
    :param features_extractor: the features extractor, shared by the critics
    :param features_dim: number of features
    :param net_arch: each critic's hidden layer sizes
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param n_critics: number of Q-networks, at least 2
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        n_critics: int = 2,
    ) -> None:
        super().__init__(
            observation_space, action_space, features_extractor, features_dim, net_arch, activation_fn, normalize_images
        )
        self.n_critics = n_critics
        # In place of QNetwork's one MLP: all the critics' MLPs, batched.
        self.q_net = BatchedMLP(  # type: ignore[assignment]
            features_dim, int(action_space.n), self.net_arch, activation_fn, n_critics
        )

    def critic_q_values(self, obs: PyTorchObs) -> th.Tensor:
        """:return: each critic's Q-values, shape ``(batch, n_critics, n_actions)``"""
        return self.q_net(self.extract_features(obs, self.features_extractor))

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        """:return: the critics' mean Q-values, shape ``(batch, n_actions)``"""
        return self.critic_q_values(obs).mean(dim=1)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "n_critics": self.n_critics}


def n_critics(q_net: nn.Module) -> int:
    """:return: how many critics ``q_net`` computes: a :class:`CriticsQNetwork`'s ``n_critics``, else 1"""
    return q_net.n_critics if isinstance(q_net, CriticsQNetwork) else 1


def critic_q_values(q_net: nn.Module, obs: PyTorchObs) -> th.Tensor:
    """
    :param q_net: a Q-network: a :class:`CriticsQNetwork`, or any other (one critic)
    :param obs: observations
    :return: each critic's Q-values, shape ``(batch, critics, n_actions)``
    """
    if isinstance(q_net, CriticsQNetwork):
        return q_net.critic_q_values(obs)
    return q_net(obs).unsqueeze(1)


class NFQPolicy(DQNPolicy):
    """
    Policy for NFQ: a single Q-network ``q_net`` and its optimizer.

    It is SB3's :class:`~stable_baselines3.dqn.policies.DQNPolicy` without the target network:
    NFQ computes its targets with the network being fitted (detached), as in the textbook.

    :param observation_space: Observation space
    :param action_space: Action space (``Discrete``)
    :param lr_schedule: Learning rate schedule (could be constant)
    :param net_arch: Hidden layer sizes of the Q-network after the features extractor.
        Default: the textbook's ``[512, 128]``; ``[]`` after the ``NatureCNN`` extractor,
        whose own last layer is already 512 wide (as SB3's DQN does).
    :param activation_fn: Activation function (ReLU, as in the textbook)
    :param features_extractor_class: Features extractor to use.
    :param features_extractor_kwargs: Keyword arguments to pass to the features extractor.
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param optimizer_class: The optimizer to use, ``th.optim.RMSprop`` by default (the textbook's);
        ``th.optim.Adam`` and ``th.optim.Rprop`` (the 2005 paper's) work too.
    :param optimizer_kwargs: Additional keyword arguments, excluding the learning rate, to pass to the optimizer
    :param n_critics: 1 (textbook): one Q-network. More: an ensemble of that many Q-networks on one features
        extractor (:class:`CriticsQNetwork`), each fitted to its own TD targets; NFQ acts and is evaluated on their
        mean Q-values, and ``exploration_ucb`` collects on their spread
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.RMSprop,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_critics: int = 1,
    ) -> None:
        if not is_positive_int(n_critics):
            raise ValueError(f"n_critics (Q-networks of the ensemble) must be a positive integer, got {n_critics!r}")
        self.n_critics = n_critics
        if net_arch is None:
            net_arch = [] if features_extractor_class == NatureCNN else list(TEXTBOOK_NET_ARCH)
        if not all(is_positive_int(size) for size in net_arch):
            raise ValueError(f"net_arch must be a list of positive layer sizes, got {net_arch!r}")
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=net_arch,
            activation_fn=activation_fn,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
        )

    def make_q_net(self) -> QNetwork:
        """:return: the Q-network: SB3's ``QNetwork``, or with ``n_critics`` above 1 a :class:`CriticsQNetwork`"""
        if self.n_critics == 1:
            return super().make_q_net()
        net_args = self._update_features_extractor(self.net_args, features_extractor=None)
        return CriticsQNetwork(**net_args, n_critics=self.n_critics).to(self.device)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "n_critics": self.n_critics}

    def _build(self, lr_schedule: Schedule) -> None:
        """
        Create the Q-network and its optimizer (no target network).

        :param lr_schedule: Learning rate schedule; ``lr_schedule(1)`` is the initial learning rate
        """
        self.q_net = self.make_q_net()
        self.optimizer = self.optimizer_class(  # type: ignore[call-arg]
            self.q_net.parameters(),
            lr=lr_schedule(1),
            **self.optimizer_kwargs,
        )


MlpPolicy = NFQPolicy


class CnnPolicy(NFQPolicy):
    """
    NFQ policy for image observations (``NatureCNN`` features extractor).

    :param observation_space: Observation space
    :param action_space: Action space
    :param lr_schedule: Learning rate schedule (could be constant)
    :param net_arch: Hidden layer sizes after the CNN (default ``[]``)
    :param activation_fn: Activation function
    :param features_extractor_class: Features extractor to use.
    :param features_extractor_kwargs: Keyword arguments to pass to the features extractor.
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param optimizer_class: The optimizer to use, ``th.optim.RMSprop`` by default
    :param optimizer_kwargs: Additional keyword arguments, excluding the learning rate, to pass to the optimizer
    :param n_critics: number of Q-networks (see :class:`NFQPolicy`)
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = NatureCNN,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.RMSprop,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_critics: int = 1,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch,
            activation_fn,
            features_extractor_class,
            features_extractor_kwargs,
            normalize_images,
            optimizer_class,
            optimizer_kwargs,
            n_critics,
        )


class MultiInputPolicy(NFQPolicy):
    """
    NFQ policy for ``Dict`` observations (``CombinedExtractor`` features extractor).

    :param observation_space: Observation space (``Dict``)
    :param action_space: Action space
    :param lr_schedule: Learning rate schedule (could be constant)
    :param net_arch: Hidden layer sizes after the combined features (default ``[512, 128]``)
    :param activation_fn: Activation function
    :param features_extractor_class: Features extractor to use.
    :param features_extractor_kwargs: Keyword arguments to pass to the features extractor.
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param optimizer_class: The optimizer to use, ``th.optim.RMSprop`` by default
    :param optimizer_kwargs: Additional keyword arguments, excluding the learning rate, to pass to the optimizer
    :param n_critics: number of Q-networks (see :class:`NFQPolicy`)
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.RMSprop,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_critics: int = 1,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch,
            activation_fn,
            features_extractor_class,
            features_extractor_kwargs,
            normalize_images,
            optimizer_class,
            optimizer_kwargs,
            n_critics,
        )
