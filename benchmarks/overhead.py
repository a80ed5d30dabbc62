"""
Framework overhead of sb3_nfq.NFQ against the plain-PyTorch reference, on this machine, same thread count.

    python -m benchmarks.overhead [--threads 1] [--repeats 20] [--env CartPole-v1] [--profile] [--json out.json]

(a) One round (collect 1024 transitions with epsilon-greedy, then 40 full-batch fitted iterations): NFQ (inside
    ``learn()``, timed by a callback from the start of the round's collection to the end of its fit) against
    ``ReferenceNFQ`` (``collect_round()`` then ``fit()``). Rounds of the two alternate (and which goes first
    alternates), after one untimed warm-up round each, so that load from other processes hits both alike.
    Medians, and their ratio. Both envs are wrapped in :class:`EnvTimer`, so each round's time inside the env's
    ``step``/``reset`` is known: the target (<= 1.0) is judged on the round time *without* it, the time that is
    the implementation's own. On CartPole a step costs the same in any state, but on Box2D envs such as
    LunarLander it depends on the lander's state (contacts, engine particles), so two agents whose policies
    differ pay different env costs for the same number of steps.
(b) The fitting alone: ``NFQ.train(40)`` against a bare torch loop (``reference_nfq.fit_q_network``) on the SAME
    1024 transitions, from the SAME initial weights with the same optimizer (RMSprop, lr 5e-4). The first
    repetition also checks that both end at the same weights. Medians and their ratio (target <= 1.1).
``--profile`` adds a cProfile of NFQ rounds (the functions where the time goes).
"""

import argparse
import cProfile
import io
import json
import pstats
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger

from benchmarks.reference_nfq import ReferenceNFQ, Transitions, fit_q_network, make_q_network
from benchmarks.run import machine_line
from sb3_nfq import NFQ

ROUND_TARGET = 1.0
FIT_TARGET = 1.1


class EnvTimer(gym.Wrapper):
    """Adds up the seconds spent inside the wrapped env's ``step`` and ``reset``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.seconds = 0.0

    def step(self, action: Any) -> Any:
        start = time.perf_counter()
        try:
            return self.env.step(action)
        finally:
            self.seconds += time.perf_counter() - start

    def reset(self, **kwargs: Any) -> Any:
        start = time.perf_counter()
        try:
            return self.env.reset(**kwargs)
        finally:
            self.seconds += time.perf_counter() - start


class RoundTimer(BaseCallback):
    """Timestamps of the phases of NFQ's rounds: collection start, collection end, end of the fit."""

    def __init__(self) -> None:
        super().__init__()
        self.starts: list[float] = []
        self.collected: list[float] = []
        self.ends: list[float] = []

    def _on_rollout_start(self) -> None:
        self.starts.append(time.perf_counter())

    def _on_rollout_end(self) -> None:
        self.collected.append(time.perf_counter())

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        self.ends.append(time.perf_counter())


RoundTimes = tuple[float, float, float]


def nfq_round(model: NFQ, timer: RoundTimer, env_timer: EnvTimer) -> RoundTimes:
    """
    Train NFQ for exactly one more round.

    :return: seconds collecting, seconds from the end of the collection to the end of the fit, and the part of
        the collection spent inside the env's ``step``/``reset``
    """
    env_before = env_timer.seconds
    model.learn(int(model.train_freq.frequency), callback=timer, reset_num_timesteps=False)  # type: ignore[union-attr]
    collect, fit = timer.collected[-1] - timer.starts[-1], timer.ends[-1] - timer.collected[-1]
    return collect, fit, env_timer.seconds - env_before


def reference_round(agent: ReferenceNFQ, env_timer: EnvTimer) -> RoundTimes:
    """
    Run one round of the reference.

    :return: seconds collecting, seconds fitting, and the part of the collection spent inside the env
    """
    env_before = env_timer.seconds
    start = time.perf_counter()
    batch = agent.collect_round()
    collected = time.perf_counter()
    agent.fit(batch)
    return collected - start, time.perf_counter() - collected, env_timer.seconds - env_before


