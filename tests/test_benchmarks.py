"""
Tests of the benchmark suite (benchmarks/): the plain-PyTorch reference NFQ, the configs, the runner (evaluation,
JSON lines, resumability, the book's protocol, local pool, Ray) and the report, on the recorded results. Real envs,
tiny budgets, no mocks.
"""

import inspect
import json
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml

import sb3_nfq
from benchmarks import configs, report, run
from benchmarks.reference_nfq import ReferenceNFQ, Transitions, fit_q_network, make_q_network, td_targets
from sb3_nfq.configs import ZOO_FILE, ZOO_KEYS, read_entry

RESULTS = run.DEFAULT_RESULTS.parent


def _job(algo: str, **kwargs: Any) -> run.Job:
    defaults: dict[str, Any] = {"budget": 2048, "eval_every": 1024, "n_eval_episodes": 5}
    return run.make_jobs([algo], ["CartPole-v1"], [0], **{**defaults, **kwargs})[0]


class Rule:
    """A fixed CartPole policy: push right where ``push_right(obs)``; wait ``delay`` seconds at each ``predict``."""

    def __init__(self, push_right: Callable[[np.ndarray], np.ndarray], delay: float = 0.0) -> None:
        self.push_right, self.delay = push_right, delay

    def predict(self, obs: np.ndarray, state: Any = None, episode_start: Any = None, deterministic: bool = True) -> Any:
        time.sleep(self.delay)
        return self.push_right(obs).astype(int), None


#: Episodes of about 25 to 70 steps, depending on the start state.
POLE_ANGLE = Rule(lambda obs: obs[:, 2] > 0)
#: Keeps the pole up to the time limit from most start states.
BALANCER = Rule(lambda obs: obs[:, 2] + obs[:, 3] > 0)


def test_reference_truncation_bootstraps_and_termination_does_not() -> None:
    agent = ReferenceNFQ(
        "CartPole-v1", seed=3, epsilon=1.0, transitions_per_round=512, env_kwargs={"max_episode_steps": 15}
    )
    batch = agent.collect_round()
    episode_ends = th.cat([(batch.next_observations[:-1] != batch.observations[1:]).any(dim=1), th.tensor([False])])
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


def test_nfq_fit_equals_the_reference_fit_on_the_same_round() -> None:
    """Fidelity: from the same weights and the same round, NFQ's textbook fit ends at the reference's weights."""
    from stable_baselines3.common.callbacks import BaseCallback
    from torch.nn.utils import parameters_to_vector, vector_to_parameters

    class SnapshotBeforeFit(BaseCallback):
        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            self.batch = self.model._stored_transitions()  # type: ignore[attr-defined]
            self.weights = parameters_to_vector(self.model.q_net.parameters()).detach().clone()  # type: ignore[attr-defined]

    model = sb3_nfq.NFQ("MlpPolicy", run.make_env("CartPole-v1", 1, seed=4), seed=4)
    snapshot = SnapshotBeforeFit()
    model.learn(1024, callback=snapshot)  # one round: collect, then fit
    batch, reference_net = snapshot.batch, make_q_network(4, 2)
    vector_to_parameters(snapshot.weights.clone(), reference_net.parameters())  # its parameters become views of it
    reference_batch = Transitions(
        batch.observations, batch.actions.long(), batch.rewards, batch.next_observations, batch.dones
    )
    fit_q_network(reference_net, th.optim.RMSprop(reference_net.parameters(), lr=5e-4), reference_batch, 1.0, 40)
    fitted = parameters_to_vector(model.q_net.parameters()).detach()
    assert th.allclose(fitted, parameters_to_vector(reference_net.parameters()).detach(), rtol=1e-4, atol=1e-5)
    assert not th.equal(fitted, snapshot.weights)  # not a comparison of two untouched networks


