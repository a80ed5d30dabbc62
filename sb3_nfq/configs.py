"""
The NFQ configs this project ships and measures, as data: zoo-format YAML files in ``sb3_nfq/hyperparams/``
(``nfq.yml``, read by the RL Zoo bridge, and named variants such as ``nfq-shared.yml``), and the conversion of their
entries into ``NFQ`` keyword arguments, as the RL Zoo does it.

.. code-block:: python

    from sb3_nfq import NFQ
    from sb3_nfq.configs import nfq_kwargs

    model = NFQ("MlpPolicy", "CartPole-v1", **nfq_kwargs("nfq-shared", "CartPole-v1"))
"""

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch as th
import yaml
from torch import nn

#: Where the YAML files live (shipped with the package).
HYPERPARAMS_DIR = Path(__file__).resolve().parent / "hyperparams"
#: Keys of a zoo entry that are not ``NFQ`` keyword arguments: the budget, the policy and the number of envs.
ZOO_KEYS = ("n_timesteps", "policy", "n_envs")


def config_names() -> list[str]:
    """:return: the configs shipped: one per YAML file in :data:`HYPERPARAMS_DIR`"""
    return sorted(path.stem for path in HYPERPARAMS_DIR.glob("*.yml"))


def read_entry(name: str, env_id: str) -> dict[str, Any]:
    """
    :param name: a config name (see :func:`config_names`)
    :param env_id: a gymnasium env id with an entry in that file
    :return: the entry as written (plain data: ``policy_kwargs`` a string, ``n_timesteps`` included)
    """
    path = HYPERPARAMS_DIR / f"{name}.yml"
    if not path.is_file():
        raise KeyError(f"no config named {name!r}; shipped: {config_names()}")
    table = yaml.safe_load(path.read_text())
    if env_id not in table:
        raise KeyError(f"config {name!r} has no entry for {env_id}; it has {sorted(table)}")
    return dict(table[env_id])


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


def nfq_kwargs(name: str, env_id: str) -> dict[str, Any]:
    """
    :param name: a config name (see :func:`config_names`)
    :param env_id: a gymnasium env id with an entry in that file
    :return: the entry as ``NFQ`` keyword arguments (its budget, policy and number of envs left out)
    """
    entry = read_entry(name, env_id)
    return zoo_to_kwargs({key: value for key, value in entry.items() if key not in ZOO_KEYS})
