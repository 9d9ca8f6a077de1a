"""Lazy public APIs: a package names its exports and the submodule of each, and imports that
submodule only when the name is first used (PEP 562), so ``import brave6d.serve`` costs no torch,
Open3D or FastAPI. Every stage's ``__init__`` uses this (docs/ARCHITECTURE.md, "public APIs")."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from importlib import import_module
from typing import Any


def lazy_exports(package: str, exports: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of ``package`` for ``exports`` (name -> submodule,
    relative like ``".bundle"``); an unknown name raises the usual :class:`AttributeError`."""
    table = dict(exports)

    def __getattr__(name: str) -> Any:
        if name in table:
            return getattr(import_module(table[name], package), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(table) | set(import_module(package).__dict__))

    return __getattr__, __dir__
