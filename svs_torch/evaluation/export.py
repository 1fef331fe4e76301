"""Dense disparity maps written in the layouts the official evaluation tools read (``eval`` and ``estimate``'s
``--disparity-out``).

* ``middlebury`` (MiddEval3 SDK): ``DIR/<scene>/disp0<METHOD>.pfm``, float32, ``+inf`` = unknown, and
  ``DIR/<scene>/time<METHOD>.txt``, the pair's pipeline seconds. The maps are sparse (unknown outside the kept
  regions), and Middlebury's upload format (vision.middlebury.edu/stereo/submit3/upload-format.html) keeps
  ``disp0<METHOD>.pfm`` for dense maps without unknown values and names a sparse one ``disp0<METHOD>_s.pfm``
  (the MiddEval3 training data ship ``disp0SGM.pfm`` and ``disp0SGM_s.pfm`` so): ``--method-name SVSTorch_s``
  writes that name (with ``timeSVSTorch_s.txt`` beside it; an upload takes one ``time<METHOD>.txt``). The
  local ``evaldisp`` reads either, ``+inf`` as unknown;
* ``kitti`` (devkit): ``DIR/<pair>.png``, uint16, disparity × 256, 0 = unknown.

``<scene>`` / ``<pair>`` is the last part of the pair's name without an image suffix (``eval3/Teddy`` → ``Teddy``,
``kitti2012/000000_10`` → ``000000_10``, ``dir/left.png`` → ``left``; a pair labelled apart from another of its
name keeps the label's folders, ``eval3/Teddy (x/a)`` → ``Teddy_x_a``).

Each map is the pair's dense disparity (:attr:`~svs_torch.pipeline.PipelineResult.dense`) in the pixel grid and
disparity units of the image the pipeline ran on: the pair's own size, or the ``--size`` it was resized to, padding cut
off. The official tools score a map only at its ground truth's size (the MiddEval3 SDK also at exactly 1/2 or 1/4 of it,
scaling its disparities itself; the KITTI devkit not), so a map at another ``--size`` is for reading, not for them
(``eval`` and ``estimate`` warn: :func:`resized_maps_note`). Pixels the dense stage did not measure (outside the kept
regions' crop, or rejected) are unknown. A rectified pair's map is in rectified pixels; it is brought back to the left
image's grid by nearest sampling of the rectified map at ``H_left · x`` (unknown where that falls outside), its values
still rectified disparities (``Z = f·B / (d + doffs)`` holds for them as for the GT; the horizontal offsets of the raw
images differ by the rectification). A pair rectified before the pipeline by a rig's calibration (``--calibration``) is
the pipeline's input as it is: its map stays in the rectified pixels. Files go through the atomic writer
(:mod:`svs_torch.core.files`). A pair a run could not range (unreadable, too small, or its run raised) gets no
map, and the map an earlier run left for it is removed, warned (:meth:`DisparityExport.forget_unrun`): the folder
holds this run's maps only.

Reading a map back to the reported depths: an object's median (and percentiles) in ``estimate``'s JSON is over
its region's pixels inside the searched box (``dense_box_xywh``) after each unknown pixel takes its row's
nearest known neighbours' disparity (their mean where within 1 px, else the smaller; ``DenseConfig.fill_invalid``),
``Z = f·B / (d + doffs)``. Done so from the written PFMs of the ten MiddEval3 Q scenes, all 20 objects' medians
agree with the JSON within its 0.1 mm rounding (tests/evaluation/test_disparity_export.py does it for Teddy).
"""

from __future__ import annotations

import contextlib
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Iterator

import numpy as np
import torch

from ..core.checks import InputError, check_instance
from ..core.dataset_files import make_export_folder, resized_maps_note
from ..core.files import write_bytes_atomic, write_failure
from ..core.types import StereoBatch
from ..data.datasets import GENERIC_LEFT_NAME
from ..data.formats import write_kitti_disparity, write_pfm
from ..geometry.rectification import warp_rectified
from ..pipeline import PipelineResult

