"""The checkout the library runs from, as reports record it: its commit, and whether tracked files differ from it
(a table made on edited code read as one made at the commit; an audit). One reader for sweeps' stores, the
benchmark's report and the experiments' metadata, which had three that disagreed (12 against 7 characters, one
without ``-dirty`` and one that could wait on git forever)."""

from __future__ import annotations

import subprocess
from pathlib import Path

__all__ = ["checkout_commit", "code_version", "short_commit"]

#: Characters of the commit recorded: as ``git log --abbrev=12`` prints them.
SHORT_COMMIT_CHARS = 12


def checkout_commit() -> tuple[str, bool] | None:
    """The full commit of the git checkout holding the package and whether tracked files differ from it; None
    where the package is not at the top of a checkout (an installed wheel, also in a virtual environment inside
    another project's checkout) or git is missing or does not answer in 10 s."""
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():  # an installed copy: git would answer for any checkout around it (a venv's)
        return None
    git = ["git", "-C", str(root)]
    try:
        commit = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10,
                                check=True).stdout.strip()
        changed = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                                 text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return commit, bool(changed)


def short_commit() -> str:
    """``<commit, 12 characters>[-dirty]``, or ``unknown`` outside a checkout."""
    found = checkout_commit()
    if found is None:
        return "unknown"
    return found[0][:SHORT_COMMIT_CHARS] + ("-dirty" if found[1] else "")


def code_version() -> str:
    """``<package version>+git.<commit, 12 characters>[-dirty]`` in a checkout, else the package version."""
    from .. import __version__

    found = short_commit()
    return __version__ if found == "unknown" else f"{__version__}+git.{found}"
