"""The NFQ loop: rounds of fresh transitions, K full-batch fitted iterations, detached targets, bootstrapping."""

from collections.abc import Callable
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv
from torch.nn import functional as F

from sb3_nfq import NFQ
from sb3_nfq.fitting import flushes_denormals, minibatch_indices
from sb3_nfq.parameters import loss_function
from tests.conftest import TransitionRecorder, record_fitting


@pytest.mark.parametrize("n_envs", [1, 3])
def test_each_round_fits_gradient_steps_times_on_exactly_its_own_transitions(n_envs: int) -> None:
    env = make_vec_env("CartPole-v1", n_envs=n_envs, seed=0)
    model = NFQ("MlpPolicy", env, train_freq=64, gradient_steps=5, seed=0)
    steps_per_round = -(-64 // n_envs)  # ceil: a round is rounded up to a multiple of n_envs
    round_size = steps_per_round * n_envs
    fitting = record_fitting(model)
    recorder = TransitionRecorder()

    model.learn(2 * round_size, callback=recorder)

    assert model.num_timesteps == 2 * round_size
    assert fitting.optimizer_steps == 2 * 5
    assert model._n_updates == 2 * 5
    assert len(fitting.grad_inputs) == 2 * 5
    for round_index in range(2):
        expected_obs, _, _ = recorder.transitions(round_index * steps_per_round, (round_index + 1) * steps_per_round)
        for fitted_iteration in range(5):
            fitted_obs = fitting.grad_inputs[round_index * 5 + fitted_iteration].numpy()
            # every transition of this round exactly once, in order, and nothing from another round
            np.testing.assert_array_equal(fitted_obs, expected_obs)


def one_sgd_round(env: str | VecEnv, **kwargs: Any) -> tuple[NFQ, ReplayBufferSamples, list[th.Tensor]]:
    """
    Train one real 200-transition round with a single plain SGD step (learning rate 0.1, gamma 0.9, a 16-unit net).

    :return: the model after the step, the round's transitions, and the Q-network's parameters before the step
    """
    model = NFQ(
        "MlpPolicy",
        env,
        train_freq=200,
        gradient_steps=1,
        gamma=0.9,
        learning_rate=0.1,
        policy_kwargs={"optimizer_class": th.optim.SGD, "net_arch": [16]},
        seed=0,
        **kwargs,
    )
    captured: dict[str, Any] = {}

    class BeforeFit(BaseCallback):
        def _on_rollout_end(self) -> None:
            captured["data"] = model._stored_transitions()
            captured["params"] = [p.detach().clone() for p in model.q_net.parameters()]

        def _on_step(self) -> bool:
            return True

    model.learn(200, callback=BeforeFit())
    assert isinstance(captured["data"], ReplayBufferSamples)
    return model, captured["data"], captured["params"]


def hand_step(
    model: NFQ, data: ReplayBufferSamples, params: list[th.Tensor], loss_fn: Callable[..., th.Tensor]
) -> list[th.Tensor]:
    """:return: the parameters after one SGD step (0.1) from ``params`` on ``loss_fn``, targets from a separate pass"""
    q_net = model.policy.make_q_net().to(model.device)
    with th.no_grad():
        for param, value in zip(q_net.parameters(), params, strict=True):
            param.copy_(value)
        target = data.rewards + (1 - data.dones) * 0.9 * q_net(data.next_observations).max(dim=1).values.reshape(-1, 1)
    loss_fn(th.gather(q_net(data.observations), 1, data.actions.long()), target).backward()
    after = []
    for before, param in zip(params, q_net.parameters(), strict=True):
        assert param.grad is not None
        after.append(before - 0.1 * param.grad)
    return after


def test_shared_forward_pass_gives_the_textbook_update_on_a_real_round() -> None:
    # Real CartPole round with several episode ends: NFQ reads most Q(s') from the Q(s) pass; the update
    # must equal the textbook's, computed by hand with a separate target pass over every s'.
    model, data, params = one_sgd_round(make_vec_env("CartPole-v1", n_envs=2, seed=0))
    assert data.dones.sum() >= 2
    for got, hand in zip(model.q_net.parameters(), hand_step(model, data, params, F.mse_loss), strict=True):
        th.testing.assert_close(got.detach(), hand, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("huber_delta", [0.5, 1.0])
def test_huber_delta_is_where_the_loss_of_a_real_round_turns_linear(huber_delta: float) -> None:
    # One SGD step on a real CartPole round must equal the step of torch's Huber loss with that delta, computed by
    # hand; the step with the other delta must differ (some TD errors exceed 0.5), so the test can fail.
    model, data, params = one_sgd_round("CartPole-v1", loss="huber", huber_delta=huber_delta)
    got = [param.detach() for param in model.q_net.parameters()]
    for got_param, hand_param in zip(
        got, hand_step(model, data, params, partial(F.huber_loss, delta=huber_delta)), strict=True
    ):
        th.testing.assert_close(got_param, hand_param, rtol=1e-5, atol=1e-6)
    other = hand_step(model, data, params, partial(F.huber_loss, delta=1.0 if huber_delta == 0.5 else 0.5))
    assert any(not th.allclose(a, b, rtol=1e-5, atol=1e-6) for a, b in zip(got, other, strict=True))


def test_huber_delta_1_is_sb3_dqns_smooth_l1_loss() -> None:
    generator = th.Generator().manual_seed(0)
    q_values, targets = th.randn(500, 1, generator=generator) * 3, th.randn(500, 1, generator=generator) * 3
    assert th.equal(loss_function("huber", 1.0)(q_values, targets), th.nn.functional.smooth_l1_loss(q_values, targets))


def test_round_is_discarded_after_fitting() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=32, gradient_steps=2, seed=0)
    model.learn(64)
    assert model.replay_buffer.size() == 0
    assert model._n_rounds == 2


@pytest.mark.parametrize("flushing_before", [False, True])
def test_every_gradient_step_runs_with_denormals_flushed_and_the_mode_found_comes_back(flushing_before: bool) -> None:
    if not th.set_flush_denormal(flushing_before):
        pytest.skip("this CPU cannot flush denormal floats to zero")
    modes: list[bool] = []

    class ModeRecordingAdam(th.optim.Adam):
        def step(self, closure: Any = None) -> Any:
            modes.append(flushes_denormals())
            return super().step(closure)

    try:
        assert flushes_denormals() == flushing_before
        # On a CPU: on another device the fit runs as it is.
        kwargs: dict[str, Any] = dict(train_freq=32, gradient_steps=2, seed=0, device="cpu")
        model = NFQ("MlpPolicy", "CartPole-v1", policy_kwargs=dict(optimizer_class=ModeRecordingAdam), **kwargs)
        model.learn(64)
        assert modes == [True] * 4
        assert flushes_denormals() == flushing_before
    finally:
        th.set_flush_denormal(False)


def test_the_flush_probe_reads_the_mode_whatever_the_default_dtype() -> None:
    if not th.set_flush_denormal(True):
        pytest.skip("this CPU cannot flush denormal floats to zero")
    default_dtype = th.get_default_dtype()
    try:
        th.set_default_dtype(th.float64)
        assert flushes_denormals()
        th.set_flush_denormal(False)
        assert not flushes_denormals()
    finally:
        th.set_default_dtype(default_dtype)
        th.set_flush_denormal(False)


def test_batch_size_splits_each_fitted_iteration_into_one_epoch_of_minibatches() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=3, batch_size=16, seed=0)
    fitting = record_fitting(model)
    recorder = TransitionRecorder()
    model.learn(64, callback=recorder)

    assert fitting.optimizer_steps == 3 * 4
    expected_obs, _, _ = recorder.transitions(0, 64)
    for fitted_iteration in range(3):
        epoch = th.cat(fitting.grad_inputs[fitted_iteration * 4 : (fitted_iteration + 1) * 4]).numpy()
        assert [len(batch) for batch in fitting.grad_inputs[fitted_iteration * 4 : (fitted_iteration + 1) * 4]] == [
            16
        ] * 4
        # the epoch covers every transition exactly once
        np.testing.assert_array_equal(np.sort(epoch, axis=0), np.sort(expected_obs, axis=0))


