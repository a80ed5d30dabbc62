"""
Telling an NFQ checkpoint from anything else before SB3 loads it, loading those of earlier versions, and loading one
without unpickling: SB3 stores what JSON cannot hold (spaces, schedules, classes) as cloudpickle, which runs code when
it is loaded.
"""

import io
import json
import pathlib
import warnings
import zipfile
from typing import Any, NoReturn

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.save_util import load_from_zip_file, open_path
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import FloatSchedule, LinearSchedule

from sb3_nfq.parameters import RETIRED_PARAMETERS
from sb3_nfq.policies import NFQPolicy


def check_nfq_checkpoint(path: str | pathlib.Path | io.BufferedIOBase, custom_objects: dict[str, Any] | None) -> None:
    """
    Raise a ``ValueError`` unless ``path`` holds a model saved by ``NFQ.save`` (not, say, a DQN zip or a corrupt file).

    :param path: the file, or a file-like (left at the position it was at)
    :param custom_objects: as for ``NFQ.load``
    """
    start = path.tell() if isinstance(path, io.BufferedIOBase) else None
    try:
        data, _, _ = load_from_zip_file(path, load_data=True, custom_objects=custom_objects, device="cpu")
    except FileNotFoundError:
        raise
    except Exception as error:
        raise ValueError(f"{path} is not an NFQ checkpoint (a zip saved by NFQ.save): {error}") from error
    finally:
        if start is not None:
            path.seek(start)  # type: ignore[union-attr]
    policy_class = (data or {}).get("policy_class")
    if not (isinstance(policy_class, type) and issubclass(policy_class, NFQPolicy)):
        found = getattr(policy_class, "__name__", policy_class)
        raise ValueError(f"{path} is not an NFQ checkpoint: it holds a {found} policy, not an NFQ policy")


def train_freq_json(train_freq: TrainFreq | Any) -> list[int | str]:
    """
    :param train_freq: NFQ's ``train_freq`` once the model has set up
    :return: it as plain JSON, saved beside SB3's pickle of it, for ``NFQ.load(safe=True)``
    """
    assert isinstance(train_freq, TrainFreq)
    return [train_freq.frequency, train_freq.unit.value]


def drop_retired(
    attributes: dict[str, Any],
    load_path_or_dict: str | pathlib.Path | io.BufferedIOBase | dict[str, Any],
    device: th.device | str,
) -> dict[str, Any]:
    """
    Drop what a model saved by an earlier version holds for the parameters NFQ no longer has
    (:data:`~sb3_nfq.parameters.RETIRED_PARAMETERS`), with a ``UserWarning`` naming what was dropped where it changes
    what the model does (a value other than the one that did what NFQ does now, or a network). In ``NFQ.load``, SB3
    has already put the zip's data on the model, so its retired attributes are dropped too.

    :param attributes: the model's attributes, the zip's data among them (changed in place)
    :param load_path_or_dict: the zip (or a file-like), or its networks and optimizer states
    :param device: where to load the zip's tensors
    :return: the networks and optimizer states without the retired networks
    """
    if isinstance(load_path_or_dict, dict):
        params = load_path_or_dict
    else:
        _, params, _ = load_from_zip_file(load_path_or_dict, device=device, load_data=False)
    dropped = []
    for name, retired in RETIRED_PARAMETERS.items():
        value = attributes.pop(name, retired.default)
        found = [f"{name}={value!r}"] if value != retired.default else []
        for saved in retired.saved:
            attributes.pop(saved, None)
            found += [saved] if saved in params else []
        if found:
            dropped.append(f"{', '.join(found)} ({retired.instead})")
    if dropped:
        warnings.warn(
            "This NFQ model was saved by an earlier sb3-nfq, with parameters NFQ no longer has; dropped on loading: "
            + "; ".join(dropped)
            + ". The model holds its policy's saved weights.",
            UserWarning,
            stacklevel=3,
        )
    retired_names = {saved for retired in RETIRED_PARAMETERS.values() for saved in retired.saved}
    return {name: value for name, value in params.items() if name not in retired_names}


#: Classes a safe load may put back in ``policy_kwargs``, by the text SB3 stores for them next to the pickle.
_SAFE_CLASSES: dict[str, type] = {
    str(cls): cls
    for module in (th.optim, th.nn.modules.activation)
    for cls in vars(module).values()
    if isinstance(cls, type) and issubclass(cls, th.optim.Optimizer | th.nn.Module)
}


def _read_data_json(path: str | pathlib.Path | io.BufferedIOBase) -> dict[str, Any]:
    """:return: the ``data`` entry of an SB3 zip as plain JSON, nothing unpickled"""
    file = open_path(path, "r", verbose=0, suffix="zip")
    start = file.tell()
    try:
        with zipfile.ZipFile(file) as archive:
            data = json.loads(archive.read("data").decode())
    except (zipfile.BadZipFile, KeyError) as error:
        raise ValueError(f"{path} is not an NFQ checkpoint (a zip saved by NFQ.save): {error}") from error
    finally:
        if isinstance(path, str | pathlib.Path):
            file.close()
        else:
            file.seek(start)
    return data


def _refuse(key: str, why: str) -> NoReturn:
    raise ValueError(
        f"NFQ.load(safe=True) cannot rebuild the checkpoint's {key!r} without unpickling it: {why}. Pass it in "
        f"custom_objects={{{key!r}: ...}}, or, for a checkpoint you trust, use NFQ.load(safe=False)."
    )


