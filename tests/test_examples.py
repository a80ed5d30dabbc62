"""Every example runs as is (here on tiny budgets)."""

import json
import runpy
import sys
import warnings
from pathlib import Path
from typing import Any

import pytest
import torch as th
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.env_util import make_vec_env

from benchmarks.run import script_result
from sb3_nfq import NFQ
from sb3_nfq.configs import nfq_kwargs
from sb3_nfq.parameters import HYPERPARAMETERS

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _module(name: str) -> dict[str, Any]:
    return runpy.run_path(str(EXAMPLES / name))


def _main(name: str) -> Any:
    return _module(name)["main"]


def test_quickstart_trains_for_its_budget_and_evaluates(capsys: pytest.CaptureFixture[str]) -> None:
    _main("quickstart.py")(["--total-timesteps", "2048"])
    printed = capsys.readouterr().out
    assert "Greedy return over 20 episodes after 2048 steps" in printed and "One greedy episode lasted" in printed


def test_examples_use_one_torch_thread_unless_told_otherwise() -> None:
    th.set_num_threads(2)
    _main("quickstart.py")(["--total-timesteps", "1024"])
    assert th.get_num_threads() == 1
    for example in sorted(EXAMPLES.rglob("*.py")):
        assert '"--threads", type=int, default=1' in example.read_text(), example.name


def test_callbacks_tensorboard_example_writes_evaluations_checkpoints_and_tensorboard(tmp_path: Path) -> None:
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*load_replay_buffer")  # the resume goes on with the round
        log_dir = _main("callbacks_tensorboard.py")(["--total-timesteps", "10240", "--log-dir", str(tmp_path)])
    assert (log_dir / "eval" / "evaluations.npz").is_file()
    assert (log_dir / "best_model" / "best_model.zip").is_file()
    assert sorted(p.name for p in (log_dir / "checkpoints").iterdir()) == [
        "nfq_10240_steps.zip",
        "nfq_replay_buffer_10240_steps.pkl",
    ]
    runs = sorted(p.name for p in (log_dir / "tensorboard").iterdir())
    assert runs[0] == "NFQ_1" and runs[1].startswith("NFQ_resumed"), runs
    assert NFQ.load(log_dir / "best_model" / "best_model.zip").n_envs == 2


def test_callbacks_tensorboard_example_says_when_its_budget_is_too_small_for_a_checkpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _main("callbacks_tensorboard.py")(["--total-timesteps", "2048", "--log-dir", str(tmp_path)])
    printed = capsys.readouterr().out
    assert "--total-timesteps 2048 is below 10240, the steps between checkpoints" in printed
    assert "resume demo skipped (it needs --total-timesteps 10240+)" in printed


def test_main_job_trains_evaluates_saves_and_reloads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    output = tmp_path / "nfq_cartpole.zip"
    status = _main("solve_cartpole.py")(
        ["--max-steps", "2048", "--threads", "1", "--no-progress-bar", "--output", str(output)]
    )
    printed = capsys.readouterr().out
    assert status == 1  # two rounds cannot solve CartPole; the job says so
    assert "NOT solved" in printed and "Final evaluation on 100 new greedy episodes: " in printed
    final = float(printed.split("Final evaluation on 100 new greedy episodes: ")[1].split()[0])
    # The loaded zip replays the final evaluation's 100 episodes and reproduces its score.
    assert f"the loaded agent on the same 100 episodes: {final:.1f}, " in printed
    assert "The first of them, replayed step by step by the loaded agent: return " in printed
    result = json.loads(printed.split("RESULT ")[1])
    assert result["solved"] is False and result["confirmations_tried"] == 0
    assert result["final_eval_mean"] == result["loaded_eval_mean"] == round(final, 1)
    assert NFQ.load(output).num_timesteps == 2048