def test_configs_resolve_every_algorithm_on_every_env_and_refuse_unknown_names() -> None:
    for algo in configs.algorithm_names():
        for env_id in configs.ENVS:
            config = configs.resolve(algo, env_id)
            assert config.budget > 0 and "n_timesteps" not in config.kwargs
            assert config.kwargs.get("keep_best", False) == algo.endswith("-keep-best")
    assert configs.resolve("reference-nfq", "CartPole-v1").budget == configs.resolve("nfq-book", "CartPole-v1").budget
    assert "n_quantiles" in configs.resolve("qrdqn-zoo", "Acrobot-v1").kwargs["policy_kwargs"]
    assert {algo.removesuffix(configs.keep_best_suffix(algo)) for algo in configs.SHIPPED.values()} <= set(
        configs.NFQ_CONFIG_NAMES
    )
    batch_128 = configs.resolve("nfq-front-loaded-batch-128", "CartPole-v1").kwargs
    assert configs.resolve("nfq-front-loaded-batch-128-keep-best", "CartPole-v1").kwargs == batch_128 | {
        "keep_best": True
    }
    assert not set(configs.SEEDS) & set(configs.HELD_OUT_SEEDS)
    with pytest.raises(KeyError, match="unknown algorithm config 'nfq-tuned'"):
        configs.resolve("nfq-tuned", "CartPole-v1")


def test_the_shipped_file_holds_the_settings_each_of_its_entries_was_measured_with() -> None:
    text = ZOO_FILE.read_text()
    # A benchmark config may spell out NFQ's defaults (as a study's trial does); the shipped entry needs no line for one
    defaults = {name: p.default for name, p in inspect.signature(sb3_nfq.NFQ).parameters.items()}

    def settings(kwargs: dict[str, Any]) -> dict[str, Any]:
        return {key: value for key, value in kwargs.items() if key not in ZOO_KEYS and defaults.get(key, ...) != value}

    for entry_name, algo in configs.SHIPPED.items():
        comment = re.search(rf"((?:^#.*\n)+){re.escape(entry_name)}:", text, re.MULTILINE)
        assert comment is not None and re.findall(r"Measured as ([\w.-]*\w)", comment.group(1)) == [algo], entry_name
        entry = read_entry(entry_name)
        measured = configs.resolve(algo, entry_name if entry_name in configs.ENVS else "LunarLander-v3")
        if entry_name in configs.ENVS:
            assert entry["n_timesteps"] == measured.budget, entry_name
        keep_best = measured.kwargs.pop("keep_best", False)
        assert ("callback" in entry) == keep_best, entry_name
        assert settings(entry) == settings(measured.kwargs), entry_name


def test_configs_refuse_an_entry_that_normalizes_the_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "nfq-book.yml").write_text("CartPole-v1:\n  n_timesteps: 1000\n  normalize: true\n")
    monkeypatch.setattr(configs, "HYPERPARAMS_DIR", tmp_path)
    with pytest.raises(NotImplementedError, match=r"nfq-book.yml's entry for CartPole-v1 sets \['normalize'\]"):
        configs.resolve("nfq-book", "CartPole-v1")


def test_recorded_runs_of_kept_configs_keep_their_job_keys() -> None:
    """The configs' move and the new runner keep the hashes, so the recorded runs still count as done."""
    records = [*run.read_results(RESULTS / "runs.jsonl"), *run.read_results(RESULTS / "book_protocol.jsonl")]
    kept = [record for record in records if record["algo"] in configs.algorithm_names()]
    for record in kept:
        fields = {key: record[key] for key in ("budget", "eval_every", "n_eval_episodes", "stop_at_solve")}
        fields["protocol"] = record.get("protocol", "rounds")
        (job,) = run.make_jobs([record["algo"]], [record["env"]], [record["seed"]], **fields)
        assert job.key == run.result_key(record)
    assert len(kept) > 250


def test_evaluation_episode_i_starts_from_reset_seed_base_plus_i() -> None:
    base = 1_000_000
    expected = []
    for i in range(20):
        env, total, done = gym.make("CartPole-v1"), 0.0, False
        obs, _ = env.reset(seed=base + i)
        while not done:
            obs, reward, terminated, truncated, _ = env.step(int(POLE_ANGLE.predict(obs[None])[0][0]))
            total, done = total + float(reward), terminated or truncated
        expected.append(total)
    evaluations = run.Evaluations(_job("nfq-book", n_eval_episodes=20), seed_base=base)
    for _ in range(2):  # every evaluation replays the same episodes
        returns = evaluations.returns(POLE_ANGLE, base)
        assert sorted(returns) == sorted(expected) and len(set(expected)) > 5


