"""``--calibration FILE`` of estimate, eval, capture and guide: a rig calibrated by ``svs-depth calibrate``."""

from __future__ import annotations

import argparse

from ..core.camera import calibration_value_expected
from .common import _number

#: Rows of a pair rectified by a calibration agree within this many pixels (matching candidates farther apart are
#: not considered): 3x the largest row error of the shared chessboards' corners (0.63 px), for a rig's drift.
CALIBRATED_BAND_PX = 2.0

__all__ = ["add_calibration_option", "baseline_m_value", "calibration_file_source", "calibration_from_args",
           "calibration_kept_beside", "check_no_manual_calibration", "doffs_px_value", "focal_px_value",
           "kept_calibration_gone", "kept_calibrations", "rectified_by_rig", "rig_list_files", "take_kept_calibration",
           "with_calibrated_rectification"]


def _calibration_path(text: str) -> str:
    """argparse type: a path that is not empty (``--calibration "$RIG"`` with RIG unset must not run uncalibrated)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a calibration file from 'svs-depth calibrate', got {text!r}")
    return text


def _calibration_value(text: str, key: str) -> float:
    """argparse: a finite number in ``key``'s range (:data:`svs_torch.core.camera.CALIBRATION_RANGES`, the one a
    pair list's line, ``index.jsonl`` and a ``calib.txt`` are held to); else the error "expected ..."."""
    value = _number(text, float)
    expected = calibration_value_expected(key, value)
    if expected is not None:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def focal_px_value(text: str) -> float:
    """argparse type of ``--focal-px``: pixels, :data:`~svs_torch.core.camera.MIN_FOCAL_PX` to its MAX."""
    return _calibration_value(text, "focal_px")


def baseline_m_value(text: str) -> float:
    """argparse type of ``--baseline-m``: metres, :data:`~svs_torch.core.camera.MIN_BASELINE_M` to its MAX."""
    return _calibration_value(text, "baseline_m")


def doffs_px_value(text: str) -> float:
    """argparse type of ``--doffs-px``: pixels, at most :data:`~svs_torch.core.camera.MAX_FOCAL_PX` either way."""
    return _calibration_value(text, "doffs_px")


def add_calibration_option(parser: argparse.ArgumentParser, applies_to: str = "the pairs",
                           kept_beside: bool = False) -> None:
    """``--calibration``; ``kept_beside``: the command takes a capture folder's kept copy without it
    (:func:`calibration_kept_beside`)."""
    kept = ", or for a capture folder's index.jsonl the calibration.json kept beside it" if kept_beside else ""
    parser.add_argument("--calibration", metavar="RIG.json", type=_calibration_path,
                        help=f"a calibration file from 'svs-depth calibrate': {applies_to} are rectified with it "
                             "and take its focal length, baseline and doffs (scaled to their size: a pair of "
                             "another size is taken as the calibrated frames resampled, so never crop them; boxes "
                             "and figures are then in rectified pixels); without it the paper's uncalibrated "
                             f"rectification runs{kept}")


def calibration_from_args(args: argparse.Namespace):
    """The :class:`~svs_torch.geometry.calibration.StereoCalibration` of ``--calibration``, read once per ``args`` (a
    worker process reads its own copy), or None without the option.

    Raises:
        InputError: one line naming ``--calibration``, for a file that is not a calibration.
    """
    path = getattr(args, "calibration", None)
    if path is None:
        return None
    cached = vars(args).get("_calibration_read")
    if cached is None or cached[0] != path:
        from ..geometry.calibration import read_calibration

        cached = (path, read_calibration(path, "--calibration"))
        vars(args)["_calibration_read"] = cached
        _warn_of_a_poor_fit(path, cached[1])
        if getattr(args, "emulator", False):  # said once, as the file is read once (an audit: guide's obstacle gone)
            import warnings

            warnings.warn("--calibration with --emulator: the emulator renders an ideal SVS rig whose rows already "
                          "align, and a real rig's rectification warps its frames: their distances mean nothing "
                          "(the option is for the boards themselves)", stacklevel=2)
    return cached[1]


