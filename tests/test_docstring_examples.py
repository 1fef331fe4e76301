"""Every ``>>>`` example in the package's docstrings runs and prints what it shows (nothing else ran them), and the
statuses' docstrings, what help() shows of them, say what each value means."""

from __future__ import annotations

import doctest
import importlib
import re
from pathlib import Path

import svs_torch
from conftest import resolves_in_package

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


def test_help_of_every_status_says_what_each_value_means():
    """A library user's audit: ``help(svs_torch.PipelineStatus)`` (and the other per-pair statuses') listed the
    values' names and numbers only, their meanings being source comments that help() never shows."""
    from svs_torch import FundamentalStatus, PipelineStatus, SegmentationStatus
    from svs_torch.depth import ObstacleSide
    from svs_torch.geometry.rectification import RectificationStatus

    for status in (PipelineStatus, FundamentalStatus, SegmentationStatus, RectificationStatus, ObstacleSide):
        doc = " ".join(status.__doc__.replace("−", "-").split())
        for member in status:
            assert re.search(rf"\b{member.name} \({member.value}\)[:,]? \w", doc), f"{status.__name__}.{member.name}"


def test_every_full_cross_reference_in_the_docstrings_resolves():
    """A library user's audit followed ``:func:`~svs_torch.data.scene_name``` (PairSource.loaded_name's) to a name
    the package does not have (it is ``svs_torch.data.datasets.scene_name``): every ``:func:``, ``:class:``,
    ``:mod:``, ``:data:``, ``:meth:`` or ``:attr:`` reference spelled from ``svs_torch`` must import."""
    import warnings

    pattern = r":(?:func|class|mod|data|meth|attr|exc):`~?(svs_torch(?:\.\w+)+)`"
    references = {(name, str(path.relative_to(ROOT.parent))) for path in sorted(ROOT.rglob("*.py"))
                  for name in re.findall(pattern, path.read_text(encoding="utf-8"))}
    assert len(references) > 200
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # old module paths are named on purpose
        unresolved = sorted(f"{path}: {name}" for name, path in references if not resolves_in_package(name))
    assert unresolved == []