def test_seconds_to_solve_count_training_before_the_solving_evaluation_and_no_evaluation() -> None:
    evaluations = run.Evaluations(_job("nfq-book"), seed_base=1_000_000)
    evaluations.started = time.perf_counter() - 10.0  # training began 10 s ago
    evaluations.evaluate(0, Rule(POLE_ANGLE.push_right, 0.02))  # a slow evaluation, then two that solve
    evaluations.evaluate(1024, BALANCER)
    evaluations.evaluate(2048, BALANCER)
    assert evaluations.curve[0][1] < 475 <= min(evaluations.curve[1][1], evaluations.curve[2][1])
    assert evaluations.steps_to_solve == 1024 and evaluations.eval_seconds > 0.5
    assert evaluations.seconds_to_solve is not None and 10.0 <= evaluations.seconds_to_solve < 10.4


@pytest.mark.parametrize("algo", ["nfq-book", "reference-nfq", "dqn-zoo", "qrdqn-zoo"])
def test_a_job_evaluates_at_step_0_after_each_period_and_at_the_end(algo: str) -> None:
    record = run.run_job(_job(algo, budget=1500))
    assert [steps for steps, _ in record["curve"]] == [0, 1024, record["steps_trained"]]
    assert record["steps_trained"] >= 1500 and record["torch_threads"] == 1
    assert record["final_n_episodes"] == 5 and record["kind"] == configs.resolve(algo, "CartPole-v1").kind
    assert not record["solved"] and record["train_seconds_to_solve"] is None
    json.dumps(record)


@pytest.mark.parametrize("algo", ["nfq-book", "reference-nfq"])
def test_the_book_protocol_evaluates_after_every_training_episode(algo: str) -> None:
    record = run.run_job(_job(algo, budget=600, protocol="book"))
    assert record["protocol"] == "book" and record["stop_at_solve"] and not record["solved"]
    assert record["episodes_trained"] > 10 and record["curve"] == []


def test_keep_best_configs_run_with_the_keep_best_callback() -> None:
    for algo in ("dqn-zoo-keep-best", "nfq-front-loaded-batch-128-keep-best"):
        _, callbacks = run.build_sb3_model(_job(algo))
        assert [type(callback) for callback in callbacks] == [sb3_nfq.KeepBestCallback]
    assert run.build_sb3_model(_job("dqn-zoo"))[1] == []
    assert configs.peers_of("nfq-book-keep-best") == ["dqn-zoo-keep-best", "qrdqn-zoo-keep-best"]
    record = run.run_job(_job("nfq-front-loaded-batch-128-keep-best", budget=1500))
    assert record["config"]["keep_best"] is True and record["curve"][-1][0] == record["steps_trained"]


def test_runner_reads_seed_ranges_appends_and_resumes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run.parse_seeds(["0-2", "7", "5,1"]) == [0, 1, 2, 7, 5]
    argv = ["--algos", "reference-nfq", "--envs", "CartPole-v1", "--seeds", "0-1", "--budget", "1024"]
    argv += ["--eval-episodes", "2", "--workers", "0", "--results", str(tmp_path / "runs.jsonl")]
    assert run.main(argv) == 0
    assert [record["seed"] for record in run.read_results(tmp_path / "runs.jsonl")] == [0, 1]
    assert run.main(argv) == 0 and len(run.read_results(tmp_path / "runs.jsonl")) == 2  # nothing run twice
    assert "2 already in" in capsys.readouterr().out
    with pytest.raises(SystemExit):  # no default set of algorithms: a run names what it runs
        run.main(argv[2:])


def test_a_rerun_skips_only_what_its_command_recorded_on_this_hardware(tmp_path: Path) -> None:
    assert run.hardware("AMD EPYC, 2 cores (x86_64), 24 GiB RAM, Linux 6.18.44-fc-v1300") == (
        "AMD EPYC, 2 cores (x86_64), 24 GiB RAM"
    )
    results = tmp_path / "runs.jsonl"
    argv = ["--algos", "reference-nfq", "--envs", "CartPole-v1", "--seeds", "0", "--budget", "1024"]
    argv += ["--eval-episodes", "2", "--workers", "0", "--rerun", "--results", str(results)]
    assert run.main(argv) == 0 and run.main(argv) == 0 and len(run.read_results(results)) == 1
    (record,) = run.read_results(results)
    other_release = {**record, "machine": f"{run.hardware(record['machine'])}, Linux 0.0-another-boot"}
    other_cpu = {**record, "machine": "Another CPU, 2 cores (x86_64), 24 GiB RAM, Linux 0.0"}
    for recorded, lines_after in ((other_release, 1), (other_cpu, 2)):  # skipped; run again
        results.write_text(json.dumps(recorded) + "\n")
        assert run.main(argv) == 0 and len(run.read_results(results)) == lines_after