def rig_list_files(sources: list) -> list[str | None]:
    """The list file of each pair ``source`` a rig calibration applies to: listed image pairs, not scene folders,
    pairs listed with their own calibration, nor lines that are a problem (those keep their own)."""
    return [source.list_file for source in sources
            if not (source.scene or source.problem or source.focal_px is not None)]


def kept_calibrations(list_files: list[str | None]) -> dict:
    """Each of ``list_files`` once (None: not read from a list file), with the ``calibration.json`` kept beside it
    where it is a capture folder's ``index.jsonl`` that has one (``capture --calibration``, ``guide --record``),
    else None."""
    from pathlib import Path

    from .pairs_folder import CALIBRATION_NAME

    kept: dict = {}
    for list_file in dict.fromkeys(list_files):
        saved = None if list_file is None or Path(list_file).suffix != ".jsonl" else Path(list_file).parent
        kept[list_file] = saved / CALIBRATION_NAME if saved and (saved / CALIBRATION_NAME).is_file() else None
    return kept


def calibration_kept_beside(args: argparse.Namespace, list_files: list[str | None]) -> str | None:
    """Without ``--calibration`` (nor ``--focal-px``, ``--baseline-m`` or ``--doffs-px``): the rig calibration that
    ``capture --calibration`` and ``guide --record`` keep beside their ``index.jsonl`` (``calibration.json``), which
    the listed pairs are to be rectified with (:func:`take_kept_calibration`), or None. Why: such a folder ranged
    again was ranged in the SVS model's metres, unrectified, without a word (an audit). ``list_files``: the list
    file of each listed pair the option's calibration would apply to (None: not read from a list file).

    Raises:
        InputError: naming ``--calibration``, where those pairs were not all captured with one kept calibration.
    """
    from ..core.errors import InputError

    kept = kept_calibrations(list_files)
    found = [path for path in kept.values() if path is not None]
    manual = [getattr(args, option, None) is not None for option in ("focal_px", "baseline_m")]
    if getattr(args, "calibration", None) or any(manual) or getattr(args, "doffs_px", None):  # (doffs: 0 default)
        _warn_if_another_rig(args, found)
        return None
    if gone := kept_calibration_gone([name for name, path in kept.items() if path is None]):
        raise InputError(f"--calibration: {gone} lists pairs captured with a rig calibration, and no "
                         "calibration.json is beside it: copy the rig's file there, or name it with --calibration")
    if not found:
        return None
    without = [str(name) for name, path in kept.items() if path is None]
    if without or len({_kept_rig_content(path) for path in found}) > 1:  # what they hold, not their bytes
        others = f"{', '.join(without)} without one" if without else "another with a different one"
        raise InputError(f"--calibration: {found[0].parent} was captured with a rig calibration ({found[0].name} "
                         f"beside its index), and {others}: range them apart, or name the rig's file with "
                         "--calibration")
    return str(found[0])


def kept_calibration_gone(list_files: list[str | None]) -> str | None:
    """The first ``index.jsonl`` of ``list_files`` (those without a kept calibration: :func:`kept_calibrations`)
    whose first line says its pairs were captured with a rig calibration (capture's ``rig_calibration``, guide
    --record's ``calibration_rectified``), or None. Why: a folder copied without its calibration.json was ranged in
    the SVS model's metres, unrectified, the baseline 29 % off for OpenCV's chessboard rig, and said only "the SVS
    model assumed" (an audit of recordings)."""
    import json
    from pathlib import Path

    for name in list_files:
        if name is None or Path(name).suffix != ".jsonl":
            continue
        try:
            with open(name, "rb") as index:
                first = json.loads(index.readline(1 << 20))
        except (OSError, ValueError, RecursionError):  # the list's reader names what is wrong with it
            continue
        if isinstance(first, dict) and (first.get("rig_calibration") or first.get("calibration_rectified") is True):
            return name
    return None


