"""
Callbacks for any SB3 algorithm: the book's definition of "solved", and ending training with the best weights.

"Grokking Deep Reinforcement Learning" trains its value-based agents episode by episode: after *every* training
episode the greedy policy plays *one* evaluation episode, and training stops once the mean of the last 100
evaluation returns reaches the goal (475 on CartPole-v1). :class:`BookCriterion` is that bookkeeping, with no SB3
in it; :class:`StopTrainingOnBookCriterion` drives it from any SB3 algorithm's ``learn()``. :class:`KeepBestCallback`
ends ``learn()`` with the policy's best-scoring weights, scored by the training episodes' returns.
"""

import collections
import copy
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import VecMonitor, is_vecenv_wrapped

from sb3_nfq.parameters import is_positive_int

#: A greedy policy for one observation: observation -> action.
GreedyAct = Callable[[Any], Any]


class BookCriterion:
    """
    One greedy evaluation episode per training episode; solved when the mean of the last ``window`` evaluation
    returns reaches ``threshold``. As in the book's code, the mean is over all evaluations while there are fewer
    than ``window`` of them.

    :param eval_env: the env the evaluation episodes are played on (kept apart from the training env)
    :param threshold: the goal for the mean evaluation return (the book: 475 on CartPole-v1)
    :param window: how many of the latest evaluation returns are averaged (the book: 100)
    :param seed: seeds the evaluation env's first reset; later episodes go on from its random stream
    """

    def __init__(self, eval_env: gym.Env, threshold: float = 475.0, window: int = 100, seed: int | None = None) -> None:
        if not is_positive_int(window):
            raise ValueError(f"window must be a positive integer (evaluation returns averaged), got {window!r}")
        if not np.isfinite(threshold):
            raise ValueError(f"threshold must be a finite number, got {threshold!r}")
        self.eval_env = eval_env
        self.threshold = float(threshold)
        self.window = window
        self._seed = seed
        #: Return of each evaluation episode, one per training episode so far.
        self.evaluation_returns: list[float] = []
        #: Env steps trained when each evaluation was played.
        self.evaluation_steps: list[int] = []
        #: Env steps and training episodes at the first evaluation where the criterion held (``None``: not yet).
        self.steps_to_solve: int | None = None
        self.episodes_to_solve: int | None = None
        #: Seconds spent playing evaluation episodes (to subtract from training time, as the book does).
        self.eval_seconds = 0.0

    @property
    def solved(self) -> bool:
        """:return: whether the criterion has held at some evaluation"""
        return self.steps_to_solve is not None

    @property
    def mean_return(self) -> float:
        """:return: the mean of the last ``window`` evaluation returns (NaN before the first)"""
        if not self.evaluation_returns:
            return float("nan")
        return float(np.mean(self.evaluation_returns[-self.window :]))

    def play_episode(self, act: GreedyAct) -> float:
        """
        :param act: the greedy policy, one observation in, one action out
        :return: the undiscounted return of one episode on the evaluation env
        """
        obs, _ = self.eval_env.reset(seed=self._seed)
        self._seed = None
        episode_return, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = self.eval_env.step(act(obs))
            episode_return += float(reward)
            done = terminated or truncated
        return episode_return

    def on_training_episode_end(self, steps: int, act: GreedyAct) -> bool:
        """
        Play the evaluation episode that follows a training episode, and check the criterion.

        :param steps: env steps trained so far
        :param act: the greedy policy
        :return: whether the criterion holds now
        """
        start = time.perf_counter()
        self.evaluation_returns.append(self.play_episode(act))
        self.evaluation_steps.append(steps)
        self.eval_seconds += time.perf_counter() - start
        holds = self.mean_return >= self.threshold
        if holds and not self.solved:
            self.steps_to_solve, self.episodes_to_solve = steps, len(self.evaluation_returns)
        return holds


