"""Row alignment of a loosely mounted right camera: a similarity of the right view that puts every match on its
left row (roll, vertical shift and scale of a real rig's second board), fitted robustly to the putative matches,
and the keystone of a camera turned about its y or x axis where the rows show one.

Why not only the fundamental matrix: the SVS's obstacles are a few nearly planar regions, so F fitted to a few
dozen of their matches is loose, and the projective rectification derived from it is often refused (epipole
"in the image") or adds shear; a right camera turned by 2° about its optical axis or moved by 3 % of the image
height then leaves the dense stage matching along the wrong rows (``experiments/real_rig.py``). A similarity has
three free parameters that depth does not touch: with ``p' = A p`` for a right pixel ``p = (x, y)`` and

    A = [[a, −b, t_x], [b, a, t_y], [0, 0, 1]],

a match ``(p_left, p_right)`` of an ideal rig satisfies ``b·x_r + a·y_r + t_y = y_l`` whatever its disparity,
one linear equation per match: three matches fix ``(a, b, t_y)``. ``t_x`` cannot be told from disparity, so the
image centre keeps its column (the two principal points stay where they were).

Keystone: a right camera turned by θ about its y axis (or its x axis) sees, about the image centre, the
projective map ``p' = p / (1 + w·p)`` with ``w = (−θ/f, 0)`` (or ``(0, θ/f)``), f the focal length in pixels; its
shift of the whole view, f·tan θ, is a convergence change no uncalibrated method tells from depth and is left to
the principal points as above. Its row moves, ``θ·u·v/f`` (and ``θ·v²/f``) in pixels ``(u, v)`` from the centre,
stay under a pixel at 320×240, so the similarity's row test never sees them, but its column moves, ``θ·u²/f``
(and ``θ·u·v/f``), bias the disparity near the edges by about a pixel: up to 7 points of an object's depth
accuracy on the tuned shared scenes (``experiments/real_rig.py``, tilt y −1°: PianoL 98.9 → 92.3 %). The rows
give θ back: the similarity's inliers are refitted by least squares to ``y_l = a·v + b·u + t + p·u·v/f + q·v²/f``
(first order in θ and the roll), and a turn term is kept where it reads at least ``keystone_min_deg`` and
``keystone_min_t`` standard errors (the straight tuned pairs read up to 0.9° at three standard errors: Teddy).
The right view is then mapped about the centre by the unturn ``[[1, 0, 0], [0, 1, 0], [−p/(a·f), −q/(a·f), 1]]``
and the similarity after it, which undoes the turn's columns as well as its rows; the pipeline applies it
whatever its rows' move (``PipelineConfig.row_alignment``).

Batched over pairs: RANSAC over 3-match samples (the seeded counter-based draws of :mod:`svs_torch.geometry.ransac`, so
a pair's result does not depend on its batch), then a least-squares refit on the inliers. Not differentiable (the
inlier sets are discrete); the refit is differentiable w.r.t. the points given the inliers. Where no gradient is
asked for, the similarity's whole fit and the test of whether the rows read a keystone run as one compiled kernel a
pair (``kernels/row_alignment_fit.c``: at B = 1, 3.2 → 0.6 ms); the torch code stays its reference, and there the
hypotheses' MSAC costs are summed by ``kernels/row_alignment_cost.c`` (whose reference is :func:`_msac_cost`'s own
expression). The keystone's least squares are in :mod:`.row_alignment_keystone`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..core.checks import (InputError, check_count, check_device, check_dtype, check_finite_where, check_instance,
                           check_real, check_shape)
from ..core.kernels.checks import check_positive_hw
from . import kernels
from .ransac_sampling import draw_minimal_samples
from .row_alignment_keystone import keystone_homography, keystone_refit, mapped_row_residuals

__all__ = ["RowAlignment", "RowAlignmentConfig", "fit_row_alignment", "row_alignment_homography"]

_SAMPLE = 3  # matches per minimal sample: one row equation each, three unknowns (a, b, t_y)
#: The largest count setting (the kernel reads its settings as float64: whole numbers below 2^53).
MAX_COUNT = 2**31 - 1


@dataclass(frozen=True)
class RowAlignmentConfig:
    """Options of :func:`fit_row_alignment`.

    Attributes:
        threshold_px: a match is an inlier when the aligned right row is within this of the left row, pixels.
        num_hypotheses: 3-match samples per pair.
        min_inliers: fewest inliers to accept an alignment.
        min_inlier_share: least share of the matches that must be inliers.
        min_gain: the alignment must put at least ``max(min_gain, min_gain_share · n₀)`` more matches on their
            rows than the raw rows do (n₀ of them): with a dozen matches, three free parameters also fit a couple
            of wrong matches (Middlebury PianoL at 320×240: 10 of 11 aligned against 8 raw, a spurious 1° roll
            that cost 6 points).
        min_gain_share: see ``min_gain``.
        max_roll_deg, max_scale_change, max_shift_fraction: the largest roll, relative scale change and vertical
            shift (share of the height) accepted; beyond them the views are not a side-by-side rig. Chosen on the
            tuned split past the issue's envelope (``experiments/real_rig.py --beyond``; ``experiments/real_rig.md``,
            "Beyond the envelope"): at 5°, 10 % and 10 % a right camera rolled 10°, shifted 12 % or 20 % larger was
            left on its raw rows and ranged wrong with the status OK (77.9-95.8 % per object against 99.3 %);
            aligned, 98.6-98.9 %. Widened again past those (``--far``, "Farther"): at 25°, 35 % and 30 % a right
            view shifted 35-45 % or scaled ±40-45 % was rectified from F or left raw and ranged at 3.6-64.9 %;
            at 45°, 50 % and 50 %, 85.7-98.8 %. Neither widening changed a pair of the envelope's suites (every row
            the same).
        min_correction_px: the pipeline applies the alignment only where it moves some image corner's row by
            more than this (pixels) or corrects a keystone; a straighter rig keeps its raw rows
            (``PipelineConfig.rectify="auto"``).
        keystone_min_deg: a turn of the right camera about its y or x axis is corrected where the fit reads at least
            this many degrees (module docstring, "Keystone"); None: the similarity only.
        keystone_min_t: ... and the reading is at least this many standard errors from zero. Both chosen on the
            tuned split (``experiments/real_rig.md``): at 5 standard errors PianoL's turn goes unread (tilt y −1°
            at 320×240: 98.35 → 97.78 % per object), at 3 a straight pair is unturned; 0.3° reads as 0.5° does.
        keystone_min_inliers: fewest inliers to read a keystone (its standard error needs many matches).
        keystone_max_deg: the largest turn accepted (chosen with the limits above: 3° left a turn of 5° unread,
            92.2-97.6 % per object against 96.4-99.0 % read).
    """

    threshold_px: float = 1.0
    num_hypotheses: int = 256
    min_inliers: int = 7
    min_inlier_share: float = 0.25
    min_gain: int = 3
    min_gain_share: float = 0.25
    max_roll_deg: float = 45.0
    max_scale_change: float = 0.5
    max_shift_fraction: float = 0.5
    min_correction_px: float = 1.0
    keystone_min_deg: float | None = 0.5
    keystone_min_t: float = 4.0
    keystone_min_inliers: int = 30
    keystone_max_deg: float = 8.0

    def __post_init__(self) -> None:
        # Each field named: min_gain, min_gain_share and the keystone's were not checked (a string or -1 ran), and a
        # huge count or an inf failed in the kernel as "settings['min_inliers']", not as the field (an audit).
        for name in ("threshold_px", "max_roll_deg", "max_scale_change", "max_shift_fraction", "keystone_max_deg"):
            check_real(getattr(self, name), name, 0.0, low_open=True)
        for name in ("min_correction_px", "keystone_min_t"):
            check_real(getattr(self, name), name, 0.0)
        check_real(self.keystone_min_deg, "keystone_min_deg", 0.0, optional=True)
        check_real(self.min_inlier_share, "min_inlier_share", 0.0, 1.0)
        check_real(self.min_gain_share, "min_gain_share", 0.0, 1e6)  # a gain of more matches than the raw rows hold
        check_count(self.num_hypotheses, "num_hypotheses", 1, most=kernels.MAX_HYPOTHESES)
        for name, least in (("min_inliers", _SAMPLE), ("min_gain", 0), ("keystone_min_inliers", 0)):
            check_count(getattr(self, name), name, least, most=MAX_COUNT)


@dataclass(frozen=True)
class RowAlignment:
    """Per-pair row alignment (B pairs).

    Attributes:
        H_right: ``(B, 3, 3)`` right pixels to aligned pixels (the identity where not ``valid``).
        inliers: ``(B, K)`` bool, matches on their left row after the alignment.
        num_inliers: ``(B,)`` int64.
        correction_px: ``(B,)`` the largest row displacement of an image corner, pixels (0 where not ``valid``).
        valid: ``(B,)`` bool, an alignment within the config's limits was found.
        keystone: ``(B,)`` bool, the alignment also undoes a turn of the right camera about its y or x axis.
        keystone_deg: ``(B, 2)`` the turn about the y and the x axis read from the rows, degrees (0 where not
            ``keystone`` and for a term not significant; a right camera turned as ``experiments/real_rig.py`` turns
            it by +1° reads about +1°).
    """

    H_right: torch.Tensor
    inliers: torch.Tensor
    num_inliers: torch.Tensor
    correction_px: torch.Tensor
    valid: torch.Tensor
    keystone: torch.Tensor
    keystone_deg: torch.Tensor


def _row_residuals(params: torch.Tensor, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """|b·x_r + a·y_r + t_y − y_l| ``(B, M, K)`` for parameters ``(B, M, 3)`` = (a, b, t_y) and points
    ``(B, K, 2)``."""
    a, b, t = params.unbind(-1)
    aligned = b[..., None] * right[:, None, :, 0] + a[..., None] * right[:, None, :, 1] + t[..., None]
    return (aligned - left[:, None, :, 1]).abs()


def _msac_cost(params: torch.Tensor, left: torch.Tensor, right: torch.Tensor, valid: torch.Tensor,
               threshold_px: float) -> torch.Tensor:
    """MSAC cost ``(B, M)`` of each hypothesis: its truncated squared row errors summed over the valid matches,
    +inf for a degenerate sample. The compiled kernel (:func:`svs_torch.geometry.kernels.row_alignment_cost`) sums
    each hypothesis in one pass; this torch expression is its reference, which writes ``(B, M, K)`` arrays."""
    fast = kernels.row_alignment_cost(params, left[..., 1], right[..., 0], right[..., 1], valid, threshold_px)
    if fast is not None:
        return fast
    residuals = _row_residuals(params, left, right)  # (B, M, K)
    cost = torch.where(valid[:, None], residuals.clamp(max=threshold_px) ** 2, 0.0).sum(-1)
    return torch.where(params.isnan().any(-1), float("inf"), cost)


def _sample_params(left: torch.Tensor, right: torch.Tensor, valid: torch.Tensor, seeds: torch.Tensor,
                   num_hypotheses: int) -> torch.Tensor:
    """(a, b, t_y) of each pair's 3-match samples ``(B, M, 3)``, NaN where a sample is degenerate."""
    if valid.shape[1] == 0:  # no match rows at all: nothing to sample (every hypothesis degenerate)
        return torch.full((valid.shape[0], num_hypotheses, 3), float("nan"), dtype=left.dtype, device=left.device)
    order = torch.argsort((~valid).to(torch.int8), dim=1, stable=True)  # valid rows first
    ranks = draw_minimal_samples(seeds, 0, num_hypotheses, valid.sum(1), _SAMPLE)  # (B, M, 3)
    # A pair with fewer than three matches has ranks past its rows: kept in range, and its samples dropped below.
    rows = torch.gather(order, 1, ranks.clamp(max=valid.shape[1] - 1).flatten(1)).view_as(ranks)

    def pick(points: torch.Tensor, coordinate: int) -> torch.Tensor:
        return torch.gather(points[..., coordinate], 1, rows.flatten(1)).view_as(rows)

    system = torch.stack([pick(right, 1), pick(right, 0), torch.ones_like(pick(right, 0))], -1)  # (B, M, 3, 3)
    target = pick(left, 1).unsqueeze(-1)
    # Collinear or repeated samples make the system singular: their hypotheses are dropped, not perturbed.
    scale = system[..., :2].abs().amax((-1, -2)).clamp(min=1.0)
    ok = (torch.linalg.det(system / scale[..., None, None]).abs() > 1e-6) & (valid.sum(1, keepdim=True) >= _SAMPLE)
    identity = torch.eye(3, dtype=system.dtype, device=system.device).expand_as(system)
    safe = torch.where(ok[..., None, None], system, identity)
    params = torch.linalg.solve(safe, target).squeeze(-1)
    return torch.where(ok[..., None], params, torch.full_like(params, float("nan")))