__all__ = ["EXPORT_FORMATS", "METHOD_NAME", "DisparityExport", "export_name", "left_view_disparity",
           "resized_maps_note"]

EXPORT_FORMATS = ("middlebury", "kitti")
_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".pbm", ".bmp", ".tif", ".tiff", ".webp"}
#: The SDK builds file names from the method name: letters, digits, '_' and '-' only.
METHOD_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")


def export_name(pair_name: str) -> str:
    """The file or folder name of a pair in an export (module docstring); unusual characters become ``_``. A pair
    labelled with the folders that tell it from another of its name (``eval3/Teddy (x/a)``,
    :attr:`~svs_torch.data.PairSource.label`) keeps them: ``Teddy_x_a``."""
    labelled = re.fullmatch(r"(.*) \(([^()]+)\)", pair_name)
    base, folders = (labelled[1], labelled[2]) if labelled else (pair_name, "")
    path = PurePosixPath(base.replace("\\", "/"))
    last = path.name or "pair"
    if path.suffix.lower() in _IMAGE_SUFFIXES:
        # A view's generic name (Piano/im0.png, a list line with its calibration) is its folder's, as a plain
        # line's pair is named (data.datasets.pair_name): every MiddEval3 line was 'im0' and one map was kept.
        last = path.parent.name if GENERIC_LEFT_NAME.fullmatch(path.stem) and path.parent.name else path.stem
    last += f"_{folders}" if folders else ""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", last).lstrip(".") or "pair"


def _not_an_export(target: Path, timing: Path | None) -> str | None:
    """What an existing ``target`` is when it is not a map an export wrote (which a run again replaces), or None.
    Why: ``--disparity-out`` pointed at the pairs' own folder wrote a KITTI map over the left image it was named
    after, and ``--method-name GT`` a scene's ``disp0GT.pfm``. A Middlebury map of ours has its time file beside
    it; a KITTI map is a 16-bit one-channel PNG (an image is 8-bit or colour)."""
    if target.parent.exists() and not target.parent.is_dir():
        return f"under {target.parent}, a file where its folder goes"
    if not target.exists():
        return None
    if not target.is_file():
        return "there and not a file"
    if timing is not None:
        return None if timing.is_file() else "there, a PFM without its time file (ground truth?)"
    with open(target, "rb") as handle:
        header = handle.read(26)
    # PNG: 8-byte signature, IHDR length and type, width, height, then bit depth (byte 24) and colour type (25).
    is_png = header[:8] == b"\x89PNG\r\n\x1a\n" and len(header) == 26
    return None if is_png and header[24] == 16 and header[25] == 0 else "there, an image, not a 16-bit disparity map"


def left_view_disparity(batch: StereoBatch, result: PipelineResult, index: int) -> tuple[np.ndarray, np.ndarray]:
    """Pair ``index``'s dense disparity in its left image's grid (module docstring): ``(H, W)`` float32
    disparity (0 where unknown) and ``(H, W)`` bool validity, at the pair's own ``image_hw``."""
    check_instance(batch, "batch", StereoBatch)
    check_instance(result, "result", PipelineResult)
    if result.dense is None:
        raise InputError("result: expected a dense disparity map (the 'dense' range rule), got none")
    height, width = (int(v) for v in batch.image_hw[index].tolist())
    disparity = result.dense.disparity_px[index:index + 1]
    valid = result.dense.valid[index:index + 1]
    if bool(result.rectified[index]):
        back = torch.linalg.inv(result.rectification.H_left[index:index + 1].to(torch.float64))
        disparity = warp_rectified(disparity.to(torch.float64), back, mode="nearest").to(disparity.dtype)
        valid = warp_rectified(valid.to(torch.float64), back, mode="nearest") > 0.5
    disparity = disparity[0, 0, :height, :width].numpy().astype(np.float32)
    valid = valid[0, 0, :height, :width].numpy() & np.isfinite(disparity)
    return np.where(valid, disparity, np.float32(0)), valid


