"""
sb3_nfq.callbacks on real SB3 algorithms: the book's solve criterion (and its bookkeeping), and KeepBestCallback.
"""

import copy
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import DQN
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, StopTrainingOnMaxEpisodes
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_nfq import NFQ, BookCriterion, KeepBestCallback, StopTrainingOnBookCriterion

SMALL_NFQ: dict[str, Any] = {"train_freq": 64, "gradient_steps": 2, "policy_kwargs": {"net_arch": [16]}}


def _always_left(obs: np.ndarray) -> int:
    return 0


def _balance(obs: np.ndarray) -> int:
    return int(obs[2] + obs[3] > 0)  # push towards the side the pole falls to: long episodes


def _lean(obs: np.ndarray) -> int:
    return int(obs[2] > 0)  # follow the pole's angle only: episodes of varying length


def test_book_criterion_averages_the_last_window_and_records_the_first_solve() -> None:
    criterion = BookCriterion(gym.make("CartPole-v1"), threshold=60.0, window=3, seed=5)
    holds = [criterion.on_training_episode_end(steps, _always_left) for steps in (10, 20, 30, 40)]
    holds += [criterion.on_training_episode_end(steps, _balance) for steps in (50, 60, 70, 80)]

    returns = criterion.evaluation_returns
    assert len(returns) == 8 and criterion.evaluation_steps == [10, 20, 30, 40, 50, 60, 70, 80]
    assert max(returns[:4]) < 20 and min(returns[4:]) > 100  # the two policies are told apart
    means = [np.mean(returns[max(0, i - 2) : i + 1]) for i in range(8)]
    assert holds == [mean >= 60.0 for mean in means]
    first = next(i for i, mean in enumerate(means) if mean >= 60.0)
    assert first in (4, 5)  # one or two good episodes lift a 3-episode mean over 60
    assert criterion.episodes_to_solve == first + 1
    assert criterion.steps_to_solve == criterion.evaluation_steps[first]
    assert criterion.mean_return == pytest.approx(np.mean(returns[-3:]))
    assert criterion.eval_seconds > 0


def test_book_criterion_evaluation_episodes_are_reproducible_from_the_seed() -> None:
    first = BookCriterion(gym.make("CartPole-v1"), seed=3)
    second = BookCriterion(gym.make("CartPole-v1"), seed=3)
    for steps in range(1, 6):
        first.on_training_episode_end(steps, _lean)
        second.on_training_episode_end(steps, _lean)
    assert first.evaluation_returns == second.evaluation_returns
    assert len(set(first.evaluation_returns)) > 1  # later episodes start elsewhere: the seed is used once


def test_callback_stops_nfq_at_the_end_of_the_episode_that_meets_the_criterion() -> None:
    env = make_vec_env("CartPole-v1", n_envs=1, seed=0)
    model = NFQ("MlpPolicy", env, seed=0, **SMALL_NFQ)
    callback = StopTrainingOnBookCriterion(gym.make("CartPole-v1"), threshold=0.0, seed=0)
    model.learn(10_000, callback=callback)

    assert isinstance(env, DummyVecEnv)
    monitor = env.envs[0]
    assert isinstance(monitor, Monitor)
    first_episode = monitor.get_episode_lengths()
    assert len(first_episode) == 1  # stopped right after the first training episode (any return is >= 0)
    assert model.num_timesteps == first_episode[0]  # the evaluation episode's steps are not training steps
    assert callback.criterion.steps_to_solve == first_episode[0]
    assert callback.criterion.episodes_to_solve == 1


def test_callback_without_stopping_evaluates_after_every_episode_of_every_env() -> None:
    env = make_vec_env("CartPole-v1", n_envs=2, seed=0)
    model = NFQ("MlpPolicy", env, seed=0, **SMALL_NFQ)
    callback = StopTrainingOnBookCriterion("CartPole-v1", threshold=0.0, stop_at_solve=False, seed=0)
    model.learn(256, callback=callback)

    assert isinstance(env, DummyVecEnv)
    finished = sum(len(monitor.get_episode_lengths()) for monitor in env.envs if isinstance(monitor, Monitor))
    assert finished > 2
    assert len(callback.criterion.evaluation_returns) == finished
    assert model.num_timesteps == 256
    assert callback.criterion.episodes_to_solve == 1  # solved at once, and kept evaluating


