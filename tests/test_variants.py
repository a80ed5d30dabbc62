"""
Beyond the book: the growing memory, fixed targets per iteration (classic FQI), Rprop, random actions repeated
over several steps (temporally-extended epsilon-greedy), an ensemble of Q-networks collecting optimistically, and
n-step returns.
"""

import itertools
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit

from sb3_nfq import NFQ
from sb3_nfq.exploration import greedy_actions
from sb3_nfq.fitting import loss_and_gradient, take, td_targets
from sb3_nfq.memory import stored_transitions
from sb3_nfq.policies import critic_q_values
from sb3_nfq.rounds import fresh_round_transitions, round_length, round_size
from tests.conftest import TransitionRecorder, record_fitting


def test_growing_memory_refits_on_every_transition_so_far() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", train_freq=64, gradient_steps=2, seed=0)
    fitting = record_fitting(model)
    recorder = TransitionRecorder()
    model.learn(192, callback=recorder)

    assert [len(x) for x in fitting.grad_inputs] == [64, 64, 128, 128, 192, 192]
    all_obs, _, _ = recorder.transitions(0, 192)
    np.testing.assert_array_equal(fitting.grad_inputs[-1].numpy(), all_obs)
    assert model.replay_buffer.size() == 192  # kept, not discarded


def test_textbook_default_memory_is_fresh() -> None:
    assert NFQ("MlpPolicy", "CartPole-v1").memory == "fresh"


def test_growing_memory_drops_the_oldest_transitions_past_buffer_size() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", buffer_size=128, train_freq=64, gradient_steps=1)
    fitting = record_fitting(model)
    recorder = TransitionRecorder()
    model.learn(256, callback=recorder)

    assert [len(x) for x in fitting.grad_inputs] == [64, 128, 128, 128]
    newest, _, _ = recorder.transitions(128, 256)
    fitted = fitting.grad_inputs[-1].numpy()
    assert sorted(map(tuple, fitted)) == sorted(map(tuple, newest))


def test_growing_memory_with_minibatches_covers_the_whole_memory_each_iteration() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", train_freq=96, gradient_steps=2, batch_size=50, seed=0)
    fitting = record_fitting(model)
    recorder = TransitionRecorder()
    model.learn(192, callback=recorder)

    # round 1: 96 transitions = 2 mini-batches per iteration; round 2: 192 = 4 mini-batches per iteration
    sizes = [len(x) for x in fitting.grad_inputs]
    assert sizes == [50, 46] * 2 + [50, 50, 50, 42] * 2
    all_obs, _, _ = recorder.transitions(0, 192)
    last_iteration = th.cat(fitting.grad_inputs[-4:]).numpy()
    np.testing.assert_array_equal(np.sort(last_iteration, axis=0), np.sort(all_obs, axis=0))


def _sgd_model(target_mode: str, fit_epochs: int, **kwargs: Any) -> NFQ:
    model = NFQ(
        "MlpPolicy",
        "CartPole-v1",
        train_freq=4,
        gamma=0.9,
        target_mode=target_mode,  # type: ignore[arg-type]
        fit_epochs=fit_epochs,
        seed=3,
        learning_rate=0.5,
        policy_kwargs={"optimizer_class": th.optim.SGD, "net_arch": [8]},
        **kwargs,
    )
    model.set_logger(Logger(folder=None, output_formats=[]))
    rng = np.random.default_rng(1)
    for _ in range(4):
        obs, next_obs = rng.normal(size=(2, 1, 4)).astype(np.float32)
        model.replay_buffer.add(obs, next_obs, np.array([[rng.integers(2)]]), np.array([1.0]), np.array([0.0]), [{}])
    return model


def _by_hand(model: NFQ, n_steps: int, recompute: bool) -> list[th.Tensor]:
    """SGD steps on a copy of the network, with targets recomputed each step or fixed at the start."""
    data = model._stored_transitions()
    q_net = model.policy.make_q_net()
    q_net.load_state_dict(model.q_net.state_dict())
    optimizer = th.optim.SGD(q_net.parameters(), lr=0.5)

    def targets() -> th.Tensor:
        with th.no_grad():
            return data.rewards + model.gamma * q_net(data.next_observations).max(dim=1).values.reshape(-1, 1)

    fixed = targets()
    for _ in range(n_steps):
        target = targets() if recompute else fixed
        loss = th.nn.functional.mse_loss(th.gather(q_net(data.observations), 1, data.actions.long()), target)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return [p.detach() for p in q_net.parameters()]


