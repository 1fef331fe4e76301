"""``svs-depth guide``'s warm-up: a pair ranged before the first frame, so that the walker's first warnings do not
wait for what a process does only once; and the ranger it warms up (:func:`pair_ranger`).

What a process does once: load the C kernels, make torch's first calls, and import the modules the pipeline imports
only when a pair first needs them. The largest of these is kornia (0.24–0.29 s on this machine), which the noisy
retries' Gaussian (:func:`svs_torch.pipeline.stages.gaussian_smoothed`) and the rectifying warp
(:func:`svs_torch.geometry.rectification.warp_rectified`) import at their first call: a command ranging clean,
aligned pairs never pays for it, but a walker's guide would pay it in the middle of a walk, at the first noisy or
loose-rig frame. Measured on the shared real pairs as 320×240 camera frames (JPEG digit 4, noise σ 4), two
threads, a fresh process each: the first frame took 172 ms where it takes 61 ms once warm, and the first frame that
took the noisy retry 572 ms against 200 ms.
"""

from __future__ import annotations

import argparse
import importlib
import time
import warnings
from collections.abc import Callable

import torch

from ..core.camera import SVS_CAMERA, SVSCamera
from ..core.types import StereoBatch
from .rig import calibration_from_args, with_calibrated_rectification

__all__ = ["import_deferred_modules", "pair_ranger", "warm_up"]

#: The board's default JPEG quality digit and a camera's sensor noise (8-bit levels) of the warm-up pair: a
#: camera's frame, so that the pair takes the paths a camera's frames take.
WARM_UP_DIGIT, WARM_UP_NOISE_LEVELS = 4, 4.0


#: What the pipeline imports inside a function, at a pair's first need (the module docstring says where);
#: ``tests/capture/test_guide.py`` finds every such import in the pipeline's packages and checks it is here.
DEFERRED_MODULES = ("kornia.filters", "kornia.geometry.transform")


def import_deferred_modules() -> None:
    """Import :data:`DEFERRED_MODULES`."""
    for name in DEFERRED_MODULES:
        importlib.import_module(name)


def warm_up(ranged: Callable[[StereoBatch], object], size_wh: tuple[int, int], camera: SVSCamera = SVS_CAMERA,
            seed: int = 0) -> float:
    """Range one rendered scene of ``size_wh`` (two obstacles 1–2 m ahead, as ``camera``'s frames: JPEG at
    :data:`WARM_UP_DIGIT`, sensor noise of :data:`WARM_UP_NOISE_LEVELS` levels, drawn from ``seed``) by ``ranged``
    (what the live loop calls on each grabbed pair), after :func:`import_deferred_modules`. Its result is not
    used, and the warnings it raises are not shown: they would be about a pair the walker never sees (and Python
    shows a warning once: the walk's own would then go unshown). Returns the seconds it took. Not
    differentiable."""
    from ..data.camera_frames import camera_frames
    from ..data.synthetic import random_obstacle_scenes

    started = time.perf_counter()
    import_deferred_modules()
    generator = torch.Generator().manual_seed(seed)
    # One ray a pixel (supersample 1): a warm-up needs a pair with obstacles to range, not an anti-aliased one.
    scenes = random_obstacle_scenes(1, 2, size_wh=tuple(size_wh), camera=camera, generator=generator, supersample=1)
    views = [camera_frames(view, WARM_UP_DIGIT, WARM_UP_NOISE_LEVELS, generator)
             for view in (scenes.batch.left, scenes.batch.right)]
    batch = StereoBatch.from_images(*views, focal_px=camera.focal_px(size_wh[0]), baseline_m=camera.baseline_m,
                                    calibrated=False, names=("warm-up",))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ranged(batch)
    return time.perf_counter() - started


def pair_ranger(args: argparse.Namespace, size: tuple[int, int]):
    """The whole pipeline as guide runs it on one grabbed pair (a :class:`~svs_torch.core.types.StereoBatch` of
    one): rectified with ``--calibration`` (checked against ``size`` before the camera opens) if given, the
    walker's segmentation (``--floor``) and ``--second-passes``
    (:meth:`~svs_torch.pipeline.PipelineConfig.for_guide`), no gradients."""
    from ..pipeline import PipelineConfig, estimate_obstacle_depth

    calibration = calibration_from_args(args)
    if calibration is not None:
        from ..geometry.calibration import rectify_with_calibration

        calibration.scaled_to(size, "--calibration")  # a rig of another aspect ratio fails before the camera opens
    config = with_calibrated_rectification(PipelineConfig(), args).for_guide(args.floor == "on",
                                                                               args.second_passes == "on")

    def ranged(batch):
        with torch.inference_mode():  # read, never trained on: no copy of the result (core.inference)
            return estimate_obstacle_depth(batch if calibration is None
                                           else rectify_with_calibration(batch, calibration), config)

    return ranged
