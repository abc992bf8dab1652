"""The constraint files agree with pyproject.toml: constraints/floors.txt pins every direct
dependency at the floor pyproject declares (what `make test-floors` tests), and
constraints/lock.txt (the tested set of the development venv) satisfies every requirement."""

from __future__ import annotations

from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

ROOT = Path(__file__).resolve().parents[1]


def declared() -> dict[str, Requirement]:
    """Every direct dependency of the core and of all extras (not safenav's own extras)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    lines = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        lines += extra
    reqs = [Requirement(line) for line in lines]
    return {canonicalize_name(r.name): r for r in reqs if canonicalize_name(r.name) != "safenav"}


def pins(name: str) -> dict[str, Version]:
    out = {}
    for line in (ROOT / "constraints" / name).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            package, version = line.split("==")
            out[canonicalize_name(package)] = Version(version)
    return out


def test_floors_pin_every_dependency_at_its_declared_floor():
    reqs, floors = declared(), pins("floors.txt")
    assert set(floors) == set(reqs)
    for name, req in reqs.items():
        lower = [Version(s.version) for s in req.specifier if s.operator == ">="]
        assert len(lower) == 1, f"{name}: declare one '>=' floor, got {req.specifier}"
        assert floors[name] == lower[0], f"{name}: floors.txt {floors[name]}, pyproject {req}"


def test_lock_satisfies_every_declared_requirement():
    reqs, lock = declared(), pins("lock.txt")
    for name, req in reqs.items():
        if req.marker is not None and not req.marker.evaluate():
            continue  # not for this Python (tomli before 3.11)
        assert name in lock, f"{name} is missing from lock.txt"
        assert req.specifier.contains(lock[name], prereleases=True), f"lock {lock[name]}, {req}"