def _warn_if_another_rig(args: argparse.Namespace, kept: list) -> None:
    """Warn where the calibration the options give is not the one kept beside the listed pairs' index: the pairs
    were captured with that rig, and another file replaced it without a word (an audit of calibration use)."""
    given = getattr(args, "calibration", None)
    # A calibration file first: a missing one was named by no option, a FIFO hung (an audit).
    content = None if given is None else _rig_content(calibration_from_args(args))
    differs = [path for path in kept if content != _kept_rig_content(path)]
    if differs:
        import warnings

        what = f"--calibration {given}" if given else "--focal-px / --baseline-m / --doffs-px"
        warnings.warn(f"{what} used: the pairs were captured with the rig calibration {differs[0]}, which differs",
                      stacklevel=3)


def _rig_content(calibration) -> str:
    """What a calibration holds, not how its file is laid out: capture and guide --record keep the file they read
    written anew, so the same rig's file with other line ends or indentation was said to differ (an audit)."""
    import json

    return json.dumps(calibration.to_json(), sort_keys=True)  # (NaN written alike on both sides)


def _kept_rig_content(path) -> str:
    """:func:`_rig_content` of the calibration kept at ``path``, or "" where it is no calibration: it differs from
    any file given and from no file (--focal-px alone)."""
    from ..core.errors import InputError
    from ..geometry.calibration import read_calibration

    try:
        return _rig_content(read_calibration(path, "--calibration"))
    except InputError:
        return ""


def take_kept_calibration(args: argparse.Namespace, path: str | None, prog: str) -> None:
    """``args.calibration`` set to :func:`calibration_kept_beside`'s ``path`` (nothing if None), said on standard
    error."""
    if path is None:
        return
    import sys

    args.calibration = path
    print(f"{prog}: the pairs were captured with a rig calibration: rectified with {path} (--calibration names "
          "another)", file=sys.stderr)


def _warn_of_a_poor_fit(path: str, calibration) -> None:
    """Once per file read: a calibration whose fit calibrate doubted (:func:`~svs_torch.geometry.chessboard.fit_doubts`;
    one written before calibrate left out the pairs that spoil it, or one it warned of) gives distances that may be
    far off (audits: "Stop" at 0.9 m; an obstacle at 0.80 m ranged 1.65 m, "OK", rows 2.2 px apart said nowhere)."""
    from ..geometry.chessboard import fit_doubts

    if doubts := fit_doubts(calibration):
        import warnings

        warnings.warn(f"--calibration: {path}: {'; '.join(doubts)}: distances may be far off; calibrate again "
                      "(svs-depth calibrate leaves out the pairs that spoil the fit; tilt the board between pairs)",
                      stacklevel=3)


def check_no_manual_calibration(args: argparse.Namespace) -> None:
    """``--calibration`` excludes ``--focal-px``, ``--baseline-m`` and ``--doffs-px`` (the file gives them)."""
    from ..core.errors import InputError

    given = [getattr(args, option, None) is not None for option in ("focal_px", "baseline_m")]
    if getattr(args, "calibration", None) is not None and (any(given) or getattr(args, "doffs_px", None)):
        raise InputError("--calibration: the file gives focal, baseline and doffs; drop --focal-px, --baseline-m "
                         "and --doffs-px")


def calibration_file_source(args: argparse.Namespace, source) -> str | None:
    """Where a listed pair's calibration comes from when ``--calibration`` rectified it (its provenance in every
    report: :func:`svs_torch.data.calibration_record`), or None when the option is absent or does not apply (a
    scene folder or a list line with its own calibration)."""
    path = getattr(args, "calibration", None)
    if not path or source.scene or source.focal_px is not None:
        return None
    return rig_provenance(path)