@pytest.mark.parametrize(("threshold", "steps", "confirmations"), [(0.0, 1024, 1), (1e9, 3072, 0)])
def test_main_job_stops_only_on_a_confirmed_evaluation(threshold: float, steps: int, confirmations: int) -> None:
    stop_when_confirmed = _module("solve_cartpole.py")["StopWhenConfirmed"](threshold, seed=20_000)
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0)
    evaluation = EvalCallback(
        make_vec_env("CartPole-v1", n_envs=10, seed=10_000),
        n_eval_episodes=10,
        eval_freq=1024,
        callback_after_eval=stop_when_confirmed,
        verbose=0,
    )
    model.learn(3072, callback=evaluation)
    assert model.num_timesteps == steps
    assert [seed for _, seed, _ in stop_when_confirmed.confirmations] == [20_000] * confirmations


def test_custom_env_example_checks_its_env_and_trains_with_multi_input_policy(
    capsys: pytest.CaptureFixture[str],
) -> None:
    success_rate = _main("custom_env_gridworld.py")(["--total-timesteps", "2048"])
    assert f"After 2048 steps: greedy success rate {success_rate:.0%} over 100 random" in capsys.readouterr().out


def test_plot_learning_curve_example_writes_a_png(tmp_path: Path) -> None:
    png = _main("plot_learning_curve.py")(["--total-timesteps", "3072", "--log-dir", str(tmp_path)])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "evaluations.npz").is_file()


def test_offline_minari_example_records_a_local_dataset_and_fits_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    minari = pytest.importorskip("minari")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))  # the example sets it; restored after the test
    mean_length = _main("offline_minari.py")(
        ["--episodes", "5", "--iterations", "2", "--minari-dir", str(tmp_path / "minari")]
    )
    printed = capsys.readouterr().out
    dataset = minari.load_dataset("cartpole/uniform-random-v0")
    assert dataset.total_episodes == 5 and any((tmp_path / "minari").rglob("*.hdf5"))
    # the dataset it fits holds every recorded step
    assert f"{dataset.total_steps} transitions from 5 random episodes" in printed
    assert f"mean episode length {mean_length:.0f} over 20 episodes" in printed


def test_growing_memory_example_keeps_every_transition(capsys: pytest.CaptureFixture[str]) -> None:
    _main("growing_memory_cartpole.py")(["--total-timesteps", "2048"])
    assert "Memory holds 2048 transitions after 2048 steps. 2 evaluations;" in capsys.readouterr().out


def test_coming_from_dqn_nfq_script_uses_the_shipped_cartpole_entry_and_dqns_buffer_size() -> None:
    env = make_vec_env("CartPole-v1", n_envs=4, seed=0)
    script = _module("coming_from_dqn/nfq_cartpole.py")["make_model"](env, 0)
    config = NFQ("MlpPolicy", env, seed=0, buffer_size=100_000, **nfq_kwargs("CartPole-v1"))
    for name in HYPERPARAMETERS - {"learning_rate"}:  # one a LinearSchedule, the other the zoo's function
        assert getattr(script, name) == getattr(config, name), name
    assert script.policy_kwargs == config.policy_kwargs
    progress = (1.0, 0.5, 0.0)
    assert [script.lr_schedule(p) for p in progress] == pytest.approx([config.lr_schedule(p) for p in progress])


@pytest.mark.slow  # two fresh processes: about a minute on a busy 2-core machine
def test_coming_from_dqn_scripts_train_save_load_and_evaluate_at_the_same_budget(tmp_path: Path) -> None:
    def run(name: str) -> dict[str, Any]:
        script = EXAMPLES / "coming_from_dqn" / name
        options = ["--total-timesteps", "2048", "--seed", "0", "--threads", "1", "--log-dir", str(tmp_path)]
        return script_result([sys.executable, str(script), *options])[0]

    results = [run(name) for name in ("dqn_cartpole.py", "nfq_cartpole.py")]
    assert [(r["algo"], r["steps"], r["threads"]) for r in results] == [("DQN", 2048, 1), ("NFQ", 2048, 1)]
    assert (tmp_path / "dqn" / "dqn_cartpole.zip").is_file() and (tmp_path / "nfq" / "nfq_cartpole.zip").is_file()
    assert NFQ.load(tmp_path / "nfq" / "nfq_cartpole.zip").memory == "growing"
