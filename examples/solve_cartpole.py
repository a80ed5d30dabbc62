"""
The main job: train NFQ with the textbook defaults on CartPole-v1 until it is solved, then evaluate,
save, load it back and show the loaded agent acting.

"Solved" is the book's criterion: the mean return of 100 greedy episodes reaches 475. After every round
(1024 steps) an EvalCallback runs 100 greedy episodes on a separate env; training stops at the first
evaluation that reaches the threshold, or when the step budget runs out.

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
from stable_baselines3.common.callbacks import EvalCallback, StopTrainingOnRewardThreshold
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

import sb3_nfq
from sb3_nfq import NFQ

ENV_ID = "CartPole-v1"
SOLVED_AT = 475.0


def main(argv: list[str] | None = None) -> int:
    """
    Run the main job.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: exit status: 0 if solved within the budget, 1 otherwise
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
    eval_env = make_vec_env(ENV_ID, n_envs=100, seed=args.seed + 10_000)
    stop_when_solved = StopTrainingOnRewardThreshold(reward_threshold=SOLVED_AT, verbose=1)
    evaluate_every_round = EvalCallback(
        eval_env,
        n_eval_episodes=100,
        eval_freq=int(model.train_freq.frequency),  # type: ignore[union-attr]  # one round, in env.step() calls
        callback_on_new_best=stop_when_solved,
        deterministic=True,
        verbose=0,
    )

    start = time.perf_counter()
    model.learn(args.max_steps, callback=evaluate_every_round, progress_bar=not args.no_progress_bar)
    train_seconds = time.perf_counter() - start
    solved = evaluate_every_round.best_mean_reward >= SOLVED_AT
    print(
        f"{'Solved' if solved else 'NOT solved'}: best greedy mean over 100 episodes "
        f"{evaluate_every_round.best_mean_reward:.1f} after {model.num_timesteps} env steps, "
        f"{model._n_rounds} rounds, {train_seconds:.0f} s (training and per-round evaluations)"
    )

    final_env = make_vec_env(ENV_ID, n_envs=100, seed=args.seed + 20_000)
    mean_return, std_return = evaluate_policy(model, final_env, n_eval_episodes=100, deterministic=True)
    assert isinstance(mean_return, float) and isinstance(std_return, float)
    print(f"Final evaluation on 100 new greedy episodes: {mean_return:.1f} +/- {std_return:.1f}")

    model.save(args.output)
    loaded = NFQ.load(args.output)
    print(f"Saved to {args.output} and loaded back")

    env = gym.make(ENV_ID)
    obs, _ = env.reset(seed=args.seed + 30_000)
    with th.no_grad():
        start_q = loaded.q_net(loaded.policy.obs_to_tensor(np.asarray(obs))[0])[0].numpy()
    print(
        f"Loaded agent at a new start state {[round(float(x), 3) for x in obs]}: Q(s, left) = {start_q[0]:.1f}, "
        f"Q(s, right) = {start_q[1]:.1f} (the return it expects from there, at most 500)"
    )
    episode_return, done = 0.0, False
    while not done:
        action, _ = loaded.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, _ = env.step(int(action))
        episode_return += float(reward)
        done = terminated or truncated
    ending = "balanced to the 500-step limit" if truncated and not terminated else "the pole fell"
    print(f"Loaded agent, one greedy episode from that state: return {episode_return:.0f} ({ending})")

    print(
        "RESULT "
        + json.dumps(
            {
                "solved": bool(solved),
                "steps": model.num_timesteps,
                "rounds": model._n_rounds,
                "train_seconds": round(train_seconds, 1),
                "best_eval_mean": round(float(evaluate_every_round.best_mean_reward), 1),
                "final_eval_mean": round(float(mean_return), 1),
                "seed": args.seed,
                "threads": th.get_num_threads(),
            }
        )
    )
    return 0 if solved else 1


if __name__ == "__main__":
    sys.exit(main())
