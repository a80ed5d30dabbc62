"""
NFQ with the SB3 tooling you already use: EvalCallback (greedy evaluation, best model),
CheckpointCallback (zip checkpoints, with the replay buffer) and TensorBoard logging, then resuming from a checkpoint.

    python examples/callbacks_tensorboard.py [--total-timesteps 60000] [--log-dir logs/nfq_cartpole]
    tensorboard --logdir logs/nfq_cartpole/tensorboard
"""

import argparse
from pathlib import Path

import torch as th
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_nfq import NFQ


def main(argv: list[str] | None = None) -> Path:
    """
    Train with evaluation, checkpoints and TensorBoard, then resume training from the last checkpoint.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: the log directory
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--total-timesteps", type=int, default=60_000)
    parser.add_argument("--log-dir", type=Path, default=Path("logs/nfq_cartpole"))
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: see README)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    log_dir: Path = args.log_dir

    # Two envs: a round is still 1024 transitions in total (512 steps in each env).
    env = make_vec_env("CartPole-v1", n_envs=2, seed=0)
    model = NFQ("MlpPolicy", env, seed=0, tensorboard_log=str(log_dir / "tensorboard"))

    round_steps = 1024 // env.num_envs  # callbacks count env.step() calls, each of n_envs transitions
    callbacks = [
        EvalCallback(
            make_vec_env("CartPole-v1", n_envs=10, seed=1),
            n_eval_episodes=20,
            eval_freq=5 * round_steps,
            best_model_save_path=str(log_dir / "best_model"),
            log_path=str(log_dir / "eval"),
            deterministic=True,
        ),
        # With its replay buffer, a checkpoint taken partway through a round resumes that round where it stopped.
        CheckpointCallback(
            save_freq=10 * round_steps,
            save_path=str(log_dir / "checkpoints"),
            name_prefix="nfq",
            save_replay_buffer=True,
        ),
    ]
    checkpoint_steps = 10 * round_steps * env.num_envs
    if args.total_timesteps < checkpoint_steps:
        print(
            f"--total-timesteps {args.total_timesteps} is below {checkpoint_steps}, the steps between checkpoints: "
            f"no checkpoint will be saved, so the resume demo will be skipped (pass --total-timesteps "
            f"{checkpoint_steps} or more to see it)."
        )
    model.learn(args.total_timesteps, callback=callbacks, progress_bar=True)

    checkpoints = sorted((log_dir / "checkpoints").glob("nfq_*_steps.zip"), key=lambda p: int(p.stem.split("_")[1]))
    print(f"Checkpoints: {[p.name for p in checkpoints]}")
    if checkpoints:
        # Resume from the last checkpoint: weights, optimizer state, step counter and the round's transitions.
        resumed = NFQ.load(checkpoints[-1], env=env)
        steps = checkpoints[-1].stem.split("_")[1]
        resumed.load_replay_buffer(log_dir / "checkpoints" / f"nfq_replay_buffer_{steps}_steps.pkl")
        resumed.learn(2048, reset_num_timesteps=False, tb_log_name="NFQ_resumed")
        print(f"Resumed from {checkpoints[-1].name} and trained on to {resumed.num_timesteps} steps")
    else:
        print(f"No checkpoint to resume from: resume demo skipped (it needs --total-timesteps {checkpoint_steps}+)")
    print(f"TensorBoard logs: tensorboard --logdir {log_dir / 'tensorboard'}")
    return log_dir


if __name__ == "__main__":
    main()
