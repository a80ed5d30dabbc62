"""
The main job: train NFQ with the textbook defaults on CartPole-v1 until it is solved, then save it, load it back
and show that the loaded agent balances.

"Solved" is the book's criterion: the mean return of 100 greedy episodes reaches 475. After every round
(1024 steps) an EvalCallback runs 100 greedy episodes on a separate env. The textbook's NFQ swings from one round
to the next, so one such evaluation can reach 475 by luck: when it does, the agent is evaluated again on 100 new
greedy episodes, and training stops only if those reach 475 too (otherwise it goes on). Training also stops when
the step budget runs out.

    python examples/solve_cartpole.py [--seed 0] [--max-steps 300000] [--threads 1] [--output nfq_cartpole.zip]
"""

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import stable_baselines3
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

import sb3_nfq
from sb3_nfq import NFQ

ENV_ID = "CartPole-v1"
SOLVED_AT = 475.0
EPISODES = 100


def evaluate_on_new_episodes(model: NFQ, seed: int) -> list[float]:
    """
    :param model: the agent, acting greedily
    :param seed: the episodes' seed: env ``i`` of the 100 starts from ``seed + i``, so a seed names 100 episodes
    :return: the returns of those 100 episodes, in the order they ended
    """
    returns, _ = evaluate_policy(
        model,
        make_vec_env(ENV_ID, n_envs=EPISODES, seed=seed),
        EPISODES,
        deterministic=True,
        return_episode_rewards=True,
    )
    assert isinstance(returns, list)
    return [float(r) for r in returns]


class StopWhenConfirmed(BaseCallback):
    """
    Called by an EvalCallback after each evaluation: when it reaches the threshold, evaluate the agent on 100 new
    greedy episodes (a seed not used before) and stop training only if their mean reaches it too.

    :param threshold: the mean return to reach (the book's 475)
    :param seed: the first confirmation's episode seed; the next ones follow it, 100 apart
    """

    def __init__(self, threshold: float, seed: int) -> None:
        super().__init__()
        self.threshold, self.seed = threshold, seed
        #: one (env steps, episode seed, mean return) per confirmation tried
        self.confirmations: list[tuple[int, int, float]] = []

    def _on_step(self) -> bool:
        assert isinstance(self.parent, EvalCallback) and isinstance(self.model, NFQ)
        if self.parent.last_mean_reward < self.threshold:
            return True
        seed = self.seed + EPISODES * len(self.confirmations)
        mean = float(np.mean(evaluate_on_new_episodes(self.model, seed)))
        self.confirmations.append((self.num_timesteps, seed, mean))
        verdict = "confirmed" if mean >= self.threshold else "training goes on"
        print(
            f"Evaluation at {self.num_timesteps} steps: {self.parent.last_mean_reward:.1f}; "
            f"on 100 new greedy episodes: {mean:.1f} ({verdict})"
        )
        return mean < self.threshold


def main(argv: list[str] | None = None) -> int:
    """
    Run the main job.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: exit status: 0 if solved (and confirmed) within the budget, 1 otherwise
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-steps", type=int, default=300_000, help="env-step budget for training")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: see README)")
    parser.add_argument("--output", type=Path, default=Path("nfq_cartpole.zip"), help="where to save the model")
    parser.add_argument("--no-progress-bar", action="store_true")
    args = parser.parse_args(argv)

    th.set_num_threads(args.threads)
    print(
        f"sb3-nfq {sb3_nfq.__version__}, SB3 {stable_baselines3.__version__}, torch {th.__version__} "
        f"({th.get_num_threads()} threads), Python {platform.python_version()}, {platform.machine()}"
    )

    model = NFQ("MlpPolicy", ENV_ID, seed=args.seed, verbose=0)
    stop_when_confirmed = StopWhenConfirmed(SOLVED_AT, seed=args.seed + 20_000)
    evaluate_every_round = EvalCallback(
        make_vec_env(ENV_ID, n_envs=EPISODES, seed=args.seed + 10_000),
        n_eval_episodes=EPISODES,
        eval_freq=int(model.train_freq.frequency),  # type: ignore[union-attr]  # one round, in env.step() calls
        callback_after_eval=stop_when_confirmed,
        deterministic=True,
        verbose=0,
    )

    start = time.perf_counter()
    model.learn(args.max_steps, callback=evaluate_every_round, progress_bar=not args.no_progress_bar)
    train_seconds = time.perf_counter() - start
    confirmations = stop_when_confirmed.confirmations
    solved = bool(confirmations) and confirmations[-1][2] >= SOLVED_AT
    print(
        f"{'Solved' if solved else 'NOT solved'} after {model.num_timesteps} env steps, {model._n_rounds} rounds, "
        f"{train_seconds:.0f} s (training and evaluations); best evaluation after a round: "
        f"{evaluate_every_round.best_mean_reward:.1f}"
    )

    # The final score: the confirming episodes if solved (this reproduces their mean), else 100 not seen before.
    final_seed = confirmations[-1][1] if solved else args.seed + 20_000 + EPISODES * len(confirmations)
    final_mean = float(np.mean(evaluate_on_new_episodes(model, final_seed)))
    which = "the ones that confirmed the solve" if solved else "not seen in training"
    print(f"Final evaluation on 100 new greedy episodes: {final_mean:.1f} ({which})")

    model.save(args.output)
    loaded = NFQ.load(args.output)
    loaded_returns = evaluate_on_new_episodes(loaded, final_seed)
    print(
        f"Saved to {args.output} and loaded back; the loaded agent on the same 100 episodes: "
        f"{np.mean(loaded_returns):.1f}, {sum(r == 500 for r in loaded_returns)} of them balanced to the "
        f"500-step limit, the shortest lasted {min(loaded_returns):.0f} steps"
    )

    env = gym.make(ENV_ID)
    obs, _ = env.reset(seed=final_seed)  # the first of those 100 episodes
    episode_return, terminated, truncated = 0.0, False, False
    while not (terminated or truncated):
        action, _ = loaded.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, _ = env.step(int(action))
        episode_return += float(reward)
    ending = "balanced to the 500-step limit" if truncated and not terminated else "the pole fell"
    print(f"The first of them, replayed step by step by the loaded agent: return {episode_return:.0f} ({ending})")

    print(
        "RESULT "
        + json.dumps(
            {
                "solved": solved,
                "steps": model.num_timesteps,
                "rounds": model._n_rounds,
                "train_seconds": round(train_seconds, 1),
                "best_eval_mean": round(float(evaluate_every_round.best_mean_reward), 1),
                "final_eval_mean": round(final_mean, 1),
                "loaded_eval_mean": round(float(np.mean(loaded_returns)), 1),
                "confirmations_tried": len(confirmations),
                "seed": args.seed,
                "threads": th.get_num_threads(),
            }
        )
    )
    return 0 if solved else 1


if __name__ == "__main__":
    sys.exit(main())