def _refit(left: torch.Tensor, right: torch.Tensor, inliers: torch.Tensor) -> torch.Tensor:
    """Least-squares (a, b, t_y) ``(B, 3)`` over each pair's inliers (normal equations, masked)."""
    design = torch.stack([right[..., 1], right[..., 0], torch.ones_like(right[..., 0])], -1)  # (B, K, 3)
    weight = inliers.to(design.dtype).unsqueeze(-1)
    normal = (design * weight).transpose(1, 2) @ design + 1e-9 * torch.eye(3, dtype=design.dtype, device=design.device)
    rhs = (design * weight).transpose(1, 2) @ left[..., 1:2]
    return torch.linalg.solve(normal, rhs).squeeze(-1)


def _homography(params: torch.Tensor, image_hw: torch.Tensor) -> torch.Tensor:
    """``A`` ``(B, 3, 3)`` with t_x keeping the image centre's column (module docstring)."""
    a, b, t_y = params.unbind(-1)
    cy, cx = ((image_hw.to(params.dtype) - 1) / 2).unbind(-1)
    t_x = cx - (a * cx - b * cy)
    zero, one = torch.zeros_like(a), torch.ones_like(a)
    return torch.stack([torch.stack([a, -b, t_x], -1), torch.stack([b, a, t_y], -1),
                        torch.stack([zero, zero, one], -1)], -2)