@pytest.mark.parametrize(
    ("n_transitions", "batch_size", "sizes"),
    [(65, 32, [32, 33]), (33, 32, [33]), (66, 32, [32, 32, 2]), (97, 16, [16] * 5 + [17]), (5, 1, [1] * 5)],
)
def test_minibatch_indices_cover_each_transition_once_with_no_lone_last_row(
    n_transitions: int, batch_size: int, sizes: list[int]
) -> None:
    batches = [batch for batch in minibatch_indices(n_transitions, batch_size, device=th.device("cpu"))]
    assert all(batch is not None for batch in batches)
    assert [len(batch) for batch in batches if batch is not None] == sizes
    indices = th.cat([batch for batch in batches if batch is not None])
    assert sorted(indices.tolist()) == list(range(n_transitions))


class BatchNormFeatures(BaseFeaturesExtractor):
    """A features extractor with a BatchNorm layer, which cannot normalise a mini-batch of one row in training."""

    def __init__(self, observation_space: gym.spaces.Box) -> None:
        super().__init__(observation_space, features_dim=8)
        self.net = th.nn.Sequential(th.nn.Linear(observation_space.shape[0], 8), th.nn.BatchNorm1d(8))

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.net(observations)


def test_batch_norm_network_learns_a_round_whose_size_leaves_one_row_over() -> None:
    model = NFQ(
        "MlpPolicy",
        "CartPole-v1",
        train_freq=65,
        batch_size=32,
        gradient_steps=2,
        seed=0,
        policy_kwargs={"features_extractor_class": BatchNormFeatures},
    )
    fitting = record_fitting(model)
    model.learn(65)
    assert model._n_rounds == 1
    assert [len(batch) for batch in fitting.grad_inputs] == [32, 33] * 2


