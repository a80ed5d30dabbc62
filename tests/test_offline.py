"""Offline fitting: datasets from arrays, SB3 replay buffers and Minari, validated; the result is a normal NFQ."""

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env

from sb3_nfq import NFQ, TransitionDataset
from sb3_nfq.memory import stored_transitions
from tests.conftest import record_fitting
from tests.envs import random_cartpole_arrays


def cartpole_observation_space() -> spaces.Box:
    space = gym.make("CartPole-v1").observation_space
    assert isinstance(space, spaces.Box)
    return space


def dataset_from(arrays: dict[str, np.ndarray]) -> TransitionDataset:
    return TransitionDataset.from_arrays(
        arrays["obs"],
        arrays["act"],
        arrays["rew"],
        arrays["next"],
        arrays["term"],
        arrays["trunc"],
        action_space=spaces.Discrete(2),
        observation_space=cartpole_observation_space(),  # so that the model can go online on CartPole
    )


def test_fit_offline_from_arrays_gives_a_normal_nfq_that_saves_loads_and_learns_online(tmp_path: Path) -> None:
    dataset = dataset_from(random_cartpole_arrays(10, seed=0))
    model = NFQ.for_dataset("MlpPolicy", dataset, gradient_steps=3, train_freq=64, seed=0)
    assert model.env is None
    fitting = record_fitting(model)
    before = [p.detach().clone() for p in model.q_net.parameters()]

    model.fit_offline(dataset)

    assert fitting.optimizer_steps == 3 and [len(x) for x in fitting.grad_inputs] == [len(dataset)] * 3
    np.testing.assert_array_equal(fitting.grad_inputs[0].numpy(), dataset.observations)
    assert any(not th.equal(a, b) for a, b in zip(before, model.q_net.parameters(), strict=True))
    obs = dataset.observations[:20]
    actions, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(
        actions, model.q_net(th.as_tensor(obs, device=model.device)).argmax(dim=1).cpu().numpy()
    )

    model.save(tmp_path / "offline.zip")
    loaded = NFQ.load(tmp_path / "offline.zip", env=make_vec_env("CartPole-v1", n_envs=1, seed=0))
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], actions)
    loaded.learn(64)
    assert loaded._n_rounds == 2 and loaded.num_timesteps == 64

    model.set_env(make_vec_env("CartPole-v1", n_envs=1, seed=1))
    model.learn(64)
    assert model._n_rounds == 2


def test_fit_offline_uses_the_datasets_episode_ends() -> None:
    arrays = random_cartpole_arrays(30, seed=1, max_episode_steps=15)
    dataset = dataset_from(arrays)
    assert dataset.truncated.any() and dataset.terminated.any()
    data = dataset.samples()
    # only true terminations bootstrap on 0
    np.testing.assert_array_equal(data.dones.flatten().cpu().numpy().astype(bool), arrays["term"])


def test_a_datasets_samples_are_what_its_replay_buffer_holds() -> None:
    dataset = dataset_from(random_cartpole_arrays(30, seed=2, max_episode_steps=15))
    from_buffer = stored_transitions(dataset.to_replay_buffer("cpu"))
    for name, tensor in dataset.samples("cpu")._asdict().items():
        expected = getattr(from_buffer, name)
        if expected is None:  # SB3's n-step discounts, which neither holds
            assert tensor is None, name
            continue
        assert tensor.dtype == expected.dtype and tensor.shape == expected.shape, name
        np.testing.assert_array_equal(tensor.numpy(), expected.numpy())


def test_fit_offline_from_a_saved_sb3_replay_buffer(tmp_path: Path) -> None:
    env = make_vec_env(lambda: gym.make("CartPole-v1", max_episode_steps=10), n_envs=2, seed=0)
    collector = NFQ("MlpPolicy", env, memory="growing", buffer_size=600, train_freq=300, gradient_steps=1, seed=0)
    collector.learn(300)
    collector.save_replay_buffer(tmp_path / "buffer.pkl")

    dataset = TransitionDataset.from_replay_buffer(tmp_path / "buffer.pkl")
    assert len(dataset) == 300
    stored = collector._stored_transitions()
    np.testing.assert_array_equal(dataset.observations, stored.observations.cpu().numpy())
    np.testing.assert_array_equal(dataset.terminated, stored.dones.flatten().cpu().numpy().astype(bool))
    assert dataset.truncated.any()

    model = NFQ("MlpPolicy", "CartPole-v1", gradient_steps=2, seed=0)
    fitting = record_fitting(model)
    model.fit_offline(dataset, iterations=4)
    assert fitting.optimizer_steps == 4


