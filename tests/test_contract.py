"""
Breaks of the SB3 contract that SB3's own algorithm tests found in NFQ: the one-liner, ``predict``'s types and its
error for an ``(obs, info)`` tuple, targets computed in eval mode, rounds cut short, an empty memory.
"""

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, StopTrainingOnMaxEpisodes
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from sb3_nfq import NFQ
from sb3_nfq.fitting import td_targets
from sb3_nfq.policies import critic_q_values
from tests.envs import Frames, LineWorld


class StopAfterSteps(BaseCallback):
    """Stop training after ``n_steps`` calls of ``env.step()``."""

    def __init__(self, n_steps: int) -> None:
        super().__init__()
        self.n_steps = n_steps

    def _on_step(self) -> bool:
        return self.n_calls < self.n_steps


class NormalizedFeatures(BaseFeaturesExtractor):
    """A features extractor whose output depends on the mode: BatchNorm, then Dropout."""

    def __init__(self, observation_space: gym.spaces.Box, features_dim: int = 16) -> None:
        super().__init__(observation_space, features_dim)
        n_inputs = int(np.prod(observation_space.shape))
        self.net = th.nn.Sequential(
            th.nn.Linear(n_inputs, features_dim), th.nn.BatchNorm1d(features_dim), th.nn.ReLU(), th.nn.Dropout(0.5)
        )

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.net(observations)


NORMALIZED = {"features_extractor_class": NormalizedFeatures, "net_arch": [16]}


# 1. The design's one-liner


def test_learn_has_the_textbooks_budget_as_default_and_the_one_liner_trains_saying_so() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1")
    with pytest.warns(UserWarning, match=r"without total_timesteps.* 300,000 env steps.*progress_bar=True"):
        model.learn(callback=StopAfterSteps(2_100))  # the one-liner, cut after two textbook rounds
    assert model._total_timesteps == 300_000
    assert model._n_rounds == 2 and model.num_timesteps == 2_100


# 2. and 3. predict


@pytest.mark.parametrize(
    "env_factory",
    [lambda: gym.make("CartPole-v1"), lambda: LineWorld("image"), lambda: LineWorld("dict")],
    ids=["box", "image", "dict"],
)
def test_predict_returns_an_ndarray_whether_it_explores_or_acts_greedily(env_factory: Any) -> None:
    env = env_factory()
    policy = "MlpPolicy" if isinstance(env.observation_space, gym.spaces.Box) else "MultiInputPolicy"
    if isinstance(env, LineWorld) and env.kind == "image":
        policy = "CnnPolicy"
    model = NFQ(policy, env, seed=0)
    obs, _ = env.reset(seed=0)
    for deterministic, epsilon in ((False, 0.5), (False, 1.0), (False, 0.0), (True, 0.5)):
        model.exploration_rate = epsilon
        for _ in range(20):  # with epsilon 0.5, both the explore and the greedy branch are taken
            action, _ = model.predict(obs, deterministic=deterministic)
            assert isinstance(action, np.ndarray) and action.shape == (), (deterministic, epsilon, type(action))
            assert env.action_space.contains(int(action))


@pytest.mark.parametrize(("deterministic", "epsilon"), [(False, 0.5), (False, 1.0), (True, 0.5), (False, 0.0)])
def test_predict_on_an_obs_info_tuple_explains_the_mistake_on_every_path(deterministic: bool, epsilon: float) -> None:
    env = gym.make("CartPole-v1")
    model = NFQ("MlpPolicy", env, seed=0)
    model.exploration_rate = epsilon
    for _ in range(10):
        with pytest.raises(ValueError, match=r"obs, info = env\.reset\(\)"):
            model.predict(env.reset(seed=0), deterministic=deterministic)  # type: ignore[arg-type]


@pytest.mark.parametrize("deterministic", [False, True])
def test_predict_takes_lists_and_tuples_of_numbers_as_dqn_does(deterministic: bool) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0)  # exploration_rate 0.5: both the explore and the greedy branch
    for _ in range(20):
        for observation in ([0.0, 0.0, 0.0, 0.0], (0.0, 0.1, 0.0, -0.1)):
            action, _ = model.predict(observation, deterministic=deterministic)  # type: ignore[arg-type]
            assert isinstance(action, np.ndarray) and action.shape == () and int(action) in (0, 1)
        actions, _ = model.predict([[0.0, 0.0, 0.0, 0.0]] * 3, deterministic=deterministic)  # type: ignore[arg-type]
        assert isinstance(actions, np.ndarray) and actions.shape == (3,)


# 4. Targets in eval mode


def test_targets_are_computed_in_eval_mode_and_q_of_s_a_in_training_mode() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=3, seed=0, policy_kwargs=NORMALIZED)
    calls: list[tuple[bool, bool]] = []  # (training mode, gradient enabled) of each BatchNorm forward
    batch_norm = next(m for m in model.q_net.modules() if isinstance(m, th.nn.BatchNorm1d))
    batch_norm.register_forward_pre_hook(lambda module, args: calls.append((module.training, th.is_grad_enabled())))
    model.learn(128)
    fitting_calls = [call for call in calls if call[1]]
    target_calls = [call for call in calls if not call[1]]
    assert len(fitting_calls) == 6 and all(training for training, _ in fitting_calls)
    assert len(target_calls) >= 6 and not any(training for training, _ in target_calls)
    assert model.q_net.training  # back in training mode after each target pass