def test_fixed_targets_are_computed_once_per_iteration_and_regressed_on_for_fit_epochs() -> None:
    model = _sgd_model("fixed_per_iteration", fit_epochs=3)
    fixed = _by_hand(model, 3, recompute=False)
    recomputed = _by_hand(model, 3, recompute=True)
    assert any(not th.allclose(a, b) for a, b in zip(fixed, recomputed, strict=True))

    fitting = record_fitting(model)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # e.g. torch's warning on mismatched target and prediction shapes
        model.train(gradient_steps=1)
    assert fitting.optimizer_steps == 3
    assert fitting.no_grad_batch_sizes == [4]  # one target pass over the memory for the whole iteration
    for got, expected in zip(model.q_net.parameters(), fixed, strict=True):
        th.testing.assert_close(got.detach(), expected)


def test_textbook_targets_are_recomputed_before_every_step() -> None:
    model = _sgd_model("recompute_every_step", fit_epochs=1)
    recomputed = _by_hand(model, 3, recompute=True)
    fitting = record_fitting(model)
    model.train(gradient_steps=3)
    assert fitting.no_grad_batch_sizes == [4, 4, 4]
    for got, expected in zip(model.q_net.parameters(), recomputed, strict=True):
        th.testing.assert_close(got.detach(), expected)


def test_fixed_targets_with_minibatches_use_each_transitions_own_target() -> None:
    model = NFQ(
        "MlpPolicy",
        "CartPole-v1",
        memory="growing",
        target_mode="fixed_per_iteration",
        fit_epochs=2,
        batch_size=32,
        train_freq=64,
        gradient_steps=3,
        seed=0,
    )
    fitting = record_fitting(model)
    model.learn(128)
    # per iteration: one target pass over the memory, then 2 epochs of 64/32 or 128/32 mini-batches
    assert fitting.no_grad_batch_sizes.count(64) == 3 and fitting.no_grad_batch_sizes.count(128) == 3
    assert fitting.optimizer_steps == 3 * 2 * 2 + 3 * 2 * 4


def test_rprop_trains_full_batch_in_both_memories() -> None:
    for memory in ("fresh", "growing"):
        model = NFQ(
            "MlpPolicy",
            "CartPole-v1",
            memory=memory,
            target_mode="fixed_per_iteration",
            fit_epochs=5,
            train_freq=64,
            gradient_steps=2,
            learning_rate=0.01,
            policy_kwargs={"optimizer_class": th.optim.Rprop},
            seed=0,
        )
        fitting = record_fitting(model)
        model.learn(128)
        assert fitting.optimizer_steps == 2 * 2 * 5
        assert {len(x) for x in fitting.grad_inputs} == ({64} if memory == "fresh" else {64, 128})


def test_iteration_transitions_fits_each_iteration_on_that_many_of_a_larger_memory_drawn_at_random() -> None:
    model = NFQ(
        "MlpPolicy",
        "CartPole-v1",
        memory="growing",
        target_mode="fixed_per_iteration",
        iteration_transitions=96,
        batch_size=32,
        train_freq=64,
        gradient_steps=2,
        seed=0,
    )
    fitting = record_fitting(model)
    recorder = TransitionRecorder()
    model.learn(192, callback=recorder)

    # per iteration, one target pass then one epoch of 32-row mini-batches: over the whole memory of 64, then over
    # 96 of the 128 and of the 192
    assert [size for size in fitting.no_grad_batch_sizes if size > 1] == [64, 64, 96, 96, 96, 96]
    assert [len(x) for x in fitting.grad_inputs] == [32] * 2 * 2 + [32] * 3 * 4
    all_obs, _, _ = recorder.transitions(0, 192)
    memory = {tuple(row) for row in all_obs}
    last_two = fitting.grad_inputs[-6:-3], fitting.grad_inputs[-3:]
    iterations = [{tuple(row) for row in th.cat(inputs).numpy()} for inputs in last_two]
    assert all(len(rows) == 96 and rows <= memory for rows in iterations)
    assert iterations[0] != iterations[1]  # drawn anew for each iteration