@dataclass(frozen=True)
class DisparityExport:
    """Where and how dense maps are written (module docstring).

    Attributes:
        directory: the output folder (made if missing; its parent must exist).
        format: ``"middlebury"`` or ``"kitti"``.
        method: the method name in Middlebury's file names (``disp0<method>.pfm``).
    """

    directory: Path
    format: str = "middlebury"
    method: str = "SVSTorch"
    # Export name -> the pair written under it in this process, so a second pair of that name is not written (warned).
    _claimed: dict[str, str] = field(default_factory=dict, compare=False, repr=False)
    # Export names claimed from a whole list before any pair ran (claim_ahead: worker processes).
    _claimed_ahead: set[str] = field(default_factory=set, compare=False, repr=False)
    # The folder, where prepare() made it.
    _made: list[Path] = field(default_factory=list, compare=False, repr=False)
    # Export names this process wrote a map under (forget_unrun leaves them).
    _written: set[str] = field(default_factory=set, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.format not in EXPORT_FORMATS:
            raise InputError(f"format (--disparity-format): expected one of {', '.join(EXPORT_FORMATS)}, got "
                             f"{self.format!r}")
        if not isinstance(self.method, str) or not METHOD_NAME.fullmatch(self.method):
            raise InputError(f"method (--method-name): expected 1-64 letters, digits, '_' or '-', got "
                             f"{self.method!r}")

    def prepare(self) -> None:
        """Make the folder (before any work, so a bad name fails at once): see
        :func:`~svs_torch.core.dataset_files.make_export_folder`, which refuses a folder of a KITTI dataset: its
        ground truth is a 16-bit PNG named as the frame, which the export took for a map of its own and replaced
        (``eval kitti --disparity-out kitti/disp_occ``, an audit)."""
        if make_export_folder(self.directory, "--disparity-out"):
            self._made.append(Path(self.directory))

    def remove_if_unused(self) -> None:
        """Remove the folder :meth:`prepare` made if nothing was written into it: a command that failed after it
        (a refused ``--db``) left it behind, empty (an audit)."""
        for folder in self._made:
            with contextlib.suppress(OSError):  # not empty, or gone: kept as it is
                folder.rmdir()

    def claim_ahead(self, pair_name: str) -> None:
        """Give ``pair_name``'s export name to it before any pair is written, unless an earlier pair has it: worker
        processes each see a part of a list, and every one claims from the whole list, so a later pair of a
        shared name is skipped, warned, wherever it runs (:meth:`write`)."""
        key = export_name(pair_name)
        self._claimed.setdefault(key, pair_name)
        self._claimed_ahead.add(key)

    def paths(self, pair_name: str) -> tuple[Path, Path | None]:
        """The map's file and (Middlebury) the time file of a pair."""
        key = export_name(pair_name)
        if self.format == "kitti":
            return Path(self.directory) / f"{key}.png", None
        folder = Path(self.directory) / key
        return folder / f"disp0{self.method}.pfm", folder / f"time{self.method}.txt"

    def write(self, batch: StereoBatch, result: PipelineResult, time_s: float) -> list[Path]:
        """Write every pair of a pipeline run (each with ``time_s`` seconds); returns the map files.

        A pair whose :func:`export_name` another pair of this process was written under (``eval3/Teddy`` and
        ``2003/Teddy``, ``kitti2012/000000_10`` and ``kitti2015/000000_10``) is not written, with a
        ``RuntimeWarning`` naming both: a map is never overwritten in silence, and the pair's own results (its
        scores in ``eval``) stand. Export such pairs in separate runs. Likewise a target that is there and not a
        map an export wrote (an input image, a ground truth: :func:`_not_an_export`) is left alone, warned (the
        command line then exits 1 at the end: ``svs_torch.cli._maps_not_written``). A
        write that fails (a full disk) raises ``OSError`` naming ``--disparity-out`` and the file.
        """
        written = []
        for index in range(batch.batch_size):
            name = batch.names[index] if batch.names else str(index)
            key = export_name(name)
            if self._claimed.setdefault(key, name) != name:
                what = ("its export name belongs to {!r}, listed before it" if key in self._claimed_ahead
                        else "it would overwrite {!r}").format(self._claimed[key])
                warnings.warn(f"--disparity-out: {name!r} not written: {what}, written as {key!r}; export them in "
                              f"separate runs", RuntimeWarning, stacklevel=2)
                continue
            target, timing = self.paths(name)
            other = _not_an_export(target, timing)
            if other:
                warnings.warn(f"--disparity-out: {name!r} not written: {target} is {other}, not a map this "
                              f"command wrote; name another folder", RuntimeWarning, stacklevel=2)
                continue
            disparity, valid = left_view_disparity(batch, result, index)
            failing = target
            try:
                if self.format == "kitti":
                    write_kitti_disparity(target, disparity, valid)
                else:
                    # The time file first, the map last: a map is never left without the time file the SDK
                    # reads beside it (a full disk once refused the time file after the map, and the error
                    # named the map, which was there).
                    failing = timing
                    with _scene_folder(target.parent):
                        write_bytes_atomic(timing, f"{time_s:.6f}\n".encode("ascii"))
                        failing = target
                        _write_map_beside(timing, target, np.where(valid, disparity, np.float32(np.inf)))
            except OSError as error:  # a full disk, EPERM: the run stops (exit 1), the option and the file named
                raise write_failure(f"--disparity-out: cannot write {failing}", error) from None
            written.append(target)
            self._written.add(key)
        return written

    def forget_unrun(self, pair_name: str, status: str) -> Path | None:
        """Remove the map (and time file) an earlier run left for ``pair_name``, a pair this run could not range
        (``status``: ``BAD_INPUT``, ``TOO_SMALL``, ``ERROR``), with a ``RuntimeWarning``; returns the map removed.

        Why: a pair whose image had become unreadable kept the map of the run before, beside this run's maps of
        the others, and the SDK scored it as this run's (an audit of the export). Only a map an export wrote is
        removed (:func:`_not_an_export`), never one of this process's, nor one under a name another pair has.
        """
        key = export_name(pair_name)
        if key in self._written or self._claimed.get(key, pair_name) != pair_name:
            return None
        target, timing = self.paths(pair_name)
        if not target.is_file() or _not_an_export(target, timing):
            return None
        try:
            target.unlink()
            if timing is not None:
                timing.unlink(missing_ok=True)
        except OSError as error:  # read-only, gone meanwhile: the run's results stand, the map is named
            warnings.warn(f"--disparity-out: {pair_name!r} not run ({status}); the map an earlier run left, "
                          f"{target}, could not be removed: {error.strerror or error}", RuntimeWarning, stacklevel=2)
            return None
        warnings.warn(f"--disparity-out: {pair_name!r} not run ({status}): the map an earlier run left, {target}, "
                      "removed", RuntimeWarning, stacklevel=2)
        return target


@contextlib.contextmanager
def _scene_folder(folder: Path) -> Iterator[None]:
    """Make a pair's Middlebury folder for the body's files, and remove it again if the body fails and leaves it
    empty: a full disk (or Ctrl-C) once left an empty scene folder under ``--disparity-out``, a scene the SDK lists
    with no map (the last stop's note)."""
    made = not folder.is_dir()
    folder.mkdir(exist_ok=True)
    try:
        yield
    except BaseException:
        if made:
            with contextlib.suppress(OSError):  # not empty (another process's file), or gone: left as it is
                folder.rmdir()
        raise


def _write_map_beside(timing: Path, target: Path, disparity: np.ndarray) -> None:
    """Write ``target``'s map after its ``timing`` file; a map that is not written (Ctrl-C, SIGTERM, a full disk)
    takes its new time file with it, unless an earlier map is there: an interrupted eval left a scene folder
    with its time file and no map (an audit of interrupts), a pair the SDK reads as one, half there."""
    try:
        write_pfm(target, disparity)
    except BaseException:
        if not target.exists():
            timing.unlink(missing_ok=True)
        raise
