"""Neural Fitted Q-Iteration (NFQ) as a Stable-Baselines3 off-policy algorithm."""

import io
import math
import pathlib
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import (
    GymEnv,
    MaybeCallback,
    ReplayBufferSamples,
    Schedule,
    TrainFreq,
    TrainFrequencyUnit,
)
from stable_baselines3.common.utils import LinearSchedule, configure_logger

from sb3_nfq import rounds
from sb3_nfq.checkpoints import check_nfq_checkpoint, drop_retired, safe_custom_objects, train_freq_json
from sb3_nfq.exploration import (
    epsilon_greedy,
    epsilon_greedy_predict,
    greedy_actions,
    reject_obs_info_pair,
    repeated_epsilon_greedy,
)
from sb3_nfq.fitting import (
    check_loss_is_finite,
    check_q_values_bounded,
    denormals_flushed,
    iteration_rows,
    loss_and_gradient,
    minibatch_indices,
    shared_successor_states,
    take,
    td_targets,
)
from sb3_nfq.memory import make_memory, stored_transitions
from sb3_nfq.offline import TransitionDataset
from sb3_nfq.parameters import (
    DEFAULT_EXPLORATION_FRACTION,
    HYPERPARAMETERS,
    ExplorationStartName,
    LossName,
    MemoryName,
    TargetModeName,
    check_action_space,
    check_full_batch_optimizer,
    check_hyperparameters,
    check_total_timesteps,
    is_positive_int,
    loss_function,
    reject_unknown_parameters,
)
from sb3_nfq.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, NFQPolicy, QNetwork

SelfNFQ = TypeVar("SelfNFQ", bound="NFQ")