def fit_row_alignment(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor,
                      image_hw: torch.Tensor, config: RowAlignmentConfig = RowAlignmentConfig(),
                      pair_seeds: torch.Tensor | None = None, focal_px: torch.Tensor | None = None) -> RowAlignment:
    """Fit each pair's right-view similarity that puts its matches on their left rows, and where ``focal_px`` is
    given, the keystone of a right camera turned about its y or x axis (module docstring).

    Points that require grad take the torch path: ``H_right``, ``correction_px`` (and a keystone's ``keystone_deg``)
    carry gradients to the points (and ``focal_px``) through the least-squares refit on the chosen inliers.

    Args:
        points_left, points_right: ``(B, K, 2)`` matched pixels (x = column).
        valid: ``(B, K)`` bool, rows holding a match.
        image_hw: ``(B, 2)`` int64, each pair's (height, width).
        config: :class:`RowAlignmentConfig`.
        pair_seeds: ``(B,)`` int64 seeds of the samples (default 0 for every pair).
        focal_px: ``(B,)`` each pair's focal length, pixels: the keystone's scale (None: the similarity only).
    """
    dims = check_shape(points_left, "points_left", ["B", "K", 2])
    check_shape(points_right, "points_right", [dims["B"], dims["K"], 2])
    check_shape(valid, "valid", [dims["B"], dims["K"]])
    check_positive_hw(image_hw, dims["B"])  # a 0 x 0 pair was taken (an audit)
    check_dtype(points_left, "points_left", "float")
    check_dtype(points_right, "points_right", "float")
    check_dtype(valid, "valid", "bool")
    check_instance(config, "config", RowAlignmentConfig)  # another kind failed on its first field (an audit)
    # As RANSAC and the match refinement check them (an audit: NaN points in valid rows were taken).
    for name, points in (("points_left", points_left), ("points_right", points_right)):
        check_finite_where(points, name, valid.unsqueeze(-1), "valid")
    if focal_px is not None:
        check_shape(focal_px, "focal_px", [dims["B"]])
        check_dtype(focal_px, "focal_px", "int|float")  # complex: deep NotImplementedError; bool: 1 px (an audit)
        check_device(focal_px, "focal_px", points_left, "the points'")  # (a meta one: a RuntimeError from its bool())
        if not bool(((focal_px > 0) & focal_px.isfinite()).all()):
            raise InputError("focal_px: expected finite focal lengths > 0, pixels")
    left, right = points_left.to(torch.float64), points_right.to(torch.float64)
    seeds = torch.zeros(dims["B"], dtype=torch.int64, device=left.device) if pair_seeds is None else pair_seeds
    keystone = focal_px is not None and config.keystone_min_deg is not None
    focal = focal_px.to(left.dtype) if keystone else None
    fast = None
    if not (torch.is_grad_enabled() and (points_left.requires_grad or points_right.requires_grad)):
        fast = _fit_similarity_kernel(left, right, valid, image_hw, seeds, focal, config)
    if fast is not None:
        similarity, inliers, reads_turn = fast
        keystone = keystone and bool(reads_turn.any())  # else _fit_keystone finds no turn either
    else:
        similarity, inliers = _fit_similarity(left, right, valid, image_hw, seeds, config)
    if not keystone:
        return similarity
    turned = _fit_keystone(left, right, inliers, valid, image_hw, focal, config)
    if turned is None:
        return similarity
    use = turned.valid
    return RowAlignment(H_right=torch.where(use[:, None, None], turned.H_right, similarity.H_right),
                        inliers=torch.where(use[:, None], turned.inliers, similarity.inliers),
                        num_inliers=torch.where(use, turned.num_inliers, similarity.num_inliers),
                        correction_px=torch.where(use, turned.correction_px, similarity.correction_px),
                        valid=similarity.valid | use, keystone=use, keystone_deg=turned.keystone_deg)


