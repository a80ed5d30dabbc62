"""Checkpoints: save -> load gives the same agent, optimizer state included, and training resumes."""

import base64
import io
import json
import pickle
import warnings
import zipfile
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import DQN
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.save_util import load_from_zip_file, save_to_zip_file

from sb3_nfq import NFQ
from sb3_nfq.parameters import RETIRED_PARAMETERS
from tests.conftest import record_fitting


@pytest.fixture
def trained(tmp_path: Path) -> tuple[NFQ, Path]:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=3, loss="huber", huber_delta=5.0, seed=0)
    model.learn(128)
    path = tmp_path / "nfq.zip"
    model.save(path)
    return model, path


def test_loaded_model_predicts_the_same_actions_and_q_values(trained: tuple[NFQ, Path]) -> None:
    model, path = trained
    loaded = NFQ.load(path)
    obs = np.random.default_rng(0).normal(size=(200, 4)).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    on_device = th.as_tensor(obs, device=model.device)
    th.testing.assert_close(loaded.q_net(on_device), model.q_net(on_device))
    assert loaded.q_net is loaded.policy.q_net
    assert (loaded.train_freq, loaded.gradient_steps, loaded.loss, loaded.huber_delta) == (
        model.train_freq,
        3,
        "huber",
        5.0,
    )
    assert loaded._n_rounds == 2 and loaded._n_updates == 6


def test_optimizer_state_survives_save_and_load(trained: tuple[NFQ, Path]) -> None:
    model, path = trained
    loaded = NFQ.load(path)
    saved_state = model.policy.optimizer.state_dict()
    loaded_state = loaded.policy.optimizer.state_dict()
    assert isinstance(loaded.policy.optimizer, th.optim.RMSprop)
    assert saved_state["param_groups"] == loaded_state["param_groups"]
    assert len(saved_state["state"]) == len(loaded_state["state"]) > 0
    for index, state in saved_state["state"].items():
        assert th.count_nonzero(state["square_avg"]) > 0
        th.testing.assert_close(loaded_state["state"][index]["square_avg"], state["square_avg"])


def test_training_resumes_identically_after_load(trained: tuple[NFQ, Path]) -> None:
    model, path = trained
    env = make_vec_env("CartPole-v1", n_envs=1, seed=3)
    loaded = NFQ.load(path, env=env)
    fitting = record_fitting(loaded)
    loaded.learn(64, reset_num_timesteps=False)
    assert loaded.num_timesteps == 192 and loaded._n_rounds == 3
    assert fitting.optimizer_steps == 3

    # same parameters, same optimizer state, same data -> same update as the original model
    model.set_env(make_vec_env("CartPole-v1", n_envs=1, seed=3))
    model.set_random_seed(5)
    model.learn(64, reset_num_timesteps=False)
    again = NFQ.load(path, env=make_vec_env("CartPole-v1", n_envs=1, seed=3))
    again.set_random_seed(5)
    again.learn(64, reset_num_timesteps=False)
    for a, b in zip(model.q_net.parameters(), again.q_net.parameters(), strict=True):
        th.testing.assert_close(a, b)


def test_set_parameters_set_env_and_load_on_more_envs(trained: tuple[NFQ, Path]) -> None:
    model, path = trained
    fresh = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=3, seed=1)
    fresh.set_parameters(str(path))
    obs = np.random.default_rng(1).normal(size=(50, 4)).astype(np.float32)
    np.testing.assert_array_equal(fresh.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])

    fresh.set_env(make_vec_env("CartPole-v1", n_envs=1, seed=0))
    fresh.learn(64)
    assert fresh._n_rounds == 1

    # another number of envs goes through load(path, env), as in SB3; the round is still 64 transitions
    on_four_envs = NFQ.load(path, env=make_vec_env("CartPole-v1", n_envs=4, seed=0))
    fitting = record_fitting(on_four_envs)
    on_four_envs.learn(64)
    assert [len(batch) for batch in fitting.grad_inputs] == [64] * 3


def test_load_from_a_file_object(trained: tuple[NFQ, Path]) -> None:
    model, path = trained
    loaded = NFQ.load(io.BytesIO(path.read_bytes()))
    obs = th.zeros((1, 4), device=model.device)
    th.testing.assert_close(loaded.q_net(obs), model.q_net(obs))


def test_loading_something_that_is_not_an_nfq_checkpoint_fails_clearly(tmp_path: Path) -> None:
    dqn_path = tmp_path / "dqn.zip"
    DQN("MlpPolicy", "CartPole-v1").save(dqn_path)
    with pytest.raises(ValueError, match=r"not an NFQ checkpoint.*DQNPolicy"):
        NFQ.load(dqn_path)

    text_file = tmp_path / "notes.zip"
    text_file.write_text("not a zip")
    with pytest.raises(ValueError, match="not an NFQ checkpoint"):
        NFQ.load(text_file)

    empty_zip = tmp_path / "empty.zip"
    with zipfile.ZipFile(empty_zip, "w") as archive:
        archive.writestr("readme.txt", "nothing")
    with pytest.raises(ValueError, match="not an NFQ checkpoint"):
        NFQ.load(empty_zip)

    with pytest.raises(FileNotFoundError):
        NFQ.load(tmp_path / "missing.zip")


def _earlier_versions_zip(model: NFQ, path: Path, retired: dict[str, Any]) -> Path:
    """Save ``model`` as an earlier version did: with ``retired`` data keys and, where used, their networks."""
    model.save(path)
    data, params, variables = load_from_zip_file(path)
    assert data is not None and params is not None
    networks: dict[str, Any] = dict(params)
    for name, used in (("q_net_lagged", "double_q"), ("q_net_best", "keep_best")):
        if retired[used]:
            networks[name] = model.q_net.state_dict()
    save_to_zip_file(path, data={**data, **retired}, params=networks, pytorch_variables=variables)
    return path


