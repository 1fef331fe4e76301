"""Views as an SVS board sends them: sensor noise, then a baseline JPEG at the board's quality digit (issue 33).

Why here: the scenes the pipeline is scored and timed on are clean images, but every frame of a real SVS is a
JPEG (quality digit 1–8, default 4) from an OV9655 sensor with its own noise. ``experiments/real_rig.py`` scores
the pipeline on such frames and ``svs-depth bench`` times ``guide``'s one-pair latency on them; the SVS emulator
(``hw/``) encodes its frames with the same digit-to-quality map.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from ..core.checks import InputError, check_image, check_instance
from ..core.types import StereoBatch

__all__ = ["JPEG_QUALITY_FOR_DIGIT", "camera_frame_pairs", "camera_frames"]

#: The board's JPEG quality digit (1 best … 8 worst, default 4) → OpenCV JPEG quality (0–100): an emulator's
#: choice, not the firmware's, which ``hw/``'s SVS emulator encodes its frames with.
JPEG_QUALITY_FOR_DIGIT = {1: 95, 2: 90, 3: 85, 4: 75, 5: 65, 6: 50, 7: 35, 8: 20}


def camera_frames(images: torch.Tensor, digit: int, sigma_levels: float, generator: torch.Generator
                  ) -> torch.Tensor:
    """``images`` ``(B, 1, H, W)`` in [0, 1] as camera frames: Gaussian sensor noise of ``sigma_levels`` 8-bit
    levels (drawn from ``generator``, all of the batch's noise in one draw, in float64), rounded to 8-bit levels,
    JPEG-encoded at the board's quality ``digit`` (:data:`JPEG_QUALITY_FOR_DIGIT`) and decoded; the same shape
    and dtype. Not differentiable (a JPEG round trip)."""
    dims = check_image(images, "images")  # 0-255 by mistake came out all white; NaN as noise near 0
    if not (isinstance(digit, int) and digit in JPEG_QUALITY_FOR_DIGIT):
        raise InputError(f"digit: expected the board's JPEG quality digit, an int in 1..8, got {digit!r}")
    if not (isinstance(sigma_levels, (int, float)) and 0 <= sigma_levels < 256):
        raise InputError(f"sigma_levels: expected a noise level in [0, 256) 8-bit levels, got {sigma_levels!r}")
    if not isinstance(generator, torch.Generator):  # None drew from torch's global generator: another answer each run
        raise InputError(f"generator: expected a torch.Generator (the noise is drawn from it; seed one with "
                         f"manual_seed), got {type(generator).__name__}")
    if dims["B"] == 0:
        return images.detach().clone()
    noise = torch.randn(images.shape, generator=generator, dtype=torch.float64) * sigma_levels
    levels = (images.detach().cpu().to(torch.float64) * 255 + noise).round().clamp(0, 255).to(torch.uint8).numpy()
    quality = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY_FOR_DIGIT[digit]]
    decoded = []
    for i in range(dims["B"]):  # OpenCV encodes one image at a time
        ok, encoded = cv2.imencode(".jpg", levels[i, 0], quality)
        if not ok:
            raise RuntimeError("cv2.imencode failed on a frame")
        decoded.append(cv2.imdecode(encoded, cv2.IMREAD_GRAYSCALE))
    frames = torch.from_numpy(np.stack(decoded).astype(np.float32) / 255)
    return frames.view(images.shape).to(device=images.device, dtype=images.dtype)


def camera_frame_pairs(batch: StereoBatch, digit: int, sigma_levels: float, generator: torch.Generator
                       ) -> StereoBatch:
    """The :class:`~svs_torch.core.types.StereoBatch` ``batch`` with both views made camera frames
    (:func:`camera_frames`), the left view's noise drawn from ``generator`` first, then the right's: two boards'
    independent noise. Not differentiable."""
    import dataclasses

    check_instance(batch, "batch", StereoBatch)
    return dataclasses.replace(batch, left=camera_frames(batch.left, digit, sigma_levels, generator),
                               right=camera_frames(batch.right, digit, sigma_levels, generator))
