"""
The RL Zoo bridge (``python -m sb3_nfq.zoo``) with the real rl_zoo3, Optuna and files, on tiny budgets.

The zoo's commands run in subprocesses: importing rl_zoo3 patches gymnasium's ``TimeLimit`` for the whole
process, which must not leak into the other tests. This module imports rl_zoo3 nowhere.
"""

import os
import re
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import optuna
import pytest
import yaml
from optuna.storages.journal import JournalFileBackend
from optuna.trial import FixedTrial, TrialState
from stable_baselines3.common.type_aliases import TrainFreq

from sb3_nfq import NFQ
from sb3_nfq.configs import ZOO_FILE, nfq_kwargs, read_entry, zoo_to_kwargs
from sb3_nfq.parameters import HYPERPARAMETERS
from sb3_nfq.zoo import (
    ALGO_NAME,
    BUFFER_SIZES,
    CATEGORICAL_SPACE,
    DEFAULT_CONF_FILE,
    EXPLORATION_UCBS,
    HUBER_DELTAS,
    ITERATION_TRANSITIONS,
    N_CRITICS,
    NET_ARCHS,
    OPTIMIZERS,
    convert_nfq_params,
    main,
    sample_nfq_params,
    zoo_arguments,
)

ENV_ID = "CartPole-v1"
#: The repository's root: the tests read its documentation and recorded studies, which the wheel does not hold.
ROOT = Path(__file__).resolve().parent.parent
#: The studies recorded by the benchmark's tuning runs
TUNING_JOURNALS = ROOT / "benchmarks" / "results" / "tuning"
#: One torch/BLAS thread per zoo process (the machine is shared).
SINGLE_THREAD_ENV = {
    **os.environ,
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
}
TIMEOUT_S = 300
#: The zoo's documentation page, whose table lists the search space.
ZOO_PAGE = ROOT / "docs" / "zoo.md"
#: Tiny tuning runs: trials of 1024 steps, evaluated once on 2 episodes, no plots.
TINY_OPTIMIZE_ARGS = ["-optimize", "-n", "1024", "--n-evaluations", "1", "--eval-episodes", "2", "--no-optim-plots"]