def test_targets_are_deterministic_and_leave_batchnorm_statistics_alone() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=1, seed=0, policy_kwargs=NORMALIZED)
    model.learn(64, callback=StopAfterSteps(63))  # 63 transitions in the memory, none fitted yet
    batch_norm = next(m for m in model.q_net.modules() if isinstance(m, th.nn.BatchNorm1d))
    model.q_net.train(True)
    batch = model._stored_transitions()
    stats_before = (batch_norm.running_mean.clone(), batch_norm.running_var.clone())  # type: ignore[union-attr]
    first, second = td_targets(model.q_net, batch, model.gamma), td_targets(model.q_net, batch, model.gamma)
    th.testing.assert_close(first, second)  # no Dropout on the targets
    th.testing.assert_close(batch_norm.running_mean, stats_before[0])
    th.testing.assert_close(batch_norm.running_var, stats_before[1])
    model.train(gradient_steps=1)  # the Q(s, a) pass does update them
    assert not th.equal(batch_norm.running_mean, stats_before[0])  # type: ignore[arg-type]


def test_a_round_whose_only_new_next_state_is_one_row_trains_with_batchnorm() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=8, gradient_steps=2, seed=0, policy_kwargs=NORMALIZED)
    model.learn(400)  # rounds of 8 steps inside one episode bring one new next state each
    assert model._n_rounds == 50


# 5. A round cut short keeps its data


def test_a_round_stopped_by_stop_training_on_max_episodes_is_kept_saved_and_completed(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=512, gradient_steps=2, seed=0)
    model.learn(10_000, callback=StopTrainingOnMaxEpisodes(max_episodes=3))
    kept = model.replay_buffer.size()
    assert model._n_rounds == 0 and kept == model.num_timesteps > 0  # every step of the three episodes is kept
    assert model.replay_buffer.dones[:kept].sum() == 3
    model.save_replay_buffer(tmp_path / "memory.pkl")
    model.save(tmp_path / "model.zip")

    loaded = NFQ.load(tmp_path / "model.zip", env=gym.make("CartPole-v1"))
    loaded.load_replay_buffer(tmp_path / "memory.pkl")
    np.testing.assert_array_equal(loaded.replay_buffer.observations[:kept], model.replay_buffer.observations[:kept])
    loaded.learn(512 - kept, reset_num_timesteps=False)
    assert loaded._n_rounds == 1 and loaded.num_timesteps == 512  # the loaded round was completed, then fitted
    assert loaded.replay_buffer.size() == 0


# 6. An empty memory


def test_training_on_an_empty_memory_says_so() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0)
    with pytest.raises(ValueError, match=r"memory is empty.*learn\(\).*load_replay_buffer"):
        model.train(gradient_steps=1)


# 7. A growing memory of images is bounded


def test_an_image_memory_that_cannot_fit_in_ram_is_refused_naming_buffer_size() -> None:
    with pytest.raises(ValueError, match=r"buffer_size=100,000,000 .* GiB .*Pass a smaller buffer_size"):
        NFQ("CnnPolicy", Frames(), memory="growing", buffer_size=100_000_000)  # 5.3 TiB of frames
    from sb3_nfq.memory import available_memory_bytes, memory_bytes

    available = available_memory_bytes()
    default_needed = memory_bytes(Frames().observation_space, 1_000_000)  # the growing memory's default capacity
    if available is not None and default_needed > available:
        with pytest.raises(ValueError, match="buffer_size=1,000,000"):
            NFQ("CnnPolicy", Frames(), memory="growing")
    NFQ("MlpPolicy", "CartPole-v1", memory="growing")  # a million CartPole transitions fit anywhere


def test_fitting_reads_the_memory_without_copying_it() -> None:
    # on the CPU: a fit on a GPU copies the memory to the device
    model = NFQ(
        "CnnPolicy", Frames(), memory="growing", buffer_size=400, train_freq=100, gradient_steps=1, seed=0, device="cpu"
    )
    model.learn(100, callback=StopAfterSteps(99))
    batch = model._stored_transitions()
    assert isinstance(batch.observations, th.Tensor) and isinstance(batch.next_observations, th.Tensor)
    assert np.shares_memory(batch.observations.numpy(), model.replay_buffer.observations)
    assert np.shares_memory(batch.next_observations.numpy(), model.replay_buffer.next_observations)


