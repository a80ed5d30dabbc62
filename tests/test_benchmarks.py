"""
Fast tests of the benchmark suite (benchmarks/): the plain-PyTorch reference NFQ, the runner (JSON lines,
resumability, local pool, Ray), the report, the per-env tuning sweep and the overhead script. Tiny budgets, real
envs, no mocks.
"""

import dataclasses
import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th
from torch.nn import functional as F

from benchmarks import configs, main_job, memory_images, overhead, readme_blocks, report, run, scaling, tune_nfq
from benchmarks.reference_nfq import ReferenceNFQ, Transitions, fit_q_network, make_q_network, td_targets
from sb3_nfq.configs import read_entry, vec_normalize_kwargs, zoo_to_kwargs

RESULT_FIELDS = {
    "algo": str,
    "env": str,
    "seed": int,
    "budget": int,
    "config_hash": str,
    "solved": bool,
    "steps_trained": int,
    "train_seconds": float,
    "eval_seconds": float,
    "wall_seconds": float,
    "curve": list,
    "final_score": float,
    "final_n_episodes": int,
    "torch_threads": int,
    "versions": dict,
    "machine": str,
    "command": str,
    "eval_every": int,
    "threshold": float,
}


# --- reference NFQ ----------------------------------------------------------------------------------------------


def test_reference_runs_rounds_and_fits() -> None:
    agent = ReferenceNFQ("CartPole-v1", seed=0, transitions_per_round=256, fitting_iterations=5)
    rounds: list[int] = []

    def after_round(trained: ReferenceNFQ) -> bool:
        rounds.append(trained.num_timesteps)
        return True

    agent.learn(300, callback=after_round)
    assert rounds == [256, 512]  # whole rounds until the budget is reached
    assert agent.n_rounds == 2 and agent.last_losses.shape == (5,)
    assert th.isfinite(agent.last_losses).all()
    greedy, _ = agent.predict(np.zeros((3, 4), dtype=np.float32))
    assert greedy.shape == (3,) and set(greedy.tolist()) <= {0, 1}


def test_reference_fitting_learns() -> None:
    """With gamma = 0 fitting is plain regression on the rewards: 40 full-batch steps must reduce the loss."""
    agent = ReferenceNFQ("CartPole-v1", seed=1, transitions_per_round=512, gamma=0.0)
    batch = agent.collect_round()
    losses = fit_q_network(agent.q_net, agent.optimizer, batch, gamma=0.0, iterations=40)
    assert losses[-1] < 0.1 * losses[0]


def test_reference_targets_are_constants() -> None:
    agent = ReferenceNFQ("CartPole-v1", seed=2, transitions_per_round=128)
    batch = agent.collect_round()
    targets = td_targets(agent.q_net, batch, gamma=1.0)
    assert not targets.requires_grad and targets.grad_fn is None

    def gradient(loss: th.Tensor) -> th.Tensor:
        agent.q_net.zero_grad()
        loss.backward()
        return th.cat([p.grad.flatten() for p in agent.q_net.parameters() if p.grad is not None])

    q_taken = agent.q_net(batch.observations).gather(1, batch.actions)
    with_constant_targets = gradient(F.mse_loss(q_taken, targets))
    q_taken = agent.q_net(batch.observations).gather(1, batch.actions)
    max_next = agent.q_net(batch.next_observations).max(dim=1, keepdim=True).values  # NOT detached: the bug
    through_targets = gradient(F.mse_loss(q_taken, batch.rewards + (1 - batch.terminated) * max_next))
    assert not th.allclose(with_constant_targets, through_targets)  # the check can tell the two apart


def test_reference_truncation_bootstraps_and_termination_does_not() -> None:
    # Random actions, episodes cut at 15 steps: both truncations and true terminations occur in 512 steps.
    agent = ReferenceNFQ(
        "CartPole-v1", seed=3, epsilon=1.0, transitions_per_round=512, env_kwargs={"max_episode_steps": 15}
    )
    batch = agent.collect_round()
    next_is_next_obs = (batch.next_observations[:-1] == batch.observations[1:]).all(dim=1)
    episode_ends = th.cat([~next_is_next_obs, th.tensor([False])])
    terminated = batch.terminated.flatten() == 1
    truncated = episode_ends & ~terminated
    assert terminated.any() and truncated.any()

    targets = td_targets(agent.q_net, batch, gamma=1.0).flatten()
    with th.no_grad():
        max_next_q = agent.q_net(batch.next_observations).max(dim=1).values
    rewards = batch.rewards.flatten()
    assert th.allclose(targets[terminated], rewards[terminated])  # bootstraps on 0
    assert th.allclose(targets[truncated], rewards[truncated] + max_next_q[truncated])  # bootstraps on Q(s')
    assert (max_next_q[truncated].abs() > 0).all()


@pytest.mark.parametrize("episode_length", [500, 15])  # 15: truncations and terminations inside the round
def test_nfq_fit_equals_the_reference_fit_on_the_same_round(episode_length: int) -> None:
    """
    Fidelity: from the same weights and the same collected round, NFQ's textbook fit (40 full-batch iterations,
    RMSprop 5e-4, targets recomputed before each step, gamma = 1) ends at the same weights as the reference's.
    """
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_nfq import NFQ

    class SnapshotBeforeFit(BaseCallback):
        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            model = self.model
            assert isinstance(model, NFQ)
            self.batch = model._stored_transitions()
            self.weights = [p.detach().clone() for p in model.q_net.parameters()]

    env = make_vec_env("CartPole-v1", n_envs=1, seed=4, env_kwargs={"max_episode_steps": episode_length})
    model = NFQ("MlpPolicy", env, seed=4)
    snapshot = SnapshotBeforeFit()
    model.learn(1024, callback=snapshot)  # one round: collect, then fit
    batch = snapshot.batch

    reference_net = make_q_network(4, 2)
    with th.no_grad():
        for reference_param, weights in zip(reference_net.parameters(), snapshot.weights, strict=True):
            reference_param.copy_(weights)
    reference_batch = Transitions(
        observations=batch.observations,
        actions=batch.actions.long(),
        rewards=batch.rewards,
        next_observations=batch.next_observations,
        terminated=batch.dones,
    )
    if episode_length == 15:
        assert 0 < int(batch.dones.sum()) < int((batch.next_observations[:-1] != batch.observations[1:]).any(1).sum())
    optimizer = th.optim.RMSprop(reference_net.parameters(), lr=5e-4)
    fit_q_network(reference_net, optimizer, reference_batch, gamma=1.0, iterations=40)

    for nfq_param, reference_param in zip(model.q_net.parameters(), reference_net.parameters(), strict=True):
        assert th.allclose(nfq_param, reference_param, rtol=1e-4, atol=1e-5)
    moved = [
        not th.equal(after, before) for after, before in zip(model.q_net.parameters(), snapshot.weights, strict=True)
    ]
    assert all(moved)  # the comparison is not between two untouched networks


