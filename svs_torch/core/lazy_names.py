"""A package's public names loaded on first use (PEP 562), so that importing it loads none of its heavy modules:
``svs_torch`` (``svs-depth --help`` without torch) and ``svs_torch.capture`` (capture's arguments checked without
torch). Only the standard library is imported.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable

__all__ = ["lazy_names"]


def lazy_names(package: str, exports: dict[str, str]) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of ``package`` (its ``__name__``), whose names ``exports`` maps to the
    submodule (relative to the package) that defines each. A name is imported on its first lookup and then kept in
    the package's namespace, so later lookups skip ``__getattr__``."""
    namespace = sys.modules[package].__dict__

    def __getattr__(name: str) -> object:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f".{module}", package), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