def fill_memory(model: NFQ, batch: Transitions) -> None:
    """Put the reference's transitions into NFQ's (empty) one-round memory, in order."""
    model.replay_buffer.reset()
    for i in range(len(batch.rewards)):
        model.replay_buffer.add(
            batch.observations[i : i + 1].numpy(),
            batch.next_observations[i : i + 1].numpy(),
            batch.actions[i : i + 1].numpy(),
            batch.rewards[i].numpy(),
            batch.terminated[i].numpy(),  # done = true termination only: truncations bootstrap in both
            [{}],
        )


def compare_rounds(env_id: str, repeats: int, seed: int) -> dict[str, Any]:
    """(a) NFQ rounds against reference rounds, alternating."""
    nfq_env = EnvTimer(gym.make(env_id))  # NFQ wraps it in Monitor and a DummyVecEnv, as it does an env id
    model = NFQ("MlpPolicy", nfq_env, seed=seed, device="cpu")
    agent = ReferenceNFQ(env_id, seed=seed)
    agent.env = reference_env = EnvTimer(agent.env)
    timer = RoundTimer()
    nfq_round(model, timer, nfq_env)  # warm-up
    reference_round(agent, reference_env)
    nfq_times, reference_times = [], []
    for repetition in range(repeats):  # alternate which goes first, so that neither always runs on a warm cache
        if repetition % 2:
            reference_times.append(reference_round(agent, reference_env))
            nfq_times.append(nfq_round(model, timer, nfq_env))
        else:
            nfq_times.append(nfq_round(model, timer, nfq_env))
            reference_times.append(reference_round(agent, reference_env))

    def medians(times: list[RoundTimes]) -> dict[str, float]:
        return {
            "total": statistics.median(c + f for c, f, _ in times),
            "collect": statistics.median(c for c, _, _ in times),
            "fit": statistics.median(f for _, f, _ in times),
            "env": statistics.median(e for _, _, e in times),
            "without_env": statistics.median(c + f - e for c, f, e in times),
        }

    nfq, reference = medians(nfq_times), medians(reference_times)
    return {
        "nfq": nfq,
        "reference": reference,
        "ratio": nfq["total"] / reference["total"],
        "ratio_without_env": nfq["without_env"] / reference["without_env"],
    }


def compare_fitting(env_id: str, repeats: int, seed: int) -> dict[str, Any]:
    """(b) NFQ.train against a bare loop on identical data and identical initial weights."""
    agent = ReferenceNFQ(env_id, seed=seed)
    batch = agent.collect_round()
    model = NFQ("MlpPolicy", env_id, seed=seed, device="cpu")
    model.set_logger(Logger(folder=None, output_formats=[]))
    fill_memory(model, batch)
    iterations = model.gradient_steps
    assert agent.n_actions == int(model.action_space.n)  # type: ignore[attr-defined]
    bare = make_q_network(batch.observations.shape[1], agent.n_actions)
    bare.load_state_dict(model.q_net.q_net.state_dict())
    bare_optimizer = th.optim.RMSprop(bare.parameters(), lr=float(model.policy.optimizer.param_groups[0]["lr"]))

    nfq_times, bare_times = [], []
    max_difference = 0.0

    def time_nfq() -> float:
        start = time.perf_counter()
        model.train(gradient_steps=iterations, batch_size=model.batch_size)
        return time.perf_counter() - start

    def time_bare() -> float:
        start = time.perf_counter()
        fit_q_network(bare, bare_optimizer, batch, model.gamma, iterations)
        return time.perf_counter() - start

    for repetition in range(repeats + 1):  # alternate which goes first
        if repetition % 2:
            bare_seconds, nfq_seconds = time_bare(), time_nfq()
        else:
            nfq_seconds, bare_seconds = time_nfq(), time_bare()
        if repetition == 0:  # same data, same start, same optimizer: same result
            max_difference = max(
                float((a.detach() - b.detach()).abs().max())
                for a, b in zip(model.q_net.q_net.parameters(), bare.parameters(), strict=True)
            )
        else:  # the first repetition is a warm-up for timing
            nfq_times.append(nfq_seconds)
            bare_times.append(bare_seconds)
    nfq, bare_median = statistics.median(nfq_times), statistics.median(bare_times)
    return {
        "nfq": nfq,
        "bare": bare_median,
        "ratio": nfq / bare_median,
        "iterations": iterations,
        "transitions": len(batch.rewards),
        "max_weight_difference_after_first_fit": max_difference,
    }