def _zoo(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run ``python -m sb3_nfq.zoo ARGS`` to completion with one thread and return its outcome."""
    return subprocess.run(
        [sys.executable, "-m", "sb3_nfq.zoo", *args, "--num-threads", "1"],
        cwd=cwd,
        env=SINGLE_THREAD_ENV,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )


def _start_zoo(*args: str, cwd: Path, output: Path) -> subprocess.Popen[bytes]:
    """Start ``python -m sb3_nfq.zoo ARGS`` with one thread, its stdout and stderr going to ``output``."""
    with open(output, "wb") as file:
        return subprocess.Popen(
            [sys.executable, "-m", "sb3_nfq.zoo", *args, "--num-threads", "1"],
            cwd=cwd,
            env=SINGLE_THREAD_ENV,
            stdout=file,
            stderr=subprocess.STDOUT,
        )


def _check(result: subprocess.CompletedProcess[str]) -> str:
    """:return: the command's stdout, once it is known to have succeeded"""
    assert result.returncode == 0, f"exit status {result.returncode}\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"
    return result.stdout


def _read_yaml(path: Path) -> Any:
    with open(path) as file:
        return yaml.load(file, Loader=yaml.UnsafeLoader)  # the zoo's files hold Python objects (OrderedDict, classes)


# --- the command line the zoo gets ---


@pytest.mark.parametrize(
    ("command", "args", "expected"),
    [
        ("train", ["--env", ENV_ID], ["--algo", "nfq", "--conf-file", str(DEFAULT_CONF_FILE), "--env", ENV_ID]),
        ("train", ["--algo", "nfq"], ["--conf-file", str(DEFAULT_CONF_FILE), "--algo", "nfq"]),
        ("train", ["--algo=nfq", "-conf", "my.yml"], ["--algo=nfq", "-conf", "my.yml"]),
        ("train", ["--conf-file=my.yml"], ["--algo", "nfq", "--conf-file=my.yml"]),
        ("train", ["--conf", "my.yml"], ["--algo", "nfq", "--conf", "my.yml"]),  # argparse abbreviation
        ("train", ["--algo", "dqn", "--env", ENV_ID], ["--algo", "dqn", "--env", ENV_ID]),  # other algos: untouched
        (
            "train",
            ["-params", "n_timesteps:2048", "train_freq:64"],
            ["--algo", "nfq", "--conf-file", str(DEFAULT_CONF_FILE), "-params", "n_timesteps:2048", "train_freq:64"],
        ),
        ("enjoy", ["--env", ENV_ID], ["--algo", "nfq", "--folder", "logs", "--env", ENV_ID]),
        ("enjoy", ["-f", "runs", "--no-render"], ["--algo", "nfq", "-f", "runs", "--no-render"]),
        ("enjoy", ["--algo", "ppo"], ["--algo", "ppo"]),  # the zoo's own default folder (downloaded agents)
        ("train", ["--algo"], ["--algo"]),  # malformed: the zoo's parser reports it
    ],
)
def test_zoo_gets_the_arguments_untouched_after_the_nfq_defaults(
    command: str, args: list[str], expected: list[str]
) -> None:
    assert zoo_arguments(command, args) == expected


def test_packaged_hyperparameter_file_is_the_configs_file() -> None:
    assert DEFAULT_CONF_FILE == ZOO_FILE and DEFAULT_CONF_FILE.is_file()


def test_help_and_unknown_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    assert "python -m sb3_nfq.zoo {train,enjoy}" in capsys.readouterr().out
    assert main(["fly"]) == 2
    assert "unknown command 'fly'" in capsys.readouterr().err


# --- the hyperparameter file ---


def _hyperparameter_file() -> dict[str, dict[str, Any]]:
    with open(DEFAULT_CONF_FILE) as file:
        entries = yaml.safe_load(file)  # the zoo reads it with safe_load too
    assert isinstance(entries, dict)
    return entries


# --- the Optuna search space ---


def test_sampler_gives_valid_nfq_parameters_and_the_converter_rebuilds_them() -> None:
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0), direction="maximize")
    entries = {env_id: nfq_kwargs(env_id) for env_id in _hyperparameter_file() if env_id != "atari"}
    for _ in range(40):
        trial = study.ask()
        hyperparams = sample_nfq_params(trial, 0, 1, {"using_her_replay_buffer": False, "her_kwargs": {}})
        converted = convert_nfq_params(trial.params)  # what `--trial-id` reloads, in the zoo's format
        rate, linear = trial.params["learning_rate"], trial.params["lr_schedule"] == "linear"
        assert converted["learning_rate"] == (f"lin_{rate!r}" if linear else rate)
        assert repr(converted | {"learning_rate": 0}) == repr(hyperparams | {"learning_rate": 0})
        growing, huber = trial.params["memory"] == "growing", trial.params["loss"] == "huber"
        ensemble = trial.params["n_critics"] > 1
        assert set(trial.params) == {
            "learning_rate",
            "lr_schedule",
            "fit_cost",
            "exploration_initial_eps",
            "exploration_final_eps",
            "exploration_fraction",
            "net_arch",
            "optimizer",
            "n_critics",
            *CATEGORICAL_SPACE,
            *(["buffer_size", "iteration_transitions"] if growing else []),
            *(["huber_delta"] if huber else []),
            *(["exploration_ucb"] if ensemble else []),
        }
        assert trial.user_attrs["worker"] == f"{socket.gethostname()}:{os.getpid()}"
        for env_id, entry in entries.items():  # the zoo puts the sampled values over the env's entry
            model = NFQ("MlpPolicy", ENV_ID, **(entry | hyperparams))
            assert isinstance(model.policy.optimizer, OPTIMIZERS[trial.params["optimizer"]]), env_id
            assert model.policy.net_arch == NET_ARCHS[trial.params["net_arch"]]
            assert model.huber_delta == trial.params.get("huber_delta", 1.0)
            assert model.exploration_repeat_mu == trial.params["exploration_repeat_mu"]
            assert model.exploration_start == trial.params["exploration_start"]  # over Acrobot's entry's too
            assert model.n_steps == trial.params["n_steps"]  # over LunarLander's entry's n_steps too
            assert model.policy.n_critics == trial.params["n_critics"]  # over LunarLander's ensemble too
            assert model.exploration_ucb == trial.params.get("exploration_ucb")  # None for one network
            iteration_transitions = trial.params.get("iteration_transitions")  # over MountainCar's sampled fit too
            assert model.iteration_transitions == iteration_transitions
            memory_size = trial.params.get("buffer_size", trial.params["train_freq"])
            iteration_size = min(iteration_transitions or memory_size, memory_size)
            epochs = max(1, round(trial.params["fit_cost"] * trial.params["train_freq"] / iteration_size))
            assert (model.gradient_steps, model.fit_epochs) == (epochs, 1)
            assert model.round_fraction is None
        assert model.lr_schedule(1.0) == pytest.approx(rate) and model.lr_schedule(0.0) == (0.0 if linear else rate)
        study.tell(trial, 0.0)
    assert {trial.params["batch_size"] for trial in study.trials} == set(CATEGORICAL_SPACE["batch_size"])
    assert {trial.params["memory"] for trial in study.trials} == {"fresh", "growing"}
    assert {trial.params.get("iteration_transitions") for trial in study.trials} == set(ITERATION_TRANSITIONS)
    assert {trial.params["n_critics"] for trial in study.trials} == set(N_CRITICS)
    assert {trial.params.get("exploration_ucb", 0) for trial in study.trials} == {0, *EXPLORATION_UCBS}


