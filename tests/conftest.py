"""Shared helpers: record what NFQ collects and what it fits on, with real SB3 callbacks and torch hooks."""

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_nfq import NFQ


class TransitionRecorder(BaseCallback):
    """Record every transition (s, a, r) collected, in collection order, plus the policy mode while collecting."""

    def __init__(self) -> None:
        super().__init__()
        self.observations: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []
        self.rewards: list[np.ndarray] = []
        self.training_mode_while_collecting: set[bool] = set()

    def _on_step(self) -> bool:
        # on_step runs after env.step() and before the transition is stored: _last_obs is still s.
        assert isinstance(self.model._last_obs, np.ndarray)
        self.observations.append(self.model._last_obs.copy())
        self.actions.append(np.asarray(self.locals["actions"]).copy())
        self.rewards.append(np.asarray(self.locals["rewards"]).copy())
        self.training_mode_while_collecting.add(self.model.policy.training)
        return True

    def transitions(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        :param start: first env.step() call (0-based)
        :param stop: one past the last env.step() call
        :return: observations, actions and rewards of those calls, flattened step-major then env
        """
        obs = np.concatenate(self.observations[start:stop])
        return obs, np.concatenate(self.actions[start:stop]), np.concatenate(self.rewards[start:stop])


@dataclass
class FitRecord:
    """What the Q-network saw while fitting: the inputs of the forward passes that carried gradient."""

    grad_inputs: list[Any] = field(default_factory=list)  # tensors, or dicts of tensors for Dict observations
    no_grad_batch_sizes: list[int] = field(default_factory=list)
    training_mode_while_fitting: set[bool] = field(default_factory=set)
    optimizer_steps: int = 0


def record_fitting(model: NFQ) -> FitRecord:
    """
    Attach real torch hooks to ``model.q_net`` and its optimizer.

    :param model: the NFQ model to watch
    :return: the record, filled as the model trains
    """
    record = FitRecord()

    def on_forward(module: th.nn.Module, args: tuple[Any, ...]) -> None:
        (obs,) = args
        if isinstance(obs, dict):
            copy: Any = {key: value.detach().cpu().clone() for key, value in obs.items()}
            batch_size = len(next(iter(obs.values())))
        else:
            copy, batch_size = obs.detach().cpu().clone(), len(obs)
        if th.is_grad_enabled():
            record.grad_inputs.append(copy)
            record.training_mode_while_fitting.add(module.training)
        else:
            record.no_grad_batch_sizes.append(batch_size)

    def on_optimizer_step(optimizer: th.optim.Optimizer, args: Any, kwargs: Any) -> None:
        record.optimizer_steps += 1

    model.q_net.register_forward_pre_hook(on_forward)
    model.policy.optimizer.register_step_post_hook(on_optimizer_step)
    return record


@pytest.fixture(autouse=True)
def _one_torch_thread() -> None:
    """Unit tests use tiny networks: one thread is faster and leaves the other core free."""
    th.set_num_threads(1)
