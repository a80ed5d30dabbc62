"""The hyperparameter file shipped as data (sb3_nfq/hyperparams/nfq.yml) and its reading into NFQ's arguments."""

from pathlib import Path

import gymnasium as gym
import pytest
import torch as th
import yaml
from stable_baselines3.common.callbacks import ProgressBarCallback, StopTrainingOnMaxEpisodes
from stable_baselines3.common.env_util import make_atari_env
from stable_baselines3.common.type_aliases import TrainFreq
from stable_baselines3.common.vec_env import VecFrameStack

from sb3_nfq import NFQ
from sb3_nfq.configs import (
    ENV_KEYS,
    ZOO_FILE,
    nfq_callbacks,
    nfq_kwargs,
    read_entry,
    vec_normalize_kwargs,
    zoo_to_kwargs,
)

BENCHMARK_ENVS = ["CartPole-v1", "Acrobot-v1", "MountainCar-v0", "LunarLander-v3"]


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "my_nfq.yml"
    path.write_text(text)
    return path


def test_the_file_has_an_entry_per_benchmark_env_the_default_and_atari() -> None:
    assert list(yaml.safe_load(ZOO_FILE.read_text())) == [*BENCHMARK_ENVS, "default", "atari"]
    assert ZOO_FILE.parent.name == "hyperparams" and ZOO_FILE.parent.parent.name == "sb3_nfq"


def test_the_entries_are_the_configs_measured_for_them() -> None:
    cartpole, mountain_car, default = (read_entry(env_id) for env_id in ("CartPole-v1", "MountainCar-v0", "default"))
    # CartPole: nfq-front-loaded-batch-128-keep-best, its keep_best now the callback
    assert (cartpole["round_fraction"], cartpole["round_fraction_offset"], cartpole["train_freq"]) == (0.4, 4000, 128)
    assert cartpole["batch_size"] == 128
    assert cartpole["callback"] == "sb3_nfq.KeepBestCallback" and "keep_best" not in cartpole
    # LunarLander: nfq-LunarLander-v3-30k-trial-119, trial 119 of the study nfq-LunarLander-v3-30k: a memory of 10,000,
    # half of it per fitted iteration, two networks collecting optimistically, epsilon held until the first termination
    lunar = read_entry("LunarLander-v3")
    assert (lunar["buffer_size"], lunar["iteration_transitions"], lunar["train_freq"], lunar["gradient_steps"]) == (
        10000,
        5000,
        128,
        1,
    )
    assert (lunar["loss"], lunar["huber_delta"], lunar["learning_rate"], lunar["n_steps"]) == (
        "huber",
        1.0,
        "lin_0.007607431015322478",
        3,
    )
    assert (lunar["exploration_ucb"], nfq_kwargs("LunarLander-v3")["policy_kwargs"]["n_critics"]) == (1.0, 2)
    assert lunar["exploration_start"] == "first_termination" and "max_grad_norm" not in lunar
    # Acrobot: nfq-front-loaded-batch-128-k12-first-termination-keep-best, CartPole's entry with 12 fitted iterations
    # per round and epsilon's schedule from the first termination
    acrobot_changes = {"gradient_steps": 12, "exploration_start": "first_termination"}
    assert {**read_entry("Acrobot-v1"), "n_timesteps": 0} == {**cartpole, "n_timesteps": 0, **acrobot_changes}
    # the one config: MountainCar's entry, at its own budget
    assert {**default, "n_timesteps": 0} == {**mountain_car, "n_timesteps": 0}
    assert (default["n_timesteps"], mountain_car["n_timesteps"]) == (100_000, 120_000)


@pytest.mark.parametrize("entry", [*BENCHMARK_ENVS, "default"])
def test_every_entry_builds_nfq_on_its_env_and_trains_one_round(entry: str) -> None:
    env_id = "CartPole-v1" if entry == "default" else entry
    if env_id == "LunarLander-v3":
        pytest.importorskip("Box2D")
    assert read_entry(entry)["n_timesteps"] > 0
    model = NFQ(read_entry(entry)["policy"], gym.make(env_id), seed=0, **nfq_kwargs(entry))
    assert isinstance(model.train_freq, TrainFreq)
    model.learn(total_timesteps=model.train_freq.frequency, callback=nfq_callbacks(entry))
    assert model._n_updates > 0


