"""The module paths that moved when the package was grouped by stage (issue 35), and the import hook that keeps
them importable for one release.

``import svs_torch.dense`` (or ``from svs_torch import dense``) still works: the hook (:class:`MovedModuleFinder`,
on ``sys.meta_path`` from ``svs_torch/__init__.py``) imports the new module, warns once with a
:class:`DeprecationWarning` naming the new path, and binds the old name to that same module object, so attributes
set through either name (a test's ``monkeypatch``) are seen through both. One table, no module files at the old
paths. The old modules ``segmentation``, ``features``, ``depth`` and ``pipeline`` are the new packages of the same
names, whose ``__init__`` re-exports the old modules' public names: they need no entry.

Imports only the standard library: ``svs-depth --help`` installs the hook without loading torch.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

__all__ = ["MOVED", "MovedModuleFinder", "install"]

#: Old module path → where the module is now.
MOVED = {
    "svs_torch.errors": "svs_torch.core.errors",
    "svs_torch.checks": "svs_torch.core.checks",
    "svs_torch.files": "svs_torch.core.files",
    "svs_torch.types": "svs_torch.core.types",
    "svs_torch.ordering": "svs_torch.core.ordering",
    "svs_torch.mask_reductions": "svs_torch.core.mask_reductions",
    "svs_torch.compiling": "svs_torch.core.compiling",
    "svs_torch.camera": "svs_torch.core.camera",
    "svs_torch.pair_trees": "svs_torch.core.pair_trees",
    "svs_torch.size_groups": "svs_torch.core.size_groups",
    "svs_torch.workers": "svs_torch.core.workers",
    "svs_torch.image_files": "svs_torch.core.image_files",
    "svs_torch.kernels": "svs_torch.core.kernels",
    "svs_torch.kernels.loader": "svs_torch.core.kernels.loader",
    "svs_torch.kernels.checks": "svs_torch.core.kernels.checks",
    "svs_torch.threshold": "svs_torch.segmentation.threshold",
    "svs_torch.morphology": "svs_torch.segmentation.morphology",
    "svs_torch.components": "svs_torch.segmentation.components",
    "svs_torch.canny": "svs_torch.segmentation.canny",
    "svs_torch.soft_segmentation": "svs_torch.segmentation.soft",
    "svs_torch.learned_segmentation": "svs_torch.segmentation.learned",
    "svs_torch.nearness_segmentation": "svs_torch.segmentation.nearness",
    "svs_torch.integral": "svs_torch.features.integral",
    "svs_torch.hessian": "svs_torch.features.hessian",
    "svs_torch.detector": "svs_torch.features.detector",
    "svs_torch.descriptor": "svs_torch.features.descriptor",
    "svs_torch.matching": "svs_torch.geometry.matching",
    "svs_torch.epipolar": "svs_torch.geometry.epipolar",
    "svs_torch.ransac": "svs_torch.geometry.ransac",
    "svs_torch.rectification": "svs_torch.geometry.rectification",
    "svs_torch.row_alignment": "svs_torch.geometry.row_alignment",
    "svs_torch.soft_geometry": "svs_torch.geometry.soft",
    "svs_torch.calibration": "svs_torch.geometry.calibration",
    "svs_torch.chessboard": "svs_torch.geometry.chessboard",
    "svs_torch.dense": "svs_torch.depth.dense",
    "svs_torch.dense_depth": "svs_torch.depth.dense_objects",
    "svs_torch.soft_pipeline": "svs_torch.pipeline.soft",
    "svs_torch.worker_preload": "svs_torch.pipeline.preload",
    "svs_torch.benchmark": "svs_torch.evaluation.benchmark",
    "svs_torch.bench_rivals": "svs_torch.evaluation.bench_rivals",
    "svs_torch.figures": "svs_torch.plotting.figures",
    "svs_torch.plots": "svs_torch.plotting.plots",
    "svs_torch.rectified_figure": "svs_torch.plotting.rectified",
}


class MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds the old paths of :data:`MOVED`; loading one returns the module at its new path."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        new = MOVED[spec.name]
        warnings.warn(f"{spec.name} has moved to {new}; the old path will be removed in the next release",
                      DeprecationWarning, stacklevel=_importer_stacklevel())
        # The module object itself: importlib keeps its own __name__ and __spec__ (they are set), and binds it
        # under the old name in sys.modules and as an attribute of the old parent package.
        return importlib.import_module(new)

    def exec_module(self, module) -> None:
        """Nothing to run: the module at the new path is already imported."""


def _importer_stacklevel() -> int:
    """The stack level of the frame that wrote the import, past importlib's frames and this module's."""
    frame, level = sys._getframe(1), 1
    while frame is not None and (frame.f_code.co_filename.startswith("<frozen importlib")
                                 or frame.f_code.co_filename == __file__):
        frame, level = frame.f_back, level + 1
    return level


def install() -> None:
    """Put the finder first on ``sys.meta_path`` (once): it answers only the old paths, and must answer
    ``svs_torch.kernels.loader`` before the path finder loads a second copy of the file from the new package's
    folder."""
    if not any(isinstance(finder, MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, MovedModuleFinder())
