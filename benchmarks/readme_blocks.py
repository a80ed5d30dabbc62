"""
Measured tables that the top-level README shows: each script writes its results (JSON and a markdown table) and puts
the table between its own pair of markers in README.md, so the README holds no number copied by hand.
"""

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

README = Path(__file__).resolve().parent.parent / "README.md"


def replace_block(text: str, markers: tuple[str, str], block: str) -> str:
    """:return: ``text`` with ``block`` between the two markers (which stay)"""
    start, end = text.index(markers[0]) + len(markers[0]), text.index(markers[1])
    return text[:start] + "\n" + block + "\n" + text[end:]


def publish(
    out: Path, results: Sequence[dict[str, Any]], block: str, markers: tuple[str, str], readme: Path | None = README
) -> None:
    """
    Write ``out`` (the results with the machine and package versions), ``out`` with a ``.md`` suffix (the table)
    and, unless ``readme`` is ``None``, the table into the README between ``markers``.

    :param out: the JSON results file
    :param results: one record per measured run
    :param block: the markdown table of the results
    :param markers: the README's markers around the table
    :param readme: the README to update, or ``None``
    """
    from benchmarks.run import machine_line, package_versions

    out.parent.mkdir(parents=True, exist_ok=True)
    payload = {"machine": machine_line(), "versions": package_versions(), "results": list(results)}
    out.write_text(json.dumps(payload, indent=2) + "\n")
    out.with_suffix(".md").write_text(block + "\n")
    if readme is not None:
        readme.write_text(replace_block(readme.read_text(), markers, block))


def script_parser(description: str | None, default_out: Path) -> argparse.ArgumentParser:
    """
    :param description: the script's docstring
    :param default_out: where its results JSON goes by default
    :return: a measurement script's command-line parser, with its ``--out``
    """
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=default_out, help="the results JSON (the table goes beside it)")
    return parser