def test_a_zip_with_retired_parameters_loads_without_them_and_warns_naming_them(
    trained: tuple[NFQ, Path], tmp_path: Path
) -> None:
    model, _ = trained
    retired: dict[str, Any] = {
        "double_q": True,
        "round_step_size": 0.5,
        "keep_best": True,
        "_best_score": 187.0,
        "_returns_since_fit": [9.0],
    }
    old = _earlier_versions_zip(model, tmp_path / "old.zip", retired)
    with pytest.warns(UserWarning, match="saved by an earlier sb3-nfq") as caught:
        loaded = NFQ.load(old, env=make_vec_env("CartPole-v1", n_envs=1, seed=3))
    (message,) = [str(warning.message) for warning in caught if "earlier sb3-nfq" in str(warning.message)]
    for dropped in (
        "double_q=True, q_net_lagged",
        "round_step_size=0.5",
        "keep_best=True, q_net_best",
        "KeepBestCallback",
    ):
        assert dropped in message
    for name, parameter in RETIRED_PARAMETERS.items():
        assert all(not hasattr(loaded, attribute) for attribute in (name, *parameter.saved))
    obs = np.random.default_rng(2).normal(size=(50, 4)).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    loaded.learn(64, reset_num_timesteps=False)
    assert loaded._n_rounds == 3

    fresh = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=3, seed=1)
    with pytest.warns(UserWarning, match=r"dropped on loading: q_net_lagged \(.*\); q_net_best \("):
        fresh.set_parameters(str(old))
    np.testing.assert_array_equal(fresh.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def test_a_zip_with_retired_parameters_at_their_textbook_values_loads_without_them_silently(
    trained: tuple[NFQ, Path], tmp_path: Path
) -> None:
    model, _ = trained
    retired: dict[str, Any] = {
        "double_q": False,
        "round_step_size": 1.0,
        "keep_best": False,
        "_best_score": None,
        "_returns_since_fit": [],
    }
    old = _earlier_versions_zip(model, tmp_path / "old.zip", retired)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = NFQ.load(old)
    for name, parameter in RETIRED_PARAMETERS.items():
        assert all(not hasattr(loaded, attribute) for attribute in (name, *parameter.saved))


def test_a_model_saved_mid_round_and_loaded_without_its_memory_collects_a_whole_round(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=2, seed=0)
    model.learn(40)  # 40 of the round's 64 transitions collected, not fitted
    model.save(tmp_path / "model.zip")
    loaded = NFQ.load(tmp_path / "model.zip", env=make_vec_env("CartPole-v1", seed=1))
    fitting = record_fitting(loaded)
    with pytest.warns(UserWarning, match=r"40 env.step\(\) calls into round 1.*holds 0.*load_replay_buffer"):
        loaded.learn(24)
    assert loaded._n_rounds == 0 and loaded._round_steps == 24  # no short round of 24 transitions fitted
    loaded.learn(40, reset_num_timesteps=False)
    assert loaded._n_rounds == 1
    assert {len(batch) for batch in fitting.grad_inputs} == {64}


class _CreatesFile:
    """Unpickling this creates ``path``: what a crafted checkpoint could do with any code."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        return open, (str(self.path), "w")


def _replace_entry(source: Path, target: Path, key: str, value: Any) -> None:
    """Copy the checkpoint ``source`` to ``target`` with the pickle of its ``data`` entry ``key`` replaced."""
    with zipfile.ZipFile(source) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(entries["data"])
    data[key][":serialized:"] = base64.b64encode(pickle.dumps(value)).decode()
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(target, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)


def test_safe_load_runs_no_pickled_code_and_predicts_as_the_original(tmp_path: Path) -> None:
    model = NFQ(
        "MlpPolicy",
        "CartPole-v1",
        train_freq=64,
        gradient_steps=2,
        seed=0,
        policy_kwargs={"net_arch": [32], "optimizer_class": th.optim.Adam, "activation_fn": th.nn.Tanh},
    )
    model.learn(128)
    model.save(tmp_path / "nfq.zip")
    marker = tmp_path / "marker"
    _replace_entry(tmp_path / "nfq.zip", tmp_path / "crafted.zip", "exploration_schedule", _CreatesFile(marker))

    for env in (None, gym.make("CartPole-v1")):
        loaded = NFQ.load(tmp_path / "crafted.zip", env=env, safe=True)
        assert not marker.exists()
        obs = np.random.default_rng(0).normal(size=(200, 4)).astype(np.float32)
        np.testing.assert_array_equal(
            loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0]
        )
        assert loaded.policy.optimizer_class is th.optim.Adam and loaded.policy.activation_fn is th.nn.Tanh
        assert (loaded.train_freq, loaded.exploration_schedule(0.5)) == (model.train_freq, 0.5)
    loaded.learn(64)  # trains on from the safe load
    assert loaded._n_rounds == 3

    NFQ.load(tmp_path / "crafted.zip")  # the plain load runs the crafted pickle: the test's zip is a real attack
    assert marker.exists()


def test_safe_load_refuses_what_it_cannot_rebuild_naming_it(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=1, learning_rate=lambda progress: 1e-3)
    model.save(tmp_path / "nfq.zip")
    with pytest.raises(ValueError, match=r"cannot rebuild the checkpoint's 'learning_rate'.*custom_objects"):
        NFQ.load(tmp_path / "nfq.zip", safe=True)
    loaded = NFQ.load(tmp_path / "nfq.zip", safe=True, custom_objects={"learning_rate": 1e-3})
    assert loaded.learning_rate == 1e-3
