"""The one exception type of the public API, importable without torch (the command line's ``--help`` and
argument checks use it before any heavy import)."""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """A public function was given an argument of the wrong shape, dtype, range or format."""
