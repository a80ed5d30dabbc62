"""Telling an NFQ checkpoint from anything else before SB3 loads it, and loading those of earlier versions."""

import io
import pathlib
import warnings
from typing import Any

from stable_baselines3.common.save_util import load_from_zip_file

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


def drop_retired(attributes: dict[str, Any], params: dict[str, Any]) -> dict[str, Any]:
    """
    Drop what a model saved by an earlier version holds for the parameters NFQ no longer has
    (:data:`~sb3_nfq.parameters.RETIRED_PARAMETERS`), with a ``UserWarning`` naming what was dropped where it changes
    what the model does (a value other than the one that did what NFQ does now, or a network).

    :param attributes: the model's attributes, the zip's data among them (changed in place)
    :param params: the zip's networks and optimizer states
    :return: ``params`` without the retired networks
    """
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
