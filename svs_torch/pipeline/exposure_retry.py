"""A second run, with the right view's exposure matched, for the pairs the first run could not range and whose
two views' exposures differ (issue 33, item 2: two boards, two gains).

Why a retry and not always: matching the exposure before every stage (``PipelineConfig.exposure``) ranges a
tuned scene behind a right camera 30 % brighter (Middlebury Piano: 0 → 99.5 %) but loses one whose two views are
lit by different lamps (PianoL), where the map of one view's quartiles onto the other's is wrong for most of the
image (``experiments/exposure.md``). A pair that the first run verified and ranged fully is left as it is; only a
pair left unverified, or with a kept object unranged, or measured on the dense stage's coarse grid
(``PipelineResult.coarse``), or whose nearness split was taken again (``StereoSegmentation.split_retaken``), whose
views' quartiles differ by more than ``ExposureConfig.min_change`` (by default
:data:`~svs_torch.pipeline.exposure.RETRY_MIN_CHANGE`: below it the difference is the two views' content, not a
gain, and a second run there only costs time), is run again on the matched views. The second
result is kept only where it is verified and ranges more objects (or as many, the first being unverified or coarse
and the second not; or, the first's split taken again and the second's not, any object with more of the kept
regions measured): views of two different scenes are never verified (``experiments/verify_views.py``), so the
retry cannot let them through.

Why the map must bring the matched points together (``PipelineConfig.exposure_retry_max_residual_ratio``): a
second run helps where one camera's gain differs from the other's, and a gain is one map for every point of the
view. Where the map fitted to the two views' quartiles leaves the first run's RANSAC inliers as far apart as before
(:func:`~svs_torch.pipeline.exposure.matched_residual_ratio` over 0.8), the views differ by their lighting or their
content, and the second run is another draw of the same noise, not a corrected pair. Such runs were seven in ten
of those the tuning sets ran (199 of 288: 186 whose second was not kept, PianoL's among them, guide's one frame over
50 ms, and 13 that were, mostly PianoL's: a draw that fell better, balanced by as many that fell worse, the
camera-frame suite 98.668 -> 98.660 % per object; ``experiments/exposure.md``, "The map at the matched points").

Why a complete first result needs a plausible second: a first run verified with every kept object ranged is
retried only because the dense stage measured it on its coarse grid. Where the matched views are measured on the
coarse grid too, a second that ranges more objects has not ranged what the first could not; it has kept another
region, and on a camera frame that region may be a blob of wrong matches (tuned PianoL at 320×240, right camera
30 % brighter, JPEG digit 4: an extra object at 63 px among a scene of 7–23 px, ranged at 0.75 m where its truth is
1.86: 99.5 → 69.7 % per object). Such a second replaces the first only where each object it ranges lies within
the features' reach: its disparity at most :data:`~svs_torch.pipeline.near_surface.MAX_INLIER_RATIO` times the
pair's :data:`INLIER_RANK`-th largest RANSAC inlier disparity plus
:data:`~svs_torch.pipeline.near_surface.INLIER_MARGIN_PX`, the near-surface rule's bound. A rendered scene whose
matched frame finds its second box still takes it (digit 8, right camera 30 % brighter: 99.2 % per object,
where the first kept would give 75.0). The same bound works the other way: where the first was measured on the
coarse grid and the second is not, the first's objects beyond the features' reach do not count against the
second's (tuned Piano at native size, right camera 30 % brighter: a clipped patch ranged at 1.24 m beside the
piano, 80.1 %; the matched run's piano alone, 99.7 %).

Why the taken-again split: a brighter right camera clips its highlights, the clipped patch draws wrong matches
above the scene, and the split taken under them may keep the wrong regions yet range them (tuned Piano at
320×240, right camera 30 % brighter: two objects ranged at 89.3 % with its split taken again, its nearest at
99.3 % on the matched views, whose split is the usual one). A scene whose matched views still need the split
taken again (PianoL, two lamps) keeps its first result. No held-out clean pair takes its split again, so they
never pay for the check.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch

from ..core.pair_trees import take_pairs
from ..core.size_groups import replace_pairs
from ..core.types import StereoBatch
from .config import PipelineConfig, PipelineResult
from .exposure import pairs_to_match
from .near_surface import INLIER_MARGIN_PX, MAX_INLIER_RATIO
from .ranging import measured_share, second_pass_is_better, unranged_kept_object

__all__ = []

#: Which of the pair's RANSAC inlier disparities, from the largest, bounds its objects' (module docstring): the third,
#: so that one or two wrong inliers along a row do not widen the bound (the PianoL frame above: 133.5, 30.9, 19.6 px).
INLIER_RANK = 3


def retry_with_exposure(batch: StereoBatch, result: PipelineResult, config: PipelineConfig,
                        run: Callable[[StereoBatch, PipelineConfig], PipelineResult]) -> PipelineResult:
    """``result`` with the pairs the module docstring names run again by ``run`` with
    ``exposure=config.exposure_retry``, where that second result is better. ``batch``: the pairs ``result`` was
    computed on (one size group, filling its tensors). Differentiable where ``run`` is (the retried pairs' map
    carries gradients to both views, as ``PipelineConfig.exposure`` does)."""
    if config.exposure_retry is None or config.exposure is not None or result.verified is None:
        return result
    # A pair measured on the coarse grid counts as unfinished too: a brighter camera's clipped highlights leave the
    # working-width SAD as few unique windows as noise does, and the coarse grid may range the clipped patch
    # (tuned Piano at native size, right camera 30 % brighter: verified at 31.7 %; exposure matched: 99.4 %).
    coarse = result.coarse  # set with verified, under the dense rule
    # A nearness split taken again counts too: a brighter camera's clipped patch also draws wrong matches above
    # the scene, and the split taken under them may range a pair whose obstacle it lost (module docstring).
    retaken = _split_retaken(result)
    unranged = unranged_kept_object(result.segmentation, result.depth.objects)
    unfinished = ~result.verified | unranged | coarse
    retried = unfinished | retaken
    if not bool(retried.any()):
        return result
    # The views' quantiles only of the unfinished pairs: over every pair they took 1.8 of 30 ms a pair (64 real
    # 320x240 pairs, one thread), where 23 of the benchmark's 512 real pairs are unfinished.
    # Those whose views' exposures differ, and whose map brings the first run's RANSAC inliers together (module
    # docstring; too few inliers to tell: run again).
    candidates = retried.nonzero().flatten()
    points, inliers = result.points, result.fundamental.inliers & result.points.valid
    index = candidates[pairs_to_match(
        *(t.detach().index_select(0, candidates) for t in (batch.left, batch.right)),
        batch.image_hw.index_select(0, candidates),
        *(t.index_select(0, candidates) for t in (points.left, points.right, inliers)),
        config.exposure_retry, config.exposure_retry_max_residual_ratio)]
    if len(index) == 0:
        return result
    pairs = batch.select(index)
    second = run(pairs, dataclasses.replace(config, exposure=config.exposure_retry))
    why = (t.index_select(0, index) for t in (unfinished, retaken, unranged))
    pick = _second_is_better(result, second, index, *why, pairs, batch)
    if not bool(pick.any()):
        return result
    return replace_pairs(result, index[pick], take_pairs(second, pick.nonzero().flatten(), len(index)),
                         batch.batch_size, batch.size_hw)


def _second_is_better(first: PipelineResult, second: PipelineResult, index: torch.Tensor, unfinished: torch.Tensor,
                      retaken: torch.Tensor, unranged: torch.Tensor, retried: StereoBatch, batch: StereoBatch
                      ) -> torch.Tensor:
    """``(b,)`` bool: the retried pairs ``index`` of ``first`` whose ``second`` result replaces the first
    (``unfinished``, ``retaken`` ``(b,)``: why each was retried; ``unranged`` ``(b,)``: those the first left with a
    kept object unranged; ``retried``: those pairs, for their calibration; ``batch``: every pair of ``first``;
    module docstring)."""
    coarse = first.coarse.index_select(0, index)
    # Against a second measured at the working width, a first from the coarse grid counts as unverified: the
    # second replaces it where verified and ranging as many objects ...
    finer = coarse & ~second.coarse
    verified_first = first.verified.index_select(0, index) & ~finer
    # ... of the first's objects within the features' reach: one beyond it is likelier a clipped patch's wrong
    # matches, which the coarse grid ranged (tuned Piano at native size, right camera 30 % brighter: 70.9 px where
    # the inliers reach 62.7, ranged at 1.24 m for a true 2.05; the matched views range the piano at 99.7 %).
    beyond, _ = _beyond_inliers(first, batch)
    ranged_first = first.depth.objects.valid.index_select(0, index) & ~(finer.unsqueeze(1)
                                                                        & beyond.index_select(0, index))
    # A first verified with every kept object ranged (retried for its coarse grid alone) gives way only to a second
    # whose objects the features reach (module docstring).
    complete = verified_first & ~unranged
    pick = unfinished & (~complete | _objects_within_inliers(second, retried)) & second_pass_is_better(
        verified_first, ranged_first, second.verified, second.depth.objects.valid)
    # Where the first run's split was taken again and the matched views' split is not, the matched views give the
    # scene's usual map and the first's regions are suspect, however many it ranged: the second replaces the first
    # where verified, ranging an object and measuring more of its kept regions (Piano at 320×240, +30 %: two
    # objects ranged on 59 % of their pixels at 89.3 %, matched one on 82 % at 99.3 %). A pair retried only for
    # its split is not replaced because the second ranges more objects: PianoL's split is taken again on matched
    # views too, and their extra region was wrong (JPEG digit 1: 97.7 -> 90.3 %).
    usual = retaken & ~_split_retaken(second) & second.verified & second.depth.objects.valid.any(1)
    more_measured = measured_share(second.depth.objects) > measured_share(first.depth.objects).index_select(0, index)
    return pick | (usual & more_measured)


def _split_retaken(result: PipelineResult) -> torch.Tensor:
    """``(B,)`` bool: the pairs whose nearness split was taken again (all False for a segmenter without one)."""
    retaken = result.segmentation.split_retaken
    return torch.zeros_like(result.verified) if retaken is None else retaken


def _objects_within_inliers(result: PipelineResult, batch: StereoBatch) -> torch.Tensor:
    """``(B,)`` bool: the pairs of ``result`` (on ``batch``) whose every ranged object lies within the features'
    reach (:func:`_beyond_inliers`; False for a pair without an inlier). Not differentiable (a choice between
    results)."""
    beyond, has_inliers = _beyond_inliers(result, batch)
    return has_inliers & ~beyond.any(1)


def _beyond_inliers(result: PipelineResult, batch: StereoBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, N)`` bool: the ranged objects of ``result`` (on ``batch``) whose disparity (from its median depth,
    ``f·B / Z − doffs``) exceeds ``MAX_INLIER_RATIO`` times the pair's :data:`INLIER_RANK`-th largest RANSAC inlier
    disparity plus ``INLIER_MARGIN_PX`` (the largest there is, with fewer inliers); and ``(B,)`` bool, the pairs
    with an inlier (every ranged object of a pair without one counts as beyond). Not differentiable."""
    sparse = result.depth.disparities
    disparity = sparse.disparity_px.detach()
    known = result.fundamental.inliers & sparse.valid & disparity.isfinite()
    objects = result.depth.objects
    rank = min(INLIER_RANK, disparity.shape[1])
    if rank == 0:
        return objects.valid.clone(), torch.zeros_like(result.verified)
    top = torch.where(known, disparity, torch.full_like(disparity, -torch.inf)).topk(rank, dim=1).values
    count = known.sum(1).clamp(max=rank)
    reach = top.gather(1, (count - 1).clamp_min(0).unsqueeze(1)).to(torch.float64) * MAX_INLIER_RATIO + INLIER_MARGIN_PX
    scale = (batch.focal_px * batch.baseline_m).detach().to(torch.float64).unsqueeze(1)
    object_disparity = (scale / objects.depth_median_m.detach().to(torch.float64).clamp_min(1e-12)
                        - batch.doffs_px.detach().to(torch.float64).unsqueeze(1))
    has_inliers = count > 0
    return objects.valid & ((object_disparity > reach) | ~has_inliers.unsqueeze(1)), has_inliers
