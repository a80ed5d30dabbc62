"""NFQ behaves as an SB3 algorithm: policy aliases, vec envs, callbacks, logger, predict, modes."""

import itertools
import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_nfq import NFQ, CnnPolicy, MlpPolicy, MultiInputPolicy, NFQPolicy
from tests.conftest import TransitionRecorder, record_fitting
from tests.envs import LineWorld


def test_default_network_and_optimizer_are_the_textbooks() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1")
    linear_layers = [m for m in model.q_net.modules() if isinstance(m, th.nn.Linear)]
    assert [(layer.in_features, layer.out_features) for layer in linear_layers] == [(4, 512), (512, 128), (128, 2)]
    assert all(isinstance(m, th.nn.ReLU) for m in model.q_net.q_net if not isinstance(m, th.nn.Linear))
    assert isinstance(model.policy.optimizer, th.optim.RMSprop)
    assert model.policy.optimizer.param_groups[0]["lr"] == pytest.approx(5e-4)
    assert (model.train_freq.frequency, model.gradient_steps, model.gamma) == (1024, 40, 1.0)  # type: ignore[union-attr]
    assert model.exploration_rate == 0.5
    assert model.loss == "mse" and model.max_grad_norm is None and model.batch_size is None
    assert model.q_net is model.policy.q_net
    assert not hasattr(model.policy, "q_net_target")


@pytest.mark.parametrize(
    ("alias", "policy_class", "env_factory"),
    [
        ("MlpPolicy", MlpPolicy, lambda: gym.make("CartPole-v1")),
        ("CnnPolicy", CnnPolicy, lambda: LineWorld("image")),
        ("MultiInputPolicy", MultiInputPolicy, lambda: LineWorld("dict")),
    ],
)
def test_every_policy_alias_trains_and_predicts(alias: str, policy_class: type, env_factory: Any) -> None:
    env = env_factory()
    model = NFQ(alias, env, train_freq=32, gradient_steps=2, seed=0)
    assert type(model.policy) is policy_class
    fitting = record_fitting(model)
    params_before = [p.detach().clone() for p in model.q_net.parameters()]
    model.learn(64)
    assert fitting.optimizer_steps == 4
    assert any(not th.equal(a, b) for a, b in zip(params_before, model.q_net.parameters(), strict=True))
    obs, _ = env.reset(seed=0)
    action, _ = model.predict(obs, deterministic=True)
    assert env.action_space.contains(int(action))


def test_several_envs_train_and_vectorized_predict_returns_one_action_per_env() -> None:
    env = make_vec_env("CartPole-v1", n_envs=4, seed=0)
    model = NFQ("MlpPolicy", env, train_freq=128, gradient_steps=2, seed=0)
    model.learn(256)
    assert model.num_timesteps == 256 and model._n_rounds == 2
    obs = env.reset()
    assert isinstance(obs, np.ndarray)
    actions, _ = model.predict(obs, deterministic=False)
    assert actions.shape == (4,)


def test_works_under_vec_normalize() -> None:
    env = VecNormalize(make_vec_env("CartPole-v1", n_envs=2, seed=0))
    model = NFQ("MlpPolicy", env, train_freq=64, gradient_steps=2, seed=0)
    model.learn(128)
    assert model._n_rounds == 2


def test_callbacks_get_every_step_and_the_policy_is_in_eval_mode_while_collecting_train_mode_while_fitting() -> None:
    model = NFQ("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2, seed=0), train_freq=64, gradient_steps=3, seed=0)
    fitting = record_fitting(model)
    recorder = TransitionRecorder()
    model.learn(128, callback=recorder)
    assert recorder.n_calls == 128 // 2
    assert recorder.training_mode_while_collecting == {False}
    assert fitting.training_mode_while_fitting == {True}


def test_a_callback_can_stop_training_mid_round_and_the_next_learn_completes_and_fits_that_round() -> None:
    class StopAfter(BaseCallback):
        def _on_step(self) -> bool:
            return self.n_calls < 100

    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=3, seed=0)
    fitting = record_fitting(model)
    recorder = TransitionRecorder()
    model.learn(10_000, callback=[StopAfter(), recorder])
    assert model.num_timesteps == 100
    assert fitting.optimizer_steps == 3  # only the first, complete round was fitted
    assert model.replay_buffer.size() == 36  # the cut round's 36 steps, the one the callback stopped at included
    model.learn(28, reset_num_timesteps=False, callback=recorder)
    assert fitting.optimizer_steps == 6 and model.num_timesteps == 128
    observations, _, _ = recorder.transitions(64, 128)
    th.testing.assert_close(fitting.grad_inputs[-1], th.as_tensor(observations))  # steps 65-128 fitted together
    assert model.replay_buffer.size() == 0  # a fitted fresh round is discarded