def test_iteration_transitions_at_least_the_memory_fits_as_without_it() -> None:
    def weights(**kwargs: Any) -> list[th.Tensor]:
        model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", train_freq=64, batch_size=32, seed=0, **kwargs)
        model.learn(192)
        return [p.detach() for p in model.q_net.parameters()]

    for got, expected in zip(weights(iteration_transitions=192), weights(), strict=True):
        th.testing.assert_close(got, expected, rtol=0, atol=0)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"memory": "growing", "batch_size": 256},
        {"memory": "fresh", "batch_size": 256},
        {"memory": "fresh", "train_freq": (3, "episode"), "buffer_size": 5000, "batch_size": 256},
    ],
)
def test_rprop_with_minibatches_is_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError, match="Rprop needs full-batch gradients, but batch_size=256"):
        NFQ("MlpPolicy", "CartPole-v1", policy_kwargs={"optimizer_class": th.optim.Rprop}, **kwargs)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"memory": "growing", "iteration_transitions": 64},
        {"memory": "fresh", "train_freq": 128, "iteration_transitions": 64},
        {"memory": "fresh", "train_freq": (3, "episode"), "buffer_size": 5000, "iteration_transitions": 64},
    ],
)
def test_rprop_with_iteration_transitions_that_can_split_the_fit_is_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError, match="Rprop needs full-batch gradients, but iteration_transitions=64 would fit"):
        NFQ("MlpPolicy", "CartPole-v1", policy_kwargs={"optimizer_class": th.optim.Rprop}, **kwargs)


def test_rprop_with_iteration_transitions_that_cover_the_fresh_round_takes_full_batch_steps() -> None:
    policy_kwargs = {"optimizer_class": th.optim.Rprop}
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=2, iteration_transitions=64, seed=0,
                policy_kwargs=policy_kwargs)  # fmt: skip
    fitting = record_fitting(model)
    model.learn(64)
    assert fitting.optimizer_steps == 2 and [len(x) for x in fitting.grad_inputs] == [64, 64]


def test_rprop_with_a_batch_size_that_covers_the_whole_fresh_round_takes_full_batch_steps() -> None:
    kwargs: dict[str, Any] = {
        "policy_kwargs": {"optimizer_class": th.optim.Rprop},
        "train_freq": 64,
        "gradient_steps": 3,
    }
    model = NFQ("MlpPolicy", "CartPole-v1", batch_size=64, seed=0, **kwargs)
    fitting = record_fitting(model)
    model.learn(64)
    assert fitting.optimizer_steps == 3 and [len(x) for x in fitting.grad_inputs] == [64, 64, 64]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"memory": "all"}, r"memory must be one of \['fresh', 'growing'\], got 'all'"),
        ({"target_mode": "fixed"}, r"target_mode must be one of \['recompute_every_step', 'fixed_per_iteration'\]"),
        ({"fit_epochs": 0}, "fit_epochs must be a positive integer"),
        ({"iteration_transitions": 0}, "iteration_transitions must be a positive integer or None, got 0"),
        ({"fit_epochs": 3}, "fit_epochs=3 needs target_mode='fixed_per_iteration'"),
        ({"memory": "growing", "buffer_size": 100}, "buffer_size=100 is smaller than one round of 1024"),
    ],
)
def test_bad_variant_parameters_are_rejected(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        NFQ("MlpPolicy", "CartPole-v1", **kwargs)


def test_variant_settings_and_the_growing_memory_survive_save_and_load(tmp_path: Path) -> None:
    model = NFQ(
        "MlpPolicy",
        "CartPole-v1",
        memory="growing",
        target_mode="fixed_per_iteration",
        fit_epochs=2,
        iteration_transitions=4096,
        train_freq=64,
        gradient_steps=1,
    )
    model.learn(128)
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "memory.pkl")

    loaded = NFQ.load(tmp_path / "model.zip", env=model.get_env())
    saved = (loaded.memory, loaded.target_mode, loaded.fit_epochs, loaded.iteration_transitions)
    assert saved == ("growing", "fixed_per_iteration", 2, 4096)
    loaded.load_replay_buffer(tmp_path / "memory.pkl")
    fitting = record_fitting(loaded)
    loaded.learn(64, reset_num_timesteps=False)
    assert {len(x) for x in fitting.grad_inputs} == {192}