def test_callback_works_with_dqn() -> None:
    env = make_vec_env("CartPole-v1", n_envs=1, seed=1)
    model = DQN("MlpPolicy", env, learning_starts=0, seed=1, policy_kwargs={"net_arch": [16]})
    callback = StopTrainingOnBookCriterion(gym.make("CartPole-v1"), threshold=0.0, seed=1)
    model.learn(5_000, callback=callback)
    assert callback.criterion.steps_to_solve is not None
    assert model.num_timesteps == callback.criterion.steps_to_solve < 500


@pytest.mark.parametrize("window", [0, -3, 2.5, True])
def test_bad_window_is_refused(window: object) -> None:
    with pytest.raises(ValueError, match="window must be a positive integer"):
        StopTrainingOnBookCriterion("CartPole-v1", window=window)  # type: ignore[arg-type]


def test_a_vectorised_eval_env_is_refused() -> None:
    with pytest.raises(ValueError, match=r"eval_env must be a gymnasium\.Env"):
        StopTrainingOnBookCriterion(make_vec_env("CartPole-v1", n_envs=2))  # type: ignore[arg-type]


# --- KeepBestCallback ------------------------------------------------------------------------------------------------


def _state(model: BaseAlgorithm) -> dict[str, th.Tensor]:
    return copy.deepcopy(model.policy.state_dict())


def _same(a: dict[str, th.Tensor], b: dict[str, th.Tensor]) -> bool:
    return a.keys() == b.keys() and all(th.equal(a[key], b[key]) for key in a)


def _monitor(env: Any) -> Monitor:
    assert isinstance(env, DummyVecEnv) and isinstance(env.envs[0], Monitor)
    return env.envs[0]


def test_keep_best_scores_each_rollouts_weights_by_the_monitors_returns_of_the_episodes_that_ended_in_it() -> None:
    env = make_vec_env("CartPole-v1", n_envs=1, seed=0)
    model = NFQ("MlpPolicy", env, memory="growing", train_freq=300, gradient_steps=1, seed=0)
    keep_best = KeepBestCallback()
    model.learn(600, callback=keep_best)  # two rounds: two rollouts, the first one's weights then its fit's

    monitor = _monitor(env)
    returns, ends = np.array(monitor.get_episode_rewards()), np.cumsum(monitor.get_episode_lengths())
    first, second = returns[ends <= 300], returns[ends > 300]
    assert len(first) > 5 and len(second) > 5 and first.mean() != second.mean()
    assert keep_best.best_score == pytest.approx(max(first.mean(), second.mean()))
    assert keep_best.best_weights is not None and _same(_state(model), keep_best.best_weights)


def _feed(keep_best: KeepBestCallback, returns: list[float]) -> None:
    """One rollout in which episodes with these returns end, as SB3's ``collect_rollouts`` calls the callback."""
    for episode_return in returns:
        keep_best.update_locals({"dones": np.array([True]), "infos": [{"episode": {"r": episode_return}}]})
        keep_best.on_step()
    keep_best.on_rollout_end()


def test_keep_best_leaves_a_lower_score_aside_and_an_equal_score_becomes_the_best() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", train_freq=64, gradient_steps=2, seed=0)
    model.learn(64)  # one round collected, not yet fitted
    keep_best = KeepBestCallback()
    keep_best.init_callback(model)
    keep_best.on_training_start({}, {})
    _feed(keep_best, [20.0, 30.0])
    first = _state(model)
    assert keep_best.best_score == 25.0 and keep_best.best_weights is not None
    assert _same(keep_best.best_weights, first)
    _feed(keep_best, [])  # no episode ended: not scored
    model.train(gradient_steps=2)
    fitted = _state(model)
    assert not _same(fitted, first)
    _feed(keep_best, [24.0])
    assert keep_best.best_score == 25.0 and _same(keep_best.best_weights, first)
    assert _same(_state(model), fitted)  # training goes on from the last fit
    _feed(keep_best, [25.0])
    assert keep_best.best_score == 25.0 and _same(keep_best.best_weights, fitted)


def test_keep_best_with_n_episodes_scores_by_the_last_n_episodes_when_a_rollout_ends_fewer() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", train_freq=64, gradient_steps=2, seed=0)
    model.learn(64)
    keep_best = KeepBestCallback(n_episodes=3)
    keep_best.init_callback(model)
    keep_best.on_training_start({}, {})
    _feed(keep_best, [90.0])
    _feed(keep_best, [10.0])
    assert keep_best.best_score is None and keep_best.best_weights is None  # 2 episodes so far: not scored
    _feed(keep_best, [20.0])
    assert keep_best.best_score == 40.0  # 90, 10, 20
    _feed(keep_best, [60.0])
    assert keep_best.best_score == 40.0  # 10, 20, 60: lower
    _feed(keep_best, [70.0])
    assert keep_best.best_score == 50.0  # 20, 60, 70
    _feed(keep_best, [1.0, 1.0, 1.0, 200.0])  # a rollout that ends more than 3: its own episodes alone
    assert keep_best.best_score == 50.75


