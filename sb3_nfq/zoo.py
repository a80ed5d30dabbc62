"""
RL Zoo bridge: run NFQ with the `RL Baselines3 Zoo <https://github.com/DLR-RM/rl-baselines3-zoo>`_ (``rl_zoo3``).

``rl_zoo3`` has no plug-in mechanism; its documented pattern for a new algorithm is a launcher that registers the
algorithm in the zoo's tables and then calls the zoo's own ``train()`` / ``enjoy()``. This module is that launcher::

    python -m sb3_nfq.zoo train --algo nfq --env CartPole-v1 --eval-freq 10000 --save-freq 50000
    python -m sb3_nfq.zoo enjoy --algo nfq --env CartPole-v1 -f logs
    python -m sb3_nfq.zoo train --algo nfq --env CartPole-v1 -optimize --n-trials 50 \\
        --storage sqlite:///nfq.db --study-name nfq-cartpole

Every argument is handed to the zoo untouched, so all its options work (``--eval-freq``, ``--save-freq``,
``-optimize``, ``--storage``, ``--hyperparams``, ...), with three NFQ defaults added when they are not given:
``--algo nfq``; for ``train`` with NFQ, ``--conf-file`` pointing to the packaged ``sb3_nfq/hyperparams/nfq.yml``
(the hand-edited entries of :mod:`sb3_nfq.configs`, their ``callback`` key included); for ``enjoy`` with NFQ,
``--folder logs`` (where ``train`` writes; the zoo's default folder holds downloaded agents, and none exist for NFQ).

``train -optimize`` is the project's one way to tune NFQ's hyperparameters: Optuna, with the search space below.

:func:`register` adds NFQ to ``rl_zoo3.utils.ALGOS`` and its Optuna search space (:func:`sample_nfq_params`,
:func:`convert_nfq_params`) to the zoo's ``HYPERPARAMS_SAMPLER`` / ``HYPERPARAMS_CONVERTER``, for code that
drives the zoo's ``ExperimentManager`` itself.

``rl_zoo3``, ``optuna`` and ``requests`` (imported by the zoo's ``enjoy`` but not declared by it) come with
the ``zoo`` extra (``pip install ".[zoo]"`` in a checkout); this module imports them only when a command runs.
"""

import argparse
import os
import socket
import sys
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import torch as th

from sb3_nfq.configs import ZOO_FILE, zoo_to_kwargs
from sb3_nfq.nfq import NFQ

if TYPE_CHECKING:
    import optuna

#: The algorithm's name in the zoo (``--algo nfq``, ``logs/nfq/...``, ``hyperparams/nfq.yml``).
ALGO_NAME = "nfq"
#: The zoo hyperparameter file shipped with the package, used when ``train`` gets no ``--conf-file``.
DEFAULT_CONF_FILE = ZOO_FILE
#: Where ``enjoy`` looks for agents when it gets no ``--folder`` (the zoo's ``train`` default, ``-f logs``).
DEFAULT_ENJOY_FOLDER = "logs"
#: The zoo commands this launcher runs.
COMMANDS = ("train", "enjoy")

# Optuna search space (the zoo's ``hyperparams_opt.py`` pattern). ``trial.params`` holds the raw choices below;
# :func:`convert_nfq_params` turns them into NFQ keyword arguments. It covers the textbook's fresh memory and the
# growing memory of the benchmark's configs, and it sets every key that decides the memory and the fit, so that no
# key of the env's entry (a ``round_fraction``, a ``huber_delta``) is left half-applied to a sampled memory or loss.