def _fit_similarity(left: torch.Tensor, right: torch.Tensor, valid: torch.Tensor, image_hw: torch.Tensor,
                    seeds: torch.Tensor, config: RowAlignmentConfig) -> tuple[RowAlignment, torch.Tensor]:
    """The similarity (RANSAC over 3-match samples, then the least-squares refit and :func:`_accept`) of points
    ``(B, K, 2)`` float64, and its inliers ``(B, K)`` before the acceptance (where a keystone fit starts)."""
    params = _sample_params(left, right, valid, seeds, config.num_hypotheses)
    cost = _msac_cost(params, left, right, valid, config.threshold_px)
    best = torch.gather(params, 1, cost.argmin(1).view(-1, 1, 1).expand(-1, 1, 3)).squeeze(1)
    inliers = valid & (_row_residuals(best.nan_to_num().unsqueeze(1), left, right)[:, 0] < config.threshold_px)
    refit = _refit(left, right, inliers)
    inliers = valid & (_row_residuals(refit.unsqueeze(1), left, right)[:, 0] < config.threshold_px)
    raw = (valid & ((left[..., 1] - right[..., 1]).abs() < config.threshold_px)).sum(1)
    return _accept(refit, inliers, valid, raw, image_hw, config), inliers


def _fit_similarity_kernel(left: torch.Tensor, right: torch.Tensor, valid: torch.Tensor, image_hw: torch.Tensor,
                           seeds: torch.Tensor, focal_px: torch.Tensor | None, config: RowAlignmentConfig
                           ) -> tuple[RowAlignment, torch.Tensor, torch.Tensor] | None:
    """:func:`_fit_similarity` by the C kernel (``kernels/row_alignment_fit.c``), with ``(B,)`` bool where the
    keystone model reads a significant turn (False everywhere without ``focal_px``); None where it cannot run."""
    settings = {name: getattr(config, name) for name in kernels.ROW_ALIGNMENT_SETTINGS
                if name not in ("max_roll_rad", "keystone_min_deg")}
    settings["max_roll_rad"] = math.radians(config.max_roll_deg)
    settings["keystone_min_deg"] = config.keystone_min_deg if config.keystone_min_deg is not None else 0.0
    fast = kernels.row_alignment_fit(left, right, valid, image_hw, seeds, focal_px, settings)
    if fast is None:
        return None
    homography, inliers, ok, count, correction, reads_turn = fast
    similarity = RowAlignment(H_right=homography, inliers=inliers & ok[:, None], num_inliers=torch.where(ok, count, 0),
                              correction_px=correction, valid=ok, keystone=torch.zeros_like(ok),
                              keystone_deg=torch.zeros_like(homography[:, 0, :2]))
    return similarity, inliers, reads_turn