# --- configs ----------------------------------------------------------------------------------------------------


def test_dqn_zoo_config_comes_from_rl_zoo3() -> None:
    config = configs.resolve("dqn-zoo", "CartPole-v1")
    assert config.kind == "dqn" and config.budget == 50_000  # the Zoo's n_timesteps
    kwargs = zoo_to_kwargs({k: v for k, v in config.kwargs.items() if k != "policy"})
    assert kwargs["policy_kwargs"] == {"net_arch": [256, 256]}
    for env_id in configs.ENVS:
        assert configs.resolve("dqn-zoo", env_id).budget > 0
    assert run.parse_seeds(["0-2", "7", "1"]) == [0, 1, 2, 7]


def test_nfq_configs_build_nfq_models() -> None:
    from sb3_nfq import NFQ

    tuned = configs.resolve("nfq-tuned", "CartPole-v1")
    assert tuned.kind == "nfq" and tuned.budget == 50_000
    model = NFQ("MlpPolicy", "CartPole-v1", **zoo_to_kwargs(tuned.kwargs))
    assert isinstance(model.policy.optimizer, th.optim.Adam)
    assert model.memory == "growing" and model.gradient_steps == 8
    for env_id in configs.ENVS:  # a tuned entry differs from the book's settings everywhere
        assert configs.resolve("nfq-tuned", env_id).kwargs != {}, env_id
    shared = [configs.resolve("nfq-shared", env_id) for env_id in configs.ENVS]
    assert all(config.kwargs == shared[0].kwargs for config in shared), "one config for every env"
    assert [config.budget for config in shared] == [
        configs.resolve("dqn-zoo", env_id).budget for env_id in configs.ENVS
    ]
    book = [configs.resolve("nfq-book", env_id) for env_id in configs.ENVS]
    assert all(config.kwargs == {} for config in book), "the textbook settings: NFQ's defaults"
    assert [config.budget for config in book] == [300_000, 300_000, 300_000, 500_000]
    reference = [configs.resolve("reference-nfq", env_id) for env_id in configs.ENVS]
    assert [config.budget for config in reference] == [config.budget for config in book]
    assert configs.resolve("nfq-shared", "Acrobot-v1").source == "sb3_nfq/hyperparams/nfq-shared.yml"


# --- runner -----------------------------------------------------------------------------------------------------

RUNNER_ARGS = ["--envs", "CartPole-v1", "--seeds", "0-1", "--budget", "1024", "--workers", "0"]
RUNNER_ALGOS = ["nfq-book", "reference-nfq", "dqn-zoo"]


