"""The Surveyor SVS stereo camera model.

Two SRV-1 Blackfin boards with OmniVision OV9655 sensors and 3.6 mm lenses on a fixed horizontal rig.
Constants are nominal: from the paper (baseline 10.75 cm) and from Surveyor's firmware range formula
(``../shared/SVS_PROTOCOL.md`` §5: 3.6 mm lens, 4.17 mm sensor width, 107 mm baseline). A real rig should be
calibrated; these values are what the paper's depth equations (5)–(8) use without calibration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import InputError

__all__ = ["CALIBRATION_RANGES", "MAX_BASELINE_M", "MAX_FOCAL_PX", "MAX_SIZE_PX", "MIN_BASELINE_M", "MIN_FOCAL_PX",
           "SVSCamera", "SVS_RESOLUTIONS", "SVS_CAMERA", "calibration_value_expected", "parse_size", "too_many_pixels"]

#: The largest focal length and doffs (either way) any rig may have, pixels: a 1000 mm lens on 1 µm pixels, 250
#: times the longest focal of the shared data (MiddEval3 at full size, 4000 px). ``--focal-px 1e30`` ranged Teddy at
#: 3e27 m with the status OK, 1e39 was refused as "focal_px: ... got inf" (float32), and ``--doffs-px 1e30`` put
#: every object at 0.000 m (an audit of option bounds); a pair list's line, an ``index.jsonl`` line and a
#: ``calib.txt`` did the same until they were held to these bounds too (an audit of numbers read from files).
MAX_FOCAL_PX = 1e6
#: The shortest focal length, pixels: at 1 px even the smallest pair the pipeline ranges (5 px wide) spans 136°, and
#: ``--focal-px 1e-30`` (or a list line's) put every object at 0.000 m with the status OK (an audit).
MIN_FOCAL_PX = 1.0
#: The longest baseline any rig may have, metres: one holding both cameras (the SVS's 0.1075 m, KITTI's 0.54 m),
#: as a calibration file's (``BASELINE_RANGE_M``). At 100 m, a rig's baseline in millimetres (a pair list's
#: ``l.png r.png 276 50``) was taken as metres: every distance 1000 times too far, in silence (an audit); with the
#: focal's bound f·B stays under 1e8, far inside float32 (``--baseline-m 1e20`` left every object without a depth).
MAX_BASELINE_M = 2.0
#: The shortest baseline, metres, as a calibration file's (``BASELINE_RANGE_M``): ``--baseline-m 1e-30`` put every
#: object at 0.000 m with the status OK (an audit).
MIN_BASELINE_M = 0.001
#: Each calibration number's range, wherever it is read (the command's options, a pair list's line, capture's
#: ``index.jsonl``, a ``calib.txt``, a rig's calibration file): (lowest, highest, what is expected).
CALIBRATION_RANGES: dict[str, tuple[float, float, str]] = {
    "focal_px": (MIN_FOCAL_PX, MAX_FOCAL_PX, f"a focal length in pixels from {MIN_FOCAL_PX:g} to {MAX_FOCAL_PX:,.0f}"),
    "baseline_m": (MIN_BASELINE_M, MAX_BASELINE_M,
                   f"a baseline in metres from {MIN_BASELINE_M:g} to {MAX_BASELINE_M:g} (millimetres / 1000)"),
    "doffs_px": (-MAX_FOCAL_PX, MAX_FOCAL_PX, f"pixels from -{MAX_FOCAL_PX:,.0f} to {MAX_FOCAL_PX:,.0f}"),
}


def calibration_value_expected(key: str, value: float) -> str | None:
    """None where ``value`` is a finite number in ``key``'s :data:`CALIBRATION_RANGES` (``"focal_px"``,
    ``"baseline_m"``, ``"doffs_px"``); else what is expected of it, for an error's "expected ..." (the caller names
    the option, file or line)."""
    low, high, expected = CALIBRATION_RANGES[key]
    return None if math.isfinite(value) and low <= value <= high else expected


#: The frame sizes the SVS firmware can grab, keyed by the size code in its ``##IMJ`` header
#: (SVS_PROTOCOL.md §3): ``'3'`` 160×120, ``'5'`` 320×240 (power-on default), ``'7'`` 640×480, ``'9'`` 1280×1024.
SVS_RESOLUTIONS: dict[str, tuple[int, int]] = {
    "3": (160, 120),
    "5": (320, 240),
    "7": (640, 480),
    "9": (1280, 1024),
}


@dataclass(frozen=True)
class SVSCamera:
    """Nominal optics of one SVS rig.

    Attributes:
        baseline_m: distance between the optical centres, metres. Paper: 10.75 cm (4.25 in); Surveyor's
            firmware range formula uses 107 mm.
        lens_focal_mm: lens focal length, millimetres (the 3.6 mm stock lens). Surveyor quotes it as a 90° lens,
            but with ``sensor_width_mm`` this model sees 2·atan(4.17 / 2 / 3.6) = 60° across: 90° is not the
            horizontal angle. The distances take f / sensor width, never the angle.
        sensor_width_mm: active sensor width, millimetres (firmware range formula).
    """

    baseline_m: float = 0.1075  # paper, Sec. 3.1; the firmware uses 0.107
    lens_focal_mm: float = 3.6  # SVS_PROTOCOL.md §5
    sensor_width_mm: float = 4.17  # SVS_PROTOCOL.md §5

    def focal_px(self, width_px: int) -> float:
        """Focal length in pixels for an image ``width_px`` wide: f_mm / sensor_width_mm · width.

        About 138 px at 160×120, 276 px at 320×240, 553 px at 640×480, 1105 px at 1280×1024.
        """
        if width_px <= 0:
            raise InputError(f"width_px: expected a positive width, got {width_px}")
        return self.lens_focal_mm / self.sensor_width_mm * width_px

    def principal_point_px(self, width_px: int, height_px: int) -> tuple[float, float]:
        """Nominal principal point (image centre in pixel-centre coordinates, x = column)."""
        return (width_px - 1) / 2.0, (height_px - 1) / 2.0

    def depth_m(self, disparity_px: float, width_px: int) -> float:
        """Depth of one disparity, the paper's R = f·B/d (Eq. (7)–(8)); ``inf`` for d <= 0."""
        if disparity_px <= 0:
            return float("inf")
        return self.focal_px(width_px) * self.baseline_m / disparity_px

    def disparity_px(self, depth_m: float, width_px: int) -> float:
        """Disparity of a point at ``depth_m``: d = f·B/Z."""
        if depth_m <= 0:
            raise InputError(f"depth_m: expected a positive depth, got {depth_m}")
        return self.focal_px(width_px) * self.baseline_m / depth_m