class NFQ(OffPolicyAlgorithm):
    """
    Neural Fitted Q-Iteration (NFQ)

    Paper: M. Riedmiller, "Neural Fitted Q Iteration", ECML 2005. The defaults are the CartPole settings of chapter 8
    of "Grokking Deep Reinforcement Learning": rounds of ``train_freq`` fresh epsilon-greedy transitions, each fitted
    by ``gradient_steps`` full-batch regressions on detached TD targets (no target network), then discarded.

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, MultiInputPolicy, or a policy class)
    :param env: The environment to learn from (if registered in Gymnasium, can be str), with ``Discrete`` actions;
        ``None`` with :meth:`for_dataset`
    :param learning_rate: The learning rate (Rprop's initial step size), or a function of the progress remaining
    :param train_freq: Transitions per round (the book's E) over all envs, rounded up to a multiple of ``n_envs``, or
        ``(n, "episode")``: ``n`` whole episodes (one env only)
    :param gradient_steps: Fitted iterations per round (the book's K), each covering the whole memory once
    :param batch_size: ``None`` (textbook): one full-batch gradient step per epoch; an integer: shuffled mini-batches
        that cover every transition once (a last mini-batch of one row joins the one before it)
    :param buffer_size: Most transitions the memory holds; ``None``: one round (fresh), 1,000,000 (growing); refused
        for a fresh memory of rounds counted in steps, which always holds one round
    :param memory: ``"fresh"`` (textbook): fit each round's transitions, then discard them; ``"growing"`` (2005
        paper): keep every transition (the oldest go past ``buffer_size``) and fit the whole memory every round
    :param round_fraction: With ``memory="growing"``, ``f``: a round collects ``max(train_freq, f * M)`` transitions,
        ``M`` being what the memory holds as it starts (the fit cost per env step stays bounded); ``None``: ``E``
    :param round_fraction_offset: With ``round_fraction``, transitions of the memory that ``M`` does not count
    :param target_mode: ``"recompute_every_step"`` (textbook): TD targets recomputed before every gradient step;
        ``"fixed_per_iteration"`` (fitted Q-iteration): once per iteration, then ``fit_epochs`` epochs on them
    :param fit_epochs: Epochs of regression on the fixed targets per fitted iteration (``"fixed_per_iteration"``)
    :param iteration_transitions: ``None`` (textbook): each fitted iteration covers the whole memory. An integer: a
        memory holding more has each iteration cover that many of its transitions, drawn at random (a memory larger
        than one iteration's fit, as DQN's replay buffer is larger than its gradient steps cover)
    :param gamma: The discount factor, in [0, 1] (the book's CartPole code uses 1.0)
    :param n_steps: 1 (textbook): one-step TD targets. More (SB3 DQN's n-step returns): ``r_t + gamma r_(t+1) + ... +
        gamma^(n-1) r_(t+n-1) + gamma^n max_a' Q(s_(t+n), a')``, cut short where the episode ends or at the memory's
        newest step (:func:`~sb3_nfq.memory.n_step_transitions`); online learning only
    :param loss: Regression loss between ``Q(s, a)`` and the TD targets: ``"mse"`` (textbook) or ``"huber"``
    :param huber_delta: With ``loss="huber"``, the TD error where the loss turns linear (1.0: SB3 DQN's loss)
    :param exploration_fraction: Fraction of the training period over which epsilon goes linearly from its initial
        to its final value, in (0, 1]; refused, unless the default, when the two are equal
    :param exploration_initial_eps: Initial probability of a random action while collecting
    :param exploration_final_eps: Final probability of a random action while collecting
    :param exploration_repeat_mu: ``None`` (textbook): a random action lasts one step. A number ``mu > 1``:
        temporally-extended epsilon-greedy while collecting (Dabney et al., 2021, whose choice is 2.0): a random
        action is taken for ``n ~ Zeta(mu)`` steps (``P(n) ~ n^-mu``; smaller ``mu``, longer repeats) or until the
        episode ends, and epsilon is the chance of starting one. ``predict(deterministic=False)`` stays
        epsilon-greedy, one step at a time
    :param exploration_start: When epsilon's schedule starts: ``"first_step"`` (SB3 DQN's) or
        ``"first_termination"``: at the first transition into a terminal state (not a time-limit truncation) that
        NFQ collects, epsilon staying at ``exploration_initial_eps`` until then. Where an episode ends only at the
        goal (Acrobot, MountainCar), exploration does not wind down before the goal was reached once
    :param exploration_ucb: ``None`` (textbook): the greedy actions while collecting are greedy on the Q-values. A
        number ``c >= 0``, with ``policy_kwargs=dict(n_critics=...)`` of at least 2: SUNRISE's optimistic actions (Lee
        et al., 2021), greedy on the critics' mean Q-values plus ``c`` times their standard deviation, which leads to
        where the critics disagree. ``predict`` (epsilon-greedy or greedy) and evaluations act on the mean
    :param max_grad_norm: Clip the gradient norm to this value; ``None`` (textbook): no clipping
    :param stats_window_size: Window size for the rollout logging, specifying the number of episodes to average
        the reported success rate, mean episode length, and mean reward over
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation
        (``net_arch``, ``activation_fn``, ``optimizer_class``, ``optimizer_kwargs``, features extractor, ...)
    :param verbose: Verbosity level: 0 for no output, 1 for info messages (such as device or wrappers used), 2 for
        debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run.
        Setting it to auto, the code will be run on the GPU if possible.
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    :param kwargs: Nothing: DQN's other parameters and those NFQ no longer has raise a ``TypeError`` saying what
        NFQ does instead
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    exploration_schedule: Schedule
    q_net: QNetwork
    policy: NFQPolicy
    replay_buffer: ReplayBuffer

    def __init__(
        self,
        policy: str | type[NFQPolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 5e-4,
        train_freq: int | tuple[int, str] = 1024,
        gradient_steps: int = 40,
        batch_size: int | None = None,
        buffer_size: int | None = None,
        memory: MemoryName = "fresh",
        round_fraction: float | None = None,
        round_fraction_offset: int = 0,
        target_mode: TargetModeName = "recompute_every_step",
        fit_epochs: int = 1,
        iteration_transitions: int | None = None,
        gamma: float = 1.0,
        n_steps: int = 1,
        loss: LossName = "mse",
        huber_delta: float = 1.0,
        exploration_fraction: float = DEFAULT_EXPLORATION_FRACTION,
        exploration_initial_eps: float = 0.5,
        exploration_final_eps: float = 0.5,
        exploration_repeat_mu: float | None = None,
        exploration_start: ExplorationStartName = "first_step",
        exploration_ucb: float | None = None,
        max_grad_norm: float | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
        **kwargs: Any,
    ) -> None:
        reject_unknown_parameters(kwargs)
        check_hyperparameters(**{name: value for name, value in locals().items() if name in HYPERPARAMETERS})
        super().__init__(
            policy,
            env,  # type: ignore[arg-type]  # None: spaces come from load() or for_dataset()
            learning_rate,
            buffer_size=buffer_size,  # type: ignore[arg-type]  # None: one round, resolved in make_memory
            learning_starts=0,
            batch_size=batch_size,  # type: ignore[arg-type]  # None: full batch
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            action_noise=None,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            sde_support=False,
            supported_action_spaces=None,  # checked in _setup_model, with a clearer error than SB3's assert
            support_multi_env=True,
        )
        self.n_steps = n_steps
        self.loss = loss
        self.huber_delta = huber_delta
        self.memory = memory
        self.round_fraction = round_fraction
        self.round_fraction_offset = round_fraction_offset
        self.target_mode = target_mode
        self.fit_epochs = fit_epochs
        self.iteration_transitions = iteration_transitions
        self.exploration_initial_eps = exploration_initial_eps
        self.exploration_final_eps = exploration_final_eps
        self.exploration_fraction = exploration_fraction
        self.exploration_repeat_mu = exploration_repeat_mu
        self.exploration_start = exploration_start
        self.exploration_ucb = exploration_ucb
        # The step at which epsilon's schedule started (None: not yet, with exploration_start="first_termination").
        self._exploration_started_at: int | None = 0 if exploration_start == "first_step" else None
        self.max_grad_norm = max_grad_norm
        # Probability of a random action while collecting ("epsilon" of epsilon-greedy)
        self.exploration_rate = exploration_initial_eps
        self._n_rounds = 0
        # How much of the current round is in the memory (env.step() calls; episodes, for episode rounds): a round
        # cut short by a callback or by the end of learn() is completed by the next learn(), then fitted.
        self._round_steps = 0
        self._round_episodes = 0
        # The current round's length (env.step() calls; episodes, for episode rounds), fixed when it starts (0: not
        # yet): with round_fraction, it follows what the memory holds then.
        self._round_target = 0
        # The largest |reward| fitted so far, and whether this learn() has warned that Q-values passed what it allows.
        self._max_abs_reward = 0.0
        self._q_bound_warned = False
        # With exploration_repeat_mu: for each env, the steps its random action still lasts, and that action.
        self._repeat_steps_left: np.ndarray | None = None
        self._repeated_actions: np.ndarray | None = None

        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        check_action_space(self.action_space)
        self._convert_train_freq()
        self._train_freq_json = train_freq_json(self.train_freq)
        if self.replay_buffer is None:
            self.replay_buffer = make_memory(
                self.observation_space,
                self.action_space,
                self.train_freq,
                self.n_envs,
                self.buffer_size,
                self.memory,
                self.device,
            )
            self.replay_buffer_class = type(self.replay_buffer)
        # SB3 sets up n-step returns in its own NStepReplayBuffer and warns that a given buffer class has none: NFQ
        # computes them from its memory each round (stored_transitions), so SB3's setup sees n_steps=1.
        n_steps, self.n_steps = self.n_steps, 1
        super()._setup_model()
        self.n_steps = n_steps
        self.q_net = self.policy.q_net
        if self.exploration_ucb is not None and self.policy.n_critics < 2:
            raise ValueError(
                f"exploration_ucb={self.exploration_ucb} collects on the spread of an ensemble's Q-values, but the "
                f"policy has n_critics={self.policy.n_critics}: pass policy_kwargs=dict(n_critics=...) of at least 2, "
                "or drop exploration_ucb"
            )
        # Rprop needs a round's fit in full batches, which only a fresh memory of step rounds bounds.
        fit_size = rounds.fresh_round_transitions(self.train_freq, self.n_envs, self.memory)
        check_full_batch_optimizer(
            self.policy.optimizer,
            self.batch_size,
            self.iteration_transitions,
            fit_size,
            f"a round's fit (memory={self.memory!r})",
        )
        self.exploration_schedule = LinearSchedule(
            self.exploration_initial_eps, self.exploration_final_eps, self.exploration_fraction
        )

    def learn(
        self: SelfNFQ,
        total_timesteps: int | None = None,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "NFQ",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfNFQ:
        """
        Train NFQ for ``total_timesteps`` environment steps (rounded up to a multiple of ``n_envs``), fitting each
        round once it is complete. A round that is not complete when training stops (at ``total_timesteps``, or
        because a callback returned False) stays in the memory, unfitted: the next ``learn()`` completes it and
        fits it, and ``save_replay_buffer`` saves it. With ``train_freq`` counted in episodes, training runs in
        whole rounds and may go past ``total_timesteps``.

        :param total_timesteps: The total number of environment steps to train on; ``None`` (DQN has no default):
            300,000, the textbook's CartPole-v1 budget, with a ``UserWarning`` saying how to watch the progress
        :param callback: callback(s) called at every step with state of the algorithm.
        :param log_interval: Log data every ``log_interval`` episodes
        :param tb_log_name: the name of the run for TensorBoard logging
        :param reset_num_timesteps: whether or not to reset the current timestep number (used in logging)
        :param progress_bar: Display a progress bar using tqdm and rich.
        :return: the trained model
        """
        total_timesteps = check_total_timesteps(total_timesteps)
        total_timesteps, callback = self._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        callback.on_training_start(locals(), globals())
        assert self.env is not None
        self._q_bound_warned = False
        if reset_num_timesteps and self._exploration_started_at is not None:
            self._exploration_started_at = 0  # a schedule that has started restarts with the step count

        if rounds.missing_from_memory(self._round_steps, self.replay_buffer, self._n_rounds + 1):
            self._round_steps = self._round_episodes = self._round_target = 0
        length = rounds.round_length(self.train_freq, self.n_envs)
        by_episode = length.unit == TrainFrequencyUnit.EPISODE
        while True:
            if (self._round_episodes if by_episode else self._round_steps) >= self._round_size(length):
                # 2. Fit: gradient_steps fitted iterations on the memory.
                self.train(gradient_steps=self.gradient_steps, batch_size=self.batch_size)
                self._round_steps = self._round_episodes = self._round_target = 0
                # 3. The textbook discards the fitted round; a growing memory keeps it.
                if self.memory == "fresh":
                    self.replay_buffer.reset()
            if self.num_timesteps >= total_timesteps:
                break
            # 1. Collect (the rest of) a round with the epsilon-greedy policy, stopping at total_timesteps.
            self.exploration_rate = self.exploration_schedule(self._exploration_progress_remaining())
            if by_episode:
                to_collect = length.frequency - self._round_episodes
            else:
                steps_left = math.ceil((total_timesteps - self.num_timesteps) / self.n_envs)
                to_collect = min(self._round_size(length) - self._round_steps, steps_left)
            rollout = self.collect_rollouts(
                self.env, callback, TrainFreq(to_collect, length.unit), self.replay_buffer, log_interval=log_interval
            )
            if not rollout.continue_training:
                rounds.store_interrupted_step(self, callback)
                break  # a complete round is fitted by the next learn(), before it collects

        callback.on_training_end()
        return self

    def _round_size(self, length: TrainFreq) -> int:
        """:return: the current round's length, in episodes or ``env.step()`` calls (fixed when it starts)"""
        if self._round_target == 0:
            held = (self.replay_buffer.size() - self._round_steps) * self.n_envs
            self._round_target = rounds.round_size(
                length, self.round_fraction, held, self.n_envs, self.round_fraction_offset
            )
        return self._round_target

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """
        Store one ``env.step()``'s transitions and count them into the current round, so that the round's progress
        saved with a model always matches the memory; a round longer than the memory stops with an error at once.
        """
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        if self._exploration_started_at is None and any(
            done and not info.get("TimeLimit.truncated", False) for done, info in zip(dones, infos, strict=True)
        ):
            self._exploration_started_at = self.num_timesteps
        if self._repeat_steps_left is not None:
            self._repeat_steps_left[dones] = 0  # a repeated random action ends with its episode
        self._round_steps += 1
        self._round_episodes += int(np.sum(dones))
        rounds.check_round_fits(self._round_steps, replay_buffer, self.buffer_size, self._n_rounds + 1)

    def train(self, gradient_steps: int, batch_size: int | None = None) -> None:
        """
        Run ``gradient_steps`` fitted iterations, each covering every transition in the memory (with
        ``iteration_transitions``, at most that many of them, drawn at random).

        :param gradient_steps: Number of fitted iterations (the book's K)
        :param batch_size: ``None``: one full-batch step per epoch; else shuffled mini-batches of this size
        """
        if self.replay_buffer.size() == 0:
            raise ValueError(
                "NFQ's memory is empty: there is nothing to fit. Collect transitions with learn(), load them with "
                "load_replay_buffer(), or fit a dataset with fit_offline()."
            )
        rewards = None if self.n_steps == 1 else stored_transitions(self.replay_buffer, self._vec_normalize_env).rewards
        self._fit(self._stored_transitions(), self.replay_buffer.n_envs, gradient_steps, batch_size, rewards)

    def _fit(
        self,
        batch: ReplayBufferSamples,
        n_envs: int,
        gradient_steps: int,
        batch_size: int | None,
        rewards: th.Tensor | None = None,
    ) -> None:
        """
        Fit the Q-network on ``batch`` (a round's memory, or a dataset) by ``gradient_steps`` fitted iterations.

        :param batch: the transitions to fit on, one row per transition (step-major, then env)
        :param n_envs: how many envs the rows interleave (a transition's next state is ``n_envs`` rows on)
        :param gradient_steps: Number of fitted iterations
        :param batch_size: ``None``: one full-batch step per epoch; else shuffled mini-batches of this size
        :param rewards: the one-step rewards that bound the Q-values (default: ``batch``'s, one-step transitions)
        """
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        self._n_rounds += 1
        n_transitions, device = len(batch.rewards), batch.rewards.device
        loss_fn = loss_function(self.loss, self.huber_delta)
        shared_states = shared_successor_states(self.q_net, batch, n_envs, batch_size)

        # Denormal floats flushed to zero: the optimizer's decaying averages leave the CPU's slow path for them.
        with denormals_flushed(device):
            losses = []
            for iteration in range(gradient_steps):
                rows = iteration_rows(n_transitions, self.iteration_transitions, device)
                data, shared = (batch, shared_states) if rows is None else (take(batch, rows), None)
                # Classic fitted Q-iteration regresses on targets fixed for the iteration; the textbook recomputes them.
                fixed = td_targets(self.q_net, data, self.gamma) if self.target_mode == "fixed_per_iteration" else None
                q_abs_max = th.zeros((), device=device)  # over the last iteration: its steps cover its transitions
                for _ in range(self.fit_epochs):
                    for indices in minibatch_indices(len(data.rewards), batch_size, device):
                        known = fixed if fixed is None or indices is None else fixed[indices]
                        # Targets, the loss and its gradient; the step only if the loss is finite.
                        self.policy.optimizer.zero_grad()
                        loss_value, q_values, targets = loss_and_gradient(
                            self.q_net, loss_fn, self.gamma, take(data, indices), known, shared
                        )
                        check_loss_is_finite(
                            loss_value, self._n_rounds, iteration + 1, gradient_steps, self.num_timesteps
                        )
                        if self.max_grad_norm is not None:
                            th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                        self.policy.optimizer.step()
                        self._n_updates += 1
                        losses.append(loss_value)
                        q_abs_max = th.maximum(q_abs_max, q_values.detach().abs().max())

        exceeded = check_q_values_bounded(self, q_abs_max.item(), batch.rewards if rewards is None else rewards)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/n_rounds", self._n_rounds, exclude="tensorboard")
        self.logger.record("train/batch_transitions", n_transitions)
        self.logger.record("train/loss", float(np.mean(losses)))
        self.logger.record("train/q_mean", q_values.mean().item())
        self.logger.record("train/td_target_mean", targets.mean().item())
        self.logger.record("train/q_abs_max", q_abs_max.item())
        if self.gamma < 1:
            self.logger.record("train/q_bound_exceeded", int(exceeded))

    @classmethod
    def for_dataset(
        cls: type[SelfNFQ], policy: str | type[NFQPolicy], dataset: TransitionDataset, **kwargs: Any
    ) -> SelfNFQ:
        """
        Create an NFQ model for a dataset's spaces, with no environment (for :meth:`fit_offline`).
        Give it an env later with ``set_env`` (one env) to go on learning online.

        :param policy: The policy model to use (``"MlpPolicy"`` or a policy class)
        :param dataset: the dataset whose observation and action spaces the model takes
        :param kwargs: NFQ's other parameters (``gamma``, ``target_mode``, ``policy_kwargs``, ...)
        :return: the new model
        """
        model = cls(policy, env=None, _init_setup_model=False, **kwargs)
        model.observation_space = dataset.observation_space
        model.action_space = dataset.action_space
        model.n_envs = 1
        model._setup_model()
        return model

    def fit_offline(self: SelfNFQ, dataset: TransitionDataset, iterations: int | None = None) -> SelfNFQ:
        """
        Fit on a fixed dataset, without an environment, as :meth:`train` fits a round (``batch_size``,
        ``target_mode``, ``fit_epochs``); the online memory is left as it was. Logs ``train/*`` once at the end.

        :param dataset: the transitions to fit on; their spaces must match the model's
        :param iterations: number of fitted iterations (default: ``self.gradient_steps``)
        :return: the fitted model
        """
        dataset.check_spaces(self.observation_space, self.action_space)
        if self.n_steps != 1:
            raise ValueError(
                f"fit_offline fits one-step targets, but this model has n_steps={self.n_steps}: a dataset's "
                "transitions need not follow each other. Create the model for the dataset with n_steps=1."
            )
        iterations = self.gradient_steps if iterations is None else iterations
        if not is_positive_int(iterations):
            raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
        check_full_batch_optimizer(
            self.policy.optimizer,
            self.batch_size,
            self.iteration_transitions,
            len(dataset),
            f"the dataset's {len(dataset)} transitions",
        )
        if not hasattr(self, "_logger"):
            self.set_logger(configure_logger(self.verbose, self.tensorboard_log, "NFQ_offline"))
        self._q_bound_warned = False
        self._fit(dataset.samples(self.device), 1, iterations, self.batch_size)
        self.logger.dump(step=self.num_timesteps)
        return self

    def _stored_transitions(self) -> ReplayBufferSamples:
        """:return: every transition in the memory as a round fits them (:func:`~sb3_nfq.memory.stored_transitions`)"""
        return stored_transitions(self.replay_buffer, self._vec_normalize_env, self.n_steps, self.gamma)

    def _exploration_progress_remaining(self) -> float:
        """:return: the progress remaining that epsilon's schedule is at (1: not started; counted from its start)"""
        if self._exploration_started_at is None:
            return 1.0
        if self._exploration_started_at == 0:  # SB3's own progress, so that the default stays SB3's schedule exactly
            return self._current_progress_remaining
        return 1.0 - (self.num_timesteps - self._exploration_started_at) / self._total_timesteps

    def _on_step(self) -> None:
        """Update the exploration rate; called by ``collect_rollouts()`` after each environment step."""
        self.exploration_rate = self.exploration_schedule(self._exploration_progress_remaining())
        self.logger.record("rollout/exploration_rate", self.exploration_rate)

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """
        Get the action(s) for observation(s): greedy if ``deterministic``, else epsilon-greedy,
        with an independent coin flip for each observation of a batch (``epsilon = self.exploration_rate``).

        :param observation: the input observation (or a batch of them)
        :param state: The last states (unused, for recurrent policies)
        :param episode_start: The last masks (unused, for recurrent policies)
        :param deterministic: Whether to return the greedy action(s)
        :return: the action(s), always an ``np.ndarray`` (0-d for one observation), and the next state (unused)
        """
        reject_obs_info_pair(observation)
        if deterministic or self.exploration_rate <= 0:
            return self.policy.predict(observation, state, episode_start, deterministic=True)
        return epsilon_greedy_predict(self.policy, observation, self.exploration_rate), state

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """
        The behaviour policy while collecting: epsilon-greedy for the ``n_envs`` current observations, drawn
        exactly as ``predict(deterministic=False)`` draws them; with ``exploration_repeat_mu``, its temporally-extended
        form, which carries each env's repeated random action over from step to step.

        :param learning_starts: unused (NFQ has no warm-up)
        :param action_noise: unused (discrete actions)
        :param n_envs: number of envs
        :return: the actions to take and to store (the same for discrete actions)
        """
        assert self._last_obs is not None
        last_obs = self._last_obs

        def greedy() -> np.ndarray:
            return greedy_actions(self.policy, last_obs, self.exploration_ucb)

        if self.exploration_repeat_mu is None:
            actions = epsilon_greedy(self.exploration_rate, self.action_space, n_envs, greedy)
            return actions, actions
        if self._repeat_steps_left is None or len(self._repeat_steps_left) != n_envs:
            self._repeat_steps_left = np.zeros(n_envs, dtype=np.int64)
            self._repeated_actions = np.zeros(n_envs, dtype=np.int64)
        assert self._repeated_actions is not None
        actions = repeated_epsilon_greedy(
            self.exploration_rate,
            self.action_space,
            self.exploration_repeat_mu,
            self._repeat_steps_left,
            self._repeated_actions,
            greedy,
        )
        return actions, actions

    @classmethod
    def load(
        cls: type[SelfNFQ],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        safe: bool = False,
        **kwargs: Any,
    ) -> SelfNFQ:
        """
        Load an NFQ model from a zip saved by :meth:`save` (anything else raises a ``ValueError``); see
        :meth:`stable_baselines3.common.base_class.BaseAlgorithm.load`.

        SB3 stores spaces, schedules and classes as cloudpickle, which runs any code a crafted checkpoint holds: load
        only checkpoints you trust, or use ``safe=True``. A safe load unpickles nothing: it rebuilds each pickled entry
        from the checkpoint's plain JSON and from ``env`` (without ``env``, only a small ``Box`` observation space),
        loads the weights with ``torch.load(weights_only=True)``, refuses, naming it, an entry it cannot rebuild (a
        learning-rate schedule, a custom features extractor class: pass those in ``custom_objects``), and starts the
        next ``learn()`` with new episodes and empty episode statistics. ``load_replay_buffer`` always unpickles its
        file: load only replay buffers you trust.

        :param path: path to the file (or a file-like) where to load the agent from
        :param env: the new environment to run the loaded model on
        :param device: Device on which the code should run.
        :param custom_objects: Dictionary of objects to replace upon loading.
        :param print_system_info: Whether to print system info from the saved model
        :param force_reset: Force call to ``reset()`` before training
        :param safe: unpickle nothing (see above); ``False``: SB3's load, which runs the checkpoint's pickles
        :param kwargs: extra arguments to change the model when loading
        :return: new model instance with loaded parameters
        """
        if safe:
            env = None if env is None else cls._wrap_env(env)  # as SB3's load wraps it, to read its spaces
            custom_objects = safe_custom_objects(path, env, custom_objects, cls.policy_aliases)
        check_nfq_checkpoint(path, custom_objects)
        return super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)

    def set_parameters(
        self,
        load_path_or_dict: str | pathlib.Path | io.BufferedIOBase | dict[str, Any],
        exact_match: bool = True,
        device: th.device | str = "auto",
    ) -> None:
        """
        Load the policy's and optimizer's parameters from a zip saved by :meth:`save` or from :meth:`get_parameters`;
        what an earlier version saved for the parameters NFQ no longer has is dropped with a ``UserWarning``.
        See :meth:`stable_baselines3.common.base_class.BaseAlgorithm.set_parameters`.

        :param load_path_or_dict: the zip file (or a file-like), or a dict of state dicts by name
        :param exact_match: whether the parameters must cover every network and each of its parameters
        :param device: Device on which the code should run.
        """
        super().set_parameters(drop_retired(vars(self), load_path_or_dict, device), exact_match, device)

    def _excluded_save_params(self) -> list[str]:
        # The repeats in progress belong to the envs of this learn(): a loaded model starts without any.
        return [*super()._excluded_save_params(), "q_net", "_repeat_steps_left", "_repeated_actions"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", "policy.optimizer"], []
