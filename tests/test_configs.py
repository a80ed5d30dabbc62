"""The configs shipped as data (sb3_nfq/hyperparams/*.yml) and their reading into NFQ's keyword arguments."""

from pathlib import Path

import pytest
import torch as th
import yaml

import sb3_nfq.configs
from sb3_nfq import NFQ
from sb3_nfq.configs import (
    RECOMMENDED,
    ZOO_FILE,
    config_names,
    nfq_kwargs,
    read_entry,
    vec_normalize_kwargs,
    zoo_file_text,
    zoo_to_kwargs,
)


def test_shipped_configs_are_the_named_files_without_the_zoo_file() -> None:
    assert config_names() == [
        "nfq-atari",
        "nfq-book",
        "nfq-capped",
        "nfq-capped-10k",
        "nfq-capped-mse",
        "nfq-front-loaded",
        "nfq-front-loaded-eps-0.01",
        "nfq-front-loaded-keep-best",
        "nfq-linear",
        "nfq-shared",
        "nfq-short-rounds",
        "nfq-short-rounds-64",
        "nfq-short-rounds-lr-lin-4e-3",
        "nfq-short-rounds-lr-lin-4e-3-huber",
        "nfq-short-rounds-lr-lin-4e-3-huber-10",
        "nfq-short-rounds-lr-lin-4e-3-huber-5",
        "nfq-tuned",
    ]


def test_an_env_without_an_entry_gets_the_default_entry() -> None:
    assert read_entry("nfq-book", "Pendulum-v1") == read_entry("nfq-book", "CartPole-v1") == {"n_timesteps": 300_000}
    assert read_entry("nfq-book", "LunarLander-v3") == {"n_timesteps": 500_000}


def test_the_zoo_file_is_generated_from_the_recommended_configs() -> None:
    assert ZOO_FILE.read_text() == zoo_file_text(), "regenerate it: python -m sb3_nfq.configs"
    table = yaml.safe_load(ZOO_FILE.read_text())
    assert list(table) == list(RECOMMENDED)
    for env_id, name in RECOMMENDED.items():
        entry = dict(table[env_id])
        assert entry.pop("policy") == read_entry(name, env_id).get("policy", "MlpPolicy")
        assert entry == {key: value for key, value in read_entry(name, env_id).items() if key != "policy"}
    # The envs RECOMMENDED gives nfq-short-rounds or its successor with a decaying step and the Huber loss (20k memory,
    # refitted every 128 steps), and CartPole nfq-front-loaded ending on its best-scoring fit: where they stayed solved
    # to the budget in the most seeds
    short_rounds_envs = ("MountainCar-v0", "LunarLander-v3")
    for env_id in short_rounds_envs:
        assert (table[env_id]["buffer_size"], table[env_id]["train_freq"]) == (20_000, 128)
    assert [table[env_id]["learning_rate"] for env_id in short_rounds_envs] == ["lin_0.004", 0.0005]
    assert [table[env_id]["loss"] for env_id in short_rounds_envs] == ["huber", "mse"]
    cartpole = table["CartPole-v1"]
    assert (cartpole["keep_best"], cartpole["round_fraction_offset"], cartpole["train_freq"]) == (True, 4000, 128)


def test_an_entry_becomes_nfq_keyword_arguments() -> None:
    entry = read_entry("nfq-shared", "Acrobot-v1")
    assert entry["n_timesteps"] == 100_000 and isinstance(entry["policy_kwargs"], str)
    kwargs = nfq_kwargs("nfq-shared", "Acrobot-v1")
    assert "n_timesteps" not in kwargs and kwargs["policy_kwargs"]["optimizer_class"] is th.optim.Adam
    model = NFQ("MlpPolicy", "Acrobot-v1", **kwargs)
    assert model.memory == "growing" and model.batch_size == 256
    # one config for every env: the entries differ in their budget only
    cartpole = read_entry("nfq-shared", "CartPole-v1")
    assert {key: value for key, value in entry.items() if key != "n_timesteps"} == {
        key: value for key, value in cartpole.items() if key != "n_timesteps"
    }


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


def test_nfq_kwargs_refuses_an_entry_that_normalizes_the_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "nfq-norm.yml").write_text("CartPole-v1:\n  n_timesteps: 1000\n  normalize: true\n")
    monkeypatch.setattr(sb3_nfq.configs, "HYPERPARAMS_DIR", tmp_path)
    monkeypatch.setattr(sb3_nfq.configs, "ZOO_FILE", tmp_path / "nfq.yml")
    with pytest.raises(ValueError, match="config 'nfq-norm' normalises CartPole-v1's env"):
        nfq_kwargs("nfq-norm", "CartPole-v1")


def test_unknown_names_and_envs_are_refused_clearly() -> None:
    with pytest.raises(KeyError, match="no config named 'nfq-best'"):
        read_entry("nfq-best", "CartPole-v1")
    with pytest.raises(KeyError, match="has no entry for Pong-v5"):
        read_entry("nfq-shared", "Pong-v5")
