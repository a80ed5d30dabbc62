"""Bad input fails early, with a message naming the parameter and what is allowed."""

import inspect
import warnings
from typing import Any

import gymnasium as gym
import pytest
from stable_baselines3 import DQN
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import FakeImageEnv
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_nfq import NFQ, NFQDivergenceError
from sb3_nfq.parameters import DQN_ONLY_PARAMETERS
from tests.envs import NaNRewardAfter


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"train_freq": 0}, "train_freq .* positive integer"),
        ({"train_freq": -5}, "train_freq .* positive integer"),
        ({"train_freq": 10.5}, "train_freq .* positive integer"),
        ({"train_freq": (4, "minute")}, "unit of train_freq must be 'step' or 'episode'"),
        ({"gradient_steps": 0}, "gradient_steps must be a positive integer"),
        ({"gradient_steps": -1}, "gradient_steps must be a positive integer"),
        ({"gradient_steps": True}, "gradient_steps must be a positive integer, got True"),
        ({"batch_size": 0}, "batch_size must be a positive integer"),
        ({"n_steps": 0}, "n_steps must be a positive integer, got 0"),
        ({"n_steps": 2.5}, "n_steps must be a positive integer, got 2.5"),
        ({"buffer_size": -1}, "buffer_size must be a positive integer"),
        ({"gamma": 1.5}, r"gamma must be in \[0, 1\]"),
        ({"gamma": -0.1}, r"gamma must be in \[0, 1\]"),
        ({"loss": "l1"}, r"loss must be one of \['huber', 'mse'\], got 'l1'"),
        ({"loss": "huber", "huber_delta": 0.0}, "huber_delta must be a positive number, got 0.0"),
        (
            {"huber_delta": 10.0},
            r"huber_delta=10.0 sets the Huber loss's threshold, which needs loss='huber' \(got loss='mse'\)",
        ),
        ({"learning_rate": 0.0}, "learning_rate must be a positive number"),
        ({"exploration_initial_eps": 1.2}, r"exploration_initial_eps must be a probability in \[0, 1\]"),
        ({"exploration_final_eps": -0.1}, r"exploration_final_eps must be a probability in \[0, 1\]"),
        ({"exploration_fraction": 0.0}, r"exploration_fraction must be in \(0, 1\]"),
        ({"max_grad_norm": 0.0}, "max_grad_norm must be positive or None"),
        ({"exploration_repeat_mu": 1.0}, r"exploration_repeat_mu must be None .* or a number > 1 .*, got 1.0"),
        ({"exploration_repeat_mu": "2"}, r"exploration_repeat_mu must be None .* or a number > 1 .*, got '2'"),
        ({"exploration_ucb": -1.0}, r"exploration_ucb must be None .* or a number >= 0 .*, got -1.0"),
        ({"exploration_ucb": float("nan")}, r"exploration_ucb must be None .* or a number >= 0 .*, got nan"),
        ({"exploration_ucb": True}, r"exploration_ucb must be None .* or a number >= 0 .*, got True"),
        ({"exploration_ucb": 1.0}, r"exploration_ucb=1.0 collects on .* n_critics=1: pass policy_kwargs=dict\(n_crit"),
        ({"policy_kwargs": {"n_critics": 0}}, r"n_critics \(Q-networks of the ensemble\) must be a positive integer"),
        (
            {"exploration_start": "first_goal"},
            r"exploration_start must be one of \['first_step', 'first_termination'\], got 'first_goal'",
        ),
        (
            {"exploration_start": "first_termination"},
            "exploration_start='first_termination' sets when epsilon starts .* both are 0.5.*drop exploration_start",
        ),
        ({"buffer_size": 100_000}, r"buffer_size=100000 has no effect with memory='fresh'.*memory='growing'"),
        ({"buffer_size": 1024, "train_freq": 1024}, "buffer_size=1024 has no effect with memory='fresh'"),
        ({"exploration_fraction": 0.2}, r"exploration_fraction=0.2 .* both are 0.5.*set them apart"),
        (
            {"exploration_fraction": 0.2, "exploration_initial_eps": 0.1, "exploration_final_eps": 0.1},
            "exploration_fraction=0.2 .* both are 0.1",
        ),
        ({"policy_kwargs": {"net_arch": [64, 0]}}, "net_arch must be a list of positive layer sizes"),
        ({"policy_kwargs": {"net_arch": [64, True]}}, "net_arch must be a list of positive layer sizes"),
    ],
)
def test_bad_hyperparameters_are_rejected_at_construction(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        NFQ("MlpPolicy", "CartPole-v1", **kwargs)


@pytest.mark.parametrize(
    ("name", "value", "instead"),
    [
        ("learning_starts", 1000, "no warm-up"),
        ("target_update_interval", 500, "no target network"),
        ("tau", 0.005, "no target network"),
        ("optimize_memory_usage", True, "buffer_size"),
        ("replay_buffer_class", None, "memory='fresh'"),
    ],
)
def test_dqn_parameters_get_a_type_error_saying_what_nfq_does_instead(name: str, value: Any, instead: str) -> None:
    with pytest.raises(TypeError, match=f"DQN's parameter '{name}'.*{instead}.*Coming from DQN"):
        NFQ("MlpPolicy", "CartPole-v1", **{name: value})


@pytest.mark.parametrize(
    ("name", "value", "instead"),
    [
        ("double_q", True, r"max_a' Q\(s', a'\)"),
        ("round_step_size", 0.5, "whole"),
        ("keep_best", True, "KeepBestCallback"),
    ],
)
def test_retired_parameters_get_a_type_error_saying_what_nfq_does_instead(name: str, value: Any, instead: str) -> None:
    with pytest.raises(TypeError, match=f"NFQ no longer has the parameter '{name}': .*{instead}"):
        NFQ("MlpPolicy", "CartPole-v1", **{name: value})


def test_every_parameter_of_dqn_is_an_nfq_parameter_or_a_dqn_only_one() -> None:
    dqn = set(inspect.signature(DQN.__init__).parameters) - {"self"}
    nfq = set(inspect.signature(NFQ.__init__).parameters)
    assert dqn - nfq - set(DQN_ONLY_PARAMETERS) == set()
    off_policy = set(inspect.signature(OffPolicyAlgorithm.__init__).parameters)
    assert set(DQN_ONLY_PARAMETERS) <= dqn | off_policy  # no stale entry (action_noise is OffPolicyAlgorithm's)


def test_an_unknown_keyword_is_a_type_error_naming_it() -> None:
    with pytest.raises(TypeError, match="unexpected keyword argument 'gradient_step'"):
        NFQ("MlpPolicy", "CartPole-v1", gradient_step=3)


@pytest.mark.parametrize(
    ("env_id", "space"),
    [("Pendulum-v1", "Box"), ("MountainCarContinuous-v0", "Box")],
)
def test_non_discrete_action_spaces_are_rejected(env_id: str, space: str) -> None:
    with pytest.raises(ValueError, match=f"NFQ supports only Discrete action spaces.*got {space}"):
        NFQ("MlpPolicy", env_id)


def test_discrete_action_space_not_starting_at_zero_is_rejected() -> None:
    class ShiftedActions(gym.ActionWrapper):
        def __init__(self, env: gym.Env) -> None:
            super().__init__(env)
            self.action_space = gym.spaces.Discrete(2, start=-1)

        def action(self, action: Any) -> Any:
            return int(action) + 1

    with pytest.raises(ValueError, match="start at 0"):
        NFQ("MlpPolicy", ShiftedActions(gym.make("CartPole-v1")))


def test_round_larger_than_buffer_size_is_rejected() -> None:
    with pytest.raises(ValueError, match="buffer_size=100 is smaller than one round of 1024 transitions"):
        NFQ("MlpPolicy", "CartPole-v1", memory="growing", buffer_size=100)


def test_buffer_size_and_exploration_fraction_are_accepted_where_they_have_an_effect() -> None:
    assert NFQ("MlpPolicy", "CartPole-v1", memory="growing", buffer_size=100_000).replay_buffer.buffer_size == 100_000
    episodes = NFQ("MlpPolicy", "CartPole-v1", train_freq=(2, "episode"), buffer_size=5_000)
    assert episodes.replay_buffer.buffer_size == 5_000  # a fresh memory of episode rounds: the most a round holds
    decaying = NFQ(
        "MlpPolicy", "CartPole-v1", exploration_initial_eps=1.0, exploration_final_eps=0.05, exploration_fraction=0.2
    )
    assert decaying.exploration_schedule(0.9) == pytest.approx(1.0 - 0.95 / 2)
    NFQ("MlpPolicy", "CartPole-v1", exploration_fraction=0.1)  # the default, whose effect nothing can tell


def test_episode_rounds_need_buffer_size_and_one_env() -> None:
    with pytest.raises(ValueError, match="pass buffer_size"):
        NFQ("MlpPolicy", "CartPole-v1", train_freq=(2, "episode"))
    with pytest.raises(ValueError, match="needs a single environment"):
        NFQ("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2), train_freq=(2, "episode"), buffer_size=10_000)


def test_episode_round_overflowing_buffer_size_stops_training() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=(50, "episode"), buffer_size=64, seed=0)
    with pytest.raises(ValueError, match="more than buffer_size=64 holds"):
        model.learn(1)


def test_non_finite_loss_stops_training_and_names_the_round() -> None:
    env = DummyVecEnv([lambda: NaNRewardAfter(gym.make("CartPole-v1"), n_steps=100)])
    model = NFQ("MlpPolicy", env, train_freq=64, gradient_steps=2, seed=0)
    with pytest.raises(FloatingPointError, match="loss became nan in round 2") as error:
        model.learn(10_000)
    assert isinstance(error.value, NFQDivergenceError) and isinstance(error.value, ValueError)  # zoo tuning prunes
    # the failing step was not applied: the network is still finite
    assert all(p.isfinite().all() for p in model.q_net.parameters())


@pytest.mark.parametrize("total_timesteps", [0, -100, float("nan"), "1000", True])
def test_learn_refuses_a_budget_that_is_not_a_positive_number(total_timesteps: Any) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", train_freq=64, gradient_steps=1)
    with pytest.raises(ValueError, match=r"total_timesteps .* must be a positive number, got"):
        model.learn(total_timesteps)
    assert model.num_timesteps == 0


def _zero_reward_images() -> FakeImageEnv:
    """SB3's image env: its rewards are all 0, so every true Q-value is 0."""
    return FakeImageEnv(screen_height=84, screen_width=84, n_channels=1, discrete=True)


def test_q_values_past_what_the_rewards_allow_warn_once_before_any_nan() -> None:
    model = NFQ("CnnPolicy", _zero_reward_images(), gamma=0.99, train_freq=64, gradient_steps=4, seed=0)
    model.set_logger(Logger(folder=None, output_formats=[]))
    with pytest.warns(
        UserWarning, match=r"look divergent: after round \d+ .*\|Q\(s, a\)\| .* bound every value by 0"
    ) as caught:
        model.learn(64 * 4)
    assert len([w for w in caught if "look divergent" in str(w.message)]) == 1  # once per learn()
    assert model.logger.name_to_value["train/q_bound_exceeded"] == 1
    assert model.logger.name_to_value["train/q_abs_max"] > 100


def test_gamma_1_has_no_q_value_bound_to_check() -> None:
    model = NFQ("CnnPolicy", _zero_reward_images(), gamma=1.0, train_freq=64, gradient_steps=4, seed=0)
    model.set_logger(Logger(folder=None, output_formats=[]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.learn(64 * 4)
    assert "train/q_bound_exceeded" not in model.logger.name_to_value


def test_healthy_cartpole_training_with_gamma_below_1_does_not_warn_of_divergence() -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", gamma=0.99, train_freq=256, gradient_steps=10, seed=0)
    model.set_logger(Logger(folder=None, output_formats=[]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.learn(256 * 8)
    assert model.logger.name_to_value["train/q_bound_exceeded"] == 0
