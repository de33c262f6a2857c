"""The house (docs/design.md): every import of every module of the packages points to
a lower floor, so no package sees one beside or above it and no package-level cycle can form.
Imports inside functions and under TYPE_CHECKING count too."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

FLOORS = {
    "configs": 0,  # the shipped YAML files as package data: imports nothing
    "recon": 1,
    "trajectories": 2,
    "calibration": 2,
    "registration": 2,
    "sim": 3,
    "assessment": 3,
    "scanner": 4,
    "study": 5,
}
"""Each package's floor: it may import the packages of the floors below it, and no other."""


def imported_packages(path: Path) -> set[str]:
    """The top-level modules a source file imports (absolute imports; relative ones stay in
    its own package)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found


def test_every_import_points_down() -> None:
    upward = []
    for package, floor in FLOORS.items():
        files = sorted((ROOT / package).rglob("*.py"))
        assert files, package
        for path in files:
            for other in imported_packages(path) & (set(FLOORS) - {package}):
                if FLOORS[other] >= floor:
                    upward.append(
                        f"{path.relative_to(ROOT)} ({package}, floor {floor}) imports "
                        f"{other} (floor {FLOORS[other]})"
                    )
    assert not upward, "\n".join(upward)


def test_every_package_has_a_floor() -> None:
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")}
    assert packages == set(FLOORS), packages ^ set(FLOORS)


def test_the_scanner_never_imports_the_simulator() -> None:
    """The scanner finds the simulated backend by name (scanner.registry; study.simulator
    registers it), never by an import: a scanner running the hardware carries no mock device."""
    arrows = [
        path.relative_to(ROOT)
        for path in sorted((ROOT / "scanner").rglob("*.py"))
        if "sim" in imported_packages(path)
    ]
    assert not arrows, arrows