# --- rounds that lengthen with the memory (round_fraction) -------------------------------------------------------

GROWING_ROUNDS: dict[str, Any] = {"memory": "growing", "train_freq": 64, "round_fraction": 0.5, "gradient_steps": 1}


def test_round_fraction_lengthens_rounds_with_the_memory() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0, **GROWING_ROUNDS)
    fitting = record_fitting(model)
    model.learn(648)
    # rounds of max(64, 0.5 * memory at the round's start): 64, 64 (32), 64 (64), 96, 144, 216
    assert [len(x) for x in fitting.grad_inputs] == [64, 128, 192, 288, 432, 648]
    assert model._n_rounds == 6 and model.num_timesteps == 648


def test_round_fraction_counts_the_transitions_of_every_env() -> None:
    env = make_vec_env("CartPole-v1", n_envs=3, seed=0)
    model = NFQ("MlpPolicy", env, seed=0, **{**GROWING_ROUNDS, "train_freq": 60, "round_fraction": 1.0})
    fitting = record_fitting(model)
    model.learn(480)
    # 20 steps of 3 envs, then rounds as long as the memory (in steps of 3 transitions): 60, 120, 240, 480
    assert [len(x) for x in fitting.grad_inputs] == [60, 120, 240, 480]


def test_round_fraction_offset_keeps_rounds_short_until_the_memory_passes_it(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0, round_fraction_offset=128, **GROWING_ROUNDS)
    fitting = record_fitting(model)
    model.learn(560)
    # rounds of max(64, 0.5 * (memory at the round's start - 128)): 64 while the memory holds up to 256, then 96, 144
    assert [len(x) for x in fitting.grad_inputs] == [64, 128, 192, 256, 320, 416, 560]
    model.save(tmp_path / "model.zip")
    assert NFQ.load(tmp_path / "model.zip").round_fraction_offset == 128


def test_a_resumed_round_keeps_the_length_it_started_with(tmp_path: Path) -> None:
    whole = NFQ("MlpPolicy", "CartPole-v1", seed=0, device="cpu", **GROWING_ROUNDS)
    whole.learn(648)
    split = NFQ("MlpPolicy", "CartPole-v1", seed=0, device="cpu", **GROWING_ROUNDS)
    split.learn(300)  # inside the fifth round (288 to 432 steps)
    split.save(tmp_path / "model.zip")
    saved, _, _ = load_from_zip_file(tmp_path / "model.zip")  # NFQ.load would reseed the global RNGs here
    assert saved is not None and saved["_round_target"] == 144 and saved["_round_steps"] == 12
    split.learn(348, reset_num_timesteps=False)
    assert split._n_rounds == 6
    for a, b in zip(whole.q_net.parameters(), split.q_net.parameters(), strict=True):
        assert th.equal(a, b)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"round_fraction": 0.0, "memory": "growing"}, "round_fraction must be a positive number or None"),
        ({"round_fraction": "10%", "memory": "growing"}, "round_fraction must be a positive number or None"),
        ({"round_fraction": 0.1}, "needs memory='growing'"),
        ({"round_fraction": 0.1, "memory": "growing", "train_freq": (2, "episode")}, "train_freq counted in steps"),
        *[
            ({**GROWING_ROUNDS, "round_fraction_offset": offset}, "round_fraction_offset must be an integer >= 0")
            for offset in (-1, 100.0, True)
        ],
        ({"round_fraction_offset": 100}, r"round_fraction_offset=100 .* needs round_fraction \(got None\)"),
    ],
)
def test_bad_round_fraction_is_refused(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        NFQ("MlpPolicy", "CartPole-v1", **kwargs)


def test_round_arithmetic() -> None:
    steps, episodes = TrainFrequencyUnit.STEP, TrainFrequencyUnit.EPISODE
    assert round_length(TrainFreq(1024, steps), 3) == TrainFreq(342, steps)  # rounded up to whole env.step() calls
    assert round_length(TrainFreq(5, episodes), 1) == TrainFreq(5, episodes)
    assert round_size(TrainFreq(64, steps), None, 10_000, 1) == 64
    assert round_size(TrainFreq(64, steps), 0.5, 100, 1) == 64  # train_freq is the shortest round
    assert round_size(TrainFreq(64, steps), 0.5, 1_000, 1) == 500
    assert round_size(TrainFreq(64, steps), 0.5, 999, 2) == 250  # 499.5 transitions: 250 steps of 2 envs
    assert round_size(TrainFreq(3, episodes), 0.5, 1_000, 1) == 3
    assert round_size(TrainFreq(64, steps), 0.5, 1_000, 1, offset=600) == 200  # half of the 400 past the offset
    assert round_size(TrainFreq(64, steps), 0.5, 1_000, 1, offset=1_000) == 64
    assert fresh_round_transitions(TrainFreq(1024, steps), 3, "fresh") == 1026
    assert fresh_round_transitions(TrainFreq(1024, steps), 3, "growing") is None
    assert fresh_round_transitions(TrainFreq(3, episodes), 1, "fresh") is None


def test_an_episode_round_longer_than_the_memory_stops_at_its_first_step_too_many() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=(50, "episode"), buffer_size=100, gradient_steps=1, seed=0)
    with pytest.raises(ValueError, match=r"Round 1 collected 101 transitions, more than buffer_size=100 holds"):
        model.learn(1)
    assert model.num_timesteps == 101