def profile_nfq(env_id: str, rounds: int, seed: int, top: int = 25) -> str:
    """:return: cProfile's top functions (by own time, then cumulative) over ``rounds`` NFQ rounds"""
    # The env as compare_rounds and the reference make it: from an env id SB3 would add render_mode="rgb_array",
    # whose drawing-only work (LunarLander's particles) would then show up in the profile as NFQ's.
    model = NFQ("MlpPolicy", gym.make(env_id), seed=seed, device="cpu")
    model.learn(int(model.train_freq.frequency))  # type: ignore[union-attr]  # warm-up
    profiler = cProfile.Profile()
    profiler.enable()
    model.learn(rounds * int(model.train_freq.frequency), reset_num_timesteps=False)  # type: ignore[union-attr]
    profiler.disable()
    out = io.StringIO()
    stats = pstats.Stats(profiler, stream=out)
    stats.sort_stats("tottime").print_stats(top)
    stats.sort_stats("cumulative").print_stats(top)
    return out.getvalue()


def _verdict(ratio: float, target: float) -> str:
    return "met" if ratio <= target else "not met"


def main(argv: Sequence[str] | None = None) -> int:
    """
    Command-line entry point.

    :param argv: arguments (default: ``sys.argv[1:]``)
    :return: exit status (0; the ratios are reported, not enforced)
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads for both (default 1)")
    parser.add_argument("--repeats", type=int, default=20, help="timed repetitions of each measurement")
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--profile", action="store_true", help="also cProfile NFQ rounds")
    parser.add_argument("--json", type=Path, help="also write the numbers to this JSON file")
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")

    th.set_num_threads(args.threads)
    print(f"machine: {machine_line()}")
    print(f"torch {th.__version__}, threads: {th.get_num_threads()}; env {args.env}; {args.repeats} repetitions")

    rounds = compare_rounds(args.env, args.repeats, args.seed)
    nfq, reference = rounds["nfq"], rounds["reference"]
    print("\n(a) one round = collect 1024 transitions + 40 full-batch fitted iterations (median over rounds)")
    for name, times in (("NFQ", nfq), ("reference", reference)):
        print(
            f"    {name:<10} {times['total'] * 1e3:7.1f} ms "
            f"(collect {times['collect'] * 1e3:6.1f} ms, of which in the env {times['env'] * 1e3:6.1f} ms; "
            f"fit {times['fit'] * 1e3:6.1f} ms); without the env {times['without_env'] * 1e3:7.1f} ms"
        )
    print(f"    ratio NFQ / reference, whole round: {rounds['ratio']:.3f}")
    print(
        f"    ratio NFQ / reference without the env's step/reset time: {rounds['ratio_without_env']:.3f} "
        f"(target <= {ROUND_TARGET}): {_verdict(rounds['ratio_without_env'], ROUND_TARGET)}"
    )

    fitting = compare_fitting(args.env, args.repeats, args.seed)
    print(
        f"\n(b) fitting alone: {fitting['iterations']} full-batch steps on the same {fitting['transitions']} "
        "transitions, same initial weights (median)"
    )
    print(f"    NFQ.train  {fitting['nfq'] * 1e3:7.1f} ms")
    print(f"    bare loop  {fitting['bare'] * 1e3:7.1f} ms")
    ratio = fitting["ratio"]
    print(f"    ratio NFQ / bare: {ratio:.3f} (target <= {FIT_TARGET}): {_verdict(ratio, FIT_TARGET)}")
    difference = fitting["max_weight_difference_after_first_fit"]
    print(f"    same data, same start: max |weight difference| after the first fit = {difference:.2e}")

    if args.profile:
        print("\ncProfile of NFQ rounds:\n" + profile_nfq(args.env, max(args.repeats // 2, 1), args.seed))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        numbers = {"threads": th.get_num_threads(), "env": args.env, "repeats": args.repeats, "machine": machine_line()}
        args.json.write_text(json.dumps({**numbers, "round": rounds, "fitting": fitting}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