def _policy_class(stored: dict[str, Any], aliases: dict[str, type]) -> type:
    """:return: the NFQ policy class whose module and docstring the checkpoint stored next to its pickle"""
    matches = {
        cls
        for cls in aliases.values()
        if (cls.__module__, cls.__doc__) == (stored.get("__module__"), stored.get("__doc__"))
    }
    if len(matches) != 1:
        _refuse("policy_class", "it is not one of NFQ's MlpPolicy, CnnPolicy, MultiInputPolicy")
    return matches.pop()


def _policy_kwargs(stored: dict[str, Any]) -> dict[str, Any]:
    """:return: ``policy_kwargs`` from the plain values and torch optimizer/activation classes SB3 stored beside it"""
    kwargs = {}
    for name, value in stored.items():
        if name.startswith(":"):
            continue
        if isinstance(value, str):  # SB3 stores str(value) for what JSON cannot hold: only known classes come back
            if value not in _SAFE_CLASSES:
                _refuse("policy_kwargs", f"its {name!r} is {value}, not a torch optimizer or activation class")
            kwargs[name] = _SAFE_CLASSES[value]
        else:
            kwargs[name] = value
    return kwargs


def _observation_space(stored: dict[str, Any], env: Any) -> spaces.Space:
    """:return: the env's observation space, if it has the stored shape and dtype; else one rebuilt from plain text"""
    if env is not None:
        space = env.observation_space
        if list(space.shape or []) != list(stored.get("_shape") or []) or str(space.dtype) != str(stored.get("dtype")):
            raise ValueError(
                f"The env's observation space {space} does not match the checkpoint's (shape {stored.get('_shape')}, "
                f"dtype {stored.get('dtype')})"
            )
        return space
    if ":type:" in stored and stored[":type:"] == str(spaces.Box):
        try:
            low, high = (np.array(stored[key].strip("[]").split(), dtype=np.float64) for key in ("low", "high"))
            shape = tuple(stored["_shape"])
            dtype = np.dtype(stored["dtype"])
            return spaces.Box(low.reshape(shape).astype(dtype), high.reshape(shape).astype(dtype), dtype=dtype)
        except (KeyError, ValueError, TypeError):
            pass
    _refuse("observation_space", "only a small Box is stored as plain numbers: pass env=")


def safe_custom_objects(
    path: str | pathlib.Path | io.BufferedIOBase,
    env: Any,
    custom_objects: dict[str, Any] | None,
    policy_aliases: dict[str, type],
) -> dict[str, Any]:
    """
    Replacements, built from plain JSON (and the env), for every pickled entry of an NFQ checkpoint: given to SB3's
    ``custom_objects``, they keep its loader from unpickling anything (the weights it loads with
    ``torch.load(weights_only=True)``).

    :param path: the checkpoint
    :param env: the env the model will run on, or ``None``
    :param custom_objects: the caller's replacements, used as they are
    :param policy_aliases: NFQ's policy classes
    :return: ``custom_objects`` for every pickled entry
    :raises ValueError: naming an entry that cannot be rebuilt safely
    """
    data = _read_data_json(path)
    given = dict(custom_objects or {})
    rebuilt: dict[str, Any] = {}
    pickled = {key: value for key, value in data.items() if isinstance(value, dict) and ":serialized:" in value}
    for key, stored in pickled.items():
        if key in given:
            continue
        if key == "policy_class":
            rebuilt[key] = _policy_class(stored, policy_aliases)
        elif key == "policy_kwargs":
            rebuilt[key] = _policy_kwargs(stored)
        elif key == "observation_space":
            rebuilt[key] = _observation_space(stored, env)
        elif key == "action_space":
            if stored.get(":type:") != str(spaces.Discrete):
                _refuse(key, "NFQ's actions are Discrete")
            rebuilt[key] = spaces.Discrete(int(stored["n"]), start=int(stored["start"]))
        elif key == "exploration_schedule":
            start, end, end_fraction = (stored.get(name) for name in ("start", "end", "end_fraction"))
            if not all(isinstance(value, int | float) for value in (start, end, end_fraction)):
                _refuse(key, "it is not a LinearSchedule of plain numbers")
            rebuilt[key] = LinearSchedule(float(start), float(end), float(end_fraction))  # type: ignore[arg-type]
        elif key == "learning_rate":
            _refuse(key, "it is a schedule (a function)")
        elif key == "lr_schedule":  # rebuilt from learning_rate, as NFQ's setup does
            learning_rate = given.get("learning_rate", data.get("learning_rate"))
            if not (isinstance(learning_rate, int | float) or callable(learning_rate)):
                _refuse("learning_rate", "it is a schedule (a function)")
            rebuilt[key] = FloatSchedule(learning_rate)
        elif key == "train_freq":
            plain = data.get("_train_freq_json")
            if not (isinstance(plain, list) and len(plain) == 2):
                _refuse(key, "this checkpoint predates its plain copy (_train_freq_json)")
            rebuilt[key] = TrainFreq(int(plain[0]), TrainFrequencyUnit(plain[1]))
        elif key == "replay_buffer_class":
            rebuilt[key] = None  # NFQ builds its memory itself, and sets this
        elif key in ("_last_obs", "_last_original_obs", "_last_episode_starts", "ep_info_buffer", "ep_success_buffer"):
            rebuilt[key] = None  # the next learn() resets the env and the episode statistics
        else:
            _refuse(key, "NFQ knows no plain form of it")
    return {**rebuilt, **given}