def test_atari_entry_builds_nfq_on_the_zoos_atari_stack_and_trains() -> None:
    ale_py = pytest.importorskip("ale_py")
    gym.register_envs(ale_py)
    with pytest.raises(ValueError, match="entry for atari builds the env \\(env_wrapper, frame_stack\\)"):
        nfq_kwargs("atari")
    hyperparams = read_entry("atari")
    # What the zoo builds from the entry: its wrapper, then frame stacking
    assert hyperparams.pop("env_wrapper") == ["stable_baselines3.common.atari_wrappers.AtariWrapper"]
    env = VecFrameStack(make_atari_env("PongNoFrameskip-v4", n_envs=1, seed=0), n_stack=hyperparams.pop("frame_stack"))
    assert hyperparams.pop("n_timesteps") > 0 and nfq_callbacks("atari") == []
    hyperparams.update(train_freq=64, gradient_steps=1)  # one small round: the entry's 4096 frames take minutes
    model = NFQ(env=env, seed=0, **zoo_to_kwargs(hyperparams))
    model.learn(total_timesteps=64)
    assert model._n_updates == 1  # 64 < batch_size: one full-batch step
    assert model.q_net(model.policy.obs_to_tensor(env.reset())[0]).shape == (1, 6)


def test_an_env_without_an_entry_gets_the_default_entry() -> None:
    assert read_entry("Pendulum-v1") == read_entry("default") != read_entry("CartPole-v1")
    assert nfq_kwargs("Pendulum-v1").keys() == nfq_kwargs("default").keys()


def test_a_file_read_by_path(tmp_path: Path) -> None:
    path = _write(tmp_path, "CartPole-v1:\n  n_timesteps: 1000\n  gamma: 0.9\ndefault:\n  n_timesteps: 5\n")
    assert read_entry("CartPole-v1", path) == {"n_timesteps": 1000, "gamma": 0.9}
    assert read_entry("Acrobot-v1", path) == {"n_timesteps": 5}
    assert nfq_kwargs("CartPole-v1", path) == {"gamma": 0.9}


def test_an_env_without_an_entry_or_a_default_is_refused_naming_the_entries(tmp_path: Path) -> None:
    path = _write(tmp_path, "CartPole-v1:\n  n_timesteps: 1000\nAcrobot-v1:\n  n_timesteps: 1000\n")
    with pytest.raises(KeyError, match=r"no entry for Pong-v5 and no 'default' entry; it has \['Acrobot-v1', 'Cart"):
        read_entry("Pong-v5", path)


def test_nfq_kwargs_leave_out_the_budget_policy_and_callbacks_and_read_the_rest_as_the_zoo() -> None:
    entry = read_entry("CartPole-v1")
    kwargs = nfq_kwargs("CartPole-v1")
    assert set(entry) - set(kwargs) == {"n_timesteps", "policy", "callback"}
    assert kwargs["policy_kwargs"] == {"net_arch": [256, 256], "optimizer_class": th.optim.Adam}
    assert kwargs["learning_rate"](0.5) == pytest.approx(0.00115)


def test_nfq_kwargs_refuses_an_entry_that_normalizes_the_env(tmp_path: Path) -> None:
    path = _write(tmp_path, "CartPole-v1:\n  n_timesteps: 1000\n  normalize: true\n")
    with pytest.raises(ValueError, match="entry for CartPole-v1 normalises the env \\(normalize: True\\)"):
        nfq_kwargs("CartPole-v1", path)
    path = _write(tmp_path, "CartPole-v1:\n  n_timesteps: 1000\n  normalize: false\n  gamma: 0.9\n")
    assert nfq_kwargs("CartPole-v1", path) == {"gamma": 0.9}