def test_textbook_rounds_do_not_lengthen() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", train_freq=64, gradient_steps=1, seed=0)
    assert model.round_fraction is None and NFQ("MlpPolicy", "CartPole-v1").round_fraction is None
    assert model.round_fraction_offset == 0
    fitting = record_fitting(model)
    model.learn(256)
    assert [len(x) for x in fitting.grad_inputs] == [64, 128, 192, 256]


# --- random actions repeated over several steps (exploration_repeat_mu) ------------------------------------------


class EpisodeActions(BaseCallback):
    """Record, for each env, the actions of each of its episodes."""

    def __init__(self) -> None:
        super().__init__()
        self.episodes: list[list[int]] = []
        self.current: dict[int, list[int]] = {}

    def _on_step(self) -> bool:
        for env, (action, done) in enumerate(zip(self.locals["actions"], self.locals["dones"], strict=True)):
            self.current.setdefault(env, []).append(int(action))
            if done:
                self.episodes.append(self.current.pop(env))
        return True


@pytest.mark.parametrize("n_envs", [1, 2])
def test_a_repeated_random_action_lasts_its_episode_and_the_next_episode_draws_again(n_envs: int) -> None:
    # Every action is random (epsilon 1), and durations from Zeta(1.01) are almost all longer than a CartPole episode
    # that pushes one way (about 10 steps): each episode pushes one way, and each draws its own side.
    model = NFQ(
        "MlpPolicy",
        make_vec_env("CartPole-v1", n_envs=n_envs, seed=0),
        exploration_initial_eps=1.0,
        exploration_final_eps=1.0,
        exploration_repeat_mu=1.01,
        train_freq=512,
        gradient_steps=1,
        seed=0,
    )
    recorder = EpisodeActions()
    model.learn(2048, callback=recorder)

    episodes = recorder.episodes
    assert len(episodes) > 100
    one_way = sum(len(set(actions)) == 1 for actions in episodes)
    assert one_way >= 0.9 * len(episodes)  # epsilon-greedy: 2 * 0.5 ** 9 or less of the episodes
    first_actions = [actions[0] for actions in episodes]
    assert 0.3 < np.mean(first_actions) < 0.7  # a repeat carried over to the next episode would make them equal


def test_repeated_exploration_is_kept_by_save_and_load_and_a_loaded_model_collects_with_it(tmp_path: Path) -> None:
    always_random: dict[str, Any] = {"exploration_initial_eps": 1.0, "exploration_final_eps": 1.0}
    model = NFQ("MlpPolicy", "CartPole-v1", exploration_repeat_mu=2.0, train_freq=64, gradient_steps=1, **always_random)
    model.learn(128)  # most likely mid-repeat
    model.save(tmp_path / "model.zip")
    saved, _, _ = load_from_zip_file(tmp_path / "model.zip")
    assert saved is not None and "_repeat_steps_left" not in saved

    loaded = NFQ.load(tmp_path / "model.zip", env=model.get_env())
    assert loaded.exploration_repeat_mu == 2.0
    recorder = EpisodeActions()
    loaded.learn(1024, reset_num_timesteps=False, callback=recorder)
    pairs = [(a, b) for actions in recorder.episodes for a, b in itertools.pairwise(actions)]
    # One random action a step repeats the last one half the time; Zeta(2) durations, about 4 times in 5.
    assert np.mean([a == b for a, b in pairs]) > 0.65


