"""
What SB3 users do with an algorithm, done with NFQ: vec env classes and wrappers, observation spaces, image
layouts, checkpoints and resuming, evaluation logging, compiled policies, partial saves, parameters, optimizers.
"""

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.sb2_compat.rmsprop_tf_like import RMSpropTFLike
from stable_baselines3.common.vec_env import SubprocVecEnv, VecFrameStack, VecNormalize, VecTransposeImage

from sb3_nfq import NFQ
from sb3_nfq.policies import QNetwork
from tests.conftest import record_fitting
from tests.envs import ChannelFirst, LineWorld, SpaceEnv, SplitObservation

SMALL: dict[str, Any] = {"train_freq": 64, "gradient_steps": 2, "seed": 0}


def _parameters_equal(first: NFQ, second: NFQ) -> bool:
    return all(th.equal(a, b) for a, b in zip(first.q_net.parameters(), second.q_net.parameters(), strict=True))


# --- vec envs and wrappers -----------------------------------------------------------------------------------


def test_subproc_vec_env_trains_and_predicts() -> None:
    env = make_vec_env("CartPole-v1", n_envs=2, seed=0, vec_env_cls=SubprocVecEnv)
    try:
        model = NFQ("MlpPolicy", env, **SMALL)
        model.learn(128)
        assert model._n_rounds == 2 and model.num_timesteps == 128
        actions, _ = model.predict(env.reset(), deterministic=False)  # type: ignore[arg-type]
        assert actions.shape == (2,)
    finally:
        env.close()


def test_vec_frame_stack_with_dict_observations_stacks_each_key() -> None:
    env = VecFrameStack(make_vec_env(lambda: SplitObservation(gym.make("CartPole-v1")), n_envs=2, seed=0), n_stack=3)
    model = NFQ("MultiInputPolicy", env, **SMALL)
    fitting = record_fitting(model)
    model.learn(64)
    fitted = fitting.grad_inputs[0]
    assert set(fitted) == {"cart", "pole"} and fitted["cart"].shape == (64, 6) and fitted["pole"].shape == (64, 6)


def test_vec_normalize_normalizes_observations_and_rewards_in_the_fit_and_stores_raw_values() -> None:
    env = VecNormalize(make_vec_env("CartPole-v1", n_envs=2, seed=0), norm_obs=True, norm_reward=True)
    model = NFQ("MlpPolicy", env, train_freq=64, gradient_steps=1, seed=0)
    fitting = record_fitting(model)
    model.learn(64, callback=None)
    assert model.replay_buffer.size() == 0  # the fitted fresh round is gone; look at it through the fit
    raw_rewards = np.ones((64, 1), dtype=np.float32)  # CartPole pays 1 per step
    model.learn(62, reset_num_timesteps=False)  # a second round, cut one step short: it stays in the memory
    stored = model.replay_buffer
    assert isinstance(stored.observations, np.ndarray)
    raw_obs = stored.observations[:31].reshape(-1, 4)
    assert np.all(stored.rewards[:31] == 1.0)  # raw rewards stored
    batch = model._stored_transitions()
    expected_obs = env.normalize_obs(raw_obs)
    assert isinstance(batch.observations, th.Tensor) and isinstance(expected_obs, np.ndarray)
    np.testing.assert_allclose(batch.observations.cpu().numpy(), expected_obs, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(batch.rewards.cpu().numpy()[:62], env.normalize_reward(raw_rewards[:62]), rtol=1e-5)
    assert not np.allclose(batch.rewards.cpu().numpy(), 1.0)  # the fit sees normalised rewards
    first_fit = fitting.grad_inputs[0].numpy()
    assert np.abs(first_fit.mean(axis=0)).max() < 2.0 and not np.allclose(first_fit, 0)


# --- observation spaces and images ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("space", "width"), [(spaces.Discrete(5), 5), (spaces.MultiDiscrete([3, 4]), 7), (spaces.MultiBinary(6), 6)]
)
def test_discrete_multidiscrete_and_multibinary_observations(space: spaces.Space, width: int) -> None:
    env = SpaceEnv(space)
    model = NFQ("MlpPolicy", env, train_freq=32, gradient_steps=2, seed=0)
    fitting = record_fitting(model)
    model.learn(64)
    assert model._n_rounds == 2 and fitting.optimizer_steps == 4
    assert model.q_net.features_dim == width  # one-hot encoded as SB3 does
    obs, _ = env.reset(seed=1)
    for deterministic in (True, False):
        action, _ = model.predict(obs, deterministic=deterministic)
        assert env.action_space.contains(int(action))


