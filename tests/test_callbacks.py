"""The book's solve criterion (sb3_nfq.callbacks): its bookkeeping, and the callback on real SB3 algorithms."""

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import DQN
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_nfq import NFQ, BookCriterion, StopTrainingOnBookCriterion

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