def warn_scenes_keep_their_own(args: argparse.Namespace, scenes: list[str]) -> None:
    """Warn that ``--calibration`` was not applied to the pairs named ``scenes`` (scene folders: a dataset's pair,
    not the rig's). Why: ``eval`` and ``estimate --pairs`` of scene folders with ``--calibration rig.json`` ranged
    them with their own calibration or, where a scene ships none, the SVS model, and nothing said the file given
    was not used (an audit of calibration use)."""
    path = getattr(args, "calibration", None)
    if path and scenes:
        import warnings

        from ..evaluation.kept_rows import named  # the first three and how many more, as the sweep's notices

        warnings.warn(f"--calibration {path}: not applied to {len(scenes)} scene folder{'s' * (len(scenes) > 1)} "
                      f"({named(scenes)}): a scene is not the rig's pair, and keeps its own calibration (the SVS model "
                      "where it ships none); the file rectifies listed image pairs and captures", stacklevel=3)


def eval_rig_calibration(args: argparse.Namespace, sources: list):
    """``eval``'s rig calibration over its pair ``sources``: the one of ``--calibration`` (scene folders keep their
    own: warned of), or the one kept beside the listed capture folders' index (:func:`calibration_kept_beside`,
    then set as ``args.calibration``), or None."""
    from ..core.errors import InputError

    kept = calibration_kept_beside(args, rig_list_files(sources))
    if kept and args.db:  # as --calibration with --db
        raise InputError(f"--db: the pairs were captured with a rig calibration ({kept}), which a results store "
                         "does not record yet; run without --db")
    take_kept_calibration(args, kept, "eval")
    warn_scenes_keep_their_own(args, [source.name for source in sources if source.scene and not source.problem])
    return calibration_from_args(args)


def rectified_by_rig(batch, calibration, left: str):
    """``batch`` (the pair of file ``left``) rectified by ``--calibration``'s ``calibration``; a refusal of its size
    names the EXIF turn that made it: "the pair is 480x640" of files storing 640x480 left the user looking for a
    size no image tool showed (an audit)."""
    from ..core.errors import InputError
    from ..core.image_files import turned_note
    from ..geometry.calibration import rectify_with_calibration

    try:
        return rectify_with_calibration(batch, calibration)
    except InputError as error:
        turned = turned_note(left, batch.size_hw[::-1])
        raise InputError(f"{error}; the left image is{turned[1:]}" if turned else str(error)) from None


def rig_provenance(path: str) -> str:
    """How a report names the calibration of a pair ``--calibration path`` rectified (estimate and eval alike)."""
    return f"--calibration {path} (the pair rectified by it)"


def with_calibrated_rectification(config, args: argparse.Namespace):
    """``config`` for pairs rectified by ``--calibration`` (unchanged without it):

    * ``rectify="off"``: the rig's rectification holds, and an F fitted again to a pair's matches only adds shear
      where they are few or nearly planar. On the shared chessboards rectified by their calibration
      (``experiments/calibrated_rectify.py``), ``"auto"`` rectified 3 of 13 pairs again from an F of the planar
      board: one lost its depth, two moved from 0.30 to 0.62 m and from 0.32 to 0.50 m (the board's nearest
      corner: 0.22, 0.25 m); ``"off"`` kept the dense disparity at the corners within 0.15-0.41 px of the
      calibration's (median per pair) on 11 of the 12 pairs measured there.
    * ``epipolar_band_px`` :data:`CALIBRATED_BAND_PX` unless the configuration sets one: matches only between
      points on the same rows, which the calibration guarantees (its corners' rows agree within 0.63 px there).
      On those pairs the RANSAC inliers' median |y_left - y_right| per pair went from up to 65 px (a periodic
      board matched one square off; 0.13-65 px) to 0.13-0.93 px at 640x480, and the pairs whose geometry the
      dense map verifies from 8 to 9 of 13 at 640x480 and from 4 to 9 at 320x240.
    """
    from dataclasses import replace

    if not getattr(args, "calibration", None):
        return config
    band = CALIBRATED_BAND_PX if config.epipolar_band_px is None else config.epipolar_band_px
    return replace(config, rectify="off", epipolar_band_px=band)
