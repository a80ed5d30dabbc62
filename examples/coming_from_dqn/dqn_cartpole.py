"""
A typical DQN script on CartPole-v1 (the RL Zoo's DQN settings, four envs, evaluation and checkpoint callbacks,
save, load, evaluate). nfq_cartpole.py beside it is the same script with NFQ: diff the two to see the swap.

    python examples/coming_from_dqn/dqn_cartpole.py [--total-timesteps 20000] [--seed 0] [--threads 1] [--log-dir runs]
"""

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch as th
from stable_baselines3 import DQN
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv


def make_model(env: VecEnv, seed: int) -> DQN:
    """
    :param env: the training envs
    :param seed: the model's seed
    :return: DQN with the RL Zoo's CartPole-v1 settings
    """
    return DQN(
        "MlpPolicy",
        env,
        learning_rate=2.3e-3,
        buffer_size=100_000,
        learning_starts=1000,
        batch_size=64,
        gamma=0.99,
        target_update_interval=10,
        train_freq=256,
        gradient_steps=128,
        exploration_fraction=0.16,
        exploration_final_eps=0.04,
        policy_kwargs=dict(net_arch=[256, 256]),
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
    log_dir = args.log_dir / "dqn"

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
        CheckpointCallback(save_freq=2500, save_path=str(log_dir / "checkpoints"), name_prefix="dqn_cartpole"),
    ]
    start = time.perf_counter()
    model.learn(args.total_timesteps, callback=callbacks)
    train_seconds = time.perf_counter() - start

    model.save(log_dir / "dqn_cartpole")
    loaded = DQN.load(log_dir / "dqn_cartpole")
    mean, std = evaluate_policy(
        loaded, make_vec_env("CartPole-v1", n_envs=4, seed=args.seed + 2000), n_eval_episodes=100, deterministic=True
    )
    assert isinstance(mean, float) and isinstance(std, float)
    print(f"DQN, {model.num_timesteps} steps in {train_seconds:.0f} s: {mean:.1f} +/- {std:.1f} over 100 episodes")
    result = {
        "algo": "DQN",
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
