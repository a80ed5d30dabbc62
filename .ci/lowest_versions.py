"""
Print the project's core dependencies pinned to the lowest versions ``pyproject.toml`` declares (``name>=X`` becomes
``name==X``), one per line, for the lowest-versions check (``make test-lowest``).
"""

import re
import sys
from pathlib import Path

import tomllib


def lowest_pins(pyproject: Path) -> list[str]:
    """
    :param pyproject: the project's ``pyproject.toml``
    :return: ``name==lowest`` for each dependency with a lower bound, the others as declared
    """
    dependencies = tomllib.loads(pyproject.read_text())["project"]["dependencies"]
    pins = []
    for requirement in dependencies:
        match = re.search(r">=\s*([0-9][0-9A-Za-z.]*)", requirement)
        name = re.split(r"[<>=!~\[; ]", requirement, maxsplit=1)[0]
        pins.append(f"{name}=={match.group(1)}" if match else requirement)
    return pins


if __name__ == "__main__":
    print("\n".join(lowest_pins(Path(sys.argv[1] if len(sys.argv) > 1 else "pyproject.toml"))))