def _store(model: NFQ, obs: np.ndarray, action: int, reward: float, next_obs: np.ndarray, end: str) -> None:
    """Add one transition as SB3's collection stores it: ``end`` is "none", "terminated" or "truncated"."""
    infos = [{"TimeLimit.truncated": end == "truncated"}]
    model.replay_buffer.add(
        obs[None], next_obs[None], np.array([[action]]), np.array([reward]), np.array([end != "none"]), infos
    )


def _one_fitted_step_update(model: NFQ) -> list[th.Tensor]:
    before = [p.detach().clone() for p in model.q_net.parameters()]
    model.train(gradient_steps=1, batch_size=None)
    return [after.detach() - start for after, start in zip(model.q_net.parameters(), before, strict=True)]


def _expected_sgd_update(
    model: NFQ, net_params: list[th.Tensor], terminated: th.Tensor, detach: bool
) -> list[th.Tensor]:
    """Redo the fitted step by hand on a copy of the network (SGD, lr=1): the update is minus the gradient."""
    data = model._stored_transitions()
    q_net = model.policy.make_q_net().to(model.device)
    with th.no_grad():
        for param, value in zip(q_net.parameters(), net_params, strict=True):
            param.copy_(value)
    next_q = q_net(data.next_observations).max(dim=1).values.reshape(-1, 1)
    if detach:
        next_q = next_q.detach()
    target = data.rewards + (1 - terminated.to(model.device)) * model.gamma * next_q
    q_sa = th.gather(q_net(data.observations), 1, data.actions.long())
    loss = th.nn.functional.mse_loss(q_sa, target)
    grads = th.autograd.grad(loss, list(q_net.parameters()))
    return [-g for g in grads]


def _crafted_model() -> tuple[NFQ, list[th.Tensor]]:
    model = NFQ(
        "MlpPolicy",
        "CartPole-v1",
        train_freq=3,
        gamma=0.9,
        seed=1,
        policy_kwargs={"optimizer_class": th.optim.SGD, "net_arch": [8]},
        learning_rate=1.0,
    )
    model.set_logger(Logger(folder=None, output_formats=[]))  # train() outside learn() needs a logger
    rng = np.random.default_rng(0)
    states = rng.normal(size=(6, 4)).astype(np.float32)
    _store(model, states[0], 0, 1.0, states[1], "none")
    _store(model, states[2], 1, 1.0, states[3], "terminated")
    _store(model, states[4], 1, 1.0, states[5], "truncated")
    params = [p.detach().clone() for p in model.q_net.parameters()]
    return model, params