@pytest.mark.parametrize(
    ("parameter", "choices"),
    [
        *((name, CATEGORICAL_SPACE[name]) for name in ("train_freq", "batch_size", "gamma", "n_steps")),
        ("buffer_size", BUFFER_SIZES),
        ("iteration_transitions", ITERATION_TRANSITIONS),
        ("huber_delta", HUBER_DELTAS),
        ("n_critics", N_CRITICS),
        ("exploration_ucb", EXPLORATION_UCBS),
    ],
)
def test_the_zoo_pages_search_space_table_lists_the_samplers_numeric_choices(
    parameter: str, choices: tuple[Any, ...]
) -> None:
    rows = [row for row in ZOO_PAGE.read_text().splitlines() if row.startswith(f"| `{parameter}`")]
    assert len(rows) == 1, parameter
    listed = re.sub(r"\([^)]*\)", "", rows[0].split("|")[2])  # the choices, without the words in brackets
    numbers = re.findall(r"\d{1,3}(?:,\d{3})+|\d+(?:\.\d+)?", listed)  # 10,000 is one number; "1, 5" two
    assert sorted(float(number.replace(",", "")) for number in numbers) == sorted(
        float(choice) for choice in choices if choice is not None
    )


@pytest.mark.filterwarnings("error:The value:UserWarning")  # FixedTrial's warning on a number outside its range
def test_lunarlanders_shipped_entry_is_the_trial_of_its_study_that_its_comment_names(tmp_path: Path) -> None:
    # The entry is trial 119 of nfq-LunarLander-v3-30k: the sampler, given that trial's stored values as a queued trial
    # runs them, builds the entry's model. So a study can queue the entry it tunes from, and a trial can reach it.
    journal = tmp_path / "LunarLander-v3.log"  # a copy: opening a journal may write beside it
    journal.write_bytes((TUNING_JOURNALS / journal.name).read_bytes())
    storage = optuna.storages.JournalStorage(JournalFileBackend(str(journal)))
    trial = optuna.load_study(study_name="nfq-LunarLander-v3-30k", storage=storage).trials[119]
    assert trial.state == TrialState.COMPLETE
    assert "trial 119 of the Optuna study nfq-LunarLander-v3-30k" in DEFAULT_CONF_FILE.read_text()
    # The sampler itself: FixedTrial raises on a missing value or a category outside its choices, and warns (an error
    # here) on a number outside its range.
    hyperparams = sample_nfq_params(
        FixedTrial(trial.params), 0, 1, {"using_her_replay_buffer": False, "her_kwargs": {}}
    )
    entry_model = NFQ("MlpPolicy", "LunarLander-v3", **nfq_kwargs("LunarLander-v3"))
    point_model = NFQ("MlpPolicy", "LunarLander-v3", **hyperparams)
    for name in sorted(HYPERPARAMETERS - {"learning_rate"}):
        assert getattr(point_model, name) == getattr(entry_model, name), name
    assert point_model.policy.n_critics == entry_model.policy.n_critics == 2
    assert point_model.policy.net_arch == entry_model.policy.net_arch
    assert type(point_model.policy.optimizer) is type(entry_model.policy.optimizer)
    for progress in (1.0, 0.5):
        assert point_model.lr_schedule(progress) == pytest.approx(entry_model.lr_schedule(progress))