def _accept(params: torch.Tensor, inliers: torch.Tensor, valid: torch.Tensor, raw: torch.Tensor,
            image_hw: torch.Tensor, config: RowAlignmentConfig) -> RowAlignment:
    """The alignment where it has enough inliers, ``min_gain`` more than the ``raw`` rows' ``(B,)``, and stays
    within the config's limits; the identity elsewhere."""
    a, b, t_y = params.unbind(-1)
    count = inliers.sum(1)
    homography = _homography(params, image_hw)
    height, width = image_hw.to(params.dtype).unbind(-1)
    centre_shift = t_y + b * (width - 1) / 2 + (a - 1) * (height - 1) / 2
    gain = torch.maximum(torch.full_like(raw, config.min_gain), (config.min_gain_share * raw).ceil().long())
    ok = (_within_limits(a, b, centre_shift, count, valid, height, config, config.min_inliers)
          & (count >= raw + gain) & params.isfinite().all(-1))
    identity = torch.eye(3, dtype=params.dtype, device=params.device).expand_as(homography)
    return RowAlignment(H_right=torch.where(ok[:, None, None], homography, identity), inliers=inliers & ok[:, None],
                        num_inliers=torch.where(ok, count, 0),
                        correction_px=torch.where(ok, _corner_row_move(homography, image_hw), torch.zeros_like(a)),
                        valid=ok, keystone=torch.zeros_like(ok), keystone_deg=torch.zeros_like(params[:, :2]))