#: ``net_arch`` choices, by name (``"textbook"`` is the book's 512 -> 128).
NET_ARCHS: dict[str, list[int]] = {
    "small": [64, 64],
    "medium": [256, 256],
    "textbook": [512, 128],
}
#: ``optimizer_class`` choices, by name.
OPTIMIZERS: dict[str, type[th.optim.Optimizer]] = {
    "rmsprop": th.optim.RMSprop,
    "adam": th.optim.Adam,
}
#: Categorical hyperparameters passed to NFQ as they are sampled: one row per NFQ keyword argument.
#: Adding a row adds it to the search space.
CATEGORICAL_SPACE: dict[str, tuple[bool | int | float | str | None, ...]] = {
    "train_freq": (64, 128, 256, 512, 1024, 2048, 4096),  # transitions per round (the book's E = 1024)
    "memory": ("fresh", "growing"),  # the book's, or the 2005 paper's (with a buffer_size below)
    "target_mode": ("recompute_every_step", "fixed_per_iteration"),
    "gamma": (0.95, 0.98, 0.99, 0.995, 0.999, 1.0),
    "batch_size": (None, 64, 256, 1024),  # None: one full-batch step per fitted iteration (the book)
    "loss": ("mse", "huber"),
    "max_grad_norm": (None, 10.0),
    "exploration_repeat_mu": (None, 2.0),  # one-step random actions (the book), or repeated for n ~ Zeta(2) steps
    "exploration_start": ("first_step", "first_termination"),  # epsilon's schedule from the start, or the first goal
    "n_steps": (1, 3, 5),  # one-step TD targets (the book), or n-step returns
}
#: ``buffer_size`` choices, sampled for ``memory="growing"`` only (a fresh memory holds one round).
BUFFER_SIZES = (10_000, 20_000, 50_000)
#: ``iteration_transitions`` choices, sampled for ``memory="growing"`` only (a fresh memory holds one round): each
#: fitted iteration over the whole memory (the book), or over that many of its transitions drawn at random.
ITERATION_TRANSITIONS = (None, 5_000, 10_000)
#: ``huber_delta`` choices, sampled for ``loss="huber"`` only.
HUBER_DELTAS = (1.0, 5.0, 10.0)
#: ``policy_kwargs["n_critics"]`` choices: one Q-network (the book), or an ensemble (LunarLander's entry).
N_CRITICS = (1, 2, 3)
#: ``exploration_ucb`` choices, sampled for an ensemble only (``n_critics`` above 1).
EXPLORATION_UCBS = (None, 1.0, 3.0)
#: Range of ``fit_cost``: transitions fitted per transition collected, ``gradient_steps * N / train_freq``
#: with ``N`` a fitted iteration's transitions: the memory (one round; or ``buffer_size``, which a growing memory
#: fills), or ``iteration_transitions`` where that is fewer. It sets a round's fitted iterations, rounded and at least
#: 1, so a trial's compute per env step and Q-network (the book's: 40) is its ``fit_cost`` rounded to a whole multiple
#: of ``N / train_freq``, and at least ``N / train_freq``.
FIT_COST = (5.0, 250.0)


def sample_nfq_params(
    trial: "optuna.trial.BaseTrial", n_actions: int, n_envs: int, additional_args: dict[str, Any]
) -> dict[str, Any]:
    """
    Sampler for NFQ hyperparameters, with the signature of the zoo's ``HYPERPARAMS_SAMPLER`` entries.

    It also records which process ran the trial (``trial.user_attrs["worker"]``, ``"<hostname>:<pid>"``),
    which shows how the workers of a shared study (``--storage``) divided the trials.

    :param trial: the Optuna trial to sample from (a ``FixedTrial`` gives a chosen point)
    :param n_actions: number of continuous actions (unused: NFQ has Discrete actions)
    :param n_envs: number of environments (unused: ``train_freq`` counts transitions over all envs)
    :param additional_args: the zoo's extra arguments (HER settings; unused)
    :return: NFQ keyword arguments, ``policy_kwargs`` included
    """
    trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
    sampled: dict[str, Any] = {
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 1e-2, log=True),
        "lr_schedule": trial.suggest_categorical("lr_schedule", ["constant", "linear"]),  # linear: to 0 at the budget
        "fit_cost": trial.suggest_float("fit_cost", *FIT_COST, log=True),
        "exploration_initial_eps": trial.suggest_float("exploration_initial_eps", 0.05, 1.0),
        "exploration_final_eps": trial.suggest_float("exploration_final_eps", 0.0, 0.5),
        "exploration_fraction": trial.suggest_float("exploration_fraction", 0.05, 1.0),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCHS)),
        "optimizer": trial.suggest_categorical("optimizer", list(OPTIMIZERS)),
    }
    for name, choices in CATEGORICAL_SPACE.items():
        sampled[name] = trial.suggest_categorical(name, choices)
    if sampled["memory"] == "growing":
        sampled["buffer_size"] = trial.suggest_categorical("buffer_size", BUFFER_SIZES)
        sampled["iteration_transitions"] = trial.suggest_categorical("iteration_transitions", ITERATION_TRANSITIONS)
    sampled["n_critics"] = trial.suggest_categorical("n_critics", N_CRITICS)
    if sampled["n_critics"] > 1:
        sampled["exploration_ucb"] = trial.suggest_categorical("exploration_ucb", EXPLORATION_UCBS)
    if sampled["loss"] == "huber":
        sampled["huber_delta"] = trial.suggest_categorical("huber_delta", HUBER_DELTAS)
    # The zoo applies the sampled values after turning its file's "lin_<x>" strings into schedules: do it here.
    return zoo_to_kwargs(convert_nfq_params(sampled))