def test_keep_best_refuses_n_episodes_below_one() -> None:
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="n_episodes must be an int of at least 1"):
            KeepBestCallback(n_episodes=bad)  # type: ignore[arg-type]


class _RecordWeights(BaseCallback):
    """The policy's weights at each rollout's end and at the end of training (before the callbacks after it)."""

    def __init__(self) -> None:
        super().__init__()
        self.at_rollout_ends: list[dict[str, th.Tensor]] = []
        self.at_training_end: dict[str, th.Tensor] = {}

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        self.at_rollout_ends.append(_state(self.model))

    def _on_training_end(self) -> None:
        self.at_training_end = _state(self.model)


def test_keep_best_ends_learn_with_the_best_weights_when_later_fits_score_lower() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", memory="growing", train_freq=64, gradient_steps=2, seed=0)
    keep_best, recorder = KeepBestCallback(), _RecordWeights()
    keep_best.best_score, keep_best.best_weights = 1000.0, _state(model)  # no CartPole-v1 return reaches 1000
    best = _state(model)
    model.learn(640, callback=[recorder, keep_best])

    assert model._n_rounds == 10 and len(recorder.at_rollout_ends) == 10
    assert not _same(recorder.at_rollout_ends[-1], recorder.at_rollout_ends[-2])  # each fit went on from the last
    assert not _same(recorder.at_training_end, best)
    assert _same(_state(model), best) and keep_best.best_score == 1000.0


def test_keep_best_judges_the_episodes_of_a_rollout_a_callback_stopped_early() -> None:
    env = make_vec_env("CartPole-v1", n_envs=1, seed=0)
    model = NFQ("MlpPolicy", env, train_freq=1000, seed=0)
    keep_best = KeepBestCallback()
    model.learn(1000, callback=CallbackList([StopTrainingOnMaxEpisodes(max_episodes=2), keep_best]))
    returns = _monitor(env).get_episode_rewards()
    assert len(returns) == 2 and keep_best.best_score == pytest.approx(np.mean(returns))


def test_keep_best_refuses_an_env_without_a_monitor() -> None:
    bare = DummyVecEnv([lambda: gym.make("CartPole-v1")])
    with pytest.raises(ValueError, match="KeepBestCallback judges the policy's weights by the returns of the training"):
        NFQ("MlpPolicy", bare).learn(64, callback=KeepBestCallback())


@pytest.mark.parametrize("name", ["DQN", "QRDQN"])
def test_keep_best_works_with_dqn_and_qrdqn(name: str) -> None:
    # sb3_contrib comes with the zoo extra: the lowest-versions run (make test-lowest) has no extra
    algorithm: type[DQN] = DQN if name == "DQN" else pytest.importorskip("sb3_contrib").QRDQN
    env = make_vec_env("CartPole-v1", n_envs=1, seed=1)
    # One episode per rollout: each episode's return scores the weights that played it.
    model = algorithm("MlpPolicy", env, learning_starts=0, train_freq=(1, "episode"), seed=1)
    keep_best, recorder = KeepBestCallback(), _RecordWeights()
    model.learn(300, callback=[recorder, keep_best])

    returns = _monitor(env).get_episode_rewards()
    assert len(returns) > 5 and len(set(returns)) > 1
    assert keep_best.best_score == max(returns) and keep_best.best_weights is not None
    best = len(returns) - 1 - returns[::-1].index(max(returns))  # an equal score becomes the best: the last
    assert _same(keep_best.best_weights, recorder.at_rollout_ends[best])  # target network included
    assert not _same(recorder.at_training_end, keep_best.best_weights)  # trained after the best
    assert _same(_state(model), keep_best.best_weights)


def test_the_zoo_can_name_keep_best_as_a_hyperparameters_callback() -> None:
    zoo_utils = pytest.importorskip("rl_zoo3.utils")  # the zoo extra
    (keep_best,) = zoo_utils.get_callback_list({"callback": "sb3_nfq.KeepBestCallback"})
    assert isinstance(keep_best, KeepBestCallback)
    env = make_vec_env("CartPole-v1", n_envs=1, seed=0)
    NFQ("MlpPolicy", env, train_freq=200, seed=0).learn(200, callback=keep_best)
    assert keep_best.best_score == pytest.approx(np.mean(_monitor(env).get_episode_rewards()))