def test_fit_offline_from_a_local_minari_dataset(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    minari = pytest.importorskip("minari")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    env = minari.DataCollector(gym.make("CartPole-v1", max_episode_steps=20))
    env.action_space.seed(0)
    n_steps = 0
    for episode in range(15):
        env.reset(seed=episode)
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            n_steps, done = n_steps + 1, terminated or truncated
    env.create_dataset(dataset_id="test/cartpole-random-v0", algorithm_name="uniform random")

    dataset = TransitionDataset.from_minari("test/cartpole-random-v0")
    assert len(dataset) == n_steps
    assert dataset.truncated.any() and dataset.terminated.any()
    model = NFQ.for_dataset("MlpPolicy", dataset, gradient_steps=2, seed=0)
    model.fit_offline(dataset)
    assert model._n_updates == 2


def _good_arrays() -> dict[str, Any]:
    arrays = random_cartpole_arrays(3, seed=2)
    return {
        "observations": arrays["obs"],
        "actions": arrays["act"],
        "rewards": arrays["rew"],
        "next_observations": arrays["next"],
        "terminated": arrays["term"],
        "truncated": arrays["trunc"],
        "action_space": spaces.Discrete(2),
        "observation_space": cartpole_observation_space(),
    }


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda a: {**a, "observations": a["observations"][:, :3]}, r"observations must have shape \(\d+, 4\)"),
        (lambda a: {**a, "actions": a["actions"][:-1]}, "rewards has .* rows, actions has"),
        (lambda a: {**a, "actions": a["actions"] + 1}, r"actions lie outside Discrete\(2\) \(allowed: 0..1\)"),
        (lambda a: {**a, "actions": a["actions"] - 0.5}, "actions must be integers"),
        (
            lambda a: {**a, "rewards": np.where(np.arange(len(a["rewards"])) == 3, np.nan, a["rewards"])},
            "rewards holds 1 NaN",
        ),
        (lambda a: {**a, "next_observations": a["next_observations"] * np.inf}, "next_observations holds .* NaN/inf"),
        (lambda a: {**a, "terminated": a["terminated"] * 2.0 + 1}, "terminated must hold booleans"),
        (lambda a: {key: (v[:0] if isinstance(v, np.ndarray) else v) for key, v in a.items()}, "the dataset is empty"),
        (lambda a: {**a, "action_space": spaces.Box(-1, 1, (1,))}, "action_space must be a Discrete space"),
    ],
)
def test_bad_datasets_are_rejected_with_the_field_named(change: Any, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        TransitionDataset.from_arrays(**change(_good_arrays()))


def test_a_dataset_that_does_not_fit_the_model_is_rejected() -> None:
    dataset = TransitionDataset.from_arrays(**_good_arrays())
    with pytest.raises(ValueError, match="the model expects"):
        NFQ("MlpPolicy", "Acrobot-v1").fit_offline(dataset)
    with pytest.raises(ValueError, match="iterations must be a positive integer"):
        NFQ("MlpPolicy", "CartPole-v1").fit_offline(dataset, iterations=0)
    with pytest.raises(ValueError, match="iterations must be a positive integer, got True"):
        NFQ("MlpPolicy", "CartPole-v1").fit_offline(dataset, iterations=True)
    with pytest.raises(ValueError, match="fit_offline fits one-step targets, but this model has n_steps=3"):
        NFQ("MlpPolicy", "CartPole-v1", n_steps=3).fit_offline(dataset)


def test_rprop_offline_with_minibatches_is_refused() -> None:
    dataset = TransitionDataset.from_arrays(**_good_arrays())
    model = NFQ(
        "MlpPolicy", "CartPole-v1", batch_size=16, train_freq=16, policy_kwargs={"optimizer_class": th.optim.Rprop}
    )
    with pytest.raises(ValueError, match="Rprop needs full-batch gradients"):
        model.fit_offline(dataset)


def test_rprop_offline_with_iteration_transitions_below_the_dataset_is_refused() -> None:
    dataset = TransitionDataset.from_arrays(**_good_arrays())
    rprop = {"optimizer_class": th.optim.Rprop}
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=2, iteration_transitions=2, policy_kwargs=rprop)
    with pytest.raises(ValueError, match="iteration_transitions=2 would fit a different part of the dataset's"):
        model.fit_offline(dataset)


def test_not_a_replay_buffer_file_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "buffer.pkl"
    path.write_text("garbage")
    with pytest.raises(ValueError, match="is not a replay buffer"):
        TransitionDataset.from_replay_buffer(path)