class StopTrainingOnBookCriterion(BaseCallback):
    """
    The book's criterion for any SB3 algorithm: after each training episode that ends (in any of the training
    envs), the greedy policy (``predict(deterministic=True)``) plays one episode on ``eval_env``; training stops
    once the mean of the last ``window`` of those returns reaches ``threshold``. The evaluation episodes are not
    counted as training steps. Logs ``eval/book_mean_return`` and ``eval/book_episodes``.

    The greedy policy sees ``eval_env``'s raw observations: do not use it with ``VecNormalize`` training envs.

    .. code-block:: python

        model = NFQ("MlpPolicy", "CartPole-v1", seed=12)
        book = StopTrainingOnBookCriterion(gym.make("CartPole-v1"), threshold=475, seed=12)
        model.learn(500_000, callback=book)
        print(book.criterion.steps_to_solve, book.criterion.episodes_to_solve)

    :param eval_env: the evaluation env, or an env id (made with ``gym.make``, no render mode)
    :param threshold: the goal for the mean evaluation return (the book: 475 on CartPole-v1)
    :param window: how many of the latest evaluation returns are averaged (the book: 100)
    :param stop_at_solve: stop training when the criterion first holds (the book does); ``False`` keeps training
        and keeps evaluating
    :param seed: seeds the evaluation env's first reset
    :param verbose: 1 prints the solve
    """

    def __init__(
        self,
        eval_env: gym.Env | str,
        threshold: float = 475.0,
        window: int = 100,
        stop_at_solve: bool = True,
        seed: int | None = None,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        if isinstance(eval_env, str):
            eval_env = gym.make(eval_env)
        if not isinstance(eval_env, gym.Env):
            raise ValueError(
                f"eval_env must be a gymnasium.Env or an env id (one env: one episode per training episode), "
                f"got {type(eval_env).__name__}"
            )
        self.criterion = BookCriterion(eval_env, threshold=threshold, window=window, seed=seed)
        self.stop_at_solve = stop_at_solve

    def _act(self, observation: Any) -> Any:
        action, _ = self.model.predict(observation, deterministic=True)
        return action.item() if isinstance(action, np.ndarray) and action.size == 1 else action

    def _on_step(self) -> bool:
        keep_training = True
        for done in np.asarray(self.locals["dones"]).reshape(-1):
            if not done:
                continue
            solved_before = self.criterion.solved
            holds = self.criterion.on_training_episode_end(self.num_timesteps, self._act)
            self.logger.record("eval/book_mean_return", self.criterion.mean_return)
            self.logger.record("eval/book_episodes", len(self.criterion.evaluation_returns))
            if self.criterion.solved and not solved_before and self.verbose >= 1:
                print(
                    f"Book criterion met after {self.criterion.episodes_to_solve} episodes, "
                    f"{self.criterion.steps_to_solve} steps: mean of the last {self.criterion.window} "
                    f"evaluation returns {self.criterion.mean_return:.1f} >= {self.criterion.threshold:g}"
                )
            if holds and self.stop_at_solve:
                keep_training = False
        return keep_training


class KeepBestCallback(BaseCallback):
    """
    End ``learn()`` with the best-scoring weights of the run instead of the last ones, at no extra env steps, for an
    SB3 off-policy algorithm (NFQ, DQN, QR-DQN, ...). The policy's weights change in ``train()``, between rollouts,
    not while a rollout is collected: at the end of each rollout, the weights that collected it are scored by the
    mean return of the training episodes that ended during it (the ``Monitor``'s returns, so exploratory ones), or,
    when fewer than ``n_episodes`` did, of the last ``n_episodes`` training episodes; a score at least the best so
    far keeps a copy of the policy's weights (``policy.state_dict()``: DQN's target network included) aside. Weights
    under which no episode ended, or before ``n_episodes`` episodes have ended in all, are not scored. At the end of
    ``learn()`` the best weights are loaded back into the policy, so the model ends with them (and ``model.save`` then
    saves them). Training itself is unchanged: each fit starts from the weights the previous one left.

    With short rollouts (DQN's few steps, NFQ's short rounds) one episode, often exploratory luck, would score the
    weights: ``n_episodes`` above 1 scores them by the recent run of episodes instead, of which the latest weights
    played the last ones.

    The training env must report its episodes' returns: each env wrapped in ``Monitor`` (as ``make_vec_env`` and an
    env id do) or the ``VecEnv`` in ``VecMonitor``. Logs ``train/best_score``. The best score and weights carry over
    when the same callback is passed to a later ``learn()``.

    .. code-block:: python

        model = NFQ("MlpPolicy", "CartPole-v1", seed=0)
        keep_best = KeepBestCallback()
        model.learn(100_000, callback=keep_best)
        print(keep_best.best_score)

    :param n_episodes: the fewest training episodes a score is the mean of (1: the rollout's own episodes alone)
    :param verbose: 1 prints each new best score
    """

    def __init__(self, n_episodes: int = 1, verbose: int = 0) -> None:
        if not is_positive_int(n_episodes):
            raise ValueError(f"n_episodes must be an int of at least 1 (episodes per score), got {n_episodes!r}")
        super().__init__(verbose)
        self.n_episodes = n_episodes
        #: The best mean return so far (``None``: no weights scored yet).
        self.best_score: float | None = None
        #: A copy of the policy's ``state_dict()`` that scored ``best_score`` (``None``: none yet).
        self.best_weights: dict[str, th.Tensor] | None = None
        # Returns of the training episodes that ended since the last judgement, and of the latest ones before them.
        self._returns: list[float] = []
        self._earlier: collections.deque[float] = collections.deque(maxlen=n_episodes)

    def _init_callback(self) -> None:
        env = self.training_env
        if not (is_vecenv_wrapped(env, VecMonitor) or all(env.env_is_wrapped(Monitor))):
            raise ValueError(
                "KeepBestCallback judges the policy's weights by the returns of the training episodes, which a Monitor "
                "wrapper reports, but this env has none: wrap each env in stable_baselines3.common.monitor.Monitor "
                "(make_vec_env and an env id given to the model do), or the VecEnv in VecMonitor."
            )

    def _on_step(self) -> bool:
        ended = [info for info, done in zip(self.locals["infos"], self.locals["dones"], strict=True) if done]
        self._returns += [float(info["episode"]["r"]) for info in ended]
        return True

    def _on_rollout_end(self) -> None:
        self._judge()

    def _on_training_end(self) -> None:
        self._judge()  # episodes after the last rollout's end: a callback stopped collection early
        if self.best_weights is not None:
            self.model.policy.load_state_dict(self.best_weights)

    def _judge(self) -> None:
        """Score the weights that collected the episodes ended since the last judgement; keep them if the best."""
        if not self._returns:
            return
        window = [*self._earlier, *self._returns][-max(self.n_episodes, len(self._returns)) :]
        self._earlier.extend(self._returns)
        self._returns = []
        if len(window) < self.n_episodes:
            return
        score = float(np.mean(window))
        if self.best_score is None or score >= self.best_score:
            self.best_score = score
            self.best_weights = copy.deepcopy(self.model.policy.state_dict())
            if self.verbose >= 1:
                print(f"New best score {score:.2f} after {self.num_timesteps} steps")
        self.logger.record("train/best_score", self.best_score)