# --- an ensemble of Q-networks (n_critics) and optimistic collecting on it (exploration_ucb) --------------------------


def critics_model(**kwargs: Any) -> NFQ:
    policy_kwargs = {"n_critics": 3, "net_arch": [16, 16], "optimizer_class": th.optim.Adam}
    return NFQ("MlpPolicy", "CartPole-v1", policy_kwargs=policy_kwargs, train_freq=128, seed=0, **kwargs)


def test_critics_start_apart_and_act_on_their_mean() -> None:
    model = critics_model()
    obs = th.as_tensor(np.random.default_rng(0).normal(size=(32, 4)), dtype=th.float32)
    with th.no_grad():
        per_critic = critic_q_values(model.q_net, obs)
        assert per_critic.shape == (32, 3, 2)
        th.testing.assert_close(model.q_net(obs), per_critic.mean(dim=1))
    assert (per_critic[:, 0] - per_critic[:, 1]).abs().min() > 0  # own initial weights
    greedy = model.predict(obs.numpy(), deterministic=True)[0]
    np.testing.assert_array_equal(greedy, per_critic.mean(dim=1).argmax(dim=1).numpy())


@pytest.mark.parametrize("target_mode", ["recompute_every_step", "fixed_per_iteration"])
def test_each_critic_is_fitted_to_its_own_targets(target_mode: str) -> None:
    model = critics_model(target_mode=target_mode, gamma=0.9)
    model.learn(64)  # half a round: collected, not yet fitted
    batch = stored_transitions(model.replay_buffer, None)
    q_net = model.q_net
    targets = td_targets(q_net, batch, model.gamma)
    with th.no_grad():
        next_q = critic_q_values(q_net, batch.next_observations)
    for critic in range(3):
        expected = batch.rewards[:, 0] + model.gamma * (1 - batch.dones[:, 0]) * next_q[:, critic].max(dim=1).values
        th.testing.assert_close(targets[:, critic], expected)

    # The fit's gradient for each critic is that of its own regression (the loss averages over the critics).
    q_net.zero_grad()
    loss_and_gradient(q_net, th.nn.functional.mse_loss, model.gamma, batch, targets, None)
    weights = [p for name, p in q_net.named_parameters() if ".weights." in name]
    fit_grads = [grad.clone() for p in weights if (grad := p.grad) is not None]
    assert len(fit_grads) == 3  # the three layers, each holding every critic's weights
    for critic in range(3):
        q_taken = critic_q_values(q_net, batch.observations)[:, critic].gather(1, batch.actions.long())
        own_loss = th.nn.functional.mse_loss(q_taken, targets[:, critic : critic + 1]) / 3
        for fit_grad, own_grad in zip(fit_grads, th.autograd.grad(own_loss, weights), strict=True):
            th.testing.assert_close(fit_grad[critic], own_grad[critic])


def test_optimistic_actions_take_the_critics_mean_plus_c_standard_deviations() -> None:
    model = critics_model(exploration_ucb=3.0)
    obs = np.random.default_rng(1).normal(size=(256, 4)).astype(np.float32)
    with th.no_grad():
        per_critic = critic_q_values(model.q_net, th.as_tensor(obs))
    mean, std = per_critic.mean(dim=1), per_critic.std(dim=1)
    optimistic = greedy_actions(model.policy, obs, 3.0)
    np.testing.assert_array_equal(optimistic, (mean + 3.0 * std).argmax(dim=1).numpy())
    assert (optimistic != mean.argmax(dim=1).numpy()).any()  # the spread changes some actions
    np.testing.assert_array_equal(greedy_actions(model.policy, obs, 0.0), mean.argmax(dim=1).numpy())


