"""
The 2005 paper's data-efficient NFQ on CartPole-v1 (nfq.yml's CartPole-v1 entry): a growing memory that keeps
every transition, refitted every round, in rounds that lengthen as the memory grows, with decaying exploration.
Compare with the textbook's fresh batches (examples/solve_cartpole.py), which need many times more steps.

Every 1024 steps the greedy policy plays 100 episodes; the run reports the first evaluation whose
mean reaches 475 (the book's "solved") and a final score on 100 new episodes. A few minutes on one core.

    python examples/growing_memory_cartpole.py [--total-timesteps 50000] [--seed 0]
"""

import argparse
from typing import Any

import torch as th
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_nfq import NFQ
from sb3_nfq.configs import nfq_callbacks, nfq_kwargs

#: The growing-memory settings of sb3_nfq/hyperparams/nfq.yml's CartPole-v1 entry (the file says where they were
#: measured); the entry's callbacks are given to learn().
GROWING_MEMORY_NFQ: dict[str, Any] = nfq_kwargs("CartPole-v1")


class RecordEvaluations(BaseCallback):
    """Called by ``EvalCallback`` after each evaluation: keeps (env steps, greedy mean return)."""

    def __init__(self) -> None:
        super().__init__()
        self.history: list[tuple[int, float]] = []

    def _on_step(self) -> bool:
        assert isinstance(self.parent, EvalCallback)
        self.history.append((self.num_timesteps, float(self.parent.last_mean_reward)))
        return True


def main(argv: list[str] | None = None) -> float:
    """
    Train the growing-memory NFQ, evaluating greedily every 1024 steps, and report when it first solved.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: the final greedy mean return over 100 episodes
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--total-timesteps", type=int, default=50_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: see README)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)

    model = NFQ("MlpPolicy", "CartPole-v1", seed=args.seed, **GROWING_MEMORY_NFQ)
    greedy_means = RecordEvaluations()
    evaluation = EvalCallback(
        make_vec_env("CartPole-v1", n_envs=100, seed=args.seed + 10_000),
        n_eval_episodes=100,
        eval_freq=1024,  # not every round: evaluating costs more time than training once episodes are long
        deterministic=True,
        callback_after_eval=greedy_means,
        verbose=0,
    )
    model.learn(args.total_timesteps, callback=[*nfq_callbacks("CartPole-v1"), evaluation], progress_bar=True)

    solved_at = [steps for steps, mean in greedy_means.history if mean >= 475]
    first_solve = f"{solved_at[0]} steps" if solved_at else "not reached"
    final_mean, _ = evaluate_policy(model, make_vec_env("CartPole-v1", n_envs=100, seed=args.seed + 20_000), 100)
    assert isinstance(final_mean, float)
    print(
        f"Memory holds {model.replay_buffer.size()} transitions after {model.num_timesteps} steps. "
        f"{len(greedy_means.history)} evaluations; first greedy mean >= 475: {first_solve}; "
        f"final greedy mean over 100 new episodes: {final_mean:.1f}"
    )
    return final_mean


if __name__ == "__main__":
    main()