@pytest.fixture(scope="module")
def results_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A results file written by the runner: 3 algorithms x CartPole x 2 seeds, 1024 steps each."""
    th.set_num_threads(1)
    path = tmp_path_factory.mktemp("bench") / "runs.jsonl"
    assert run.main(["--algos", *RUNNER_ALGOS, *RUNNER_ARGS, "--results", str(path)]) == 0
    return path


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_runner_writes_one_valid_line_per_job(results_file: Path) -> None:
    records = _lines(results_file)
    assert sorted((r["algo"], r["seed"]) for r in records) == sorted((a, s) for a in RUNNER_ALGOS for s in (0, 1))
    for record in records:
        for name, kind in RESULT_FIELDS.items():
            assert isinstance(record[name], kind), (name, record[name])
        assert record["steps_to_solve"] is None or isinstance(record["steps_to_solve"], int)
        assert record["torch_threads"] == 1 and record["final_n_episodes"] == 100
        assert record["eval_every"] == 1024 and record["threshold"] == 475.0
        assert set(record["versions"]) >= {"sb3_nfq", "stable_baselines3", "torch", "gymnasium", "python"}
        assert "cores" in record["machine"]
        assert record["command"].startswith("python -m benchmarks.run ")
        assert 0 <= record["train_seconds"] <= record["wall_seconds"]
        steps = [point[0] for point in record["curve"]]
        assert steps[0] == 0 and steps[-1] == record["steps_trained"] >= 1024
        assert all(isinstance(point[1], float) for point in record["curve"])
        ends = record["train_episode_ends"]
        if record["algo"] == "reference-nfq":
            assert ends is None  # its own training loop: not counted
        else:  # no episode of an untrained CartPole policy lasts the 500 steps of the time limit
            assert [point[0] for point in ends] == steps
            ended = sum(point[1] for point in ends)
            assert ended == sum(point[2] for point in ends) >= 1024 // 500
    dqn = next(r for r in records if r["algo"] == "dqn-zoo")
    assert dqn["config"]["policy_kwargs"] == "dict(net_arch=[256, 256])"
    assert dqn["effective_hyperparams"]["net_arch"] == [256, 256]


def test_runner_skips_jobs_already_done(results_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = results_file.read_text()
    assert run.main(["--algos", *RUNNER_ALGOS, *RUNNER_ARGS, "--results", str(results_file)]) == 0
    assert results_file.read_text() == before
    assert "6 already in" in capsys.readouterr().out


def test_rerun_runs_jobs_again_beside_new_ones_and_resumes_its_own(
    results_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "runs.jsonl"
    path.write_text(results_file.read_text())
    args = ["--algos", "nfq-book", *RUNNER_ARGS, "--results", str(path), "--rerun"]
    assert run.main(args) == 0
    assert "2 jobs: 0 already in" in capsys.readouterr().out
    again = [record for record in _lines(path) if record["algo"] == "nfq-book"]
    assert len(again) == 4 and len({record["command"] for record in again}) == 2
    assert run.main(args) == 0  # the same command resumes: its own runs are done
    assert "2 jobs: 2 already in" in capsys.readouterr().out and len(_lines(path)) == len(again) + 4


def test_training_envs_have_no_render_mode_like_the_reference() -> None:
    """SB3 renders LunarLander's exhaust particles for an env id; the runner's training envs must not pay for it."""
    import gymnasium as gym

    vec_env = run.make_training_env("LunarLander-v3", n_envs=2, seed=3)
    assert vec_env.get_attr("render_mode") == [None, None]
    reference_env = gym.make("LunarLander-v3")  # as ReferenceNFQ makes it
    expected, _ = reference_env.reset(seed=3)
    observations = vec_env.reset()
    assert isinstance(observations, np.ndarray)
    np.testing.assert_array_equal(observations[0], expected)
    for _ in range(30):  # fire the main engine: with a render mode, each firing adds particle bodies
        observations, _, _, _ = vec_env.step(np.array([2, 2]))
        assert isinstance(observations, np.ndarray)
        expected, _, _, _, _ = reference_env.step(2)
        np.testing.assert_array_equal(observations[0], expected)
    assert vec_env.get_attr("particles") == [[], []]


def test_training_episodes_cut_by_the_time_limit_are_not_counted_as_terminated() -> None:
    th.set_num_threads(1)
    job = run.Job(
        algo="nfq-book",
        kind="nfq",
        env_id="MountainCar-v0",
        seed=0,
        budget=600,
        kwargs={},
        threshold=-110.0,
        eval_every=1024,
        n_eval_episodes=2,
    )
    record = run.run_job(job)
    # 600 steps of an untrained policy: three episodes, each cut at MountainCar's 200 steps, none at the goal
    assert record["train_episode_ends"] == [[0, 0, 0], [600, 3, 0]]


def test_a_diverged_nfq_run_is_recorded_as_unsolved_with_the_error() -> None:
    th.set_num_threads(1)
    job = run.Job(
        algo="nfq-lr-far-too-high",
        kind="nfq",
        env_id="CartPole-v1",
        seed=0,
        budget=4096,
        kwargs={"learning_rate": 1e30},  # the first RMSprop step sends the weights to ~1e30: the loss overflows
        threshold=475.0,
        eval_every=1024,
        n_eval_episodes=2,
    )
    record = run.run_job(job)
    assert "NFQ loss became" in record["diverged"]
    assert not record["solved"] and record["steps_trained"] < job.budget
    json.dumps(record)  # still one valid JSON line


def test_reference_episode_callback_stops_at_an_episode_end_without_fitting_the_unfinished_round() -> None:
    agent = ReferenceNFQ("CartPole-v1", seed=0, transitions_per_round=256, fitting_iterations=2)
    ends: list[int] = []

    def after_episode(trained: ReferenceNFQ) -> bool:
        ends.append(trained.num_timesteps)
        return len(ends) < 3

    agent.learn(10_000, episode_callback=after_episode)
    assert len(ends) == 3 and ends[0] < ends[1] < ends[2] == agent.num_timesteps
    assert agent.n_episodes == 3 and agent.stop_requested
    assert agent.n_rounds == ends[2] // 256  # only whole rounds were fitted


@pytest.mark.parametrize("algo", ["nfq-book", "reference-nfq"])
def test_runner_book_protocol_evaluates_after_every_training_episode(algo: str) -> None:
    th.set_num_threads(1)
    (job,) = run.make_jobs([algo], ["CartPole-v1"], [12], budget=2048, protocol="book")
    (rounds_job,) = run.make_jobs([algo], ["CartPole-v1"], [12], budget=2048, stop_at_solve=True)
    assert job.stop_at_solve and job.config_hash != rounds_job.config_hash
    record = run.run_job(job)
    assert record["protocol"] == "book" and record["book_window"] == 100
    assert not record["solved"] and record["steps_to_solve"] is None and record["episodes_to_solve"] is None
    assert record["steps_trained"] == 2048  # two whole rounds: the criterion never held
    assert 2048 / 500 < record["episodes_trained"] < 2048 / 8  # one evaluation per training episode
    assert record["final_n_episodes"] == 100 and record["eval_seconds"] > 0
    steps = [point[0] for point in record["curve"]]
    assert steps == sorted(steps) and steps[-1] <= 2048 and len(steps) >= 2


def test_book_protocol_keeps_the_hashes_of_recorded_runs() -> None:
    """Runs recorded under the benchmark's own protocol stay 'done': adding the book's did not change their keys."""
    (job,) = run.make_jobs(["nfq-book"], ["CartPole-v1"], [0], stop_at_solve=True)
    assert job.config_hash == "f99e7937af26"  # as recorded in benchmarks/results/runs.jsonl
    with pytest.raises(ValueError, match="protocol must be one of"):
        run.make_jobs(["nfq-book"], ["CartPole-v1"], [0], protocol="books")


def test_runner_local_pool_spawns_a_process_per_job(tmp_path: Path) -> None:
    path = tmp_path / "runs.jsonl"
    args = ["--algos", "reference-nfq", "--envs", "CartPole-v1", "--seeds", "0", "--budget", "1024"]
    assert run.main([*args, "--workers", "1", "--stop-at-solve", "--results", str(path)]) == 0
    (record,) = _lines(path)
    assert record["launcher"].startswith("local pool") and record["torch_threads"] == 1
    assert record["pid"] != os.getpid()


def test_runner_on_local_ray(tmp_path: Path) -> None:
    ray = pytest.importorskip("ray")
    path = tmp_path / "runs.jsonl"
    args = ["--algos", "reference-nfq", "--envs", "CartPole-v1", "--seeds", "0", "--budget", "1024"]
    assert run.main([*args, "--workers", "1", "--ray-address", "local", "--results", str(path)]) == 0
    (record,) = _lines(path)
    assert record["launcher"] == "ray (local)" and record["torch_threads"] == 1
    assert not ray.is_initialized()  # the runner shut down the Ray instance it started


# --- report -----------------------------------------------------------------------------------------------------


def test_report_builds_readme_and_curves(results_file: Path, tmp_path: Path) -> None:
    out_dir = tmp_path / "report"
    assert report.main(["--results", str(results_file), "--out-dir", str(out_dir)]) == 0
    text = (out_dir / "README.md").read_text()
    records = _lines(results_file)
    assert records[0]["command"] in text and records[0]["machine"] in text
    assert "python -m benchmarks.report" in text
    for algo in RUNNER_ALGOS:
        assert f"| {algo} | 2 | 1,024 |" in text
    assert "not enough data" in text  # 2 seeds are not enough to judge a target
    png = (out_dir / "curves_CartPole-v1.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", png[16:24])
    assert width > 100 and height > 100


@pytest.fixture(scope="module")
def book_records(tmp_path_factory: pytest.TempPathFactory) -> list[dict[str, Any]]:
    """Book-protocol lines written by the runner: both implementations, CartPole, seed 12, 1024 steps."""
    th.set_num_threads(1)
    path = tmp_path_factory.mktemp("book") / "book_protocol.jsonl"
    args = ["--protocol", "book", "--algos", *report.BOOK_PAIR, "--envs", "CartPole-v1", "--seeds", "12"]
    assert run.main([*args, "--budget", "1024", "--workers", "0", "--results", str(path)]) == 0
    return _lines(path)


def _book_run(record: dict[str, Any], algo: str, seed: int, steps: int | None) -> dict[str, Any]:
    """:return: a copy of a runner line, as if ``algo`` had solved at ``steps`` with this seed (None: unsolved)"""
    return {
        **record,
        "algo": algo,
        "seed": seed,
        "solved": steps is not None,
        "steps_to_solve": steps,
        "episodes_to_solve": None if steps is None else steps // 100,
        "steps_trained": 500_000 if steps is None else steps,
        "episodes_trained": 4_000 if steps is None else steps // 100,
    }


def test_report_book_table_sits_beside_the_books_numbers_and_judges_the_difference(
    book_records: list[dict[str, Any]], results_file: Path, tmp_path: Path
) -> None:
    record = book_records[0]
    few = "\n".join(report.book_protocol_lines(book_records))
    assert "| the book, as printed (seeds 12, 34, 56, 78, 90) | 5 | — | 233,918 |" in few
    assert "| nfq-book, the book's seeds (12) | 1 | 0/1 | ≥1,024 |" in few
    assert "not judged yet: 1 seeds, 15 needed" in few

    seeds = [12, 34, 56, 78, 90, *range(10)]
    slow = [_book_run(record, "nfq-book", seed, 200_000 + 1_000 * i) for i, seed in enumerate(seeds)]
    fast = [_book_run(record, "reference-nfq", seed, 100_000 + 1_000 * i) for i, seed in enumerate(seeds)]
    text = "\n".join(report.book_protocol_lines([*slow, *fast]))
    assert "reference-nfq: **1.93**" in text  # 207,000 / 107,000
    assert "15 vs 15 seeds" in text and "a difference (p < 0.05): reference-nfq needs fewer steps" in text
    # the book's five seeds: mean steps (200,000 + 201,000 + ... + 204,000) / 5 and episodes a hundredth of that
    assert "| nfq-book, the book's seeds (12, 34, 56, 78, 90) | 5 | 5/5 | 202,000 |" in text
    assert "nfq-book 0.86x its steps and 0.86x its episodes" in text  # 202,000 / 233,918 and 2,020 / 2,344

    alike = [_book_run(record, "nfq-book", seed, 100_000 + 1_000 * i) for i, seed in enumerate(seeds)]
    alike[0] = _book_run(record, "nfq-book", 12, None)  # one unsolved run: its mean is a lower bound
    text = "\n".join(report.book_protocol_lines([*alike, *fast]))
    assert "no difference shown (p ≥ 0.05)" in text
    assert "| nfq-book, all seeds (15 seeds) | 15 | 14/15 | ≥" in text

    book_path = tmp_path / "book_protocol.jsonl"
    book_path.write_text("".join(json.dumps(line) + "\n" for line in [*slow, *fast]))
    args = ["--results", str(results_file), "--book-results", str(book_path), "--out-dir", str(tmp_path / "out")]
    assert report.main(args) == 0
    assert "## CartPole-v1 under the book's criterion" in (tmp_path / "out" / "README.md").read_text()


def test_report_labels_tell_apart_cells_of_one_algorithm(results_file: Path) -> None:
    to_budget = [record for record in _lines(results_file) if record["algo"] == "nfq-book"]
    # the same config run again with --stop-at-solve: another config hash, the same budget and evaluation period
    stopped = [{**record, "stop_at_solve": True, "config_hash": "stopped"} for record in to_budget]
    cells = report.build_cells([*to_budget, *stopped])["CartPole-v1"]
    labels = sorted(cell.label for cell in cells if cell.algo == "nfq-book")
    assert labels == ["nfq-book (stopped at solve)", "nfq-book (to the budget)"]


def test_report_keeps_runs_of_superseded_settings_out_of_the_targets(results_file: Path, tmp_path: Path) -> None:
    records = _lines(results_file)

    def five_solved(algo: str, like: str) -> list[dict[str, Any]]:
        first = next(record for record in records if record["algo"] == like)
        return [dict(first, algo=algo, seed=seed, solved=True, steps_to_solve=1024) for seed in range(5)]

    # nfq-book's runs recorded as nfq-tuned: settings that nfq-tuned does not hold today
    earlier = five_solved("nfq-tuned", like="nfq-book")
    dqn = five_solved("dqn-zoo", like="dqn-zoo")
    cells = report.build_cells([*earlier, *dqn])
    tuned = next(cell for cell in cells["CartPole-v1"] if cell.algo == "nfq-tuned")
    assert tuned.superseded
    assert tuned.label == f"nfq-tuned (config {tuned.config_hash}, since changed)"
    assert report.ratio_target(cells, "CartPole-v1", "nfq-tuned", "dqn-zoo", 0.0, 0.75)[0] == "not enough data"
    # the same runs recorded with nfq-tuned's current config are judged (ratio 1: not met)
    current = report.current_config("nfq-tuned", "CartPole-v1")
    assert current is not None and current != {}
    now = [dict(record, config=current, config_hash="now") for record in earlier]
    assert (
        report.ratio_target(report.build_cells([*now, *dqn]), "CartPole-v1", "nfq-tuned", "dqn-zoo", 0.0, 0.75)[0]
        == "not met"
    )

    path = tmp_path / "runs.jsonl"
    path.write_text("".join(json.dumps(record) + "\n" for record in [*earlier, *dqn]))
    assert report.main(["--results", str(path), "--out-dir", str(tmp_path / "report")]) == 0
    text = (tmp_path / "report" / "README.md").read_text()
    table_of_earlier = text.split("Runs whose recorded settings are not what their config name holds today")[1]
    assert f"| nfq-tuned (config {tuned.config_hash}, since changed) | 5 |" in table_of_earlier
    assert "| dqn-zoo | 5 |" in text and "| dqn-zoo | 5 |" not in table_of_earlier


def test_targets_are_read_from_data_and_bad_ones_are_refused(results_file: Path, tmp_path: Path) -> None:
    # every shipped target judges algorithms the benchmark runs
    shipped = report.read_targets()
    assert shipped and all(
        {target.get(key) for key in ("algo", "baseline", "mode")} - {None} <= set(configs.algorithm_names())
        for target in shipped
    )
    path = tmp_path / "targets.yml"
    path.write_text("- {kind: steps_ratio, algo: nfq-book, baseline: dqn-zoo, env: CartPole-v1, high: 2.5}\n")
    (target,) = report.read_targets(path)
    cells = report.build_cells(_lines(results_file))
    (reading,) = report.judge(cells, target)  # the fixture's runs share one evaluation period
    assert reading[0].startswith("nfq-book / dqn-zoo median steps to solve on CartPole-v1 ≤ 2.5")
    assert reading[1][0] == "not enough data"  # two seeds each
    path.write_text("- {kind: steps_ratio, algo: nfq-book, env: CartPole-v1, high: 2.5}\n")
    with pytest.raises(ValueError, match=r"a steps_ratio target takes \['algo', 'baseline', 'env', 'high'\]"):
        report.read_targets(path)
    path.write_text("- {kind: fastest, algo: nfq-book}\n")
    with pytest.raises(ValueError, match="unknown target kind 'fastest'"):
        report.read_targets(path)
    # a group states its targets once and judges them for each of its algorithms, in order
    path.write_text(
        "- algos: [nfq-book, nfq-tuned]\n"
        "  targets:\n"
        "    - {kind: final_score, env: CartPole-v1}\n"
        "    - {kind: solved_envs, at_least: 3}\n"
        "- {kind: flat_fit_cost, mode: nfq-linear, tolerance: 0.3}\n"
    )
    assert [(target["kind"], target.get("algo")) for target in report.read_targets(path)] == [
        ("final_score", "nfq-book"),
        ("solved_envs", "nfq-book"),
        ("final_score", "nfq-tuned"),
        ("solved_envs", "nfq-tuned"),
        ("flat_fit_cost", None),
    ]
    path.write_text("- {algos: [nfq-book], targets: [{kind: final_score, algo: nfq-tuned, env: CartPole-v1}]}\n")
    with pytest.raises(ValueError, match="a group's target takes its 'algo' from the group's 'algos'"):
        report.read_targets(path)
    path.write_text("- {algo: [nfq-book], targets: [{kind: final_score, env: CartPole-v1}]}\n")
    with pytest.raises(ValueError, match=r"a non-empty 'algos' list and 'targets' list, got \['algo', 'targets'\]"):
        report.read_targets(path)
    path.write_text("- {algos: [nfq-book], targets: [{kind: final_score}]}\n")
    with pytest.raises(ValueError, match=r"a final_score target takes \['algo', 'env'\]"):
        report.read_targets(path)


def test_seconds_ratio_is_judged_only_on_runs_made_side_by_side(results_file: Path) -> None:
    lines = _lines(results_file)
    book = next(record for record in lines if record["algo"] == "nfq-book")
    dqn = next(record for record in lines if record["algo"] == "dqn-zoo")

    def runs(first: dict[str, Any], seconds: float, command: str, **changes: Any) -> list[dict[str, Any]]:
        return [dict(first, seed=seed, train_seconds=seconds, command=command, **changes) for seed in range(5)]

    together = [*runs(book, 30.0, "together"), *runs(dqn, 20.0, "together")]
    verdict, text = report.seconds_ratio_target(together, ["CartPole-v1"], "nfq-book", "dqn-zoo", 1.5)
    assert (verdict, text) == ("met", "CartPole-v1: 1.50 (30 s / 20 s, 5 seeds, 1 job at a time)")
    assert report.seconds_ratio_target(together, ["CartPole-v1"], "nfq-book", "dqn-zoo", 1.4)[0] == "not met"
    # the baseline's faster runs of another session, and runs stopped at the solve, do not count
    apart = [*together, *runs(dqn, 5.0, "another day"), *runs(book, 1.0, "together", stop_at_solve=True)]
    assert report.seconds_ratio_target(apart, ["CartPole-v1"], "nfq-book", "dqn-zoo", 1.5)[0] == "met"
    verdict, text = report.seconds_ratio_target(runs(book, 30.0, "alone"), ["CartPole-v1"], "nfq-book", "dqn-zoo", 2.0)
    assert verdict == "not enough data" and "(none)" in text
    verdict, _ = report.seconds_ratio_target(together, ["CartPole-v1", "Acrobot-v1"], "nfq-book", "dqn-zoo", 2.0)
    assert verdict == "not enough data"
    # of two commands with five seeds each, the one that ran one job at a time counts, whichever came first
    two, one = run.launcher(2), run.launcher(1)
    shared = [*runs(book, 60.0, "two at a time", launcher=two), *runs(dqn, 30.0, "two at a time", launcher=two)]
    alone = [*runs(book, 30.0, "one at a time", launcher=one), *runs(dqn, 25.0, "one at a time", launcher=one)]
    for order in ([*shared, *alone], [*alone, *shared]):
        verdict, text = report.seconds_ratio_target(order, ["CartPole-v1"], "nfq-book", "dqn-zoo", 1.5)
        assert (verdict, text) == ("met", "CartPole-v1: 1.20 (30 s / 25 s, 5 seeds, 1 job at a time)")
    verdict, text = report.seconds_ratio_target(shared, ["CartPole-v1"], "nfq-book", "dqn-zoo", 1.5)
    assert (verdict, text) == ("not met", "CartPole-v1: 2.00 (60 s / 30 s, 5 seeds, 2 jobs at a time)")


def test_report_judges_staying_solved_only_on_runs_trained_to_the_budget(results_file: Path) -> None:
    first = next(record for record in _lines(results_file) if record["algo"] == "nfq-book")
    to_budget = [dict(first, seed=seed, solved=True, steps_to_solve=512, final_score=480.0) for seed in range(2)]
    # five more seeds, stopped at their solve: a final score taken at the solve says nothing of staying solved
    stopped = [
        dict(first, seed=seed, solved=True, steps_to_solve=512, final_score=480.0, stop_at_solve=True, config_hash="s")
        for seed in range(5)
    ]
    cells = report.build_cells([*to_budget, *stopped])
    verdict, text = report.final_score_target(cells, "CartPole-v1", "nfq-book")
    assert verdict == "not enough data" and "run to the budget (2)" in text
    more = [dict(first, seed=seed, solved=True, steps_to_solve=512, final_score=480.0) for seed in range(2, 5)]
    verdict, text = report.final_score_target(
        report.build_cells([*to_budget, *more, *stopped]), "CartPole-v1", "nfq-book"
    )
    assert verdict == "met" and text.startswith("5/5 seeds")


def test_report_judges_targets_from_runner_data(results_file: Path) -> None:
    # Five seeds of the same runs under both names: the ratio of medians is exactly 1, so the ±25% target is met.
    records = _lines(results_file)
    nfq = [r for r in records if r["algo"] == "nfq-book"]
    fake_seeds = [dict(r, seed=seed) for seed in range(5) for r in nfq[:1]]
    both = fake_seeds + [dict(r, algo="reference-nfq") for r in fake_seeds]
    cells = report.build_cells(both)
    verdict, text = report.ratio_target(cells, "CartPole-v1", "nfq-book", "reference-nfq", 0.75, 1.25)
    assert verdict == "not enough data" and "neither median solved" in text  # both medians censored
    solved = [dict(r, steps_to_solve=1024 * (1 + r["seed"]), solved=True) for r in both]
    verdict, text = report.ratio_target(
        report.build_cells(solved), "CartPole-v1", "nfq-book", "reference-nfq", 0.75, 1.25
    )
    assert verdict == "met" and text.startswith("1.00")


def test_report_bootstrap_ci_does_not_depend_on_numpy_global_state() -> None:
    """rliable 1.2 resamples with the global np.random: a cell's CI must not depend on what ran before it."""
    steps = np.array([12_288.0, 14_336, 14_336, 20_480, 40_960, 61_440, 90_112, 100_096])
    first = report.iqm_with_ci(steps)
    np.random.seed(12345)
    np.random.random(17)
    state = np.random.get_state()
    assert report.iqm_with_ci(steps) == first
    draw_after = np.random.random()
    np.random.set_state(state)
    assert np.random.random() == draw_after, "the caller's global generator is left as it was"