def test_a_study_stored_before_the_growing_memory_was_searched_converts_as_it_did() -> None:
    stored = {"learning_rate": 1e-3, "gradient_steps": 12, "train_freq": 512, "loss": "huber", "net_arch": "small"}
    assert convert_nfq_params(stored) == {
        "learning_rate": 1e-3,
        "gradient_steps": 12,
        "train_freq": 512,
        "loss": "huber",
        "policy_kwargs": {"net_arch": [64, 64]},
        "exploration_ucb": None,  # one network, as every study before n_critics had
    }


def test_a_trial_stored_with_fit_epochs_converts_as_it_ran_its_rounds_epochs_grouped_and_capped() -> None:
    def iterations_and_epochs(**params: Any) -> tuple[int, int]:
        growing = {"memory": "growing", "buffer_size": 10_000, "train_freq": 512, "fit_cost": 78.125, "loss": "mse"}
        converted = convert_nfq_params(growing | params)  # a round of 78.125 * 512 / 10,000 = 4 epochs
        return converted["gradient_steps"], converted["fit_epochs"]

    assert iterations_and_epochs() == (4, 1)  # without fit_epochs: one epoch per iteration
    assert iterations_and_epochs(target_mode="fixed_per_iteration", fit_epochs=2) == (2, 2)
    assert iterations_and_epochs(target_mode="fixed_per_iteration", fit_epochs=8) == (1, 4)  # not 8: twice the fit


# --- train, enjoy, tune: the real zoo in subprocesses ---


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """
    A zoo training run of 2048 steps on CartPole with the packaged entry, with evaluations and checkpoints; yields its
    folder, where ``train_output.txt`` holds what it printed.
    """
    workdir = tmp_path_factory.mktemp("zoo_train")
    output = _check(
        _zoo(
            "train",
            "--env",
            ENV_ID,
            "-n",
            "2048",
            "--eval-freq",
            "1024",
            "--eval-episodes",
            "2",
            "--save-freq",
            "1024",
            "--seed",
            "0",
            cwd=workdir,
        )
    )
    (workdir / "train_output.txt").write_text(output)
    yield workdir


def _assert_trains_the_entry(run: Path, env_id: str, steps: int) -> dict[str, Any]:
    """
    Check that a zoo training run of ``steps`` steps in ``run`` trained nfq.yml's entry for ``env_id``.

    :return: the entry
    """
    entry = read_entry(env_id)
    assert dict(_read_yaml(run / env_id / "config.yml")) == _hyperparameter_file()[env_id]
    model = NFQ.load(run / f"{env_id}.zip")
    assert model.num_timesteps == steps and isinstance(model.train_freq, TrainFreq)
    assert (model.train_freq.frequency, model.gradient_steps, model.gamma, model.memory, model.n_steps) == (
        entry["train_freq"],
        entry["gradient_steps"],
        entry["gamma"],
        entry["memory"],
        entry.get("n_steps", 1),
    )
    assert model.policy.net_arch == zoo_to_kwargs(entry)["policy_kwargs"]["net_arch"]
    return entry