def test_channel_first_images_train_as_they_are_and_channel_last_ones_are_transposed() -> None:
    last = NFQ("CnnPolicy", LineWorld("image"), train_freq=32, gradient_steps=1, seed=0)
    first = NFQ("CnnPolicy", ChannelFirst(LineWorld("image")), train_freq=32, gradient_steps=1, seed=0)
    assert isinstance(last.get_env(), VecTransposeImage) and not isinstance(first.get_env(), VecTransposeImage)
    assert last.observation_space.shape == first.observation_space.shape == (1, 36, 36)
    for model, env in ((last, LineWorld("image")), (first, ChannelFirst(LineWorld("image")))):
        model.learn(64)
        obs, _ = env.reset(seed=0)
        action, _ = model.predict(obs, deterministic=True)  # the env's own layout
        assert env.action_space.contains(int(action))
    fresh = NFQ("CnnPolicy", VecTransposeImage(make_vec_env(lambda: LineWorld("image"), n_envs=2)), **SMALL)
    fresh.learn(64)  # an env already wrapped by the user
    assert fresh._n_rounds == 1


@pytest.mark.parametrize(("normalize_images", "brightest"), [(True, 1.0), (False, 255.0)])
def test_normalize_images_decides_what_the_features_extractor_sees(normalize_images: bool, brightest: float) -> None:
    kwargs: dict[str, Any] = {"policy_kwargs": {"normalize_images": normalize_images}}
    model = NFQ("CnnPolicy", LineWorld("image"), train_freq=32, gradient_steps=1, seed=0, **kwargs)
    seen: list[float] = []
    extractor = model.q_net.features_extractor
    extractor.register_forward_pre_hook(lambda module, args: seen.append(float(args[0].max())))
    model.learn(32)
    assert max(seen) == brightest


# --- checkpoints, evaluation, saving ---------------------------------------------------------------------------


def test_checkpoint_with_replay_buffer_and_vecnormalize_then_resume_from_those_files(tmp_path: Path) -> None:
    env = VecNormalize(make_vec_env("CartPole-v1", n_envs=1, seed=0))
    model = NFQ("MlpPolicy", env, memory="growing", train_freq=64, gradient_steps=1, seed=0)
    checkpoint = CheckpointCallback(100, str(tmp_path), save_replay_buffer=True, save_vecnormalize=True)
    model.learn(200, callback=checkpoint)
    for kind in ("", "replay_buffer_", "vecnormalize_"):
        name = f"rl_model_{kind}100_steps.{'zip' if not kind else 'pkl'}"
        assert (tmp_path / name).exists(), name

    new_env = VecNormalize.load(str(tmp_path / "rl_model_vecnormalize_100_steps.pkl"), make_vec_env("CartPole-v1"))
    resumed = NFQ.load(tmp_path / "rl_model_100_steps.zip", env=new_env)
    resumed.load_replay_buffer(tmp_path / "rl_model_replay_buffer_100_steps.pkl")
    assert isinstance(new_env.obs_rms, RunningMeanStd)
    saved_stats = new_env.obs_rms.count
    # the checkpoint is taken in the 100th step's on_step, before that step is stored: 99 transitions, the
    # first 64 fitted, 35 of the second round waiting
    assert (resumed.num_timesteps, resumed._n_rounds, resumed.replay_buffer.size()) == (100, 1, 99)
    assert resumed._round_steps == 35
    resumed.learn(100, reset_num_timesteps=False)
    assert resumed.num_timesteps == 200 and resumed._n_rounds == 3  # rounds completed at 129 and 193 steps
    assert resumed.replay_buffer.size() == 199  # the loaded 99 and the 100 new: nothing lost
    assert resumed.get_vec_normalize_env() is new_env and new_env.obs_rms.count > saved_stats


def test_eval_callback_logs_on_the_timestep_it_evaluates_at(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=1, seed=0)
    model.set_logger(configure(str(tmp_path), ["json"]))
    eval_env = Monitor(gym.make("CartPole-v1"))
    evaluation = EvalCallback(eval_env, eval_freq=100, n_eval_episodes=2, log_path=str(tmp_path))
    model.learn(300, callback=evaluation)
    assert list(evaluation.evaluations_timesteps) == [100, 200, 300]
    rows = [json.loads(line) for line in (tmp_path / "progress.json").read_text().splitlines()]
    logged = [row["time/total_timesteps"] for row in rows if "eval/mean_reward" in row]
    assert logged == [100, 200, 300]


