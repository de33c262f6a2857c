"""The packages' public names: each resolves to the object its module defines, loaded on first
use (a bare ``import recon`` loads none of the science)."""

from __future__ import annotations

import ast
import importlib
import inspect
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("recon", "registration", "trajectories", "assessment", "sim.phantoms")


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_name_resolves_to_its_module_object(package):
    module = importlib.import_module(package)
    assert module.__all__ and sorted(module.__all__) == sorted(set(module.__all__))
    for name in module.__all__:
        obj = getattr(module, name)
        home = importlib.import_module(getattr(obj, "__module__", package) or package)
        assert getattr(home, name, obj) is obj, (package, name)
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        module.nothing_here  # noqa: B018


def test_importing_the_packages_loads_no_module_until_a_name_is_used():
    code = (
        "import sys, recon, registration, trajectories, assessment; "
        "print(' '.join(m for m in ('recon.fdk', 'registration.tracker', 'pinocchio', "
        "'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == []


def _public_callables(module):
    for name in module.__all__:
        obj = getattr(module, name)
        if inspect.isclass(obj):
            for key, member in vars(obj).items():
                if inspect.isfunction(member) and not key.startswith("_"):
                    yield f"{name}.{key}", member
        elif callable(obj):
            yield name, obj


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_function_documents_its_arguments(package):
    """An exported function or method that takes arguments has an Args section naming each."""
    missing = []
    for name, func in _public_callables(importlib.import_module(package)):
        try:
            parameters = [p for p in inspect.signature(func).parameters if p not in ("self", "cls")]
        except (TypeError, ValueError):
            continue
        doc = inspect.getdoc(func) or ""
        args = doc.partition("Args:")[2]
        undocumented = [p for p in parameters if f"\n    {p}:" not in "\n" + args]
        if parameters and undocumented:
            missing.append(f"{name}: {undocumented}")
    assert not missing, missing


@pytest.mark.parametrize("package", ["recon", "registration", "trajectories", "assessment"])
def test_the_stub_lists_every_exported_name_from_its_module(package):
    """A type checker reads ``__init__.pyi`` where the package's names load lazily: it imports
    every exported name, each from the module that holds it, and nothing else."""
    stub = ast.parse((ROOT / package / "__init__.pyi").read_text(encoding="utf-8"))
    listed = {
        alias.name: node.module
        for node in stub.body
        if isinstance(node, ast.ImportFrom)
        for alias in node.names
        if alias.asname == alias.name
    }
    assert listed == importlib.import_module(package)._EXPORTS
