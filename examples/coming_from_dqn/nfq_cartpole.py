"""
dqn_cartpole.py with DQN swapped for NFQ, and NFQ given the project's recommended growing-memory CartPole settings
(the CartPole-v1 entry of sb3_nfq/hyperparams/nfq.yml, its KeepBestCallback included); everything else is the DQN
script's. Diff the two to see the swap.

    python examples/coming_from_dqn/nfq_cartpole.py [--total-timesteps 20000] [--seed 0] [--threads 1] [--log-dir runs]
"""

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch as th
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.utils import LinearSchedule
from stable_baselines3.common.vec_env import VecEnv

from sb3_nfq import NFQ, KeepBestCallback


def make_model(env: VecEnv, seed: int) -> NFQ:
    """
    :param env: the training envs
    :param seed: the model's seed
    :return: NFQ with the settings of sb3_nfq/hyperparams/nfq.yml's CartPole-v1 entry
    """
    return NFQ(
        "MlpPolicy",
        env,
        # DQN's 2.3e-3, decayed linearly to 0 at the end of training (the Zoo's "lin_0.0023")
        learning_rate=LinearSchedule(2.3e-3, 0.0, 1.0),
        buffer_size=100_000,
        # NFQ's counterpart of a replay buffer: keep every transition and refit the whole memory every round
        memory="growing",
        # A round: 128 transitions (all envs together) until the memory holds 4320, then 0.4 of what it holds past
        # its first 4000, so that the fitting cost grows linearly with the steps
        train_freq=128,
        round_fraction=0.4,
        round_fraction_offset=4000,
        # Each round: 8 fitted iterations, each an epoch of 128-transition mini-batches over the whole memory,
        # against TD targets computed once per iteration (NFQ's stand-in for DQN's target network)
        gradient_steps=8,
        batch_size=128,
        target_mode="fixed_per_iteration",
        gamma=0.99,
        max_grad_norm=10.0,
        exploration_initial_eps=0.5,
        exploration_fraction=0.16,
        exploration_final_eps=0.04,
        # DQN's network and optimizer (NFQ's default optimizer is the textbook's RMSprop)
        policy_kwargs=dict(net_arch=[256, 256], optimizer_class=th.optim.Adam),
        seed=seed,
    )


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """
    Train, save, load back and evaluate.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: what the closing ``RESULT`` line prints
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--total-timesteps", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: see README)")
    parser.add_argument("--log-dir", type=Path, default=Path("runs"))
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    log_dir = args.log_dir / "nfq"

    env = make_vec_env("CartPole-v1", n_envs=4, seed=args.seed)
    model = make_model(env, args.seed)
    callbacks = [
        EvalCallback(
            make_vec_env("CartPole-v1", n_envs=4, seed=args.seed + 1000),
            n_eval_episodes=20,
            eval_freq=1000,  # env.step() calls of the 4 envs: every 4000 steps
            best_model_save_path=str(log_dir / "best_model"),
            log_path=str(log_dir / "eval"),
        ),
        CheckpointCallback(save_freq=2500, save_path=str(log_dir / "checkpoints"), name_prefix="nfq_cartpole"),
        # The entry's callback: learn() ends with the weights whose training episodes scored best
        KeepBestCallback(),
    ]
    start = time.perf_counter()
    model.learn(args.total_timesteps, callback=callbacks)
    train_seconds = time.perf_counter() - start

    model.save(log_dir / "nfq_cartpole")
    loaded = NFQ.load(log_dir / "nfq_cartpole")
    mean, std = evaluate_policy(
        loaded, make_vec_env("CartPole-v1", n_envs=4, seed=args.seed + 2000), n_eval_episodes=100, deterministic=True
    )
    assert isinstance(mean, float) and isinstance(std, float)
    print(f"NFQ, {model.num_timesteps} steps in {train_seconds:.0f} s: {mean:.1f} +/- {std:.1f} over 100 episodes")
    result = {
        "algo": "NFQ",
        "steps": model.num_timesteps,
        "train_seconds": round(train_seconds, 1),
        "mean": round(float(mean), 1),
        "std": round(float(std), 1),
        "seed": args.seed,
        "threads": th.get_num_threads(),
    }
    print("RESULT " + json.dumps(result))
    return result


if __name__ == "__main__":
    main()