@pytest.mark.parametrize("key", ENV_KEYS)
def test_nfq_kwargs_refuses_an_entry_that_builds_the_env(tmp_path: Path, key: str) -> None:
    path = _write(tmp_path, f"CartPole-v1:\n  n_timesteps: 1000\n  {key}: 4\n")
    with pytest.raises(ValueError, match=f"entry for CartPole-v1 builds the env \\({key}\\)"):
        nfq_kwargs("CartPole-v1", path)


def test_nfq_callbacks_builds_a_class_path(tmp_path: Path) -> None:
    path = _write(tmp_path, "CartPole-v1:\n  callback: stable_baselines3.common.callbacks.ProgressBarCallback\n")
    first, second = nfq_callbacks("CartPole-v1", path), nfq_callbacks("CartPole-v1", path)
    assert [type(callback) for callback in first] == [ProgressBarCallback] and first[0] is not second[0]
    assert nfq_callbacks("CartPole-v1", _write(tmp_path, "CartPole-v1:\n  n_timesteps: 1\n")) == []


def test_nfq_callbacks_builds_a_list_of_class_paths_and_paths_with_arguments_that_learn_runs(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        "CartPole-v1:\n  callback:\n"
        "    - stable_baselines3.common.callbacks.ProgressBarCallback\n"
        "    - stable_baselines3.common.callbacks.StopTrainingOnMaxEpisodes:\n        max_episodes: 1\n",
    )
    progress_bar, stop = nfq_callbacks("CartPole-v1", path)
    assert isinstance(progress_bar, ProgressBarCallback)
    assert isinstance(stop, StopTrainingOnMaxEpisodes) and stop.max_episodes == 1
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0)
    model.learn(2048, callback=[stop])
    assert 0 < model.num_timesteps < 500  # stopped at the end of the first episode (CartPole's limit is 500 steps)


@pytest.mark.parametrize(
    ("callback", "message"),
    [
        ("sb3_nfq.NoSuchCallback", "callback 'sb3_nfq.NoSuchCallback' of .* cannot import it"),
        ("no_such_module.Callback", "callback 'no_such_module.Callback' of .* cannot import it"),
        ("ProgressBarCallback", "expected a class path such as 'package.module.ClassName'"),
        ("sb3_nfq.NFQ", "is not a stable_baselines3 BaseCallback class"),
        ("[{a.B: {}, c.D: {}}]", "expected one class path, with its keyword arguments"),
    ],
)
def test_nfq_callbacks_refuses_what_is_not_a_callback_class_path(tmp_path: Path, callback: str, message: str) -> None:
    path = _write(tmp_path, f"CartPole-v1:\n  callback: {callback}\n")
    with pytest.raises(ValueError, match=message):
        nfq_callbacks("CartPole-v1", path)


def test_zoo_strings_become_objects() -> None:
    kwargs = zoo_to_kwargs({"learning_rate": "lin_1e-3", "train_freq": [2, "episode"], "policy_kwargs": "dict(a=1)"})
    assert kwargs["learning_rate"](0.5) == pytest.approx(5e-4)
    assert kwargs["train_freq"] == (2, "episode") and kwargs["policy_kwargs"] == {"a": 1}
    with pytest.raises(ValueError, match="unknown learning-rate schedule"):
        zoo_to_kwargs({"learning_rate": "exp_1e-3"})


def test_normalize_is_read_as_the_rl_zoo_reads_it() -> None:
    assert vec_normalize_kwargs(False) is None
    assert vec_normalize_kwargs(True) == {}
    assert vec_normalize_kwargs(True, gamma=0.98) == {"gamma": 0.98}
    assert vec_normalize_kwargs("{'norm_obs': True, 'norm_reward': False}", gamma=0.99) == {
        "norm_obs": True,
        "norm_reward": False,
        "gamma": 0.99,
    }
    assert vec_normalize_kwargs({"norm_reward": False}) == {"norm_reward": False}
    with pytest.raises(ValueError, match="normalize must be true, false or a dict"):
        vec_normalize_kwargs("yes")