def test_collecting_is_optimistic_and_predict_stays_on_the_mean() -> None:
    model = critics_model(exploration_ucb=10.0, exploration_initial_eps=0.0, exploration_final_eps=0.0)
    recorder = TransitionRecorder()
    model.learn(64, callback=recorder)  # half a round, not fitted: every action came from the initial critics
    obs, actions, _ = recorder.transitions(0, 64)
    with th.no_grad():
        per_critic = critic_q_values(model.q_net, th.as_tensor(obs))
    optimistic = (per_critic.mean(dim=1) + 10.0 * per_critic.std(dim=1)).argmax(dim=1).numpy()
    on_the_mean = per_critic.mean(dim=1).argmax(dim=1).numpy()
    assert (optimistic != on_the_mean).any()  # so that the two checks below tell them apart
    np.testing.assert_array_equal(actions.reshape(-1), optimistic)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], on_the_mean)


def test_critics_and_optimism_are_kept_by_save_and_load(tmp_path: Path) -> None:
    model = critics_model(exploration_ucb=3.0)
    model.learn(256)
    model.save(tmp_path / "model.zip")
    obs = np.random.default_rng(2).normal(size=(64, 4)).astype(np.float32)
    for loaded in (NFQ.load(tmp_path / "model.zip"), NFQ.load(tmp_path / "model.zip", safe=True, env=model.get_env())):
        assert loaded.policy.n_critics == 3 and loaded.exploration_ucb == 3.0
        greedy = loaded.predict(obs, deterministic=True)[0]
        np.testing.assert_array_equal(greedy, model.predict(obs, deterministic=True)[0])
        np.testing.assert_array_equal(greedy_actions(loaded.policy, obs, 3.0), greedy_actions(model.policy, obs, 3.0))


# --- an exploration schedule that starts at the first termination (exploration_start) -----------------------------


class StepRecorder(BaseCallback):
    """Record, at each env step, the step count, the exploration rate and whether an episode terminated."""

    def __init__(self) -> None:
        super().__init__()
        self.steps: list[tuple[int, float, bool]] = []

    def _on_step(self) -> bool:
        terminated = any(
            done and not info.get("TimeLimit.truncated", False)
            for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True)
        )
        self.steps.append((self.num_timesteps, self.model.exploration_rate, terminated))  # type: ignore[attr-defined]
        return True


SCHEDULE: dict[str, Any] = {
    "exploration_initial_eps": 1.0,
    "exploration_final_eps": 0.1,
    "exploration_fraction": 0.5,
    "train_freq": 100,
    "gradient_steps": 1,
}


def test_epsilon_holds_its_initial_value_until_the_first_termination_then_decays_from_that_step() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", exploration_start="first_termination", seed=0, **SCHEDULE)
    recorder = StepRecorder()
    model.learn(1000, callback=recorder)

    # The callback sees a step before NFQ updates epsilon for it: each rate is the one of the step before.
    first = next(steps for steps, _, terminated in recorder.steps if terminated)
    rates = {steps: rate for steps, rate, _ in recorder.steps}
    assert first > 1 and all(rates[steps] == 1.0 for steps in range(1, first + 2))
    for later in (50, 250, 400):  # the schedule spans half of the 1,000 steps, counted from the first termination
        assert rates[first + later + 1] == pytest.approx(1.0 - 0.9 * later / 500)


def test_time_limit_truncations_do_not_start_the_exploration_schedule() -> None:
    # CartPole cut at 5 steps: a random pole does not fall that soon, so every episode ends truncated.
    env = make_vec_env("CartPole-v1", n_envs=2, seed=0, env_kwargs={"max_episode_steps": 5})
    waiting = NFQ("MlpPolicy", env, exploration_start="first_termination", seed=0, **SCHEDULE)
    recorder = StepRecorder()
    waiting.learn(1000, callback=recorder)
    assert not any(terminated for _, _, terminated in recorder.steps)
    assert {rate for _, rate, _ in recorder.steps} == {1.0} and waiting.exploration_rate == 1.0

    from_the_start = NFQ("MlpPolicy", env, seed=0, **SCHEDULE)  # exploration_start="first_step"
    from_the_start.learn(1000)
    assert from_the_start.exploration_rate == pytest.approx(0.1)