@pytest.mark.parametrize("critics", [1, 2])
def test_a_target_pass_over_a_large_memory_goes_in_pieces_with_the_one_pass_targets(critics: int) -> None:
    from sb3_nfq.fitting import TARGET_CHUNK_ROWS

    kwargs: dict[str, Any] = dict(memory="growing", train_freq=5000, gamma=0.99, policy_kwargs=dict(n_critics=critics))
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0, device="cpu", **kwargs)
    model.learn(4999)  # a round cut short: 4,999 transitions in the memory, none fitted
    batch = model._stored_transitions()
    sizes: list[int] = []
    model.q_net.q_net.register_forward_pre_hook(lambda module, args: sizes.append(len(args[0])))
    targets = td_targets(model.q_net, batch, model.gamma)
    piece = TARGET_CHUNK_ROWS // critics  # each critic computes its own activations
    assert sizes == [piece] * (4999 // piece) + [4999 % piece]
    with th.no_grad():
        next_q_values = critic_q_values(model.q_net, batch.next_observations).max(dim=2).values
    th.testing.assert_close(targets, batch.rewards + (1 - batch.dones) * 0.99 * next_q_values)


def test_passes_over_an_image_memory_are_bounded_in_bytes_and_give_the_full_batch_gradient(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from sb3_nfq import memory

    # on the CPU: GPU convolutions default to TF32, whose rounding is past this tolerance
    kwargs: dict[str, Any] = {"memory": "growing", "buffer_size": 600, "train_freq": 150, "gradient_steps": 2}
    kwargs["policy_kwargs"] = {"features_extractor_kwargs": {"features_dim": 32}, "net_arch": [16]}
    whole = NFQ("CnnPolicy", Frames(), seed=3, device="cpu", **kwargs)
    whole.learn(300)

    monkeypatch.setattr(memory, "CHUNK_BYTES", 40 * 84 * 84 * 4 * 4)  # 40 frames of float32 per pass
    chunked = NFQ("CnnPolicy", Frames(), seed=3, device="cpu", **kwargs)
    batch_sizes: list[int] = []
    chunked.q_net.register_forward_pre_hook(lambda module, args: batch_sizes.append(len(args[0])))
    chunked.learn(300)

    fitted = [size for size in batch_sizes if size > 1]  # the collection's single-frame passes left out
    assert max(fitted) == 40 and len(fitted) > 2 * 2 * 300 // 40  # every pass over the memory was cut
    for a, b in zip(whole.q_net.parameters(), chunked.q_net.parameters(), strict=True):
        th.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


# Resume equals uninterrupted

RESUME_MEMORIES: dict[str, dict[str, Any]] = {
    "fresh": {"train_freq": 64, "gradient_steps": 3},
    "growing": {"train_freq": 64, "gradient_steps": 2, "memory": "growing", "batch_size": 48},
}


@pytest.mark.parametrize("memory", list(RESUME_MEMORIES))
@pytest.mark.parametrize("first", [64, 100])  # a round boundary, and mid-round
def test_learning_in_two_calls_gives_the_weights_of_one_call(memory: str, first: int) -> None:
    kwargs = {**RESUME_MEMORIES[memory], "policy_kwargs": {"net_arch": [32]}, "device": "cpu"}
    whole = NFQ("MlpPolicy", "CartPole-v1", seed=7, **kwargs)
    whole.learn(320)
    split = NFQ("MlpPolicy", "CartPole-v1", seed=7, **kwargs)
    split.learn(first)
    split.learn(320 - first, reset_num_timesteps=False)
    assert (split.num_timesteps, split._n_rounds, split._n_updates) == (320, 5, whole._n_updates)
    for a, b in zip(whole.q_net.parameters(), split.q_net.parameters(), strict=True):
        assert th.equal(a, b)
    assert split.replay_buffer.size() == whole.replay_buffer.size()


RESUME_SCRIPT = """
import json, sys
import gymnasium as gym
from sb3_nfq import NFQ
model = NFQ.load(sys.argv[1], env=gym.make("CartPole-v1"))
model.load_replay_buffer(sys.argv[2])
before = (model.num_timesteps, model._n_rounds, model._n_updates, model.replay_buffer.size())
model.learn(128, reset_num_timesteps=False)
after = (model.num_timesteps, model._n_rounds, model._n_updates, model.replay_buffer.size())
print(json.dumps({"before": before, "after": after}))
"""


def test_a_growing_memory_resumed_in_a_new_process_goes_on_where_it_stopped(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0, **RESUME_MEMORIES["growing"])
    model.learn(100)  # one round fitted, 36 steps of the second in the memory
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "memory.pkl")
    resumed = subprocess.run(
        [sys.executable, "-c", RESUME_SCRIPT, str(tmp_path / "model.zip"), str(tmp_path / "memory.pkl")],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    result = json.loads(resumed.stdout.strip().splitlines()[-1])
    updates_per_round = 2 * 2  # gradient_steps x mini-batches of 48 over a memory of 64: 2 per iteration
    assert result["before"] == [100, 1, updates_per_round, 100]
    # 128 more steps: the second round completes at 128 and the third at 192; 36 of a fourth wait in the memory
    assert result["after"][:2] == [228, 3] and result["after"][3] == 228  # every transition is kept
    assert result["after"][2] > result["before"][2]


def test_learn_with_a_budget_gives_no_budget_warning() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.learn(64)
    assert model.num_timesteps == 64