def test_recorded_commands_name_paths_inside_the_repository_relative_to_it(tmp_path: Path) -> None:
    inside = str(run.REPO_ROOT / "benchmarks" / "results" / "runs.jsonl")
    command = run.relative_command("benchmarks.run", ["--results", inside, "--x", str(tmp_path)])
    assert command == f"python -m benchmarks.run --results benchmarks/results/runs.jsonl --x {tmp_path}"


@pytest.mark.slow
def test_runner_local_pool_and_ray_run_each_job_in_its_own_process(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    for extra in (["--workers", "1"], ["--workers", "1", "--ray-address", "local"]):
        results = tmp_path / f"{len(extra)}.jsonl"
        argv = ["--algos", "reference-nfq", "--envs", "CartPole-v1", "--seeds", "0-1", "--budget", "1024"]
        assert run.main([*argv, "--eval-episodes", "2", "--results", str(results), *extra]) == 0
        records = run.read_results(results)
        launcher = "ray (local)" if "--ray-address" in extra else "local pool (1 spawned workers)"
        assert len({record["pid"] for record in records}) == 2 and records[0]["launcher"] == launcher


@pytest.fixture(scope="module")
def recorded() -> list[dict[str, Any]]:
    """The recorded CartPole runs of the fidelity pair and DQN, and of a retired config."""
    algos = {"nfq-book", "reference-nfq", "dqn-zoo", "nfq-tuned"}
    return [r for r in run.read_results(RESULTS / "runs.jsonl") if r["env"] == "CartPole-v1" and r["algo"] in algos]


#: MountainCar's entry before the current one (retired): the report's numbers below are those of its recorded
#: held-out runs beside both peers.
RECORDED_MOUNTAIN_CAR = "nfq-short-rounds-lr-lin-4e-3-huber-5-ez-2"


@pytest.fixture
def held_out(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """The recorded held-out MountainCar runs of the entry they measured and the two peers, that entry shipped."""
    monkeypatch.setitem(configs.SHIPPED, "MountainCar-v0", RECORDED_MOUNTAIN_CAR)
    algos = {RECORDED_MOUNTAIN_CAR, "dqn-zoo", "qrdqn-zoo"}
    records = run.read_results(RESULTS / "held_out.jsonl")
    return [r for r in records if r["env"] == "MountainCar-v0" and r["algo"] in algos]


def test_report_keeps_the_numbers_of_recorded_runs_and_judges_on_the_held_out_seeds(
    recorded: list[dict[str, Any]], held_out: list[dict[str, Any]]
) -> None:
    book = report.book_cells(run.read_results(RESULTS / "book_protocol.jsonl"))
    text = report.build_report(recorded, book, held_out)
    targets = {line.split("|")[1].strip(): line.split("|")[2:4] for line in text.splitlines() if "| **" in line}
    fidelity = "CartPole-v1, the book's criterion: nfq-book / reference-nfq median steps to solve within 0.75 to 1.25"
    assert targets[fidelity][0].strip() == "**met**"
    assert "1.03 (330,964 / 320,831; 95% bootstrap CI of the ratio 0.83-1.33)" in targets[fidelity][1]
    # a table row never mixes CPUs: nfq-book's development seeds 0-9 ran on one, 10-19 on another
    assert re.search(r"nfq-book +\| 0-9 +\| AMD EPYC +\|.*\| 143,360 \[100,352, 158,208\] ", text)
    assert re.search(r"nfq-book +\| 10-19 +\| Intel\(R\) Xeon\(R\) Proc.*\| 110,592 \[82,944, 117,504\] ", text)
    steps = [(target, cells) for target, cells in targets.items() if "0.75x the better peer" in target]
    (mountain_car,) = [cells for target, cells in steps if target.startswith("MountainCar-v0")]
    assert mountain_car[0].strip() == "**met**"
    assert "0.44 (40,448 / 92,160; 95% bootstrap CI of the ratio 0.29-0.55) against dqn-zoo" in mountain_car[1]
    # each target names the runner commands of the runs it judged: here the entry's two, each beside both peers
    numbered = dict(re.findall(r"^(\d+)\. `(.+)`$", text, flags=re.MULTILINE))
    (runs_of,) = [line.split("|")[4] for line in text.splitlines() if "| **" in line and mountain_car[1] in line]
    entry_commands = {record["command"] for record in held_out if record["algo"] == RECORDED_MOUNTAIN_CAR}
    assert len(entry_commands) == 2 and {numbered[n] for n in re.findall(r"\[(\d+)\]", runs_of)} == entry_commands
    assert "huber-5-ez-2 8/10 vs dqn-zoo 3/10 vs qrdqn-zoo 6/10" in text
    hardware = "AMD EPYC, 2 cores (x86_64), 24 GiB RAM"  # the seconds name the hardware they were measured on
    assert f"1.408 (451.0 s / 320.2 s, local pool (2 spawned workers), {hardware}); to the solve, median: nfq-" in text
    # an entry that ends on its best fit is compared with peers that do too
    assert configs.peers_of(configs.SHIPPED["CartPole-v1"]) == ["dqn-zoo-keep-best", "qrdqn-zoo-keep-best"]
    assert sum(verdict.strip() == "**not enough data**" for verdict, _ in targets.values()) == 13  # the other envs
    assert "nfq-tuned" not in text.split("## Targets")[1]  # retired: kept in the results file, out of the report


def test_a_median_between_a_solved_and_an_unsolved_run_is_a_lower_bound_in_steps_and_seconds() -> None:
    # A retired config's held-out MountainCar-v0 runs (out of the report, kept in the results file): 5 of 10 solved, so
    # the median interpolates between the 5th solved run (103,424) and an unsolved one (120,000 steps trained): it is
    # only a lower bound, and so is its ratio.
    records = [r for r in run.read_results(RESULTS / "held_out.jsonl") if r["env"] == "MountainCar-v0"]
    cells = report.side_by_side(records, "MountainCar-v0", ["nfq-short-rounds-lr-lin-4e-3-huber-5", "dqn-zoo"])
    assert cells is not None
    nfq, dqn = cells
    assert nfq.steps_quantile(50) == (111_712.0, True) and nfq.steps_quantile(25) == (50_944.0, False)
    assert dqn.steps_quantile(50) == (92_160.0, False)
    verdict, text = report.steps_ratio(nfq, dqn, 0.0, 0.75)
    assert verdict == "not met" and text.startswith("≥ 1.21 (median of nfq-short-rounds-lr-lin-4e-3-huber-5")
    assert "≥111,712 [50,944, ≥120,000]" in report.env_table([nfq])
    assert nfq.solve_seconds().startswith("≥") and not dqn.solve_seconds().startswith("≥")  # the same rule for seconds


def test_side_by_side_pools_the_commands_at_the_finest_evaluation_period_on_the_seeds_every_algo_ran() -> None:
    # dqn-zoo's held-out CartPole-v1 runs: seeds 5-14 by a command evaluating every 256 steps and by one evaluating
    # every 1,024 (in either order in the file, the finer grid's runs are the ones compared; the two never mix).
    every_run = run.read_results(RESULTS / "held_out.jsonl")
    records = [r for r in every_run if r["env"] == "CartPole-v1"]
    assert {r["eval_every"] for r in records if r["algo"] == "dqn-zoo"} >= {256, 1024}
    for ordered in (records, records[::-1]):
        cells = report.side_by_side(ordered, "CartPole-v1", ["dqn-zoo"])
        assert cells is not None and {r["eval_every"] for r in cells[0].runs} == {256}
        assert cells[0].n == 10 and cells[0].steps_quantile(50) == (12_160.0, False)
    # LunarLander-v3's held-out seeds 5-7 as its first command left them, stopped part-way (QR-DQN's seed 7 not run):
    # only the seeds every algo ran are compared.
    algos = ["nfq-short-rounds", "dqn-zoo", "qrdqn-zoo"]
    records = [
        r
        for r in every_run
        if r["env"] == "LunarLander-v3" and r["seed"] in (5, 6, 7) and (r["algo"], r["seed"]) != (algos[2], 7)
    ]
    assert {r["seed"] for r in records if r["algo"] in algos[:2]} == {5, 6, 7}
    cells = report.side_by_side(records, "LunarLander-v3", algos)
    assert cells is not None and [[r["seed"] for r in cell.runs] for cell in cells] == [[5, 6]] * 3


def test_side_by_side_never_pools_one_command_across_hardware(held_out: list[dict[str, Any]]) -> None:
    # the MountainCar entry's held-out runs: two commands (seeds 5-9, 10-14), each running the entry and both peers
    algos = [RECORDED_MOUNTAIN_CAR, "dqn-zoo", "qrdqn-zoo"]

    def seeds_judged_with_the_entrys_first_five_on(machine: str) -> list[int]:
        moved = [r | {"machine": machine} if r["algo"] == algos[0] and r["seed"] < 10 else r for r in held_out]
        cells = report.side_by_side(moved, "MountainCar-v0", algos)
        assert cells is not None and len({tuple(r["seed"] for r in cell.runs) for cell in cells}) == 1
        return [r["seed"] for r in cells[0].runs]

    (machine,) = {r["machine"] for r in held_out if r["algo"] == algos[0]}
    assert seeds_judged_with_the_entrys_first_five_on(machine) == list(range(5, 15))
    assert seeds_judged_with_the_entrys_first_five_on(f"{run.hardware(machine)}, Linux 0.0") == list(range(5, 15))
    assert seeds_judged_with_the_entrys_first_five_on("Another CPU, 2 cores, 24 GiB RAM, Linux 0.0") == [*range(10, 15)]


def test_readme_table_shows_the_held_out_rows_their_budgets_and_how_many_seeds_have_run(
    held_out: list[dict[str, Any]],
) -> None:
    book = report.book_cells(run.read_results(RESULTS / "book_protocol.jsonl"))
    rows = {row.split("|")[1].strip(): row for row in report.readme_table(held_out, book).splitlines()[2:]}
    all_seeds, book_row = rows["MountainCar-v0"], rows["CartPole-v1, the book's criterion"]
    assert "5-14 (held out)" in all_seeds and "40,448 vs 92,160 vs 99,328" in all_seeds
    assert "8/10 vs 3/10 vs 6/10" in all_seeds
    assert "| 451 vs 320 vs 429 (AMD EPYC) " in all_seeds  # seconds name the CPU they were measured on
    assert "330,964 vs 320,831" in book_row and "--protocol book" in book_row
    assert "| 120,000 " in all_seeds and "| 500,000 " in book_row  # one budget where every algorithm ran the same
    shorter = [r | {"budget": 80_000} if r["algo"] == configs.SHIPPED["MountainCar-v0"] else r for r in held_out]
    (row,) = [row for row in report.readme_table(shorter, book).splitlines() if row.startswith("| MountainCar")]
    assert "| 80,000 vs 120,000 vs 120,000 " in row
    first_half = [r for r in run.read_results(RESULTS / "held_out.jsonl") if "--seeds 5-9 " in r["command"]]
    table = report.readme_table(first_half, book)
    (mountain_car,) = [row for row in table.splitlines() if row.startswith("| MountainCar")]
    assert "5-9 (held out: 5 of 10 seeds so far)" in mountain_car and "5/5 vs 0/5 vs 3/5" in mountain_car
    (cartpole,) = [row for row in table.splitlines() if row.startswith("| CartPole-v1 ")]  # its entry ran 5-14 at once
    assert "held out: none run yet" in cartpole and f"{configs.SHIPPED['CartPole-v1']} vs dqn-zoo-keep-best" in cartpole
    readme = report.replace_block(
        f"a\n{report.README_MARKERS[0]}\nSTALE\n{report.README_MARKERS[1]}\nb", report.README_MARKERS, all_seeds
    )
    assert "STALE" not in readme and readme.startswith("a\n") and readme.endswith(report.README_MARKERS[1] + "\nb")


def test_targets_file_is_refused_with_a_missing_or_unknown_key(tmp_path: Path) -> None:
    targets = report.read_targets()
    assert targets["held_out"]["final_at_least"] == 8
    bad = tmp_path / "targets.yml"
    bad.write_text(yaml.safe_dump({**targets, "held_out": {**targets["held_out"], "fastest": 1}}))
    with pytest.raises(ValueError, match="'held_out' needs exactly the keys"):
        report.read_targets(bad)
    bad.write_text(yaml.safe_dump({**targets, "speed": {}}))
    with pytest.raises(ValueError, match="unknown sections"):
        report.read_targets(bad)
