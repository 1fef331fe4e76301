"""The two views' exposures matched before any stage sees the pair (issue 33, item 2).

Why: the SVS is two SRV-1 boards, each with its own sensor, gain and exposure, so one view of a pair is often
brighter than the other. The stages that compare the two views' intensities or gradients (the nearness
segmenter's and the dense stage's block matching on clipped x-Sobel levels, whose SAD grows with a gain
difference; their texture and uniqueness tests) are hurt by it: a right view 30 % brighter left a tuned scene
(Middlebury Piano) unranged (``experiments/real_rig.py``, "gain +30%"). SURF's descriptors are normalised and do
not need it.

The map is affine, fitted so that two quantiles of the right view (default the quartiles) land on the left
view's: a gain and a black level, robust to the few pixels that saturate and to the strips that only one camera
sees. It is applied to the darker view (the lower upper quantile), mapped up onto the other's exposure and
clipped to [0, 1]: ``right' = clip(scale · right + offset)`` where the right view is the darker, else
``left' = clip((left − offset) / scale)``. Why the darker one up and not the brighter one down: a brighter camera
clips its highlights, and a clipped patch has no texture. Mapped down it stays a flat patch facing a textured
one, where the block matchers find wrong matches that the nearness segmenter keeps as a near region (Piano with
the right view 50 % brighter, 18 % of it clipped: the lamp's wall kept, the pair unranged, 0 %); mapping the
darker view up clips the same patch in both views, which the texture rule then leaves alone (99.4 %; 70 %
brighter: 0 -> 93.3 %). Pairs whose views already agree, ``|scale − 1| + |offset|`` within ``min_change``, are
left exactly as they are (a pair's two views of one scene never have identical histograms, so a correction
smaller than that is noise, not exposure).

With ``ExposureConfig.min_right_clipped_share`` only pairs whose right view is clipped at white on that much more of
its pixels than the left are mapped (``PipelineConfig.exposure_right_clipped``). Why the right view: the block
matchers' texture rule reads the left (reference) window, so a highlight clipped in the left view alone is a flat
left patch the rule already rejects, while one clipped in the right view alone is a flat right patch facing a
textured left one, whose wrong matches move the objects' medians (tuned scenes made bright,
``experiments/real_rig.py --brightness 1.8``, right camera 30 % brighter: 98.78 -> 99.34 % per object at
320×240). Such a view's upper quartile may lie on its clipped plateau, so its two quantiles are fitted below the
larger clipped share of the two views (each scaled by one minus it): fitted on the quartiles, that map lost the
same pairs (96.01 %). Off by default: the held-out corners that add a gain to a turn or tilt fell with it
(``experiments/real_rig.md``, "One-sided clipping").

Differentiable: ``scale`` and ``offset`` are ``torch.quantile``'s of the views (interpolated order statistics), so
gradients flow to both images through the map and its parameters, except where the clip saturates.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..core.checks import InputError, check_shape, real_or_nan
from ..core.levels import CLIPPED_LEVEL
from ..core.numerics import per_pair
from ..depth.quantiles import row_quantile

__all__ = ["CLIPPED_LEVEL", "RETRY_MIN_CHANGE", "ExposureConfig", "exposure_change", "exposures_differ",
           "match_exposure", "matched_residual_ratio", "pairs_to_match"]

#: ``min_change`` of the default retry (``PipelineConfig.exposure_retry``). Two views of one scene never have the
#: same quartiles (their borders and occlusions show different things), so a small ``|scale − 1| + |offset|`` is
#: the scene, not a gain. The tuned scenes' pairs with a ±30 % gain measure 0.143 and up at both sizes (0.174 and
#: up but for MotorcycleE and PianoL, shot at another exposure or under another lamp, whose own views differ by
#: 0.17–0.57); the others' pairs without one, clean, as camera frames or misaligned, at most 0.148, 90 % of them
#: under 0.105 (``python experiments/exposure_change.py``). At 0.05 the retry also ran pairs whose views differ
#: only by what each sees, for no gain on the tuning sets, and a third of the held-out camera frames twice
#: (experiments/exposure.md, "Which pairs are retried").
RETRY_MIN_CHANGE = 0.14


@dataclass(frozen=True)
class ExposureConfig:
    """Options of :func:`match_exposure`.

    Attributes:
        quantiles: the two quantiles of each view the map matches (low, high), in (0, 1).
        min_change: pairs with ``|scale − 1| + |offset|`` (offset in image units, [0, 1] intensities) at or below
            this are left unchanged.
        min_right_clipped_share: None: every pair is fitted. A share in (0, 1]: only pairs whose right view has
            at least this share of its pixels more clipped at white (:data:`CLIPPED_LEVEL`) than the left view,
            and their quantiles fitted below the clipped share (module docstring).
    """

    quantiles: tuple[float, float] = (0.25, 0.75)
    min_change: float = 0.05
    min_right_clipped_share: float | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.quantiles, (tuple, list)) and len(self.quantiles) == 2
                and all(isinstance(q, (int, float)) for q in self.quantiles)):
            raise InputError(f"quantiles: expected two numbers (low, high), got {self.quantiles!r}")
        low, high = self.quantiles
        if not 0 < low < high < 1:
            raise InputError(f"quantiles: expected two quantiles 0 < low < high < 1, got {self.quantiles!r}")
        if not real_or_nan(self.min_change) >= 0:
            raise InputError(f"min_change: expected a number >= 0, got {self.min_change!r}")
        share = self.min_right_clipped_share
        if share is not None and not (type(share) in (int, float) and 0 < share <= 1):
            raise InputError(f"min_right_clipped_share: expected a share in (0, 1] or None, got {share!r}")


def match_exposure(left: torch.Tensor, right: torch.Tensor, image_hw: torch.Tensor,
                   config: ExposureConfig = ExposureConfig()) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Both views with the darker one mapped onto the brighter one's exposure (module docstring).

    Args:
        left, right: ``(B, 1, H, W)`` images in [0, 1].
        image_hw: ``(B, 2)`` int64, each pair's own size: only those pixels are measured (the pipeline calls this
            on groups of one size, which fill their tensors).
        config: :class:`ExposureConfig`.

    Returns:
        The left and the right views ``(B, 1, H, W)`` (the same tensors when no pair needs a change; in a pair that
        does, one of the two is mapped) and whether each pair was changed ``(B,)`` bool. The mapped view carries
        gradients to both images (module docstring: through the map and its quantiles, not where clipped).
    """
    _check_views(left, right, image_hw)
    index, fit = _fit_selected(left, right, config)
    if index is None:
        return _mapped(left, right, *fit)
    changed = torch.zeros(left.shape[0], dtype=torch.bool, device=left.device)
    if not bool(fit[2].any()):
        return left, right, changed
    some_left, some_right, some_changed = _mapped(left.index_select(0, index), right.index_select(0, index), *fit)
    return (left.index_copy(0, index, some_left), right.index_copy(0, index, some_right),
            changed.index_copy(0, index, some_changed))


