"""What ``svs-depth estimate`` tells of a ranged pair whose matches all fit one homography: the two images alone
cannot tell a flat surface facing the cameras (a wall, a poster), which the rig's baseline ranges, from a scene
with depth seen by a right camera turned with no baseline (no distance holds)."""

from __future__ import annotations

from .fundamental import PLANAR_SHARE, homography_share

__all__ = ["ONE_HOMOGRAPHY", "one_homography_reason"]

#: The homography's reprojection threshold, pixels of a pair 320 wide (the pipeline's RANSAC threshold), scaled down
#: with a narrower pair's width: at 160 x 120 a 1 px threshold put 95 % of a shared pair's inliers (Cloth1's) on one
#: homography, half a pixel at most 86 %, and 95-100 % of a turned camera's.
THRESHOLD_PX = 1.0

#: What a ranged pair whose matches all lie on one homography is told (an audit: Teddy's left view turned 3° about
#: the camera's y axis, no baseline, was ranged "OK", "verified", at 1.71 m by the SVS model (0.53 m turned at
#: Teddy's focal length), where a pure rotation holds no depth; OpenCV's findFundamentalMat and
#: stereoRectifyUncalibrated accept it as well). The shared Middlebury pairs put at most 77 % of their inliers on
#: one homography at 320 x 240.
ONE_HOMOGRAPHY = ("{share:.0%} of the RANSAC inliers fit one homography: the distance holds for a flat surface "
                  "facing the cameras (a wall, a poster); if the scene has depth, the right camera turned with no "
                  "baseline between the views (two frames of one turning camera) and no distance holds")


def one_homography_reason(result, index: int, width_px: int) -> str | None:
    """:data:`ONE_HOMOGRAPHY` for pair ``index`` of a pipeline result, ``width_px`` wide (its working pixels), where
    at least :data:`PLANAR_SHARE` of its RANSAC inliers (8 or more) fit one homography within :data:`THRESHOLD_PX`
    (scaled), else None."""
    points = result.points
    kept = points.valid[index] & result.fundamental.inliers[index]
    # A tensor op a side, not two a point: guide --json reports every pair it ranges.
    rows = [left + right for left, right in zip(points.left[index][kept].tolist(), points.right[index][kept].tolist())]
    share = homography_share(rows, THRESHOLD_PX * min(1.0, width_px / 320))
    return None if share is None or share < PLANAR_SHARE else ONE_HOMOGRAPHY.format(share=share)
