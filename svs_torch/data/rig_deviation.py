"""A right camera's deviation from an ideal side-by-side rig (issue 33, item 2), and the view that camera sees.

The SVS is two boards, each with its own lens and sensor, mounted by hand: nothing holds the right camera's rows on
the left camera's. :class:`RigDeviation` names how far it is off: turned about its optical axis (roll), about its
x and y axes (tilts, a keystone), moved vertically, with a lens of another focal length (scale) and another
exposure (gain). :func:`deviate_view` makes an ideal right view that camera's. ``experiments/real_rig.py`` perturbs
the shared scenes with it (their left view's ground truth is unchanged, so each object's true distance is known),
and the SVS emulator's right board sees through it (``python -m hw.emulator --right-roll-deg 2``), so that ``guide``
and ``capture`` can be tried on a loosely mounted rig without one.

A tilt's rotation would also shift the whole view by f·tan θ; the view is re-centred so that only its keystone
stays (a shift is its own field), as :func:`deviation_homography` documents.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.checks import InputError, check_real

__all__ = ["LOOSE_RIG", "RigDeviation", "deviate_view", "deviation_homography"]


@dataclass(frozen=True)
class RigDeviation:
    """How the right camera deviates from the ideal rig.

    Attributes:
        roll_deg: turn about its optical axis, degrees (positive: its view turned clockwise as shown, y down;
            OpenCV's ``getRotationMatrix2D`` by minus this angle).
        tilt_x_deg, tilt_y_deg: turns about its x (pitch) and y (yaw) axes, degrees: a keystone.
        shift_y_fraction: vertical shift, a share of the image height (0.03: 3 % down).
        scale: relative magnification (0.02: its view 2 % larger; more than -1).
        gain: relative exposure (-0.3: 30 % darker; more than -1), clipped to the 8-bit range.
    """

    roll_deg: float = 0.0
    tilt_x_deg: float = 0.0
    tilt_y_deg: float = 0.0
    shift_y_fraction: float = 0.0
    scale: float = 0.0
    gain: float = 0.0

    def __post_init__(self) -> None:
        for name in ("roll_deg", "tilt_x_deg", "tilt_y_deg"):
            check_real(getattr(self, name), name, -90.0, 90.0, low_open=True, high_open=True)
        check_real(self.shift_y_fraction, "shift_y_fraction", -1.0, 1.0)
        for name in ("scale", "gain"):
            check_real(getattr(self, name), name, -1.0, 100.0, low_open=True)

    @property
    def is_identity(self) -> bool:
        """Whether the right camera sees exactly what the ideal rig's would."""
        return self == RigDeviation()


#: A loosely mounted right board, every deviation of the issue's envelope at once within it (experiments/real_rig.py's
#: "combined"): ``svs-depth guide --emulator --emulator-loose-rig``.
LOOSE_RIG = RigDeviation(roll_deg=1.0, tilt_x_deg=0.5, tilt_y_deg=-0.5, shift_y_fraction=0.02, scale=0.01, gain=-0.2)


def deviation_homography(deviation: RigDeviation, height: int, width: int, focal_px: float) -> np.ndarray:
    """The 3×3 homography taking an ideal right view's pixels (x = column) to the deviated camera's, for a
    ``height`` × ``width`` view of focal length ``focal_px`` pixels: the turn K·Rz·Ry·Rx·K⁻¹ re-centred (its keystone
    stays, its shift of the whole view does not), then the scale about the centre, then the vertical shift."""
    check_real(float(focal_px) if isinstance(focal_px, np.floating) else focal_px, "focal_px", 0.0, low_open=True)
    cx, cy = (width - 1) / 2, (height - 1) / 2
    k = np.array([[focal_px, 0, cx], [0, focal_px, cy], [0, 0, 1]])
    ax, ay, az = (math.radians(a) for a in (deviation.tilt_x_deg, deviation.tilt_y_deg, deviation.roll_deg))
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    h = k @ rz @ ry @ rx @ np.linalg.inv(k)
    centre = h @ np.array([cx, cy, 1.0])
    recentre = np.array([[1, 0, cx - centre[0] / centre[2]], [0, 1, cy - centre[1] / centre[2]], [0, 0, 1]])
    s = 1 + deviation.scale
    scale = np.array([[s, 0, cx * (1 - s)], [0, s, cy * (1 - s)], [0, 0, 1]])
    shift = np.array([[1, 0, 0], [0, 1, deviation.shift_y_fraction * height], [0, 0, 1]])
    return shift @ scale @ recentre @ h


def deviate_view(image: np.ndarray, deviation: RigDeviation, focal_px: float) -> np.ndarray:
    """The view ``image`` ``(H, W)`` of an ideal right camera as the deviated one sees it: warped by
    :func:`deviation_homography` (bilinear; what falls outside the view is black) and scaled by ``1 + gain``.

    A float32 image in [0, 1] comes back float32 in [0, 1]; a uint8 image (a camera frame) comes back uint8, rounded.
    """
    import cv2

    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype not in (np.uint8, np.float32):
        raise InputError(f"image: expected a 2-D uint8 or float32 array, got "
                         f"{getattr(image, 'dtype', type(image).__name__)} of shape {getattr(image, 'shape', None)}")
    height, width = image.shape
    h = deviation_homography(deviation, height, width, focal_px)
    gray = image.astype(np.float32) / 255 if image.dtype == np.uint8 else image
    warped = cv2.warpPerspective(gray, h, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    seen = np.clip(warped * (1 + deviation.gain), 0, 1)
    return np.rint(seen * 255).astype(np.uint8) if image.dtype == np.uint8 else seen
