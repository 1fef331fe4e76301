"""What ``svs-depth estimate`` tells of a ranged pair whose matches all fit one homography: the two images alone
cannot tell a flat surface facing the cameras (a wall, a poster), which the rig's baseline ranges, from a scene
with depth seen by a right camera turned with no baseline (no distance holds)."""

from __future__ import annotations

from .fundamental import PLANAR_SHARE, homography_fit

__all__ = ["ONE_HOMOGRAPHY", "PARALLAX_FACTOR", "PARALLAX_POINTS", "RECHECK_SHARE", "SEARCH_DRAWS",
           "bounded_homography_fit", "one_homography_reason"]

#: The homography's reprojection threshold, pixels of a pair 320 wide (the pipeline's RANSAC threshold), scaled down
#: with a narrower pair's width: at 160 x 120 a 1 px threshold put 95 % of a shared pair's inliers (Cloth1's) on one
#: homography, half a pixel at most 86 %, and 95-100 % of a turned camera's.
THRESHOLD_PX = 1.0

#: A pair is not told :data:`ONE_HOMOGRAPHY` where this many of its inliers lie :data:`PARALLAX_FACTOR` times the
#: threshold or more off the homography: parallax, which a turning camera without a baseline cannot make. Why: the
#: emulator's scene (boxes before a textured wall) put 92 % of its inliers on the wall's homography, and every pair
#: of ``guide --emulator`` was told that no distance may hold, while its boxes' 22 inliers lay 8 px off it. Teddy's
#: view turned 1.5-6 degrees about the camera's y axis, no baseline, leaves 0-2 inliers 5 px off; the shared
#: Middlebury pairs at 320 x 240 19-163.
PARALLAX_POINTS = 8
#: How far off the homography an inlier shows parallax, in multiples of its threshold (:data:`PARALLAX_POINTS`).
PARALLAX_FACTOR = 5.0

#: RANSAC samples drawn to find the homography. Why bounded: only a share of :data:`PLANAR_SHARE` or more makes the
#: note, and four points drawn from such a set are all on it with probability 0.9^4 = 0.66, so 32 draws miss it
#: with probability 0.34^32 < 1e-14 (and OpenCV's own adaptive bound stops sooner there: the same homography; for
#: noisy points, :data:`RECHECK_SHARE`). A
#: real pair's share is 0.25-0.60, where OpenCV's default of 2000 draws ran to its end: 3.5 ms a pair of
#: ``estimate --pairs``' 46 ms (one worker, 512 real 320x240 pairs), 1.1 ms at 64 draws; no note changed over the
#: shared pairs at 160, 320 px and native.
SEARCH_DRAWS = 32
#: ... but a share from this up to :data:`PLANAR_SHARE` is fitted again with OpenCV's default: with noise, four points
#: of the set give a poorer homography, and 32 draws found 0.875 where 2000 found 0.908 (1 of 300 sets with 95 % of
#: 120 points on one homography, noise 0.4 px; found by a review of this bound). 12 of the 135 shared pairs at 160,
#: 320 px and native reach it in 32 draws (at most 0.863), and pay the default search too.
RECHECK_SHARE = 0.6

#: What a ranged pair whose matches all lie on one homography is told (an audit: Teddy's left view turned 3° about
#: the camera's y axis, no baseline, was ranged "OK", "verified", at 1.71 m by the SVS model (0.53 m turned at
#: Teddy's focal length), where a pure rotation holds no depth; OpenCV's findFundamentalMat and
#: stereoRectifyUncalibrated accept it as well). The shared Middlebury pairs put at most 77 % of their inliers on
#: one homography at 320 x 240.
ONE_HOMOGRAPHY = ("{share:.0%} of the RANSAC inliers fit one homography: the distance holds for a flat surface "
                  "facing the cameras (a wall, a poster); if the scene has depth, the right camera turned with no "
                  "baseline between the views (two frames of one turning camera) and no distance holds")


def bounded_homography_fit(rows: list[list[float]], threshold_px: float) -> tuple[float, list[float]] | None:
    """:func:`~svs_torch.cli.fundamental.homography_fit` of ``rows`` in :data:`SEARCH_DRAWS` draws, fitted again with
    OpenCV's default where its share is from :data:`RECHECK_SHARE` up to :data:`PLANAR_SHARE`: whether the share
    reaches :data:`PLANAR_SHARE` is then what the default search says."""
    fit = homography_fit(rows, threshold_px, SEARCH_DRAWS)
    if fit is not None and RECHECK_SHARE <= fit[0] < PLANAR_SHARE:
        return homography_fit(rows, threshold_px)
    return fit


def one_homography_reason(result, index: int, width_px: int) -> str | None:
    """:data:`ONE_HOMOGRAPHY` for pair ``index`` of a pipeline result, ``width_px`` wide (its working pixels), where
    at least :data:`PLANAR_SHARE` of its RANSAC inliers (8 or more) fit one homography within :data:`THRESHOLD_PX`
    (scaled) and fewer than :data:`PARALLAX_POINTS` show parallax off it, else None."""
    points = result.points
    kept = points.valid[index] & result.fundamental.inliers[index]
    # A tensor op a side, not two a point: guide --json reports every pair it ranges.
    rows = [left + right for left, right in zip(points.left[index][kept].tolist(), points.right[index][kept].tolist())]
    threshold_px = THRESHOLD_PX * min(1.0, width_px / 320)
    fit = bounded_homography_fit(rows, threshold_px)
    if fit is None or fit[0] < PLANAR_SHARE:
        return None
    parallax = sum(distance >= PARALLAX_FACTOR * threshold_px for distance in fit[1])
    return None if parallax >= PARALLAX_POINTS else ONE_HOMOGRAPHY.format(share=fit[0])