def convert_nfq_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """
    Turn sampled values (``trial.params``) into NFQ keyword arguments, as the zoo's ``HYPERPARAMS_CONVERTER``
    entries do: it is also how ``train --storage ... --study-name ... --trial-id N`` trains with a stored trial.

    :param sampled_params: raw sampled values: NFQ keyword arguments, plus ``net_arch``, ``optimizer`` and
        ``n_critics`` for ``policy_kwargs`` (the first two as names from :data:`NET_ARCHS` and :data:`OPTIMIZERS`),
        ``lr_schedule`` (``"linear"``: ``learning_rate`` decays linearly to 0 at the budget, written as the zoo's
        ``"lin_<x>"``), and ``fit_cost`` (see :data:`FIT_COST`), which with ``memory`` and ``iteration_transitions``
        (``None`` where not sampled: studies of the past fitted the whole memory) sets ``gradient_steps``,
        ``buffer_size`` and the round schedule; a stored trial's ``fit_epochs`` (searched in studies of the past)
        groups a round's epochs into iterations
    :return: NFQ keyword arguments, with ``net_arch``, ``optimizer_class`` and ``n_critics`` in ``policy_kwargs``
        (``exploration_ucb`` is ``None`` where not sampled, over an ensemble entry's: studies of the past had one
        Q-network)
    """
    hyperparams = dict(sampled_params)
    if hyperparams.pop("lr_schedule", "constant") == "linear":  # the zoo's format, which `--trial-id` reads
        hyperparams["learning_rate"] = f"lin_{hyperparams['learning_rate']!r}"
    if "fit_cost" in hyperparams:
        growing = hyperparams["memory"] == "growing"
        memory_size = hyperparams["buffer_size"] if growing else hyperparams["train_freq"]
        hyperparams["iteration_transitions"] = hyperparams.get("iteration_transitions")  # over an entry's
        iteration_size = min(hyperparams["iteration_transitions"] or memory_size, memory_size)
        # The round's fitted iterations, one epoch of iteration_size transitions each. A trial stored with fit_epochs
        # (whole memory) ran them grouped into whole iterations of at most fit_epochs epochs each (the rounding fits
        # 0.73x to 1.33x the round's epochs): it converts as it ran.
        epochs = max(1, round(hyperparams.pop("fit_cost") * hyperparams["train_freq"] / iteration_size))
        per_iteration = min(hyperparams.get("fit_epochs", 1), epochs)  # so at least one iteration
        hyperparams |= {"gradient_steps": round(epochs / per_iteration), "fit_epochs": per_iteration}
        hyperparams["buffer_size"] = memory_size if growing else None  # a fresh memory holds one round
        hyperparams |= {"round_fraction": None, "round_fraction_offset": 0}  # rounds of train_freq
    if hyperparams.get("loss", "huber") != "huber":
        hyperparams["huber_delta"] = 1.0  # the default, over an entry's threshold for its Huber loss
    policy_kwargs: dict[str, Any] = {}
    if "net_arch" in hyperparams:
        policy_kwargs["net_arch"] = list(NET_ARCHS[hyperparams.pop("net_arch")])
    if "optimizer" in hyperparams:
        policy_kwargs["optimizer_class"] = OPTIMIZERS[hyperparams.pop("optimizer")]
    if "n_critics" in hyperparams:
        policy_kwargs["n_critics"] = hyperparams.pop("n_critics")
    if policy_kwargs:  # they replace the entry's policy_kwargs (its n_critics too), so its optimism goes as well
        hyperparams["policy_kwargs"] = policy_kwargs
        hyperparams["exploration_ucb"] = hyperparams.get("exploration_ucb")
    return hyperparams


