"""Every ``>>>`` example in the package's docstrings runs and prints what it shows (nothing else ran them)."""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import svs_torch

ROOT = Path(svs_torch.__file__).parent


def _modules_with_examples() -> list[str]:
    """The modules whose source holds an example: only they are imported (importing all would load every stage)."""
    paths = [p for p in sorted(ROOT.rglob("*.py")) if ">>>" in p.read_text(encoding="utf-8")]
    return [".".join(("svs_torch", *p.relative_to(ROOT).with_suffix("").parts)).removesuffix(".__init__")
            for p in paths if p.name != "__main__.py"]


def test_every_docstring_example_runs_and_prints_what_it_shows():
    names = _modules_with_examples()
    assert names, "no module with a docstring example found"
    attempted, failed = 0, []
    for name in names:
        result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS, report=False)
        attempted += result.attempted
        if result.failed:
            failed.append(f"{name}: {result.failed} of {result.attempted} failed")
    assert attempted > 0 and not failed, "\n".join(failed)