# --- per-env tuning -----------------------------------------------------------------------------------------------


def test_every_tuning_candidate_builds_an_nfq_model() -> None:
    from sb3_nfq import NFQ

    for env_id, candidates in tune_nfq.CANDIDATES.items():
        assert env_id in configs.ENVS
        for name, candidate in candidates.items():
            job = tune_nfq.candidate_jobs(env_id, [name], [0])[0]
            assert job.stop_at_solve and job.algo == f"tune:{name}"
            assert job.budget == candidate["n_timesteps"]
            model = run.build_sb3_model(job)
            assert isinstance(model, NFQ) and model.gamma == candidate.get("gamma", 1.0)
            normalizes = vec_normalize_kwargs(candidate.get("normalize", False)) is not None
            assert (model.get_vec_normalize_env() is not None) == normalizes


def test_a_config_that_normalizes_trains_on_a_vec_normalize_env_and_records_it() -> None:
    from stable_baselines3.common.vec_env import VecNormalize

    th.set_num_threads(1)
    job = run.Job(
        algo="nfq-norm-obs",
        kind="nfq",
        env_id="MountainCar-v0",
        seed=0,
        budget=400,
        kwargs={"normalize": "{'norm_obs': True, 'norm_reward': False}", "gamma": 0.99},
        threshold=-110.0,
        eval_every=1024,
        n_eval_episodes=2,
    )
    env = run.build_sb3_model(job).get_env()
    assert isinstance(env, VecNormalize) and env.norm_obs and not env.norm_reward and env.gamma == 0.99
    record = run.run_job(job)
    assert record["effective_hyperparams"]["vec_normalize"] == {"norm_obs": True, "norm_reward": False}
    assert record["config"]["normalize"] == job.kwargs["normalize"]
    plain = run.run_job(dataclasses.replace(job, kwargs={"gamma": 0.99}))
    assert "vec_normalize" not in plain["effective_hyperparams"]


