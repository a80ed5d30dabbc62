"""
NFQ's hyperparameters as data: ``sb3_nfq/hyperparams/nfq.yml`` (:data:`ZOO_FILE`), edited by hand in the RL
Baselines3 Zoo's format (one entry per env id, ``default`` for the others, ``atari`` for every Atari game; each entry
says where it was measured), and the reading of a zoo entry as the RL Zoo's ``ExperimentManager`` reads it.

.. code-block:: python

    from sb3_nfq import NFQ
    from sb3_nfq.configs import nfq_callbacks, nfq_kwargs

    model = NFQ("MlpPolicy", "CartPole-v1", **nfq_kwargs("CartPole-v1"))
    model.learn(50_000, callback=nfq_callbacks("CartPole-v1"))
"""

import ast
import contextlib
import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch as th
import yaml
from stable_baselines3.common.callbacks import BaseCallback
from torch import nn

#: The hyperparameter file shipped with the package, read by the RL Zoo bridge (``python -m sb3_nfq.zoo train``).
ZOO_FILE = Path(__file__).resolve().parent / "hyperparams" / "nfq.yml"
#: The entry of every env without one of its own (the RL Zoo's convention).
DEFAULT_ENTRY = "default"
#: Keys of a zoo entry that :func:`nfq_kwargs` leaves out, each for its place: the budget (``learn``'s
#: ``total_timesteps``), the policy (``NFQ``'s first argument), the number of envs (the env's) and the callbacks
#: (``learn``'s ``callback``, built by :func:`nfq_callbacks`).
ZOO_KEYS = ("n_timesteps", "policy", "n_envs", "callback")
#: Keys of a zoo entry that build the env (wrappers, frame stacking), which ``NFQ`` is given: :func:`nfq_kwargs`
#: refuses an entry with one (``normalize`` included, when it normalises).
ENV_KEYS = ("env_wrapper", "vec_env_wrapper", "frame_stack", "env_kwargs", "monitor_kwargs")


def read_entry(env_id: str, path: Path = ZOO_FILE) -> dict[str, Any]:
    """
    :param env_id: a gymnasium env id: its entry, or the file's ``default`` entry if it has none (the zoo gives an
        Atari game the ``atari`` entry, which ``"atari"`` names here)
    :param path: a zoo-format YAML file
    :return: the entry as written (plain data: ``policy_kwargs`` a string, ``n_timesteps`` included)
    :raises KeyError: when the file has neither an entry for ``env_id`` nor a ``default`` one, naming those it has
    """
    table = yaml.safe_load(Path(path).read_text())
    entry = table.get(env_id, table.get(DEFAULT_ENTRY))
    if entry is None:
        raise KeyError(f"{path} has no entry for {env_id} and no {DEFAULT_ENTRY!r} entry; it has {sorted(table)}")
    return dict(entry)


def _linear_schedule(initial: float) -> Callable[[float], float]:
    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def zoo_to_kwargs(entry: dict[str, Any]) -> dict[str, Any]:
    """
    Turn zoo-style plain data into constructor kwargs, as the RL Zoo's ExperimentManager does: ``policy_kwargs``
    strings are evaluated (with ``dict``, ``nn`` and ``th`` in scope), ``"lin_<x>"`` learning rates become linear
    schedules, ``train_freq`` lists become tuples.

    :param entry: an entry's kwargs (without the keys of :data:`ZOO_KEYS`)
    :return: kwargs for the SB3 constructor
    """
    out = dict(entry)
    if isinstance(out.get("policy_kwargs"), str):
        out["policy_kwargs"] = eval(out["policy_kwargs"], {"__builtins__": {}, "dict": dict, "nn": nn, "th": th})
    if isinstance(out.get("learning_rate"), str):
        kind, value = out["learning_rate"].split("_")
        if kind != "lin":
            raise ValueError(f"unknown learning-rate schedule {out['learning_rate']!r} (the Zoo's 'lin_<x>' only)")
        out["learning_rate"] = _linear_schedule(float(value))
    if isinstance(out.get("train_freq"), list):
        out["train_freq"] = tuple(out["train_freq"])
    return out


def vec_normalize_kwargs(normalize: bool | str | dict[str, Any], gamma: float | None = None) -> dict[str, Any] | None:
    """
    Read a zoo entry's ``normalize`` key as the RL Zoo's ExperimentManager does: ``true`` normalises observations
    and rewards with ``VecNormalize``'s defaults, a dict (or a string of one, such as
    ``"{'norm_obs': True, 'norm_reward': False}"``) gives ``VecNormalize``'s arguments; the entry's discount, when it
    has one, is the one rewards are normalised with.

    :param normalize: the entry's ``normalize`` value
    :param gamma: the entry's ``gamma``, if it sets one
    :return: keyword arguments for ``VecNormalize`` (the training env's), or ``None`` for no normalisation
    """
    value: Any = normalize
    if isinstance(value, str):
        with contextlib.suppress(ValueError, SyntaxError):  # not a literal: refused below, as written
            value = ast.literal_eval(value)
    if value is False:
        return None
    if value is True:
        kwargs: dict[str, Any] = {}
    elif isinstance(value, dict):
        kwargs = dict(value)
    else:
        raise ValueError(f"normalize must be true, false or a dict of VecNormalize arguments, got {normalize!r}")
    if gamma is not None:
        kwargs["gamma"] = gamma
    return kwargs