def test_terminated_bootstraps_zero_and_truncated_bootstraps_next_q() -> None:
    model, params = _crafted_model()
    data = model._stored_transitions()
    assert data.dones.flatten().tolist() == [0.0, 1.0, 0.0]

    right = _expected_sgd_update(model, params, th.tensor([[0.0], [1.0], [0.0]]), detach=True)
    truncation_as_termination = _expected_sgd_update(model, params, th.tensor([[0.0], [1.0], [1.0]]), detach=True)
    no_termination = _expected_sgd_update(model, params, th.tensor([[0.0], [0.0], [0.0]]), detach=True)
    for wrong in (truncation_as_termination, no_termination):
        assert any(not th.allclose(a, b) for a, b in zip(right, wrong, strict=True))

    update = _one_fitted_step_update(model)
    for got, expected in zip(update, right, strict=True):
        th.testing.assert_close(got, expected, rtol=1e-4, atol=1e-6)


def test_gradient_flows_only_through_q_of_s_a_not_through_the_target() -> None:
    model, params = _crafted_model()
    terminated = model._stored_transitions().dones
    detached = _expected_sgd_update(model, params, terminated, detach=True)
    through_target = _expected_sgd_update(model, params, terminated, detach=False)
    # the two candidate updates differ, so this test can tell them apart
    assert any(not th.allclose(a, b) for a, b in zip(detached, through_target, strict=True))

    update = _one_fitted_step_update(model)
    for got, expected in zip(update, detached, strict=True):
        th.testing.assert_close(got, expected, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("n_envs", [1, 2])
def test_time_limit_truncation_is_not_termination_in_real_envs(n_envs: int) -> None:
    # CartPole cut at 5 steps: with a random policy most episodes are truncated, few terminate.
    env = DummyVecEnv([lambda: gym.make("CartPole-v1", max_episode_steps=5) for _ in range(n_envs)])
    model = NFQ(
        "MlpPolicy",
        env,
        train_freq=200,
        gradient_steps=1,
        exploration_initial_eps=1.0,
        exploration_final_eps=1.0,
        seed=0,
    )
    episode_ends: list[tuple[bool, bool]] = []

    captured: dict[str, ReplayBufferSamples] = {}

    class EndRecorder(BaseCallback):
        def _on_rollout_end(self) -> None:
            # called at the end of collection, right before fitting on the round
            captured["data"] = model._stored_transitions()

        def _on_step(self) -> bool:
            for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
                truncated = bool(info.get("TimeLimit.truncated", False))
                episode_ends.append((bool(done) and not truncated, truncated))
            return True

    model.learn(200, callback=EndRecorder())

    terminated_flags = captured["data"].dones.flatten().cpu().numpy()
    expected_terminated = np.array([terminated for terminated, _ in episode_ends], dtype=np.float32)
    assert any(truncated for _, truncated in episode_ends)
    np.testing.assert_array_equal(terminated_flags, expected_terminated)


@pytest.mark.parametrize("n_envs", [1, 2, 3, 5])
def test_round_size_is_train_freq_rounded_up_to_a_multiple_of_n_envs(n_envs: int) -> None:
    env = make_vec_env("CartPole-v1", n_envs=n_envs, seed=0)
    model = NFQ("MlpPolicy", env, train_freq=64, gradient_steps=1, seed=0)
    fitting = record_fitting(model)
    model.learn(64)
    expected = -(-64 // n_envs) * n_envs
    assert [len(x) for x in fitting.grad_inputs] == [expected]
    assert model.num_timesteps == expected


def test_episode_rounds_collect_whole_episodes() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=(3, "episode"), buffer_size=5_000, gradient_steps=2, seed=0)
    fitting = record_fitting(model)
    model.learn(1)
    assert model._episode_num == 3
    assert [len(x) for x in fitting.grad_inputs] == [model.num_timesteps] * 2
