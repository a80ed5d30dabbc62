"""
Optuna for the one config: ONE point of NFQ's search space trained on every benchmark env, the tuning path of the
one-config target (one env at a time is tuned with the zoo's ``-optimize``: benchmarks/README.md, Tuning). The
search space is the zoo's (``sb3_nfq.zoo.sample_nfq_params``); the study lives in a journal file that resumes and
that several workers share, each with its own tuning seed.

    python -m benchmarks.tune_one_config --seed 100 --n-trials 20 \\
        --storage benchmarks/results/tuning/one_config.log --study-name nfq-one-config

A trial trains its point on each env in turn for the steps the target allows there: DQN's median steps to solve on
the development seeds (``dqn-zoo`` in benchmarks/results/runs.jsonl). Its score on an env is the mean return of
``--eval-episodes`` greedy episodes at that budget, scaled so that uniformly random actions score 0 and the threshold
1 (capped at 1). The trial's value is its lowest score, reported after each env, so that the median pruner stops a
point that already falls short on one env.
"""

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import torch as th
from optuna.storages import JournalStorage
from optuna.storages.journal import JournalFileBackend
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv

from benchmarks import configs
from benchmarks.report import side_by_side
from benchmarks.run import DEFAULT_RESULTS, FINAL_SEED_BASE, make_env, read_results
from sb3_nfq import NFQ, NFQDivergenceError
from sb3_nfq.zoo import sample_nfq_params

#: The lowest tuning seed: seeds below it are the benchmark's development and held-out seeds.
FIRST_TUNING_SEED = 100


class RandomActions:
    """Uniformly random actions, behind SB3's ``predict``: the score every env's scale starts from."""

    def __init__(self, env: VecEnv, seed: int) -> None:
        self.space, self.n_envs = env.action_space, env.num_envs
        self.space.seed(seed)

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, None]:
        """:return: one random action per env"""
        return np.array([self.space.sample() for _ in range(self.n_envs)]), None


def mean_return(model: Any, env_id: str, episodes: int, seed: int) -> float:
    """
    :param model: a trained model, or ``None`` for uniformly random actions
    :param env_id: the env
    :param episodes: how many episodes, one per env of a ``VecEnv``
    :param seed: episode ``i`` starts from ``reset(seed=seed + i)``
    :return: the mean return of the greedy episodes
    """
    env = make_env(env_id, episodes, seed)
    policy = RandomActions(env, seed) if model is None else model
    returns, _ = evaluate_policy(policy, env, episodes, deterministic=True, return_episode_rewards=True)
    return float(np.mean(returns))


def dqn_budgets(results: Path, envs: Sequence[str]) -> dict[str, int]:
    """
    :param results: the runner's results file of the development seeds
    :param envs: the env ids
    :return: per env, dqn-zoo's median steps to solve on the development seeds, pooled as the targets pool runs
        (``benchmarks.report.side_by_side``)
    """
    records = [record for record in read_results(results) if int(record["seed"]) in configs.SEEDS]
    budgets = {}
    for env_id in envs:
        cells = side_by_side(records, env_id, ["dqn-zoo"])
        if cells is None:
            raise SystemExit(f"no dqn-zoo runs of {env_id} in {results}: pass --budget")
        budgets[env_id] = int(cells[0].steps_quantile(50)[0])
    return budgets


def objective(
    trial: optuna.Trial, budgets: dict[str, int], floors: dict[str, float], episodes: int, seed: int, episodes_seed: int
) -> float:
    """
    :param trial: the trial, which samples its point
    :param budgets: env id -> env steps to train for
    :param floors: env id -> the mean return of random actions there
    :param episodes: greedy episodes per score
    :param seed: the tuning seed (model, training env)
    :param episodes_seed: the scoring episodes start from ``reset(seed=episodes_seed + i)``, as ``floors``' did
    :return: the trial's lowest scaled score over the envs (pruned after an env when the median pruner says so)
    """
    kwargs = sample_nfq_params(trial, 0, 1, {})
    trial.set_user_attr("seed", seed)
    lowest = 1.0
    for step, (env_id, budget) in enumerate(budgets.items()):
        model = NFQ("MlpPolicy", make_env(env_id, 1, seed), seed=seed, device="cpu", **kwargs)
        try:
            model.learn(budget)
            score = mean_return(model, env_id, episodes, episodes_seed)
        except NFQDivergenceError:
            score = floors[env_id]
        trial.set_user_attr(env_id, {"budget": budget, "mean_return": score})
        threshold = configs.ENVS[env_id].threshold
        lowest = min(lowest, (score - floors[env_id]) / (threshold - floors[env_id]))
        trial.report(lowest, step)
        if trial.should_prune():
            raise optuna.TrialPruned()
    return lowest


def main(argv: Sequence[str] | None = None) -> int:
    """:param argv: arguments (default: ``sys.argv[1:]``) :return: exit status"""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, required=True, help=f"a tuning seed ({FIRST_TUNING_SEED} and up)")
    parser.add_argument("--storage", type=Path, required=True, help="the study's journal file")
    parser.add_argument("--study-name", default="nfq-one-config")
    parser.add_argument("--n-trials", type=int, default=10, help="trials this worker runs")
    parser.add_argument("--eval-episodes", type=int, default=20, help="greedy episodes per score")
    parser.add_argument("--envs", nargs="+", default=list(configs.ENVS), choices=list(configs.ENVS))
    parser.add_argument("--budget", type=int, help="every env's budget (default: dqn-zoo's median steps to solve)")
    args = parser.parse_args(argv)
    if args.seed < FIRST_TUNING_SEED:
        parser.error(f"--seed must be a tuning seed, {FIRST_TUNING_SEED} or more, got {args.seed}")
    th.set_num_threads(1)
    budgets = (
        dict.fromkeys(args.envs, args.budget) if args.budget is not None else dqn_budgets(DEFAULT_RESULTS, args.envs)
    )
    episodes_seed = FINAL_SEED_BASE + 1000 * args.seed
    floors = {env_id: mean_return(None, env_id, args.eval_episodes, episodes_seed) for env_id in args.envs}
    args.storage.parent.mkdir(parents=True, exist_ok=True)
    study = optuna.create_study(
        study_name=args.study_name,
        storage=JournalStorage(JournalFileBackend(str(args.storage))),
        direction="maximize",
        sampler=optuna.samplers.TPESampler(n_startup_trials=5, seed=args.seed),
        pruner=optuna.pruners.MedianPruner(n_startup_trials=5),
        load_if_exists=True,
    )
    study.set_user_attr(f"seed {args.seed}", {"budgets": budgets, "random_actions": floors})
    study.optimize(
        lambda trial: objective(trial, budgets, floors, args.eval_episodes, args.seed, episodes_seed), args.n_trials
    )
    print(f"budgets {budgets}; random actions {floors}")
    print(study.trials_dataframe(attrs=("number", "value", "state", "params")).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