def test_an_exploration_schedule_that_started_goes_on_after_save_and_load(tmp_path: Path) -> None:
    schedule = {**SCHEDULE, "exploration_fraction": 1.0}
    model = NFQ("MlpPolicy", "CartPole-v1", exploration_start="first_termination", seed=0, **schedule)
    recorder = StepRecorder()
    model.learn(200, callback=recorder)  # CartPole's first random episode ends within these steps
    first = next(steps for steps, _, terminated in recorder.steps if terminated)
    model.save(tmp_path / "model.zip")

    loaded = NFQ.load(tmp_path / "model.zip", env=model.get_env())
    assert loaded.exploration_start == "first_termination"
    recorder = StepRecorder()
    loaded.learn(200, reset_num_timesteps=False, callback=recorder)
    # As SB3's schedules do, a learn() that goes on spans the schedule over the steps of both, from the same start.
    assert recorder.steps[1][1] == pytest.approx(1.0 - 0.9 * (201 - first) / 400)


# --- n-step returns (n_steps) --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("n_envs", "buffer_size"), [(1, None), (2, 300)])
def test_n_step_transitions_sum_the_next_rewards_until_an_episode_ends_or_the_newest_step(
    n_envs: int, buffer_size: int | None
) -> None:
    env = make_vec_env("CartPole-v1", n_envs=n_envs, seed=0, env_kwargs={"max_episode_steps": 20})
    growing: dict[str, Any] = {"memory": "growing", "buffer_size": buffer_size, "train_freq": 50}
    model = NFQ(
        "MlpPolicy", env, gamma=0.9, n_steps=3, exploration_initial_eps=1.0, exploration_final_eps=1.0, **growing
    )
    model.learn(700)
    memory, gamma = model.replay_buffer, 0.9
    assert memory.full == (buffer_size is not None) and memory.pos > 0  # a wrapped memory: its newest row is inside
    assert memory.timeouts.any() and (memory.dones * (1 - memory.timeouts)).any()  # truncations and terminations
    data = model._stored_transitions()
    n_rows = memory.buffer_size if memory.full else memory.pos
    newest = memory.pos - 1
    for row, env_index in itertools.product(range(n_rows), range(n_envs)):
        step, total, discount = row, 0.0, 1.0
        for k in range(3):  # by hand: stop after an episode's last step or the memory's newest one
            total += discount * memory.rewards[step, env_index]
            discount *= gamma
            if memory.dones[step, env_index] or step == newest or k == 2:
                break
            step = (step + 1) % n_rows
        i = row * n_envs + env_index
        assert data.rewards[i, 0].item() == pytest.approx(total, rel=1e-5)
        assert data.discounts is not None and data.discounts[i, 0].item() == pytest.approx(discount, rel=1e-5)
        np.testing.assert_array_equal(data.next_observations[i].numpy(), memory.next_observations[step, env_index])
        terminated = memory.dones[step, env_index] * (1 - memory.timeouts[step, env_index])
        assert data.dones[i, 0].item() == terminated
    one_step = stored_transitions(memory)
    assert one_step.discounts is None
    th.testing.assert_close(data.observations, one_step.observations)


def test_n_step_targets_bootstrap_with_each_transitions_own_discount() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", train_freq=64, gamma=0.9, n_steps=3, seed=0)
    model.learn(128)
    data, rows = model._stored_transitions(), th.arange(0, 128, 5)
    assert data.discounts is not None and len(set(data.discounts.flatten().tolist())) > 1  # episode ends cut some
    part = take(data, rows)
    with th.no_grad():
        next_q = model.q_net(part.next_observations).max(dim=1).values.reshape(-1, 1)
    expected = part.rewards + (1 - part.dones) * data.discounts[rows] * next_q
    th.testing.assert_close(td_targets(model.q_net, part, model.gamma), expected)


def test_n_steps_is_kept_by_save_and_load_without_sb3s_n_step_buffer_warning(tmp_path: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", train_freq=64, n_steps=3)
        model.save(tmp_path / "model.zip")
        loaded = NFQ.load(tmp_path / "model.zip")
    assert loaded.n_steps == 3 and type(loaded.replay_buffer) is type(model.replay_buffer)