def test_a_candidate_is_its_base_config_with_the_keys_it_sets(tmp_path: Path) -> None:
    path = tmp_path / "candidates.yml"
    path.write_text("Acrobot-v1:\n  lower-gamma: {base: nfq-shared, gamma: 0.9}\n  book: {base: nfq-book}\n")
    candidates = tune_nfq.read_candidates(path)["Acrobot-v1"]
    assert candidates["lower-gamma"] == {**read_entry("nfq-shared", "Acrobot-v1"), "gamma": 0.9}
    assert candidates["book"] == {"n_timesteps": 300_000}
    path.write_text("Acrobot-v1:\n  orphan: {gamma: 0.9}\n")
    with pytest.raises(ValueError, match="candidate 'orphan' of Acrobot-v1 names no 'base' config"):
        tune_nfq.read_candidates(path)


def test_an_every_env_candidate_is_a_candidate_of_each_benchmark_env(tmp_path: Path) -> None:
    path = tmp_path / "candidates.yml"
    path.write_text("Acrobot-v1:\n  book: {base: nfq-book}\nevery-env:\n  capped-0.9: {base: nfq-capped, gamma: 0.9}\n")
    candidates = tune_nfq.read_candidates(path)
    assert sorted(candidates) == sorted(configs.ENVS)
    for env_id in configs.ENVS:
        assert candidates[env_id]["capped-0.9"] == {**read_entry("nfq-capped", env_id), "gamma": 0.9}
    assert sorted(candidates["Acrobot-v1"]) == ["book", "capped-0.9"]
    path.write_text("Acrobot-v1:\n  twice: {base: nfq-book}\nevery-env:\n  twice: {base: nfq-capped}\n")
    with pytest.raises(ValueError, match=r"candidates \['twice'\] are both in 'every-env' and under Acrobot-v1"):
        tune_nfq.read_candidates(path)


