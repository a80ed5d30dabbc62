"""Telling an NFQ checkpoint from anything else before SB3 loads it."""

import io
import pathlib
from typing import Any

from stable_baselines3.common.save_util import load_from_zip_file

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
