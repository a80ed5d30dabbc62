"""What the package declares and ships: license, public extras, a README that reads right as the index's page."""

import re
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
DEV_TOOLS = ("pytest", "ruff", "mypy", "types-", "build", "rliable", "matplotlib", "ray")


def test_license_is_an_spdx_expression_with_its_file() -> None:
    project = PYPROJECT["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert project["classifiers"] and project["authors"]


def test_public_extras_are_for_users_and_carry_no_development_pins() -> None:
    extras = PYPROJECT["project"]["optional-dependencies"]
    assert set(extras) == {"zoo", "offline"}
    for name, requirements in extras.items():
        for requirement in requirements:
            assert not requirement.startswith(DEV_TOOLS), (name, requirement)
    assert any(requirement.startswith("ruff") for requirement in PYPROJECT["dependency-groups"]["dev"])


def test_readme_links_work_as_the_package_long_description() -> None:
    """The README is the index's project page: a link relative to the repository would break there."""
    targets = re.findall(r"\]\(([^)]+)\)", (ROOT / "README.md").read_text())
    relative = [target for target in targets if not target.startswith(("http://", "https://", "#"))]
    assert not relative