def test_tuning_sweep_runs_ranks_and_resumes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    th.set_num_threads(1)
    results = tmp_path / "tuning.jsonl"
    args = ["--envs", "Acrobot-v1", "--candidates", "book", "book-gamma-0.99", "--seeds", "0"]
    args += ["--budget", "1024", "--eval-episodes", "2", "--workers", "0", "--results", str(results)]
    assert tune_nfq.main(args) == 0
    records = _lines(results)
    assert sorted(r["algo"] for r in records) == ["tune:book", "tune:book-gamma-0.99"]
    assert all(r["stop_at_solve"] and r["env"] == "Acrobot-v1" and r["steps_trained"] >= 1024 for r in records)
    assert all(r["command"].startswith("python -m benchmarks.tune_nfq ") for r in records)
    out = capsys.readouterr().out
    assert "| 1 | " in out and "| 2 | " in out
    assert tune_nfq.main(args) == 0
    assert len(_lines(results)) == 2 and "2 already in" in capsys.readouterr().out
    with pytest.raises(KeyError, match="unknown candidates"):
        tune_nfq.candidate_jobs("Acrobot-v1", ["no-such-candidate"], [0])


def test_tuning_ranking_prefers_solved_then_solved_at_the_end_then_fewer_steps_then_fewer_seconds() -> None:
    def record(name: str, seed: int, steps: int | None, seconds: float, final: float = -90.0) -> dict[str, Any]:
        return {
            "algo": f"tune:{name}",
            "env": "Acrobot-v1",
            "seed": seed,
            "solved": steps is not None,
            "steps_to_solve": steps,
            "steps_trained": 300_000 if steps is None else steps,
            "train_seconds": seconds,
            "final_score": final,
            "threshold": -100.0,
            "stop_at_solve": True,
        }

    records = [
        record("fast-but-fails-once", 0, 2_048, 1.0),
        record("fast-but-fails-once", 1, None, 1.0),
        record("slow", 0, 40_960, 9.0),
        record("slow", 1, 40_960, 9.0),
        record("quick", 0, 8_192, 5.0),
        record("quick", 1, 8_192, 5.0),
        record("quick-and-cheap", 0, 8_192, 2.0),
        record("quick-and-cheap", 1, 8_192, 2.0),
        record("quickest-but-falls-off", 0, 4_096, 1.0, final=-150.0),
        record("quickest-but-falls-off", 1, 4_096, 1.0),
        {**record("other-env", 0, 1, 0.1), "env": "CartPole-v1"},
        {**record("trained-to-the-budget", 0, 1, 0.1), "stop_at_solve": False},
    ]
    ranked = [summary.name for summary in tune_nfq.summarize(records, "Acrobot-v1")]
    assert ranked == ["quick-and-cheap", "quick", "slow", "quickest-but-falls-off", "fast-but-fails-once"]
    assert [summary.name for summary in tune_nfq.summarize(records, "Acrobot-v1", to_budget=True)] == [
        "trained-to-the-budget"
    ]