def _within_limits(a: torch.Tensor, b: torch.Tensor, centre_shift: torch.Tensor, count: torch.Tensor,
                   valid: torch.Tensor, height: torch.Tensor, config: RowAlignmentConfig, least: int) -> torch.Tensor:
    """``(B,)`` bool: an alignment with ``(a, b)`` (``a·v + b·u``), moving the image centre's row by
    ``centre_shift``, fitted on ``count`` of the ``valid`` matches (at least ``least`` and ``min_inlier_share``),
    stays within the config's roll, scale and shift limits."""
    scale = 1 / torch.hypot(a, b).clamp(min=1e-12)  # the right camera's magnification
    return ((count >= least) & (count >= config.min_inlier_share * valid.sum(1))
            & (torch.atan2(b, a).abs() <= math.radians(config.max_roll_deg))
            & ((scale - 1).abs() <= config.max_scale_change)
            & (centre_shift.abs() <= config.max_shift_fraction * height))


def _corner_row_move(homography: torch.Tensor, image_hw: torch.Tensor) -> torch.Tensor:
    """``(B,)`` the largest row move of the four image corners under ``homography`` ``(B, 3, 3)``, pixels."""
    height, width = image_hw.to(homography.dtype).unbind(-1)
    corners = torch.stack([torch.stack([x, y], -1) for x, y in ((0 * width, 0 * height), (width - 1, 0 * height),
                           (0 * width, height - 1), (width - 1, height - 1))], 1)  # (B, 4, 2)
    return mapped_row_residuals(homography, corners, corners).amax(1)