def _clipped_share(image: torch.Tensor) -> torch.Tensor:
    return (image.detach() >= CLIPPED_LEVEL).flatten(1).to(torch.float32).mean(1)


def _fit_selected(left: torch.Tensor, right: torch.Tensor, config: ExposureConfig
                  ) -> tuple[torch.Tensor | None, tuple[torch.Tensor, ...]]:
    """:func:`_fit` over the pairs ``config`` selects: every pair (index None), or with
    ``min_right_clipped_share`` the pairs whose right view is clipped at white (:data:`CLIPPED_LEVEL`) on that
    share more of its pixels than the left, their index ``(n,)`` and their fit below the larger clipped share.
    Only those pairs are fitted: the fit below the clipped share sorts each view."""
    if config.min_right_clipped_share is None:
        return None, _fit(left, right, config)
    clipped_left, clipped_right = _clipped_share(left), _clipped_share(right)
    index = (clipped_right - clipped_left >= config.min_right_clipped_share).nonzero().flatten()
    unclipped = 1 - torch.maximum(clipped_left, clipped_right).index_select(0, index).to(left.dtype)
    return index, _fit(left.index_select(0, index), right.index_select(0, index), config, unclipped)


def _mapped(left: torch.Tensor, right: torch.Tensor, scale: torch.Tensor, offset: torch.Tensor, changed: torch.Tensor,
            right_darker: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`match_exposure`'s views and ``changed`` from :func:`_fit`'s map."""
    if not bool(changed.any()):
        return left, right, changed
    if torch.is_grad_enabled() and (scale.requires_grad or offset.requires_grad) and left.shape[0] > 1:
        # Pair by pair: the gradient to a pair's scale and offset sums over its pixels, and batched that sum was split
        # among the threads by the batch's size, so a pair's image gradients moved with its batch (5e-8; an audit).
        return per_pair(_mapped, left, right, scale, offset, changed, right_darker)
    scale, offset = scale.view(-1, 1, 1, 1), offset.view(-1, 1, 1, 1)
    darker_right = (changed & right_darker).view(-1, 1, 1, 1)
    darker_left = (changed & ~right_darker).view(-1, 1, 1, 1)
    if bool(darker_right.any()):
        right = torch.where(darker_right, (right * scale + offset).clamp(0, 1), right)
    if bool(darker_left.any()):
        # The inverse map: scale > 0 where it applies (a flat view is never changed, _fit).
        left = torch.where(darker_left, ((left - offset) / torch.where(darker_left, scale, 1.0)).clamp(0, 1), left)
    return left, right, changed


def _fit_every_pair(left: torch.Tensor, right: torch.Tensor, config: ExposureConfig
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_fit`'s four ``(B,)`` tensors as :func:`match_exposure` applies them: :func:`_fit_selected`'s map,
    and no change (scale 1, offset 0) for a pair ``config.min_right_clipped_share`` leaves out."""
    index, fit = _fit_selected(left, right, config)
    if index is None:
        return fit
    b, device = left.shape[0], left.device
    scale = torch.ones(b, dtype=fit[0].dtype, device=device).index_copy(0, index, fit[0])
    offset = torch.zeros(b, dtype=fit[1].dtype, device=device).index_copy(0, index, fit[1])
    never = torch.zeros(b, dtype=torch.bool, device=device)
    return scale, offset, never.index_copy(0, index, fit[2]), never.index_copy(0, index, fit[3])


def exposures_differ(left: torch.Tensor, right: torch.Tensor, image_hw: torch.Tensor,
                     config: ExposureConfig = ExposureConfig()) -> torch.Tensor:
    """``(B,)`` bool: the pairs :func:`match_exposure` would change (arguments as there), without mapping any
    view. Not differentiable (bool)."""
    _check_views(left, right, image_hw)
    return _fit_every_pair(left, right, config)[2]


def exposure_change(left: torch.Tensor, right: torch.Tensor, image_hw: torch.Tensor,
                    config: ExposureConfig = ExposureConfig()) -> torch.Tensor:
    """``(B,)``: how far :func:`match_exposure`'s map would move each pair, ``|scale − 1| + |offset|`` (what
    ``config.min_change`` bounds), fitted on ``config.quantiles`` of the whole views (``min_right_clipped_share``
    not applied); 0 for a pair with a flat view, which is never mapped. Arguments as :func:`match_exposure`'s; not
    differentiable (a measurement for choosing ``min_change``)."""
    _check_views(left, right, image_hw)
    scale, offset, moved, _ = _fit(left.detach(), right.detach(), ExposureConfig(config.quantiles, min_change=0.0))
    return torch.where(moved, (scale - 1).abs() + offset.abs(), 0.0)


#: Side of the square patch, pixels, whose mean :func:`matched_residual_ratio` compares at each match: it averages
#: out a camera frame's noise and JPEG blocks, and a keypoint a pixel off moves it little.
RESIDUAL_PATCH_PX = 5

#: Fewest matches :func:`matched_residual_ratio` measures a pair on (NaN below).
MIN_RESIDUAL_MATCHES = 5


def matched_residual_ratio(left: torch.Tensor, right: torch.Tensor, image_hw: torch.Tensor, left_xy: torch.Tensor,
                           right_xy: torch.Tensor, valid: torch.Tensor, config: ExposureConfig = ExposureConfig()
                           ) -> torch.Tensor:
    """``(B,)``: how far :func:`match_exposure`'s map brings the two views together where they see the same points,
    ``median |left − right|`` over each pair's ``valid`` matches after the map divided by the same before it, on
    the means of a :data:`RESIDUAL_PATCH_PX` square patch about each point (the median of an even count being the
    lower middle value, as ``torch.median``'s).

    Why: two cameras' gains differ by one map, the same at every point, so the matched points agree after it (tuned
    Piano, right camera 30 % brighter: 0.25). Two views lit by different lamps differ by another factor at each
    point, which one map fitted to the histograms does not undo (PianoL: 0.99–1.65, ``experiments/exposure.md``).

    Args:
        left, right, image_hw, config: as :func:`match_exposure`'s (every pair filling the images).
        left_xy, right_xy: ``(B, K, 2)`` matched points (x, y), pixels, e.g. a pair's RANSAC inliers.
        valid: ``(B, K)`` bool, the matches to measure.

    Returns:
        ``(B,)`` the ratio (1 where the map leaves the pair unchanged), NaN for a pair with fewer than
        :data:`MIN_RESIDUAL_MATCHES` valid matches. Not differentiable (a measurement for choosing a second run).
    """
    _check_matches(left, right, image_hw, left_xy, right_xy, valid)
    left, right = left.detach(), right.detach()
    return _residual_ratio(left, right, left_xy, right_xy, valid, _fit_every_pair(left, right, config))


def pairs_to_match(left: torch.Tensor, right: torch.Tensor, image_hw: torch.Tensor, left_xy: torch.Tensor,
                   right_xy: torch.Tensor, valid: torch.Tensor, config: ExposureConfig = ExposureConfig(),
                   max_residual_ratio: float | None = None) -> torch.Tensor:
    """``(B,)`` bool: the pairs :func:`exposures_differ` names whose map also brings their ``valid`` matches
    together, :func:`matched_residual_ratio` at most ``max_residual_ratio`` (or NaN: too few matches to tell);
    None: every pair that differs. One fit of the map for both tests, the patch means only of the pairs that
    differ. Arguments as :func:`matched_residual_ratio`'s; not differentiable."""
    _check_matches(left, right, image_hw, left_xy, right_xy, valid)
    left, right = left.detach(), right.detach()
    fit = _fit_every_pair(left, right, config)
    differ = fit[2]
    if max_residual_ratio is None or not bool(differ.any()):
        return differ
    index = differ.nonzero().flatten()
    pick = (lambda t: t.index_select(0, index))
    ratio = _residual_ratio(pick(left), pick(right), pick(left_xy), pick(right_xy), pick(valid),
                            tuple(pick(t) for t in fit))
    return differ.index_copy(0, index, ~(ratio > max_residual_ratio))  # NaN (too few matches): True


def _check_matches(left: torch.Tensor, right: torch.Tensor, image_hw: torch.Tensor, left_xy: torch.Tensor,
                   right_xy: torch.Tensor, valid: torch.Tensor) -> None:
    dims = _check_views(left, right, image_hw)
    check_shape(left_xy, "left_xy", [dims["B"], "K", 2])
    check_shape(right_xy, "right_xy", [dims["B"], left_xy.shape[1], 2])
    check_shape(valid, "valid", [dims["B"], left_xy.shape[1]])


def _residual_ratio(left: torch.Tensor, right: torch.Tensor, left_xy: torch.Tensor, right_xy: torch.Tensor,
                    valid: torch.Tensor, fit: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """:func:`matched_residual_ratio` of detached views under :func:`_fit`'s map ``fit``."""
    if valid.shape[1] == 0:  # no match at all (surf.max_keypoints=0): too few, NaN; a median of nothing raised
        return torch.full(valid.shape[:1], torch.nan, dtype=left.dtype, device=left.device)
    before = [_patch_means(view, xy.detach()).unsqueeze(1).unsqueeze(1) for view, xy in ((left, left_xy),
                                                                                      (right, right_xy))]
    after = _mapped(*before, *fit)[:2]
    mask = valid.bool()
    medians = [torch.where(mask, (a - b).abs().flatten(1), torch.nan).nanmedian(1).values
               for a, b in (before, after)]
    ratio = medians[1] / medians[0].clamp_min(1e-6)
    return torch.where(mask.sum(1) >= MIN_RESIDUAL_MATCHES, ratio, torch.nan)


def _patch_means(image: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """``(B, K)``: the mean of ``image`` ``(B, 1, H, W)`` over the :data:`RESIDUAL_PATCH_PX` square about each of
    ``xy`` ``(B, K, 2)`` (rounded to the pixel, clamped into the image; the patch cut by the border)."""
    height, width = image.shape[-2:]
    means = F.avg_pool2d(image, RESIDUAL_PATCH_PX, stride=1, padding=RESIDUAL_PATCH_PX // 2, count_include_pad=False)
    x = xy[..., 0].round().long().clamp(0, width - 1)
    y = xy[..., 1].round().long().clamp(0, height - 1)
    return means.flatten(1).gather(1, y * width + x)


def _fit(left: torch.Tensor, right: torch.Tensor, config: ExposureConfig, unclipped: torch.Tensor | None = None
         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The map's ``scale`` and ``offset`` ``(B,)``, which pairs it changes and in which the right view is the darker
    (its upper quantile at or below the left's) ``(B,)`` bool each (module docstring); with ``unclipped`` ``(B,)``,
    each pair's quantiles scaled by it (fitted below the clipped share). The views as :func:`_check_views` passed
    them."""
    if left.shape[-2] * left.shape[-1] == 0:
        nothing = torch.zeros(left.shape[0], dtype=right.dtype, device=right.device)
        never = torch.zeros(left.shape[0], dtype=torch.bool, device=right.device)
        return nothing + 1, nothing, never, never
    if unclipped is None:
        low_high_left = row_quantile(left.flatten(1), config.quantiles)  # (B, 2)
        low_high_right = row_quantile(right.flatten(1), config.quantiles)
    else:  # below the larger clipped share, so that neither quantile lies on a clipped plateau
        q = torch.tensor(config.quantiles, dtype=left.dtype, device=left.device) * unclipped.view(-1, 1)
        low_high_left, low_high_right = _row_quantiles_of(left.flatten(1), q), _row_quantiles_of(right.flatten(1), q)
    spread_right = low_high_right[:, 1] - low_high_right[:, 0]
    spread_left = low_high_left[:, 1] - low_high_left[:, 0]
    # A flat view (no spread to scale) is left alone rather than stretched from nothing, or onto nothing.
    scale = spread_left / spread_right.clamp(min=1e-3)
    offset = low_high_left[:, 0] - scale * low_high_right[:, 0]
    changed = ((scale - 1).abs() + offset.abs() > config.min_change) & (spread_right > 1e-3) & (spread_left > 1e-3)
    return scale, offset, changed, low_high_right[:, 1] <= low_high_left[:, 1]


def _check_views(left: torch.Tensor, right: torch.Tensor, image_hw: torch.Tensor) -> dict[str, int]:
    dims = check_shape(left, "left", ["B", 1, "H", "W"])
    check_shape(right, "right", [dims["B"], 1, dims["H"], dims["W"]])
    if not bool((image_hw == torch.tensor([dims["H"], dims["W"]], device=image_hw.device)).all()):
        raise InputError(f"image_hw: expected every pair to fill the ({dims['H']}, {dims['W']}) images, got "
                         f"{image_hw.tolist()}")
    return dims


def _row_quantiles_of(values: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Each row's own quantiles: ``values`` ``(B, P)``, ``q`` ``(B, Q)`` in [0, 1] → ``(B, Q)``, interpolated between
    order statistics as ``torch.quantile`` does (rank ``q · (P − 1)``). Differentiable w.r.t. ``values``."""
    ordered = values.sort(dim=1).values
    rank = q * (values.shape[1] - 1)
    below = rank.floor().long().clamp(0, values.shape[1] - 1)
    above = (below + 1).clamp(max=values.shape[1] - 1)
    return torch.lerp(ordered.gather(1, below), ordered.gather(1, above), rank - below.to(rank.dtype))
