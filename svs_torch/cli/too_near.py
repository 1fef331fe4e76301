"""What ``svs-depth estimate`` tells of an unranged pair whose RANSAC inliers lie nearer than the dense stage
searched (:mod:`svs_torch.pipeline.beyond_range`): an obstacle that near is in view, not nothing."""

from __future__ import annotations

__all__ = ["MIN_POINTS", "TOO_NEAR", "too_near_reason"]

#: Fewest inliers beyond the range that tell of a near obstacle (RANSAC's fewest for an F): Teddy's left view beside
#: its mirror image kept 9 chance inliers, 3 of them beyond the range, and was told of an obstacle at 0.3 m.
MIN_POINTS = 8

#: What such a pair is told (an audit: a box 0.27 m away before a wall read NO_DENSE_DEPTH, the status of a flat or
#: occluded pair, with no hint; its 65 inliers read 110 px, over the 95 px searched).
TOO_NEAR = ("{count} matched points lie nearer than the dense stage searched (their median {depth:.2f} m away): an "
            "obstacle that near is in view and not ranged")


def too_near_reason(result, index: int) -> str | None:
    """:data:`TOO_NEAR` for pair ``index`` of a dense-rule pipeline result where at least :data:`MIN_POINTS` of its
    RANSAC inliers lie beyond the range its dense stage searched, else None."""
    from ..pipeline.beyond_range import inliers_beyond_search

    if result.dense is None:
        return None
    depths = result.depth.points
    beyond = inliers_beyond_search(result.depth.disparities, result.fundamental.inliers,
                                   result.dense)[index] & depths.valid[index]
    if int(beyond.sum()) < MIN_POINTS:
        return None
    return TOO_NEAR.format(count=int(beyond.sum()), depth=float(depths.depth_m[index][beyond].median()))
