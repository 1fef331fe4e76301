"""The floor is not an obstacle: the ground plane found in the nearness map and taken out of it (issue 32).

A walker's camera looks ahead and a little down, so the lower part of every frame is floor (outdoors, road), and
the floor in front of the feet is the nearest surface the camera sees. The nearness rule (:mod:`.nearness`) keeps
what is near, so without this step it keeps the floor and names it the nearest obstacle (the shared KITTI street
pair ``2015/000000_10``: the road ranged at 6.9 m while the car beside the path is not kept).

Why a plane in disparity: every 3-D plane seen by a rectified pair has a disparity affine in the pixel,
``d = a·x + b·y + c``. For the floor, at ``h`` metres below a camera pitched down by θ and rolled by φ,
``hypot(a, b) = B·cos θ / h`` (``B`` the baseline in metres; the slope is in disparity pixels per image pixel, so
it does not change with the image's size) and ``a / b = −tan φ``. So ``B / hypot(a, b)`` is an upper bound of the
camera's height that units make checkable: a fronto-parallel obstacle has ``a = b ≈ 0`` (a height beyond any
walker's), a wall seen at a slant has ``|a| ≫ b``, a floor ``b > 0`` with a height of a person's chest or a car's
roof. Nothing is seen under a floor: a plane with much of the measured scene behind it is not one; and a floor
recedes, where a shallow plane along a wall facing the camera stays at one disparity. The plane is found by RANSAC
over three-point samples of the measured map's lower rows (three nearby points, the draws shared by every pair so
that a pair's answer does not depend on the batch it came in), scored by its inliers weighted by how low they lie,
refitted by least squares on its inliers and again on those within half the tolerance, and accepted where it holds
at least ``min_share`` of the view.

Chosen on the tuning data only (the tuned Middlebury scenes, the shared KITTI pairs, our rendered walker scenes:
``experiments/walker_floor.md``): a floor is found in Motorcycle, Piano and PianoL and in all four KITTI pairs
(camera heights 1.66–1.70 m at 320 px for KITTI's 1.65), none in the other tuned scenes; ``max_behind_share``
lies between the most a true floor had behind it (KITTI 2015/000000: 0.023) and the least the best plane of any
other tuned scene had without that test (Jadeplant: 0.19; an earlier fit's, Playroom: 0.068). The heights, the
roll, the share and the span are set from the geometry, not tuned. Off by default
(``SegmentationConfig.ground=None``): on the held-out Middlebury scenes, reported once, a heap seen from above
(Rocks1, the dolls of Dolls, the cloth of Cloth3/Cloth4, Moebius's table of toys) also fits such a plane within the
tolerance and was taken out, its nearest obstacle lost (Dolls at native size: 99.8 -> 79.1 %); for a walker a
missed heap is worse than a warned floor (``experiments/walker_floor.md``).

Not differentiable: the plane and its mask are constants of the hard pass (the nearness rule's gradients flow
through the disparity of the pixels that are not floor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from ..core.checks import (FLOAT32_MAX, check_count, check_generator, check_instance, check_real, check_shape,
                           real_or_nan)
from ..core.errors import InputError
from ..core.kernels.checks import canonical_bool
from ..core.mask_reductions import any_along
from ..depth.floor_distance import refit_floor_plane
from . import kernels
from .ground_plane_grid import cell_medians, sample_planes

__all__ = ["GroundPlane", "GroundPlaneConfig", "fit_ground_plane"]

#: The most three-point samples (``GroundPlaneConfig.hypotheses``).
MAX_HYPOTHESES = 2**20


@dataclass(frozen=True)
class GroundPlaneConfig:
    """Settings of the ground plane (module docstring).

    Attributes:
        min_camera_height_m, max_camera_height_m: the plane's ``B / hypot(a, b)`` (the camera's height over it,
            divided by the cosine of its pitch) must lie in this range, metres: a walker's chest or head (about
            1–1.8 m, pitched down up to 45°) and a car's roof (KITTI: 1.65 m) inside; a table top under a camera
            held above it (a few tenths of a metre) outside, since a table is an obstacle for a walker.
        max_roll_deg: the plane's roll, ``atan(|a| / b)``, at most this many degrees (a camera worn on a body
            sways; a wall seen at a slant is far steeper).
        max_pitch_deg: the camera pitched down at most this many degrees over the plane: its horizon (``d = 0``)
            lies at most ``f·tan(max_pitch_deg)`` above the image's centre row (``f`` the focal length in pixels;
            tested where the caller gives it). A walker's camera looks ahead, at obstacles 1–2 m away, not at its
            feet; a plane whose horizon lies far above the image (a tilted table top or a backdrop seen from a
            level camera, or draped cloth) would need a camera looking down steeply.
        min_share: the plane is the ground only where its inliers are at least this share of the view's sampled
            pixels (measured or not): a strip of a table top is not a floor.
        max_behind_share: at most this share of the measured pixels below the plane's horizon may lie behind it
            (beyond the tolerance): a floor hides what is under it, and every obstacle standing on it is in front of
            it, so only wrong matches lie behind a true floor. A slanted backdrop or a tilted table top, whose
            plane runs through the scene, has much of the scene behind it.
        min_span_px: the plane's inliers span at least this many disparity pixels of the working grid: within
            the tolerance, a shallow plane runs along any upright surface (a wall facing the camera) over a band
            of rows, all at one disparity; a floor recedes. A floor seen only far off (a level camera's, beyond
            3 m) spans less and is not looked for.
        tolerance_px: a pixel lies on the plane within this many disparity pixels of the working grid (the map's
            one-pixel quantisation and its noise), or ``tolerance_fraction`` of the plane's disparity where more.
        tolerance_fraction: see ``tolerance_px``.
        noisy_tolerance_px: ``tolerance_px`` for a pair whose map the noise gate matched with the wider window
            (:mod:`.nearness_denoise`): a camera frame's map scatters about the floor by more than a pixel, and a
            share of its scatter beyond the tolerance reads as points behind the floor (rendered walker scenes
            at the board's default JPEG digit 4 with noise σ 4: a true floor's behind share 0.05–0.14 at 1 px).
            At 1 / 1.5 / 2 px the walker scenes' boxes warned of at digit 4 were 30 / 33 / 35 of 36 and the false
            warnings without them 12 / 3 / 5; the tuned PianoL's per-object Acc at digit 4, 95.0 / 94.1 / 47.8 %
            (the floor taken out under its piano left a fragment ranged at 4 m).
        noisy_cell_min_share: on a pair the noise gate widened, the three-point samples are drawn from its grid
            cells' medians: each grid point the median of the measured pixels of its cell where at least this
            share of the cell is measured, else not drawn (None: the grid pixels themselves; every test still
            reads the grid pixels, :mod:`.ground_plane_grid`). Chosen on the rendered walker scenes
            (``experiments/walker_floor.md``, "Samples from cell medians"): 0.18 is 12 of a 320-px map's 64.
        lower_rows_fraction: the samples are drawn from this lower share of the rows (the floor is at the bottom
            of a walker's view; drawing there makes a three-point sample land on it far more often).
        hypotheses: the number of three-point samples.
        grid_columns: the map is sampled on a grid about this many columns wide (rows in proportion) for the fit.
        seed: the seed of the samples' generator (the same samples for every pair and every call).
    """

    min_camera_height_m: float = 0.8
    max_camera_height_m: float = 3.0
    max_roll_deg: float = 20.0
    max_pitch_deg: float = 35.0
    min_share: float = 0.04
    max_behind_share: float = 0.04
    min_span_px: float = 4.0
    noisy_tolerance_px: float = 1.5
    noisy_cell_min_share: float | None = 0.18
    tolerance_px: float = 1.0
    tolerance_fraction: float = 0.05
    lower_rows_fraction: float = 0.4
    hypotheses: int = 64
    grid_columns: int = 40
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 < real_or_nan(self.min_camera_height_m) < real_or_nan(self.max_camera_height_m) < math.inf:
            raise InputError(f"min_camera_height_m, max_camera_height_m: expected 0 < min < max, finite metres, got "
                             f"{self.min_camera_height_m!r}, {self.max_camera_height_m!r}")
        for name in ("max_roll_deg", "max_pitch_deg"):
            if not 0 <= real_or_nan(getattr(self, name)) < 90:
                raise InputError(f"{name}: expected degrees in [0, 90), got {getattr(self, name)!r}")
        for name in ("min_share", "lower_rows_fraction", "max_behind_share"):
            if not 0 < real_or_nan(getattr(self, name)) <= 1:
                raise InputError(f"{name}: expected a share in (0, 1], got {getattr(self, name)!r}")
        most = FLOAT32_MAX  # (a float32 tensor: 1e39 failed in torch.full, an ERROR row a pair)
        if not (0 < real_or_nan(self.tolerance_px) <= most and 0 < real_or_nan(self.noisy_tolerance_px) <= most
                and 0 <= real_or_nan(self.tolerance_fraction) < 1):
            raise InputError(f"tolerance_px, noisy_tolerance_px, tolerance_fraction: expected each of the first two in "
                             f"(0, {most:.3g}] and a share in [0, 1), got {self.tolerance_px!r}, "
                             f"{self.noisy_tolerance_px!r}, {self.tolerance_fraction!r}")
        # An audit: 2^31 samples tried to allocate 86 GB, a 2^63 count or seed failed inside torch, a string or -1 as
        # min_span_px ran (2^20 samples fit a 320x240 map in 0.7 s; a generator's seed is a 64-bit number).
        check_count(self.hypotheses, "hypotheses", 8, most=MAX_HYPOTHESES)
        check_count(self.grid_columns, "grid_columns", 8)
        check_count(self.seed, "seed", -2**63, most=2**64 - 1)
        check_real(self.min_span_px, "min_span_px", 0.0)
        cell = self.noisy_cell_min_share
        if cell is not None and (isinstance(cell, bool) or not isinstance(cell, (int, float)) or not 0 < cell <= 1):
            raise InputError(f"noisy_cell_min_share: expected None or a share in (0, 1], got {cell!r}")


class GroundPlane(NamedTuple):
    """The ground plane of B disparity maps.

    Attributes:
        coefficients: ``(B, 3)`` ``a, b, c`` of ``d = a·x + b·y + c`` in the map's pixels (0 where not found).
        found: ``(B,)`` bool, a plane passing every test of :class:`GroundPlaneConfig`.
        camera_height_m: ``(B,)`` ``B / hypot(a, b)``: the camera's height over the plane over the cosine of its
            pitch (NaN where not found).
        mask: ``(B, 1, H, W)`` bool, the pixels on the plane (all False where not found).
        refitted: ``(B, 3)`` the plane refitted for the camera's pose over it, which the distances ahead along the
            floor read (:func:`svs_torch.depth.floor_distance.refit_floor_plane`; 0 where not found).
    """

    coefficients: torch.Tensor
    found: torch.Tensor
    camera_height_m: torch.Tensor
    mask: torch.Tensor
    refitted: torch.Tensor | None = None


def fit_ground_plane(disparity: torch.Tensor, measured: torch.Tensor, baseline_m: torch.Tensor,
                     config: GroundPlaneConfig = GroundPlaneConfig(), working_factor: float = 1.0,
                     generator: torch.Generator | None = None, noisy: torch.Tensor | None = None,
                     focal_px: torch.Tensor | None = None) -> GroundPlane:
    """The ground plane (module docstring) of filled disparity maps ``disparity`` ``(B, 1, H, W)`` in pixels, fitted
    to the pixels ``measured`` ``(B, 1, H, W)`` bool, for rigs of ``baseline_m`` ``(B,)`` metres (a pair without a
    positive finite baseline has no plane). ``working_factor``: map pixels per pixel of the grid its disparities
    were measured on (the tolerance is in the latter). ``generator``: the samples' source (default: one seeded
    with ``config.seed``; either way the same samples serve every pair). ``noisy`` ``(B,)`` bool: the pairs whose
    map the nearness segmenter's noise gate matched with its wider window (a camera frame's noise), which take
    ``config.noisy_tolerance_px`` and draw their samples from their cells' medians (``config.noisy_cell_min_share``).
    ``focal_px`` ``(B,)``: the map's focal length in its pixels, which the pitch limit reads (None: no pitch
    limit). Not differentiable. Each pair's fit runs as one C kernel where it can
    (``kernels/ground_plane_fit.c``: 3–6 → 0.7–1.2 ms a frame at B = 1); :func:`_fit_in_torch` is its reference."""
    b, h, w = check_shape(disparity, "disparity", ["B", 1, "H", "W"]).values()  # (a list failed in the unpacking)
    check_instance(config, "config", GroundPlaneConfig)  # another kind failed on its first field (an audit)
    _check_fit_arguments(disparity, measured, baseline_m)
    measured = canonical_bool(measured)  # a mask viewed from other bytes: nonzero is True, on both paths
    disparity = disparity.detach().to(torch.float32)
    stride = max(1, round(w / config.grid_columns))
    if min(h, w) <= stride // 2:  # no grid point: nothing to fit (an empty map, or one thinner than the stride)
        return _no_plane(disparity)
    tolerance = torch.full((b,), config.tolerance_px, device=disparity.device)
    if noisy is not None:
        tolerance = torch.where(noisy.to(disparity.device), config.noisy_tolerance_px, tolerance)
    tolerance, min_span = tolerance.view(b, 1, 1) * working_factor, config.min_span_px * working_factor
    draws = _draws(config, generator).to(disparity.device)
    cells = None  # the noisy pairs, their samples drawn from their cells' medians (.ground_plane_grid)
    if noisy is not None and config.noisy_cell_min_share is not None and bool(noisy.any()):
        cells = noisy.to(disparity.device)
    least = 0 if cells is None else math.ceil(config.noisy_cell_min_share * stride * stride - 1e-9)
    plane = _fit_by_kernel(disparity, measured, baseline_m, tolerance.view(b), focal_px, draws, config, stride,
                           min_span, cells, least)
    if plane is None:
        plane = _fit_in_torch(disparity, measured, baseline_m, focal_px, tolerance, min_span, draws, stride, config,
                              cells, least)
    return plane._replace(refitted=refit_floor_plane(disparity, plane.mask & measured, plane.coefficients, plane.found,
                                                     tolerance.view(b)))


def _fit_in_torch(disparity: torch.Tensor, measured: torch.Tensor, baseline_m: torch.Tensor,
                  focal_px: torch.Tensor | None, tolerance: torch.Tensor, min_span: float, draws: torch.Tensor,
                  stride: int, config: GroundPlaneConfig, cells: torch.Tensor | None = None,
                  cell_min_px: int = 0) -> GroundPlane:
    """:func:`fit_ground_plane` in torch, the kernel's reference: its grid ``stride``, ``tolerance`` ``(B, 1, 1)``
    and ``min_span`` in the map's pixels, the samples' ``draws`` ``(N, 5)``, drawn for the pairs ``cells`` ``(B,)``
    from their cells' medians over ``cell_min_px`` pixels (:func:`~.ground_plane_grid.cell_medians`)."""
    b, _, h, w = disparity.shape
    grid_d = disparity[:, 0, stride // 2::stride, stride // 2::stride]  # (B, gh, gw)
    grid_ok = measured[:, 0, stride // 2::stride, stride // 2::stride] & (grid_d > 0)
    gh, gw = grid_d.shape[-2:]
    ys = torch.arange(gh, dtype=torch.float32, device=disparity.device) * stride + stride // 2
    xs = torch.arange(gw, dtype=torch.float32, device=disparity.device) * stride + stride // 2
    x, y = xs.view(1, -1).expand(gh, gw).reshape(-1), ys.view(-1, 1).expand(gh, gw).reshape(-1)
    points_d, points_ok = grid_d.reshape(b, -1), grid_ok.reshape(b, -1)
    lower = (ys >= (1 - config.lower_rows_fraction) * h).view(1, -1, 1)
    sample_d, sample_ok = grid_d, grid_ok
    if cells is not None:
        median, drawable = cell_medians(disparity, measured, stride, cell_min_px)
        use = cells.view(b, 1, 1)
        sample_d, sample_ok = torch.where(use, median, grid_d), torch.where(use, drawable, grid_ok)
    hypotheses = sample_planes(sample_d, sample_ok, sample_ok & lower, xs, ys, draws)
    rig = _Rig(baseline_m, focal_px, (w - 1) / 2, (h - 1) / 2)
    plausible = _plausible(hypotheses, rig, config)
    if not bool(plausible.any()):
        # No sample can be a walker's floor (a scene of upright surfaces): the rest would find none, and its
        # scoring and the whole-view mask are about two thirds of the fit's time (``guide`` fits every frame).
        return _no_plane(disparity)
    inliers, behind = _inliers(hypotheses, x, y, points_d, points_ok, tolerance, config.tolerance_fraction)
    plausible &= (behind <= config.max_behind_share) & (_span(inliers, points_d) >= min_span)
    # Each inlier weighs by how low it lies in the view, none above the sampled rows: a shallow plane through the
    # band where a wall meets the floor gathers as many points as the floor itself, but not at the bottom.
    weight = (y - (1 - config.lower_rows_fraction) * h).clamp_min(0)
    counts = torch.where(plausible, (inliers * weight).sum(-1), -1.0)  # (B, N)
    best = counts.argmax(1)
    chosen = inliers[torch.arange(b, device=disparity.device), best]  # (B, P)
    plane = _least_squares(x, y, points_d, chosen)
    # Refitted once more on the points within half the tolerance: where the floor meets a wall or an obstacle's
    # foot, a band of rows of the upright surface lies within the tolerance of the plane, all on its near side,
    # and flattens the first refit (a floor 1.3 m under a camera pitched 15°, with a wall at 4 m: 1.43 m for 1.35).
    close = _inliers(plane.unsqueeze(1), x, y, points_d, points_ok, tolerance / 2, config.tolerance_fraction / 2)[0]
    plane = torch.where((close[:, 0].sum(-1) >= 3).view(-1, 1), _least_squares(x, y, points_d, close[:, 0]), plane)
    # Counted once more and tested again: this plane is the one the mask uses.
    on_plane, behind = _inliers(plane.unsqueeze(1), x, y, points_d, points_ok, tolerance, config.tolerance_fraction)
    share = on_plane[:, 0].sum(-1).to(torch.float32) / max(1, x.numel())
    found = _plausible(plane.unsqueeze(1), rig, config)[:, 0] & (share >= config.min_share)
    found &= (behind[:, 0] <= config.max_behind_share) & (_span(on_plane, points_d)[:, 0] >= min_span)
    found &= counts.gather(1, best.view(-1, 1))[:, 0] > 0
    if not bool(found.any()):
        return _no_plane(disparity)
    mask = _pixels_on(plane, found, disparity, tolerance.view(b, 1, 1, 1), config.tolerance_fraction)
    height = baseline_m.to(torch.float32) / torch.hypot(plane[:, 0], plane[:, 1]).clamp_min(1e-12)
    return GroundPlane(torch.where(found.view(-1, 1), plane, 0.0), found, torch.where(found, height, math.nan), mask)


def _check_fit_arguments(disparity: torch.Tensor, measured: torch.Tensor, baseline_m: torch.Tensor) -> None:
    """:func:`fit_ground_plane`'s ``measured`` and ``baseline_m`` against ``disparity``, raising :class:`InputError`."""
    b = disparity.shape[0]
    if measured.shape != disparity.shape or measured.dtype != torch.bool:
        raise InputError(f"measured: expected a bool tensor of shape {tuple(disparity.shape)}, got "
                         f"{measured.dtype} {tuple(measured.shape)}")
    if not isinstance(baseline_m, torch.Tensor) or baseline_m.shape != (b,):
        raise InputError(f"baseline_m: expected a tensor of shape ({b},), got "
                         f"{tuple(baseline_m.shape) if isinstance(baseline_m, torch.Tensor) else baseline_m!r}")


def _no_plane(disparity: torch.Tensor) -> GroundPlane:
    """The :class:`GroundPlane` of maps ``disparity`` ``(B, 1, H, W)`` where no pair has one: what the whole fit
    gives then (zero coefficients, NaN heights, an empty mask)."""
    b = disparity.shape[0]
    return GroundPlane(disparity.new_zeros(b, 3), torch.zeros(b, dtype=torch.bool, device=disparity.device),
                       disparity.new_full((b,), math.nan), torch.zeros_like(disparity, dtype=torch.bool),
                       disparity.new_zeros(b, 3))


#: The default samples' uniforms by (seed, hypotheses): the same numbers every call (guide fits every frame). At most
#: :data:`_MAX_DRAWS` tables, the oldest dropped first: unbounded, a sweep over seeds kept every table for the life of
#: the process, 40 MB each at MAX_HYPOTHESES (12 seeds: 226 → 709 MB; an audit of the API's effect on its caller).
_DRAWS: dict[tuple[int, int], torch.Tensor] = {}
_MAX_DRAWS = 4


def _draws(config: GroundPlaneConfig, generator: torch.Generator | None) -> torch.Tensor:
    """The samples' uniforms ``(N, 5)`` float64 on the CPU: from ``generator``, or from one seeded with
    ``config.seed`` (drawn once per process)."""
    check_generator(generator)
    if generator is not None:
        return torch.rand(config.hypotheses, 5, generator=generator, dtype=torch.float64)
    key = (config.seed, config.hypotheses)
    table = _DRAWS.get(key)
    if table is None:
        with torch.inference_mode(False):  # a normal tensor, whichever mode the first call ran in
            table = torch.rand(config.hypotheses, 5, generator=torch.Generator().manual_seed(config.seed),
                               dtype=torch.float64)
        while len(_DRAWS) >= _MAX_DRAWS:  # each step safe should another thread drop one meanwhile
            _DRAWS.pop(next(iter(_DRAWS), None), None)
        _DRAWS[key] = table
    return table


def _fit_by_kernel(disparity: torch.Tensor, measured: torch.Tensor, baseline_m: torch.Tensor,
                   tolerance_px: torch.Tensor, focal_px: torch.Tensor | None, draws: torch.Tensor,
                   config: GroundPlaneConfig, stride: int, min_span_px: float, cells: torch.Tensor | None = None,
                   cell_min_px: int = 0) -> GroundPlane | None:
    """:func:`fit_ground_plane` by the C kernel (``kernels/ground_plane_fit.c``) from its grid ``stride``, the
    samples' ``draws`` ``(N, 5)``, ``tolerance_px`` ``(B,)`` and ``min_span_px`` in the map's pixels, the pairs
    ``cells`` ``(B,)`` sampled from their cells' medians over ``cell_min_px`` pixels; None where it cannot run."""
    h, w = disparity.shape[-2:]
    settings = {"stride": stride, "min_span_px": min_span_px, "tolerance_fraction": config.tolerance_fraction,
                "lower_row": (1 - config.lower_rows_fraction) * h,
                "tan_roll": math.tan(math.radians(config.max_roll_deg)), "min_height_m": config.min_camera_height_m,
                "max_height_m": config.max_camera_height_m, "tan_pitch": math.tan(math.radians(config.max_pitch_deg)),
                "max_behind_share": config.max_behind_share, "min_share": config.min_share, "centre_x": (w - 1) / 2,
                "centre_y": (h - 1) / 2}
    focal = None if focal_px is None else focal_px.to(torch.float32)
    fast = kernels.ground_plane_fit(disparity, measured, baseline_m.to(torch.float32), tolerance_px, focal, draws,
                                    settings, cells, cell_min_px)
    return None if fast is None else GroundPlane(*fast)


class _Rig(NamedTuple):
    """What the plausibility tests read of the rigs: ``baseline_m`` ``(B,)``, ``focal_px`` ``(B,)`` or None, and the
    map's centre column and row."""

    baseline_m: torch.Tensor
    focal_px: torch.Tensor | None
    centre_x: float
    centre_y: float


def _plausible(planes: torch.Tensor, rig: _Rig, config: GroundPlaneConfig) -> torch.Tensor:
    """``(B, N)`` bool: planes ``(B, N, 3)`` that can be a walker's floor (``GroundPlaneConfig``'s height, roll and
    pitch) for the rigs ``rig``."""
    a, b = planes[..., 0], planes[..., 1]
    height = rig.baseline_m.to(planes.dtype).view(-1, 1) / torch.hypot(a, b)
    roll_ok = a.abs() <= math.tan(math.radians(config.max_roll_deg)) * b
    ok = (b > 0) & roll_ok & (height >= config.min_camera_height_m) & (height <= config.max_camera_height_m)
    if rig.focal_px is None:
        return ok
    # The horizon (d = 0) at the centre column lies f·tan θ above the centre row for a camera pitched down by θ.
    horizon = -(a * rig.centre_x + planes[..., 2]) / b.clamp_min(1e-12)
    lowest = rig.centre_y - rig.focal_px.to(planes.dtype).view(-1, 1) * math.tan(math.radians(config.max_pitch_deg))
    return ok & (horizon >= lowest)


def _inliers(planes: torch.Tensor, x: torch.Tensor, y: torch.Tensor, d: torch.Tensor, ok: torch.Tensor,
             tolerance_px: torch.Tensor, tolerance_fraction: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, N, P)`` bool: the grid points (``ok`` ``(B, P)``) within the tolerance (``tolerance_px`` ``(B, 1, 1)``,
    or ``tolerance_fraction`` of the plane's disparity where more) of each plane ``(B, N, 3)``
    where the plane lies in front of the camera (a positive disparity); and ``(B, N)`` the share of the points
    there that lie beyond the tolerance behind it: under a floor, where nothing can be seen (module docstring)."""
    predicted = planes[..., 0:1] * x + planes[..., 1:2] * y + planes[..., 2:3]  # (B, N, P)
    limit = torch.clamp_min(tolerance_fraction * predicted, tolerance_px)
    below_horizon = ok.unsqueeze(1) & (predicted > 0)
    offset = d.unsqueeze(1) - predicted
    behind = (below_horizon & (offset < -limit)).sum(-1) / below_horizon.sum(-1).clamp_min(1)
    return below_horizon & (offset.abs() <= limit), behind


def _span(inliers: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` the range of the disparities ``d`` ``(B, P)`` of each plane's ``inliers`` ``(B, N, P)`` (0 with
    none)."""
    top = torch.where(inliers, d.unsqueeze(1), -math.inf).amax(-1)
    bottom = torch.where(inliers, d.unsqueeze(1), math.inf).amin(-1)
    return torch.where(any_along(inliers, -1), top - bottom, 0.0)


def _least_squares(x: torch.Tensor, y: torch.Tensor, d: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``(B, 3)`` the least-squares plane of the points ``weight`` ``(B, P)`` bool selects (NaN with fewer than
    three or a singular system)."""
    design = torch.stack([x, y, torch.ones_like(x)], -1).double()  # (P, 3); float64: sums of x² over the view
    wd = weight.double()
    normal = torch.einsum("bp,pi,pj->bij", wd, design, design)
    rhs = torch.einsum("bp,pi,bp->bi", wd, design, d.double())
    solution, info = torch.linalg.solve_ex(normal, rhs.unsqueeze(-1))
    ok = (info == 0) & (weight.sum(-1) >= 3)
    return torch.where(ok.view(-1, 1), solution.squeeze(-1).to(d.dtype), math.nan)


def _pixels_on(plane: torch.Tensor, found: torch.Tensor, disparity: torch.Tensor, tolerance_px: torch.Tensor,
               tolerance_fraction: float) -> torch.Tensor:
    """``(B, 1, H, W)`` bool: the pixels of ``disparity`` within the tolerance (``tolerance_px`` ``(B, 1, 1, 1)``)
    of their pair's ``plane`` ``(B, 3)`` (none where not ``found``)."""
    b, _, h, w = disparity.shape
    xs = torch.arange(w, dtype=disparity.dtype, device=disparity.device).view(1, 1, 1, w)
    ys = torch.arange(h, dtype=disparity.dtype, device=disparity.device).view(1, 1, h, 1)
    coefficients = torch.where(found.view(-1, 1), plane, 0.0).view(b, 3, 1, 1)
    predicted = coefficients[:, 0:1] * xs + coefficients[:, 1:2] * ys + coefficients[:, 2:3]
    limit = torch.clamp_min(tolerance_fraction * predicted, tolerance_px)
    return found.view(-1, 1, 1, 1) & (predicted > 0) & ((disparity - predicted).abs() <= limit)