def register() -> None:
    """
    Register NFQ in the zoo: ``ALGOS["nfq"]``, its sampler and its converter. Safe to call more than once.

    :raises ImportError: when ``rl_zoo3`` or ``optuna`` is missing, naming the extra that installs them
    """
    try:
        from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
        from rl_zoo3.utils import ALGOS
    except ImportError as error:
        raise ImportError(
            f'The RL Zoo bridge needs rl_zoo3 and optuna: the zoo extra, pip install ".[zoo]" in a checkout ({error})'
        ) from error
    ALGOS[ALGO_NAME] = NFQ
    HYPERPARAMS_SAMPLER[ALGO_NAME] = sample_nfq_params
    HYPERPARAMS_CONVERTER[ALGO_NAME] = convert_nfq_params


def zoo_arguments(command: str, args: Sequence[str]) -> list[str]:
    """
    The zoo command line for ``command``: ``args`` untouched, after the NFQ defaults they do not set themselves
    (``--algo nfq``; for NFQ, ``train``'s ``--conf-file`` and ``enjoy``'s ``--folder``, see the module docstring).
    Options are recognised as the zoo's ``argparse`` parser does, abbreviations and ``--option=value`` included.

    :param command: ``"train"`` or ``"enjoy"``
    :param args: the arguments after the command
    :return: the arguments to run the zoo's command with
    """
    parser = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    parser.add_argument("--algo")
    if command == "train":
        parser.add_argument("-conf", "--conf-file")
    else:
        parser.add_argument("-f", "--folder")
    try:
        given, _ = parser.parse_known_args(list(args))
    except argparse.ArgumentError:  # malformed: let the zoo's parser report it
        return list(args)
    defaults: list[str] = []
    if given.algo is None:
        defaults += ["--algo", ALGO_NAME]
    if (given.algo or ALGO_NAME) == ALGO_NAME:
        if command == "train" and given.conf_file is None:
            defaults += ["--conf-file", str(DEFAULT_CONF_FILE)]
        if command == "enjoy" and given.folder is None:
            defaults += ["--folder", DEFAULT_ENJOY_FOLDER]
    return [*defaults, *args]


def _zoo_command(command: str) -> Callable[[], None]:
    """
    :param command: ``"train"`` or ``"enjoy"``
    :return: the zoo's function for it (imported here: the zoo is an optional dependency)
    """
    try:
        if command == "train":
            from rl_zoo3.train import train

            return train
        from rl_zoo3.enjoy import enjoy

        return enjoy
    except ImportError as error:
        raise ImportError(
            f'`{command}` needs rl_zoo3, optuna and requests: the zoo extra, pip install ".[zoo]" in a checkout '
            f"({error})"
        ) from error


USAGE = f"""usage: python -m sb3_nfq.zoo {{{",".join(COMMANDS)}}} [RL Zoo arguments ...]

Run the RL Baselines3 Zoo (rl_zoo3) with NFQ registered as --algo nfq.

commands:
  train   rl_zoo3's train: training, --eval-freq, --save-freq, -optimize (Optuna), --storage, ...
  enjoy   rl_zoo3's enjoy: run a trained agent

Arguments go to the zoo untouched; defaults added when absent: --algo nfq, and for NFQ
train --conf-file {DEFAULT_CONF_FILE} and enjoy --folder {DEFAULT_ENJOY_FOLDER}.
`python -m sb3_nfq.zoo train --help` lists the zoo's options.

examples:
  python -m sb3_nfq.zoo train --env CartPole-v1 --eval-freq 10000 --save-freq 50000
  python -m sb3_nfq.zoo enjoy --env CartPole-v1 --no-render -n 1000
  python -m sb3_nfq.zoo train --env CartPole-v1 -optimize --n-trials 20 -n 50000 \\
      --storage nfq_study.log --study-name nfq-cartpole --no-optim-plots
"""


def main(argv: Sequence[str] | None = None) -> int:
    """
    Run ``python -m sb3_nfq.zoo COMMAND [ARGS ...]``.

    :param argv: the arguments after the program name (default: ``sys.argv[1:]``)
    :return: the exit status (0 on success, 2 for an unknown command)
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0
    command, args = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"error: unknown command {command!r}, expected one of {', '.join(COMMANDS)}\n", file=sys.stderr)
        print(USAGE, file=sys.stderr)
        return 2
    run = _zoo_command(command)
    register()
    saved_argv = sys.argv
    # The zoo's commands parse sys.argv; argv[0] names the command in their usage messages.
    sys.argv = [f"python -m sb3_nfq.zoo {command}", *zoo_arguments(command, args)]
    try:
        run()
    finally:
        sys.argv = saved_argv
    return 0


if __name__ == "__main__":
    sys.exit(main())