@pytest.mark.slow  # the zoo in a subprocess
def test_train_uses_the_packaged_file_and_writes_a_model_nfq_loads(trained_run: Path) -> None:
    run = trained_run / "logs" / ALGO_NAME / f"{ENV_ID}_1"
    files = {path.name for path in run.iterdir()}
    assert {
        f"{ENV_ID}.zip",
        "best_model.zip",  # --eval-freq
        "evaluations.npz",
        "rl_model_1024_steps.zip",  # --save-freq
        "rl_model_2048_steps.zip",
    } <= files

    args = _read_yaml(run / ENV_ID / "args.yml")
    assert args["algo"] == ALGO_NAME and args["conf_file"] == str(DEFAULT_CONF_FILE)
    entry = _assert_trains_the_entry(run, ENV_ID, 2048)
    # The entry's callback key reached learn(): KeepBestCallback logs the best score
    assert entry["callback"] == "sb3_nfq.KeepBestCallback"
    assert "best_score" in (trained_run / "train_output.txt").read_text()
    assert NFQ.load(run / "rl_model_1024_steps.zip").num_timesteps == 1024
    assert NFQ.load(run / "best_model.zip").num_timesteps in (1024, 2048)


@pytest.mark.slow  # the zoo in a subprocess
@pytest.mark.parametrize("env_id", ["Acrobot-v1", "MountainCar-v0", "LunarLander-v3"])
def test_train_trains_the_entry_of_each_other_benchmark_env(env_id: str, tmp_path: Path) -> None:
    if env_id == "LunarLander-v3":
        pytest.importorskip("Box2D")
    _check(_zoo("train", "--env", env_id, "-n", "256", "--eval-freq", "-1", "--seed", "0", cwd=tmp_path))
    _assert_trains_the_entry(tmp_path / "logs" / ALGO_NAME / f"{env_id}_1", env_id, 256)


@pytest.mark.slow  # the zoo in a subprocess
def test_enjoy_runs_the_trained_agent(trained_run: Path) -> None:
    # No --algo and no -f: the launcher's defaults find the run under ./logs/nfq. More steps than CartPole's time
    # limit (500), so that an episode ends and its return is printed however well the agent balances.
    output = _check(_zoo("enjoy", "--env", ENV_ID, "--no-render", "-n", "600", "--deterministic", cwd=trained_run))
    assert f"Loading logs/{ALGO_NAME}/{ENV_ID}_1/{ENV_ID}.zip" in output
    assert "Mean reward:" in output


@pytest.mark.slow  # the zoo in a subprocess
def test_train_gives_learn_the_callbacks_of_the_entrys_callback_key(tmp_path: Path) -> None:
    conf_file = tmp_path / "stop_after_one_episode.yml"
    conf_file.write_text(
        f"{ENV_ID}:\n  n_timesteps: 2048\n  policy: 'MlpPolicy'\n  callback:\n"
        "    - stable_baselines3.common.callbacks.StopTrainingOnMaxEpisodes:\n        max_episodes: 1\n"
    )
    _check(_zoo("train", "--env", ENV_ID, "--conf-file", str(conf_file), "--eval-freq", "-1", cwd=tmp_path))
    model = NFQ.load(tmp_path / "logs" / ALGO_NAME / f"{ENV_ID}_1" / f"{ENV_ID}.zip")
    assert 0 < model.num_timesteps < 500  # stopped at the end of the first episode (CartPole's limit is 500 steps)