#: The rig of the paper, with its stock 3.6 mm lenses.
SVS_CAMERA = SVSCamera()


#: The largest side ``--size`` resamples to (8K video is 7680 wide; a pair at 8192 x 8192 is 0.5 GB a view in float32).
MAX_SIZE_PX = 8192


def parse_size(text: str, name: str = "size") -> tuple[int, int]:
    """Parse ``"320x240"`` into ``(width, height)``; raises :class:`InputError` naming ``name`` otherwise."""
    parts = text.lower().replace("×", "x").split("x")
    # isdecimal, not isdigit: int() refuses digits such as "²" that isdigit accepts.
    if len(parts) != 2 or not all(p.strip().isdecimal() for p in parts):
        raise InputError(f"{name}: expected WIDTHxHEIGHT such as 320x240, got {text!r}")
    width, height = (int(p) for p in parts)
    if width <= 0 or height <= 0:
        raise InputError(f"{name}: expected a positive width and height, got {text!r}")
    if max(width, height) > MAX_SIZE_PX:  # 100000x100000 stopped a whole eval run failing to allocate 40 GB
        raise InputError(f"{name}: expected a width and height of at most {MAX_SIZE_PX} px, got {text!r}")
    return width, height


def too_many_pixels(size_hw: tuple[int, int], max_pixels: int, name: str = "left", resize_with: str = "--size"
                    ) -> str | None:
    """Why a pair of this (H, W), run at its own size, is refused over ``max_pixels`` (None: it is not): the one
    message of ``estimate``, ``estimate --pairs``, ``eval`` and ``sweep`` (``svs_torch.cli.features.MAX_PIXELS``);
    ``resize_with``: the setting that resamples it, named in the message."""
    height, width = size_hw
    if height * width <= max_pixels:
        return None
    return (f"{name}: expected at most {max_pixels // 10**6} megapixels, got {width}x{height} (resample it with "
            f"{resize_with})")