def row_alignment_homography(points_left: torch.Tensor, points_right: torch.Tensor, inliers: torch.Tensor,
                             image_hw: torch.Tensor, focal_px: torch.Tensor | None = None,
                             keystone_deg: torch.Tensor | None = None) -> torch.Tensor:
    """The right view's alignment ``(B, 3, 3)`` refitted by least squares to the matches ``inliers`` ``(B, K)``
    bool (:attr:`RowAlignment.inliers`) of points ``(B, K, 2)`` pixels, for pairs of ``image_hw`` ``(B, 2)``: the
    last step of :func:`fit_row_alignment` given its inliers, in float64: the similarity, or where
    ``keystone_deg`` ``(B, 2)`` (:attr:`RowAlignment.keystone_deg`) holds a turn, with the same turn terms and
    ``focal_px`` ``(B,)``. Differentiable w.r.t. the points (the differentiable pass of the pipeline takes its
    gradient, issue 31)."""
    left, right = points_left.to(torch.float64), points_right.to(torch.float64)
    similarity = _homography(_refit(left, right, inliers), image_hw)
    if focal_px is None or keystone_deg is None:
        return similarity
    terms = keystone_deg != 0
    # Only the turned pairs are refitted: a pair without inliers has a = 0 in the turn's p / (a·f), whose NaN
    # gradient would pass a torch.where as NaN times 0.
    index = terms.any(1).nonzero().squeeze(1)
    if index.numel() == 0:
        return similarity
    focal = focal_px.to(torch.float64).expand(terms.shape[0])[index]
    params, _ = keystone_refit(left[index], right[index], inliers[index], image_hw[index], focal, terms[index])
    return similarity.index_put((index,), keystone_homography(params, image_hw[index], focal))


def _fit_keystone(left: torch.Tensor, right: torch.Tensor, inliers: torch.Tensor, valid: torch.Tensor,
                  image_hw: torch.Tensor, focal_px: torch.Tensor, config: RowAlignmentConfig) -> RowAlignment | None:
    """The keystone alignment (module docstring, "Keystone") started from the similarity's ``inliers``, valid where
    a turn term is significant and the fit stays within the config's limits; None where no pair reads a turn."""
    both_terms = torch.ones(valid.shape[0], 2, dtype=torch.bool, device=valid.device)  # (B, 2) even for K < 2
    params, error = keystone_refit(left, right, inliers, image_hw, focal_px, both_terms)
    read = params[:, 3:] / params[:, :1]
    terms = ((torch.rad2deg(torch.atan(read)).abs() >= config.keystone_min_deg)
             & (params[:, 3:].abs() >= config.keystone_min_t * error[:, 3:]))
    if not bool(terms.any()):  # no pair reads a turn (a straight rig): the refits below would change nothing
        return None
    for _ in range(2):  # refit on the matches the turned model puts on their rows (at native size, more of them)
        params, _ = keystone_refit(left, right, inliers, image_hw, focal_px, terms)
        homography = keystone_homography(params, image_hw, focal_px)
        inliers = valid & (mapped_row_residuals(homography, left, right) < config.threshold_px)
    a, b, t = params[:, 0], params[:, 1], params[:, 2]
    turn = torch.rad2deg(torch.atan(params[:, 3:] / a[:, None])) * torch.tensor([-1.0, 1.0], dtype=a.dtype,
                                                                                 device=a.device)
    count = inliers.sum(1)
    least = max(config.min_inliers, config.keystone_min_inliers)
    ok = (_within_limits(a, b, t, count, valid, image_hw[:, 0].to(a.dtype), config, least) & terms.any(1)
          & (turn.abs() <= config.keystone_max_deg).all(1) & params.isfinite().all(-1))
    return RowAlignment(H_right=homography, inliers=inliers & ok[:, None], num_inliers=torch.where(ok, count, 0),
                        correction_px=torch.where(ok, _corner_row_move(homography, image_hw), torch.zeros_like(a)),
                        valid=ok,
                        keystone=ok, keystone_deg=torch.where(ok[:, None] & terms, turn, torch.zeros_like(turn)))
