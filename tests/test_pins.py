"""The recorded versions (constraints.txt, installed by .ci/run) lie inside
pyproject.toml's ranges, and every direct dependency has a tested upper bound (issue 26
item 5)."""

import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.version import Version

ROOT = Path(__file__).resolve().parent.parent


def _pins() -> dict[str, Version]:
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not an exact pin"
            pins[name.lower().replace("_", "-")] = Version(version)
    return pins


def _requirements() -> list[Requirement]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return [Requirement(r) for r in project["dependencies"]
            + project["optional-dependencies"]["test"]]


def test_every_dependency_has_an_upper_bound_that_its_pin_satisfies():
    pins = _pins()
    assert "crank-jax" not in pins
    for req in _requirements():
        name = req.name.lower().replace("_", "-")
        assert any(s.operator in ("<", "<=", "~=", "==") for s in req.specifier), \
            f"{req}: no upper bound"
        assert name in pins, f"{name} is not pinned in constraints.txt"
        assert req.specifier.contains(pins[name]), f"{req} excludes the pinned {pins[name]}"


def test_ci_installs_the_pins():
    assert "-c constraints.txt" in (ROOT / ".ci" / "run").read_text()
