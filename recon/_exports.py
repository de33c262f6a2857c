"""Lazy public names of a package: each loaded from its module on first use (PEP 562), so that
``import recon`` stays light and the console starts fast."""

from __future__ import annotations

import importlib
from collections.abc import Callable


def lazy(package: str, exports: dict[str, str]) -> tuple[Callable, Callable]:
    """``__getattr__`` and ``__dir__`` for ``package``, whose public ``name`` lives in the module
    ``exports[name]``."""

    def __getattr__(name: str):
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(module), name)

    def __dir__() -> list[str]:
        return sorted(exports)

    return __getattr__, __dir__