@pytest.mark.slow  # the zoo in a subprocess
def test_optimize_then_train_with_a_stored_trial(tmp_path: Path) -> None:
    storage = tmp_path / "study.log"
    output = _check(
        _zoo(
            "train",
            "--env",
            ENV_ID,
            *TINY_OPTIMIZE_ARGS,
            "--n-trials",
            "2",
            "--storage",
            str(storage),
            "--study-name",
            "tiny",
            "--seed",
            "3",
            cwd=tmp_path,
        )
    )
    assert "Number of finished trials:  2" in output
    assert list((tmp_path / "logs" / ALGO_NAME).glob(f"report_{ENV_ID}_2-trials-1024-*.csv"))

    study = optuna.load_study(
        study_name="tiny",
        storage=optuna.storages.JournalStorage(JournalFileBackend(str(storage))),
    )
    assert [trial.state for trial in study.trials] == [TrialState.COMPLETE] * 2

    # Train with trial 1's hyperparameters (the zoo ignores --trial-id 0: it tests the id for truth)
    stored = study.trials[1].params
    _check(
        _zoo(
            "train",
            "--env",
            ENV_ID,
            "-n",
            "64",
            "--eval-freq",
            "-1",
            "--storage",
            str(storage),
            "--study-name",
            "tiny",
            "--trial-id",
            "1",
            cwd=tmp_path,
        )
    )
    model = NFQ.load(next((tmp_path / "logs" / ALGO_NAME).glob(f"{ENV_ID}_*/{ENV_ID}.zip")))
    assert model.lr_schedule(1.0) == pytest.approx(stored["learning_rate"])
    assert model.gradient_steps == convert_nfq_params(stored)["gradient_steps"]
    assert (model.memory, model.target_mode, model.max_grad_norm) == tuple(
        stored[key] for key in ("memory", "target_mode", "max_grad_norm")
    )
    assert (model.gamma, model.batch_size, model.loss) == (stored["gamma"], stored["batch_size"], stored["loss"])
    assert isinstance(model.policy.optimizer, OPTIMIZERS[stored["optimizer"]])
    assert model.policy.net_arch == NET_ARCHS[stored["net_arch"]]


@pytest.mark.slow  # two zoo processes
@pytest.mark.parametrize("storage_kind", ["journal", "sqlite"])
def test_two_processes_cooperate_on_one_study(tmp_path: Path, storage_kind: str) -> None:
    study_name = "nfq-shared"
    if storage_kind == "journal":
        # The zoo opens a path ending in .log as a JournalFileBackend, creating its folder
        storage_arg = str(tmp_path / "shared" / "study.log")
    else:
        storage_arg = f"sqlite:///{tmp_path / 'study.db'}"
        # An RDB study is created once before the workers start (two first connections would race on the schema)
        optuna.create_study(storage=storage_arg, study_name=study_name, direction="maximize")
    n_trials = {"a": 1, "b": 2}
    workers = {
        name: _start_zoo(
            "train",
            "--env",
            ENV_ID,
            *TINY_OPTIMIZE_ARGS,
            "--n-trials",
            str(count),
            "--storage",
            storage_arg,
            "--study-name",
            study_name,
            "--seed",
            str(index),  # different seeds: the workers sample different hyperparameters
            "-f",
            str(tmp_path / f"logs_{name}"),
            cwd=tmp_path,
            output=tmp_path / f"worker_{name}.txt",
        )
        for index, (name, count) in enumerate(n_trials.items())
    }
    try:
        for worker in workers.values():
            worker.wait(timeout=TIMEOUT_S)
    finally:
        for worker in workers.values():
            if worker.poll() is None:
                worker.kill()
                worker.wait()
    for name, worker in workers.items():
        output = (tmp_path / f"worker_{name}.txt").read_text()
        assert worker.returncode == 0, f"worker {name}:\n{output[-4000:]}"
        assert "Number of finished trials: " in output

    storage: Any = storage_arg
    if storage_kind == "journal":
        assert (tmp_path / "shared" / "study.log").is_file()
        storage = optuna.storages.JournalStorage(JournalFileBackend(storage_arg))
    study = optuna.load_study(study_name=study_name, storage=storage)
    trials = study.get_trials(states=[TrialState.COMPLETE])
    assert len(study.trials) == len(trials) == sum(n_trials.values())
    assert sorted(trial.number for trial in trials) == list(range(sum(n_trials.values())))
    ran_by = [trial.user_attrs["worker"] for trial in trials]
    for name, worker in workers.items():
        assert ran_by.count(f"{socket.gethostname()}:{worker.pid}") == n_trials[name]
    assert study.user_attrs["command"].startswith(sys.executable)  # the first worker's command line