def test_a_compiled_policy_trains_saves_and_loads(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", **SMALL)
    model.policy = th.compile(model.policy, backend="eager")  # type: ignore[assignment]
    model.learn(64)
    model.save(tmp_path / "compiled.zip")
    loaded = NFQ.load(tmp_path / "compiled.zip")
    observations = np.random.default_rng(0).normal(size=(8, 4)).astype(np.float32)
    np.testing.assert_array_equal(
        loaded.predict(observations, deterministic=True)[0], model.predict(observations, deterministic=True)[0]
    )


def test_policy_only_and_q_net_only_round_trips(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", **SMALL)
    model.learn(64)
    model.policy.save(str(tmp_path / "policy.pth"))
    policy = type(model.policy).load(str(tmp_path / "policy.pth"))
    th.save(model.q_net.state_dict(), tmp_path / "q_net.pth")
    other = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=2, seed=1)
    other.q_net.load_state_dict(th.load(tmp_path / "q_net.pth"))
    assert _parameters_equal(model, other)
    observations = np.random.default_rng(0).normal(size=(8, 4)).astype(np.float32)
    expected, _ = model.predict(observations, deterministic=True)
    np.testing.assert_array_equal(policy.predict(observations, deterministic=True)[0], expected)
    np.testing.assert_array_equal(other.predict(observations, deterministic=True)[0], expected)
    assert isinstance(policy.q_net, QNetwork)


def test_set_parameters_checks_what_it_is_given() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", **SMALL)
    parameters: Any = model.get_parameters()
    assert set(parameters) == {"policy", "policy.optimizer"}
    with pytest.raises(ValueError, match="Names of parameters do not match"):
        model.set_parameters({"policy": parameters["policy"]}, exact_match=True)
    model.set_parameters({"policy": parameters["policy"]}, exact_match=False)
    unknown: Any = {"policy": parameters["policy"], "target": {}}
    with pytest.raises(ValueError, match="invalid object name"):
        model.set_parameters(unknown, exact_match=False)
    wrong_shape: Any = {"policy": {key: th.zeros(1) for key in parameters["policy"]}}
    with pytest.raises(RuntimeError, match="size mismatch"):
        model.set_parameters({**wrong_shape, "policy.optimizer": parameters["policy.optimizer"]})


def test_save_with_exclude_and_include(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", **SMALL)
    model.learn(64)
    model.save(tmp_path / "model.zip", exclude=["gamma"], include=["_last_obs"])
    loaded = NFQ.load(tmp_path / "model.zip")
    assert loaded.gamma == 1.0  # not saved: the constructor's default
    model.gamma = 0.5
    model.save(tmp_path / "gamma.zip")
    assert NFQ.load(tmp_path / "gamma.zip").gamma == 0.5
    np.testing.assert_array_equal(loaded._last_obs, model._last_obs)


def test_load_with_custom_objects_and_system_info(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", **SMALL)
    model.save(tmp_path / "model.zip")
    loaded = NFQ.load(
        tmp_path / "model.zip", custom_objects={"learning_rate": 1e-3, "gradient_steps": 5}, print_system_info=True
    )
    assert loaded.gradient_steps == 5 and loaded.learning_rate == 1e-3
    assert "== SAVED MODEL SYSTEM INFO ==" in capsys.readouterr().out
    loaded.set_env(make_vec_env("CartPole-v1"))
    loaded.learn(64)
    assert loaded.policy.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    assert loaded._n_updates == 5


@pytest.mark.parametrize("force_reset", [True, False])
def test_set_env_and_load_with_force_reset(tmp_path: Path, force_reset: bool) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", **SMALL)
    model.learn(100)  # ends mid-episode and mid-round
    last_obs = model._last_obs.copy()  # type: ignore[union-attr]
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "memory.pkl")  # the 36 transitions of the unfinished round
    env = make_vec_env("CartPole-v1", seed=5)
    loaded = NFQ.load(tmp_path / "model.zip", env=env, force_reset=force_reset)
    loaded.load_replay_buffer(tmp_path / "memory.pkl")
    if force_reset:
        assert loaded._last_obs is None  # a new episode at the next learn()
    else:
        np.testing.assert_array_equal(loaded._last_obs, last_obs)
        env.reset()  # without force_reset, stepping a new env is the user's business, as with any SB3 algorithm
    model.set_env(make_vec_env("CartPole-v1", seed=6), force_reset=force_reset)
    assert (model._last_obs is None) == force_reset
    loaded.learn(28, reset_num_timesteps=False)  # completes the round the model was saved in
    assert loaded._n_rounds == 2


def test_stats_window_size_sets_the_episode_statistics_window() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=256, gradient_steps=1, seed=0, stats_window_size=3)
    model.learn(256)
    assert model.ep_info_buffer is not None and model.ep_info_buffer.maxlen == 3
    assert len(model.ep_info_buffer) == 3


@pytest.mark.parametrize(
    ("optimizer_class", "optimizer_kwargs"), [(th.optim.AdamW, {"weight_decay": 0.1}), (RMSpropTFLike, {})]
)
def test_other_optimizers_train_with_their_settings(optimizer_class: type, optimizer_kwargs: dict[str, Any]) -> None:
    kwargs = {"optimizer_class": optimizer_class, "optimizer_kwargs": optimizer_kwargs}
    model = NFQ("MlpPolicy", "CartPole-v1", policy_kwargs=kwargs, **SMALL)
    assert isinstance(model.policy.optimizer, optimizer_class)
    for key, value in optimizer_kwargs.items():
        assert model.policy.optimizer.param_groups[0][key] == value
    before = [p.detach().clone() for p in model.q_net.parameters()]
    model.learn(64)
    assert all(not th.equal(a, b) for a, b in zip(before, model.q_net.parameters(), strict=True))


def test_an_empty_net_arch_is_a_linear_q_function() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", policy_kwargs={"net_arch": []}, **SMALL)
    linear_layers = [m for m in model.q_net.q_net.modules() if isinstance(m, th.nn.Linear)]
    assert [(layer.in_features, layer.out_features) for layer in linear_layers] == [(4, 2)]
    model.learn(64)
    assert model._n_rounds == 1