def test_logger_records_sb3_and_nfq_keys(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=2, seed=0)
    model.set_logger(configure(str(tmp_path), ["json"]))
    model.learn(256, log_interval=1)
    rows = [json.loads(line) for line in (tmp_path / "progress.json").read_text().splitlines()]
    keys = set().union(*rows)
    for key in (
        "train/loss",
        "train/n_updates",
        "train/q_mean",
        "train/td_target_mean",
        "train/learning_rate",
        "train/n_rounds",
        "rollout/exploration_rate",
        "rollout/ep_rew_mean",
        "time/fps",
    ):
        assert key in keys, key
    assert max(row.get("train/n_updates", 0) for row in rows) <= 8
    assert {row["rollout/exploration_rate"] for row in rows if "rollout/exploration_rate" in row} == {0.5}


def test_tensorboard_run_is_named_nfq_and_progress_bar_works(tmp_path: Path) -> None:
    pytest.importorskip("tensorboard")  # an extra: absent from the lowest-versions check
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=32, gradient_steps=1, tensorboard_log=str(tmp_path), seed=0)
    model.learn(64, progress_bar=True)
    assert (tmp_path / "NFQ_1").is_dir()
    assert any((tmp_path / "NFQ_1").iterdir())


def test_exploration_schedule_decays_linearly_from_initial_to_final() -> None:
    model = NFQ(
        "MlpPolicy",
        "CartPole-v1",
        train_freq=100,
        gradient_steps=1,
        exploration_initial_eps=1.0,
        exploration_final_eps=0.1,
        exploration_fraction=0.5,
        seed=0,
    )
    rates: list[float] = []

    class RateRecorder(BaseCallback):
        def _on_step(self) -> bool:
            rates.append(self.model.exploration_rate)  # type: ignore[attr-defined]
            return True

    model.learn(1000, callback=RateRecorder())
    assert rates[0] == pytest.approx(1.0, abs=0.01)
    assert rates[249] == pytest.approx(0.55, abs=0.01)
    assert rates[-1] == pytest.approx(0.1)
    assert all(a >= b - 1e-9 for a, b in itertools.pairwise(rates))


def test_predict_is_greedy_when_deterministic_and_explores_otherwise() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0)
    obs = np.random.default_rng(0).normal(size=(500, 4)).astype(np.float32)
    greedy = model.q_net(th.as_tensor(obs, device=model.device)).argmax(dim=1).cpu().numpy()

    deterministic, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(deterministic, greedy)

    model.exploration_rate = 0.5
    explored, _ = model.predict(obs, deterministic=False)
    disagreement = np.mean(explored != greedy)
    assert 0.15 < disagreement < 0.35  # half the actions random, half of those differ from greedy

    model.exploration_rate = 0.0
    np.testing.assert_array_equal(model.predict(obs, deterministic=False)[0], greedy)

    single, _ = model.predict(obs[0], deterministic=True)
    assert single.shape == () and int(single) == greedy[0]


def test_adam_rprop_huber_and_gradient_clipping_train() -> None:
    for kwargs in (
        {"policy_kwargs": {"optimizer_class": th.optim.Adam}},
        {"policy_kwargs": {"optimizer_class": th.optim.Rprop}, "learning_rate": 0.01},
        {"loss": "huber", "max_grad_norm": 1.0},
        {"policy_kwargs": {"net_arch": [32], "activation_fn": th.nn.Tanh}},
    ):
        model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=3, seed=0, **kwargs)
        before = [p.detach().clone() for p in model.q_net.parameters()]
        model.learn(64)
        assert any(not th.equal(a, b) for a, b in zip(before, model.q_net.parameters(), strict=True)), kwargs


def test_learning_rate_schedule_is_applied_each_round() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=1, seed=0, learning_rate=lambda p: 1e-3 * p)
    model.learn(640)
    # the fit of the last round happens after all 640 steps: progress remaining is 0, so the lr is 0
    assert model.policy.optimizer.param_groups[0]["lr"] == pytest.approx(0.0, abs=1e-12)


def test_same_seed_gives_identical_results_on_cpu() -> None:
    def train(seed: int) -> tuple[list[th.Tensor], list[np.ndarray]]:
        recorder = TransitionRecorder()
        model = NFQ("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2), train_freq=128, gradient_steps=3, seed=seed)
        model.learn(512, callback=recorder)
        return [p.detach().clone() for p in model.q_net.parameters()], recorder.actions

    params_a, actions_a = train(7)
    params_b, actions_b = train(7)
    params_c, _ = train(8)
    for a, b in zip(params_a, params_b, strict=True):
        assert th.equal(a, b)
    np.testing.assert_array_equal(np.concatenate(actions_a), np.concatenate(actions_b))
    assert any(not th.equal(a, c) for a, c in zip(params_a, params_c, strict=True))


def test_nfq_policy_class_can_be_passed_directly() -> None:
    model = NFQ(NFQPolicy, DummyVecEnv([lambda: gym.make("CartPole-v1")]), train_freq=16, gradient_steps=1)
    model.learn(16)
    assert model._n_rounds == 1