def nfq_kwargs(env_id: str, path: Path = ZOO_FILE) -> dict[str, Any]:
    """
    The entry's ``NFQ`` keyword arguments. The keys of :data:`ZOO_KEYS` are left out, each for its place: the budget
    ``n_timesteps`` is ``learn``'s, ``policy`` is ``NFQ``'s first argument, ``n_envs`` is the env's, and ``callback``
    is ``learn``'s, built by :func:`nfq_callbacks`.

    :param env_id: a gymnasium env id (or ``"atari"``): its entry, or the file's ``default`` entry (see
        :func:`read_entry`)
    :param path: a zoo-format YAML file
    :return: the entry as ``NFQ`` keyword arguments
    :raises ValueError: when the entry builds the env: it normalises it (``normalize``), which is the env's, not
        ``NFQ``'s, so ``NFQ`` must be given the env wrapped in ``VecNormalize(env, **vec_normalize_kwargs(...))``;
        or it sets a key of :data:`ENV_KEYS` (the zoo's wrappers, frame stacking): train it with
        ``python -m sb3_nfq.zoo train``, which builds the env as the zoo does
    """
    entry = read_entry(env_id, path)
    if vec_normalize_kwargs(entry.get("normalize", False)) is not None:
        raise ValueError(
            f"{path}'s entry for {env_id} normalises the env (normalize: {entry['normalize']!r}), which no NFQ "
            "argument does: wrap the env in VecNormalize(env, **vec_normalize_kwargs(entry['normalize'], "
            "entry.get('gamma'))) (entry = read_entry(env_id, path)), pass it to NFQ with the other keys, or train it "
            "with `python -m sb3_nfq.zoo train`, which does both"
        )
    env_keys = [key for key in ENV_KEYS if key in entry]
    if env_keys:
        raise ValueError(
            f"{path}'s entry for {env_id} builds the env ({', '.join(env_keys)}), which no NFQ argument does: build "
            "the env as the RL Zoo does and pass it to NFQ with the other keys of read_entry(env_id, path), or train "
            "it with `python -m sb3_nfq.zoo train`, which does both"
        )
    kwargs = {key: value for key, value in entry.items() if key not in ZOO_KEYS and key != "normalize"}
    return zoo_to_kwargs(kwargs)


def _callback_class(name: Any, env_id: str, path: Path) -> type[BaseCallback]:
    """
    :param name: a class path, such as ``"sb3_nfq.KeepBestCallback"``
    :param env_id: the entry's env id (for the error message)
    :param path: the entry's file (for the error message)
    :return: the ``BaseCallback`` subclass it names
    """
    where = f"callback {name!r} of {path}'s entry for {env_id}"
    if not isinstance(name, str) or "." not in name:
        raise ValueError(f"{where}: expected a class path such as 'package.module.ClassName'")
    module_name, _, class_name = name.rpartition(".")
    try:
        found = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as error:
        raise ValueError(f"{where}: cannot import it ({error})") from error
    if not (isinstance(found, type) and issubclass(found, BaseCallback)):
        raise ValueError(f"{where}: {found!r} is not a stable_baselines3 BaseCallback class")
    return found


def nfq_callbacks(env_id: str, path: Path = ZOO_FILE) -> list[BaseCallback]:
    """
    The callbacks of the entry's ``callback`` key, for ``learn(callback=...)``, built as the RL Zoo builds them: a
    class path (``callback: sb3_nfq.KeepBestCallback``), or a list of class paths and one-key dicts of a class path
    to its keyword arguments (``- stable_baselines3.common.callbacks.StopTrainingOnMaxEpisodes: {max_episodes: 5}``).

    :param env_id: a gymnasium env id (or ``"atari"``): its entry, or the file's ``default`` entry (see
        :func:`read_entry`)
    :param path: a zoo-format YAML file
    :return: a new instance of each callback the entry names, in its order (none when it has no ``callback`` key)
    :raises ValueError: when an item is not a class path of a ``BaseCallback`` subclass that imports, or a dict of
        more than one key
    """
    value = read_entry(env_id, path).get("callback")
    items = [] if value is None else value if isinstance(value, list) else [value]
    callbacks = []
    for item in items:
        kwargs: dict[str, Any] = {}
        if isinstance(item, dict):
            if len(item) != 1:
                raise ValueError(
                    f"callback {item!r} of {path}'s entry for {env_id}: expected one class path, with its keyword "
                    "arguments"
                )
            ((item, kwargs),) = item.items()
        callbacks.append(_callback_class(item, env_id, path)(**(kwargs or {})))
    return callbacks
