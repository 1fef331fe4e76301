"""Which calibration a result used and where it came from, for every text and JSON report.

A distance in metres is only as good as its focal length, baseline and doffs. Every report names them and their
source: a scene's own file (``Teddy/calib.txt``), the pair list's line, the command-line options, a data set's
nominal values, or the SVS camera model assumed, so that nobody reads metres from a guessed focal length without
being told. Nothing here is differentiable (plain numbers and words).
"""

from __future__ import annotations

from ..core.checks import check_instance
from ..core.types import StereoBatch
from .datasets import scene_calibration_source
from .pair_list import PairSource

__all__ = ["SVS_MODEL_ASSUMED", "calibration_fields", "calibration_record", "format_calibration",
           "pair_calibration_source", "rig_scaled_source"]

#: The source of a plain pair's calibration when neither its list line nor an option gives one.
SVS_MODEL_ASSUMED = "the SVS model assumed"


def options_calibration_source(focal_px: float | None, baseline_m: float | None, doffs_px: float = 0.0) -> str:
    """The source of a plain pair's calibration from the command's ``--focal-px`` / ``--baseline-m`` /
    ``--doffs-px`` (0: not given, its default). Why the doffs: ``--doffs-px 52`` alone was reported as "the SVS
    model assumed", beside the 52 px it had put into every distance (an audit)."""
    given = [name for name, value in (("--focal-px", focal_px), ("--baseline-m", baseline_m)) if value is not None]
    given += ["--doffs-px"] if doffs_px else []
    if len(given) >= 2 and given[:2] == ["--focal-px", "--baseline-m"]:
        return "command-line options"
    if given:
        return (f"command-line option{'s' if len(given) > 1 else ''} {' and '.join(given)}, the SVS model assumed "
                "for the rest")
    return SVS_MODEL_ASSUMED


def pair_calibration_source(source: PairSource, focal_px: float | None = None,
                            baseline_m: float | None = None, doffs_px: float = 0.0) -> str:
    """Where :func:`~svs_torch.data.load_pair_source` takes ``source``'s calibration from, given the command's
    options ``focal_px`` / ``baseline_m`` (None: not given) and ``doffs_px`` (0: not given)."""
    if source.scene:
        return scene_calibration_source(source.left)
    if source.focal_px is not None:
        return f"the pair list, {source.listed_at}" if source.listed_at else "the pair list"
    return options_calibration_source(focal_px, baseline_m, doffs_px)


def rig_scaled_source(source: str, rig_wh, pair_wh) -> str:
    """``source`` (a rig file's, made at ``rig_wh``) with the size it was scaled to, where the pair's ``pair_wh``
    differs. Why: a rig calibrated at 640x480 ranged a 320x240 pair with its focal length halved, and a 480x360 crop
    of its frames with it scaled by 3/4 (0.30 m for 0.39 m), and the calibration line named only the file (an audit).
    """
    (w, h), (pw, ph) = (int(v) for v in rig_wh), (int(v) for v in pair_wh)
    return source if (w, h) == (pw, ph) else f"{source}, made at {w}x{h} and scaled to this {pw}x{ph} pair"


def calibration_record(batch: StereoBatch, index: int, source: str, width_scale: float = 1.0) -> dict:
    """``{"source", "measured", "focal_px", "baseline_m", "doffs_px"}`` of pair ``index`` of ``batch``.

    ``measured``: the data's (or the user's) calibration, not a nominal one. ``width_scale``: input width over
    ``batch``'s width, so a resampled batch reports the focal length and doffs of the INPUT images (the values a
    calib.txt or ``--focal-px`` gives).
    """
    check_instance(batch, "batch", StereoBatch)
    return calibration_fields(source, bool(batch.calibrated[index]), float(batch.focal_px[index]) * width_scale,
                              float(batch.baseline_m[index]), float(batch.doffs_px[index]) * width_scale)


def calibration_fields(source: str, measured: bool, focal_px: float, baseline_m: float, doffs_px: float) -> dict:
    """The report's calibration record (:func:`calibration_record`) from plain values, rounded alike."""
    return {"source": source, "measured": measured, "focal_px": round(focal_px, 4),
            "baseline_m": round(baseline_m, 6), "doffs_px": round(doffs_px, 4)}


def format_calibration(record: dict | None) -> str:
    """One line for text reports: ``calibration: f 1500.0 px, B 0.080 m, doffs 52.0 px (Teddy/calib.txt)``."""
    if record is None:
        return "calibration: none (the pair was not loaded)"
    return (f"calibration: f {record['focal_px']:.1f} px, B {record['baseline_m']:.4g} m, doffs "
            f"{record['doffs_px']:.1f} px ({record['source']})")