# --- overhead ---------------------------------------------------------------------------------------------------


def test_overhead_script_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "overhead.json"
    assert overhead.main(["--threads", "1", "--repeats", "1", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "threads: 1" in printed and "ratio NFQ / reference" in printed and "ratio NFQ / bare" in printed
    numbers = json.loads(out.read_text())
    assert numbers["threads"] == 1
    assert numbers["round"]["ratio"] > 0 and numbers["fitting"]["ratio"] > 0
    assert numbers["round"]["ratio_without_env"] > 0
    for implementation in ("nfq", "reference"):  # the env's share is timed, and is part of the collection
        times = numbers["round"][implementation]
        assert 0 < times["env"] <= times["collect"]
        assert times["without_env"] == pytest.approx(times["total"] - times["env"], rel=0.5)
    assert numbers["fitting"]["max_weight_difference_after_first_fit"] < 1e-4  # same data, same start: same fit


# --- memory of images ---------------------------------------------------------------------------------------------


def test_memory_images_script_measures_a_run_in_its_own_process(tmp_path: Path) -> None:
    out = tmp_path / "memory_images.json"
    assert memory_images.main(["--sizes", "200", "--out", str(out), "--no-readme"]) == 0
    (result,) = json.loads(out.read_text())["results"]
    assert result["transitions"] == 200 and result["rounds"] == 2 and result["torch_threads"] == 1
    assert result["peak_rss_mib"] >= result["peak_rss_before_learn_mib"] > 0  # 200 frames may not raise the peak
    assert result["memory_mib"] * 2**20 == 200 * (2 * 84 * 84 * 4 + 20)  # frame and next frame, then the scalars
    assert out.with_suffix(".md").read_text().strip() == memory_images.table([result])


def test_readme_memory_table_is_the_generated_one() -> None:
    payload = json.loads(memory_images.DEFAULT_OUT.read_text())
    text = readme_blocks.README.read_text()
    assert readme_blocks.replace_block(text, memory_images.MARKERS, memory_images.table(payload["results"])) == text


# --- scaling of the growing memory's cost -------------------------------------------------------------------------


def test_scaling_script_times_every_fit_of_both_modes(tmp_path: Path) -> None:
    out = tmp_path / "scaling.json"
    assert scaling.main(["--max-steps", "2048", "--round-fraction", "0.5", "--out", str(out)]) == 0
    payload = json.loads(out.read_text())
    fixed, lengthening = payload["fits"].values()
    assert [fit["memory"] for fit in fixed] == [256 * i for i in range(1, 9)]
    # rounds of max(256, 0.5 x memory): 256, 256, 256, 384, 576; the last 320 steps wait for their round's end
    assert [fit["memory"] for fit in lengthening] == [256, 512, 768, 1152, 1728]
    assert payload["torch_threads"] == 1 and out.with_suffix(".md").read_text().startswith("| memory")
    assert out.with_suffix(".png").read_bytes().startswith(b"\x89PNG")
    # another mode added to the same run: both are in the file, and the report's section names both commands
    assert scaling.main(["--max-steps", "2048", "--configs", "nfq-tuned", "--out", str(out), "--add"]) == 0
    both = json.loads(out.read_text())
    assert list(both["bins"]) == [*payload["bins"], "nfq-tuned"] and len(both["commands"]) == 2
    section = "\n".join(report.scaling_lines(both))
    assert "--add`" in section and "nfq-tuned: fit s per 1,000 steps" in section
    with pytest.raises(ValueError, match="seed=0, this one 1"):
        scaling.main(["--max-steps", "2048", "--seed", "1", "--out", str(out), "--add"])


def test_flat_fit_cost_target_is_judged_on_the_scaling_run() -> None:
    def bins(values: list[float]) -> list[dict[str, float]]:
        return [
            {"memory_up_to": high, "steps": 1000.0, "seconds": value, "per_1000_steps": value}
            for high, value in zip(scaling.BINS, values, strict=False)
        ]

    payload = {"bins": {"linear": bins([1.0, 1.2, 0.8, 1.0, 1.0]), "quadratic": bins([1.0, 2.0, 4.0, 8.0, 16.0])}}
    assert scaling.spread(payload["bins"]["linear"]) == pytest.approx(0.2)
    assert report.flat_fit_cost_target(payload, "linear", 0.3)[0] == "met"
    assert report.flat_fit_cost_target(payload, "linear", 0.1)[0] == "not met"
    assert report.flat_fit_cost_target(payload, "quadratic", 0.3)[0] == "not met"
    assert report.flat_fit_cost_target(None, "linear", 0.3)[0] == "not enough data"
    short = {"bins": {"linear": bins([1.0, 1.0, 1.0])}}
    verdict, text = report.flat_fit_cost_target(short, "linear", 0.3)
    assert verdict == "not enough data" and "50,000 transitions" in text


def test_scaling_bins_divide_fit_seconds_by_the_steps_collected_in_each_bin() -> None:
    fits = [
        {"steps": 5_000.0, "memory": 5_000.0, "seconds": 1.0},
        {"steps": 10_000.0, "memory": 10_000.0, "seconds": 2.0},
        {"steps": 16_000.0, "memory": 16_000.0, "seconds": 3.0},
        {"steps": 20_000.0, "memory": 20_000.0, "seconds": 3.0},
    ]
    rows = scaling.per_bin(fits)
    assert [(row["memory_up_to"], row["steps"], row["seconds"]) for row in rows] == [
        (10_000, 10_000.0, 3.0),
        (20_000, 10_000.0, 6.0),
    ]
    assert [row["per_1000_steps"] for row in rows] == [0.3, 0.6]


def test_benchmarks_readme_env_table_is_the_generated_one() -> None:
    table = configs.env_table()
    assert "| LunarLander-v3 | 200 | 5,120 | 500,000 |" in table
    readme = Path(configs.__file__).parent / "README.md"
    text = readme.read_text()
    assert readme_blocks.replace_block(text, configs.ENV_TABLE_MARKERS, table) == text, (
        "run python -m benchmarks.configs"
    )


def test_readme_results_table_is_the_generated_one() -> None:
    cells = report.build_cells(run.read_results(run.DEFAULT_RESULTS))
    table = report.summary_table(cells)
    assert "| LunarLander-v3 | nfq-tuned | 5 |" in table
    text = readme_blocks.README.read_text()
    assert readme_blocks.replace_block(text, report.SUMMARY_MARKERS, table) == text, "run python -m benchmarks.report"


def test_readme_main_job_table_is_the_generated_one() -> None:
    payload = json.loads(main_job.DEFAULT_OUT.read_text())
    assert [result["busy_process_beside"] for result in payload["results"]] == [False, True]
    assert all(result["threads"] == 1 for result in payload["results"])
    text = readme_blocks.README.read_text()
    assert readme_blocks.replace_block(text, main_job.MARKERS, main_job.table(payload["results"])) == text


# A runner whose job pool (the runner's own, one worker) runs one long job.
ORPHAN_SCRIPT = """
import time
from benchmarks import run

if __name__ == "__main__":
    with run.job_pool(1) as pool:
        pool.submit(time.sleep, 600)
        time.sleep(600)
"""


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


def _pool_workers(pid: int) -> list[int]:
    """
    :param pid: a process
    :return: its children that are multiprocessing's spawned workers (not its resource tracker)
    """
    children = [
        int(child) for task in Path(f"/proc/{pid}/task").iterdir() for child in (task / "children").read_text().split()
    ]
    return [child for child in children if b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes()]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads process states from /proc")
def test_a_job_pool_worker_ends_when_its_runner_is_killed() -> None:
    runner = subprocess.Popen([sys.executable, "-c", ORPHAN_SCRIPT], cwd=Path(__file__).resolve().parent.parent)
    try:
        deadline = time.monotonic() + 60.0
        while not (workers := _pool_workers(runner.pid)) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(workers) == 1, "the runner's pool started no worker"
        worker = workers[0]
        time.sleep(1.0)  # the worker may still be importing: its runner killed then, it must end too
        assert _running(worker)
    finally:
        runner.send_signal(signal.SIGKILL)  # no cleanup runs in the runner
        runner.wait()
    deadline = time.monotonic() + 30.0
    while _running(worker) and time.monotonic() < deadline:
        time.sleep(0.2)
    orphaned = _running(worker)
    if orphaned:
        os.kill(worker, signal.SIGKILL)
    assert not orphaned, "the worker outlived its runner by 30 s"
