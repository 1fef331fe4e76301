"""SAD matching vs a naive loop, OpenCV's brute-force matcher (random and real SIFT descriptors), and gates."""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import pytest
import torch

import svs_torch.geometry.matching as matching
from svs_torch import InputError, Matches
from svs_torch.core import kernels
from svs_torch.geometry.matched_points import gather_matched_points
from svs_torch.geometry.matching import match_sad, max_sad_distance


def random_sets(generator: torch.Generator, b: int = 3, k: int = 40, k2: int = 50, d: int = 16,
                dtype: torch.dtype = torch.float64):
    """Unit-L2 descriptors with padding; right set = noisy shuffled copies of the left plus distractors."""
    left = torch.randn(b, k, d, generator=generator, dtype=dtype)
    right = torch.randn(b, k2, d, generator=generator, dtype=dtype)
    right[:, :k] = left + 0.1 * torch.randn(b, k, d, generator=generator, dtype=dtype)
    right = right[:, torch.randperm(k2, generator=generator)]
    left, right = left / left.norm(dim=-1, keepdim=True), right / right.norm(dim=-1, keepdim=True)
    valid_left = torch.rand(b, k, generator=generator) < 0.85
    valid_right = torch.rand(b, k2, generator=generator) < 0.85
    return left, right, valid_left, valid_right


def naive_match(left, right, valid_left, valid_right, max_ratio, max_cost=None, mutual=False, allowed=None):
    """Reference: explicit loops over pairs and keypoints, NumPy float64."""
    b, k, _ = left.shape
    idx = np.full((b, k), -1)
    cost = np.full((b, k), np.inf)
    for p in range(b):
        table = np.abs(left[p].numpy()[:, None, :].astype(np.float64) - right[p].numpy()[None].astype(np.float64))
        table = table.sum(-1)
        mask = valid_left[p].numpy()[:, None] & valid_right[p].numpy()[None]
        if allowed is not None:
            mask &= allowed[p]
        table[~mask] = np.inf
        for i in range(k):
            order = np.argsort(table[i], kind="stable")
            d1 = table[i, order[0]] if len(order) else np.inf
            d2 = table[i, order[1]] if len(order) > 1 else np.inf
            ok = np.isfinite(d1) and d1 <= max_ratio * d2 and d2 > 0
            ok = ok and (max_cost is None or d1 <= max_cost)
            ok = ok and (not mutual or np.argmin(table[:, order[0]]) == i)
            if ok:
                idx[p, i], cost[p, i] = order[0], d1
    return idx, cost


@pytest.mark.parametrize("mutual", [False, True])
@pytest.mark.parametrize("max_ratio", [0.6, 0.9, 1.0])
def test_matches_equal_naive_loop(max_ratio, mutual, dtype, generator):
    left, right, valid_left, valid_right = random_sets(generator, dtype=dtype)
    matches = match_sad(left, right, valid_left, valid_right, max_ratio=max_ratio, mutual=mutual)
    idx, cost = naive_match(left, right, valid_left, valid_right, max_ratio, mutual=mutual)
    assert matches.idx.dtype == torch.int64 and matches.cost.dtype == dtype
    assert np.array_equal(matches.idx.numpy(), idx)
    np.testing.assert_allclose(matches.cost.numpy(), cost, rtol=1e-5)
    assert not matches.valid[~valid_left].any()
    assert (matches.idx >= 0).sum() > 20  # the test is not vacuous


def test_match_threshold_uses_matlab_percent(generator):
    left, right, valid_left, valid_right = random_sets(generator, d=64)
    assert max_sad_distance(64) == 16.0  # 2·√D for unit-L2 descriptors
    for percent in (5.0, 10.0, 20.0):
        matches = match_sad(left, right, valid_left, valid_right, match_threshold=percent)
        idx, _ = naive_match(left, right, valid_left, valid_right, 0.6, max_cost=percent / 100 * 16.0)
        assert np.array_equal(matches.idx.numpy(), idx)
    # No unit-norm descriptor pair is farther apart than 2√D.
    assert torch.cdist(left, right, p=1).max() <= max_sad_distance(64)


def test_ratio_test_single_candidate_and_ties():
    left = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]]])
    right = torch.tensor([[[1.0, 0.1], [0.0, 1.0], [0.0, 1.0]]])
    valid = torch.ones(1, 3, dtype=torch.bool)
    # SAD of keypoint 2 to the right set: 0.9, 1.0, 1.0 → ratio 0.9.
    matches = match_sad(left, right, valid, valid, max_ratio=1.0)
    # Keypoint 1 has two identical candidates at distance 0: ambiguous, so rejected even at ratio 1.
    assert matches.idx.tolist() == [[0, -1, 0]]
    assert match_sad(left, right, valid, valid, max_ratio=0.89).idx.tolist() == [[0, -1, -1]]
    # A lone candidate passes the ratio test.
    only_one = torch.tensor([[True, False, False]])
    assert match_sad(left, right, valid, only_one).idx.tolist() == [[0, 0, 0]]


@pytest.mark.parametrize("path", ["compiled", "torch"])
def test_a_ratio_exactly_at_the_bound_is_kept(monkeypatch, path):
    """MATLAB's ratio test keeps d1 / d2 ≤ MaxRatio: a ratio of exactly 0.5 passes max_ratio 0.5 on both paths, and
    fails 0.49 (a mutation audit: '≤' read as '<' went unnoticed). Distances 2 and 4 are exact in float32."""
    if path == "torch":
        monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    left = torch.tensor([[[0.0, 0.0, 0.0, 0.0]]])
    right = torch.tensor([[[0.5, 0.5, 0.5, 0.5], [1.0, 1.0, 1.0, 1.0]]])  # SAD 2 and 4
    ones = torch.ones(1, 1, dtype=torch.bool), torch.ones(1, 2, dtype=torch.bool)
    assert match_sad(left, right, *ones, max_ratio=0.5).idx.tolist() == [[0]]
    assert match_sad(left, right, *ones, max_ratio=0.49).idx.tolist() == [[-1]]


def test_padding_never_matches_even_when_identical(generator):
    left, right, valid_left, valid_right = random_sets(generator, b=1)
    valid_right[:] = True
    right[0, 0] = left[0, 0]  # an exact copy, but in a padding row
    valid_right[0, 0] = False
    valid_left[0, 0] = True
    matches = match_sad(left, right, valid_left, valid_right, max_ratio=1.0)
    assert (matches.idx != 0).all()
    padded = match_sad(left, right, torch.zeros_like(valid_left), valid_right)
    assert (padded.idx == -1).all() and torch.isinf(padded.cost).all()


def test_laplacian_and_band_gates_equal_masked_reference(generator):
    left, right, valid_left, valid_right = random_sets(generator)
    sign_left = torch.where(torch.rand(3, 40, generator=generator) < 0.5, 1, -1)
    sign_right = torch.where(torch.rand(3, 50, generator=generator) < 0.5, 1, -1)
    xy_left = 100 * torch.rand(3, 40, 2, generator=generator, dtype=torch.float64)
    xy_right = 100 * torch.rand(3, 50, 2, generator=generator, dtype=torch.float64)
    allowed = (sign_left[..., None] == sign_right[:, None]).numpy()
    allowed &= ((xy_left[..., 1, None] - xy_right[:, None, :, 1]).abs() <= 20.0).numpy()
    matches = match_sad(left, right, valid_left, valid_right, laplacian_left=sign_left, laplacian_right=sign_right,
                        xy_left=xy_left, xy_right=xy_right, epipolar_band_px=20.0, max_ratio=0.8)
    idx, _ = naive_match(left, right, valid_left, valid_right, 0.8, allowed=allowed)
    assert np.array_equal(matches.idx.numpy(), idx)
    matched = matches.idx >= 0
    partner = matches.idx.clamp(min=0)
    assert (sign_right.gather(1, partner)[matched] == sign_left[matched]).all()
    y_right = xy_right[..., 1].gather(1, partner)
    assert ((xy_left[..., 1] - y_right).abs()[matched] <= 20.0).all()


def test_grouping_over_pairs_changes_nothing(generator, monkeypatch):
    left, right, valid_left, valid_right = random_sets(generator, b=5)
    whole = match_sad(left, right, valid_left, valid_right, mutual=True)
    monkeypatch.setattr(matching, "_MAX_ENTRIES_PER_GROUP", 1)  # one pair per group
    grouped = match_sad(left, right, valid_left, valid_right, mutual=True)
    assert torch.equal(whole.idx, grouped.idx) and torch.equal(whole.cost, grouped.cost)
    single = match_sad(left[2:3], right[2:3], valid_left[2:3], valid_right[2:3], mutual=True)
    assert torch.equal(single.idx[0], whole.idx[2])


@pytest.mark.parametrize("k, k2", [(0, 5), (5, 0), (0, 0), (5, 1)])
def test_empty_and_tiny_sets(k, k2):
    left, right = torch.rand(2, k, 8), torch.rand(2, k2, 8)
    matches = match_sad(left, right, torch.ones(2, k, dtype=torch.bool), torch.ones(2, k2, dtype=torch.bool))
    assert matches.idx.shape == (2, k) and matches.cost.shape == (2, k)
    if k2 == 1:
        assert (matches.idx == 0).all()  # a single candidate always passes the ratio test
    else:
        assert (matches.idx == -1).all()


def test_equals_opencv_bruteforce_ratio_test(generator):
    """cv2.BFMatcher(NORM_L1).knnMatch(k=2) with the ratio test gives the same matches (generated with OpenCV)."""
    left, right, _, _ = random_sets(generator, b=2, k=200, k2=300, d=64, dtype=torch.float32)
    valid_left, valid_right = torch.ones(2, 200, dtype=torch.bool), torch.ones(2, 300, dtype=torch.bool)
    matches = match_sad(left, right, valid_left, valid_right, max_ratio=0.7)
    matcher = cv2.BFMatcher(cv2.NORM_L1)
    for p in range(2):
        expected = np.full(200, -1)
        for first, second in matcher.knnMatch(left[p].numpy(), right[p].numpy(), k=2):
            if first.distance <= 0.7 * second.distance:
                expected[first.queryIdx] = first.trainIdx
        assert np.array_equal(matches.idx[p].numpy(), expected)


def _sift(data_dir, name: str):
    image = cv2.imread(str(data_dir / "opencv_samples" / name), cv2.IMREAD_GRAYSCALE)
    keypoints, descriptors = cv2.SIFT_create(nfeatures=400).detectAndCompute(image, None)
    xy = torch.tensor([kp.pt for kp in keypoints], dtype=torch.float32)
    return xy, torch.from_numpy(descriptors)


def test_real_sift_matches_equal_opencv_and_gather_points(data_dir):
    """Real SIFT descriptors of the OpenCV chessboard pair 01: same matches as OpenCV's matcher."""
    xy_left, desc_left = _sift(data_dir, "left01.jpg")
    xy_right, desc_right = _sift(data_dir, "right01.jpg")
    k, k2 = len(xy_left), len(xy_right)
    matches = match_sad(desc_left[None], desc_right[None], torch.ones(1, k, dtype=torch.bool),
                        torch.ones(1, k2, dtype=torch.bool))
    expected = np.full(k, -1)
    for first, second in cv2.BFMatcher(cv2.NORM_L1).knnMatch(desc_left.numpy(), desc_right.numpy(), k=2):
        if first.distance <= 0.6 * second.distance:
            expected[first.queryIdx] = first.trainIdx
    # SIFT descriptors hold small integers, so float32 SAD sums are exact and the matches agree exactly.
    assert np.array_equal(matches.idx[0].numpy(), expected) and (expected >= 0).sum() > 30
    points = gather_matched_points(xy_left[None], xy_right[None], matches)
    matched = matches.valid[0]
    assert torch.equal(points.valid, matches.valid)
    torch.testing.assert_close(points.right[0][matched], xy_right[matches.idx[0][matched]])
    torch.testing.assert_close(points.left[0][matched], xy_left[matched])
    assert (points.left[0][~matched] == 0).all() and (points.right[0][~matched] == 0).all()


def test_cost_is_differentiable_wrt_descriptors(generator):
    left, right, _, _ = random_sets(generator, b=1, k=4, k2=5, d=3)
    valid_left, valid_right = torch.ones(1, 4, dtype=torch.bool), torch.ones(1, 5, dtype=torch.bool)
    left.requires_grad_()
    right.requires_grad_()

    def matched_cost(a, b):
        cost = match_sad(a, b, valid_left, valid_right, max_ratio=1.0).cost
        return torch.where(cost.isfinite(), cost, 0.0)

    assert torch.autograd.gradcheck(matched_cost, (left, right))


def test_gather_with_empty_right_set():
    matches = Matches(idx=torch.full((1, 3), -1), cost=torch.full((1, 3), math.inf))
    points = gather_matched_points(torch.rand(1, 3, 2), torch.rand(1, 0, 2), matches)
    assert points.right.shape == (1, 3, 2) and not points.valid.any()


def test_errors_name_the_argument():
    desc, valid = torch.rand(2, 5, 8), torch.ones(2, 5, dtype=torch.bool)
    with pytest.raises(InputError, match=r"desc_right: expected \(2, K2, 8\), got \(2, 5, 7\)"):
        match_sad(desc, torch.rand(2, 5, 7), valid, valid)
    with pytest.raises(InputError, match="valid_left: expected a bool tensor, got torch.float32"):
        match_sad(desc, desc, valid.float(), valid)
    with pytest.raises(InputError, match=r"max_ratio: expected a value in \(0, 1\], got 1.5"):
        match_sad(desc, desc, valid, valid, max_ratio=1.5)
    with pytest.raises(InputError, match="match_threshold: expected a percent"):
        match_sad(desc, desc, valid, valid, match_threshold=0.0)
    with pytest.raises(InputError, match="laplacian_right: expected it together with laplacian_left"):
        match_sad(desc, desc, valid, valid, laplacian_left=torch.ones(2, 5, dtype=torch.int64))
    with pytest.raises(InputError, match="xy_left: expected xy_left and xy_right with epipolar_band_px"):
        match_sad(desc, desc, valid, valid, epipolar_band_px=2.0)
    with pytest.raises(InputError, match=r"xy_right: expected \(2, 5, 2\), got \(2, 4, 2\)"):
        match_sad(desc, desc, valid, valid, xy_left=torch.rand(2, 5, 2), xy_right=torch.rand(2, 4, 2),
                  epipolar_band_px=2.0)


@pytest.mark.parametrize("setting, message", [
    ({"max_ratio": "0.8"}, "max_ratio: expected a value in (0, 1], got '0.8'"),  # was TypeError from '<'
    ({"match_threshold": "5"}, "match_threshold: expected a percent in (0, 100], got '5'"),
    ({"mutual": "no"}, "mutual: expected a bool, got 'no'"),  # was truthy: a mutual check in silence
    ({"epipolar_band_px": "1"}, "epipolar_band_px: expected a finite non-negative number of pixels, got '1'"),
    ({"epipolar_band_px": torch.tensor([1.0, 2.0])}, "epipolar_band_px: expected a finite"),  # was RuntimeError
    ({"epipolar_band_px": math.inf}, "epipolar_band_px: expected a finite"),  # was named 'band_px', the kernel's
    ({"epipolar_band_px": 1.0, "xy_left": torch.ones(2, 5, 2, dtype=torch.int64)},
     "xy_left: expected a float tensor, got torch.int64"),  # was named 'y_left', the kernel's
])
def test_settings_of_the_wrong_kind_are_named(setting, message):
    desc, valid = torch.rand(2, 5, 8), torch.ones(2, 5, dtype=torch.bool)
    gates = {"xy_left": torch.rand(2, 5, 2), "xy_right": torch.rand(2, 5, 2)} | setting
    with pytest.raises(InputError, match=re.escape(message)):
        match_sad(desc, desc, valid, valid, **gates)
    assert (match_sad(desc, desc, valid, valid, max_ratio=np.float32(0.8)).idx >= 0).any()  # numpy's reals stay


# --- refine_matches_lk: sub-pixel refinement of matched points --------------------------------------------------

def smooth_texture(h: int, w: int, shift_xy=(0.0, 0.0), seed: int = 0) -> torch.Tensor:
    """``(1, 1, h, w)`` analytic texture (sum of Gaussian blobs) sampled at (x + sx, y + sy): exactly shifted
    copies for any sub-pixel shift."""
    rng = np.random.default_rng(seed)
    cx, cy = rng.uniform(0, w, 120), rng.uniform(0, h, 120)
    sigma, amp = rng.uniform(1.5, 4.0, 120), rng.uniform(-1, 1, 120)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = x + shift_xy[0], y + shift_xy[1]
    image = sum(a * np.exp(-((x - u) ** 2 + (y - v) ** 2) / (2 * s**2)) for u, v, s, a in zip(cx, cy, sigma, amp))
    image = (image - image.min()) / (image.max() - image.min())
    return torch.from_numpy(image)[None, None]


def lk_problem(shifts, perturbation: float = 0.6, k: int = 30, seed: int = 3):
    """A batch of (left, right = left moved by −shift) pairs and matched points perturbed off the truth."""
    rng = np.random.default_rng(seed)
    lefts, rights, pl, pr = [], [], [], []
    for i, shift in enumerate(shifts):
        lefts.append(smooth_texture(80, 96, seed=i))
        rights.append(smooth_texture(80, 96, shift_xy=shift, seed=i))  # right(x) = left(x + shift)
        xy = np.stack([rng.uniform(16, 80, k), rng.uniform(16, 64, k)], -1)
        pl.append(xy)
        pr.append(xy - np.asarray(shift) + rng.uniform(-perturbation, perturbation, (k, 2)))
    valid = torch.from_numpy(rng.uniform(size=(len(shifts), k)) < 0.8)
    points = matching.MatchedPoints(torch.from_numpy(np.stack(pl)), torch.from_numpy(np.stack(pr)), valid)
    return torch.cat(lefts).float(), torch.cat(rights).float(), points


@pytest.fixture(params=["c", "torch"])
def lk_path(request, monkeypatch):
    """Each refinement test runs on the C kernel and on the torch path (its reference)."""
    if request.param == "torch":
        monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    elif not kernels.available("lk_refine"):
        pytest.skip("no C compiler")
    return request.param


def test_refine_lk_recovers_subpixel_shift(lk_path):
    shifts = [(0.37, -0.21), (-1.6, 0.45)]
    left, right, points = lk_problem(shifts)
    refined = matching.refine_matches_lk(left, right, points, min_correlation=-1)
    truth = points.left - torch.tensor(shifts, dtype=torch.float64)[:, None, :]
    before = (points.right - truth).norm(dim=-1)[points.valid]
    after = (refined.right - truth).norm(dim=-1)[refined.valid]
    assert torch.equal(refined.valid, points.valid)
    assert torch.equal(refined.left[refined.valid], points.left[points.valid])
    assert before.median() > 0.3 and after.max() < 0.1 and after.median() < 0.04


def test_refine_lk_agrees_with_opencv_pyrlk(lk_path):
    """An independent reference: OpenCV's LK (one pyramid level, 21 × 21 window, uint8 images) tracking the same
    points from the left positions, 0.85 px from the truth."""
    shifts = [(0.8, 0.3)]
    left, right, points = lk_problem(shifts, perturbation=0.0)
    start = matching.MatchedPoints(points.left, points.left.clone(), points.valid)
    refined = matching.refine_matches_lk(left, right, start, min_radius_px=8.0)
    keep = points.valid[0].numpy()
    truth = points.right[0].numpy()[keep]
    to_u8 = (lambda t: (t[0, 0].numpy() * 255).round().astype(np.uint8))
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(
        to_u8(left), to_u8(right), points.left[0].numpy()[keep].astype(np.float32), None, winSize=(21, 21),
        maxLevel=0, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-5))
    ours = refined.right[0].numpy()[keep]
    ok = status.ravel() == 1
    assert ok.mean() > 0.9 and np.abs(ours[ok] - tracked[ok]).max() < 0.12
    assert np.abs(ours - truth).max() < 0.06 and np.median(np.abs(tracked - truth)) < 0.03


def test_refine_lk_batched_equals_per_item_and_gain_invariant(lk_path):
    left, right, points = lk_problem([(0.4, 0.1), (-0.7, -0.3), (1.2, 0.0)])
    scale = torch.full(points.valid.shape, 2.0, dtype=torch.float64)
    batched = matching.refine_matches_lk(left, right, points, scale)
    for i in range(3):
        one = matching.refine_matches_lk(left[i:i + 1], right[i:i + 1],
                                         matching.MatchedPoints(*(t[i:i + 1] for t in points)), scale[i:i + 1])
        assert torch.allclose(one.right, batched.right[i:i + 1], atol=1e-9)
        assert torch.equal(one.valid, batched.valid[i:i + 1])
    darker = matching.refine_matches_lk(left, 0.5 * right + 0.2, points, scale)
    assert torch.allclose(darker.right, batched.right, atol=1e-3)
    # Padding rows stay zero and invalid.
    assert (batched.right[~batched.valid] == 0).all() and not (batched.valid & ~points.valid).any()


def test_refine_lk_rejects_uncorrelated_and_leaves_far_shifts(lk_path):
    left, right, points = lk_problem([(0.3, 0.2)])
    unrelated = smooth_texture(80, 96, seed=99).float()
    rejected = matching.refine_matches_lk(left, unrelated, points, min_radius_px=8.0, min_correlation=0.8)
    assert rejected.valid.sum() < 0.2 * points.valid.sum()
    assert matching.refine_matches_lk(left, right, points, min_radius_px=8.0, min_correlation=0.8).valid.sum() \
        == points.valid.sum()
    # A shift beyond max_shift_px keeps the matched position.
    far = matching.MatchedPoints(points.left, points.right + 1.5, points.valid)
    kept = matching.refine_matches_lk(left, right, far, max_shift_px=0.5, min_correlation=-1)
    assert torch.allclose(kept.right[kept.valid], far.right[far.valid])


@pytest.mark.parametrize("scale, expected", [
    (torch.tensor([[float("nan")]]), "^scale: expected finite values where points.valid holds"),  # moved in silence
    (torch.tensor([[True]]), "^scale: expected a float or int tensor"),  # taken as a scale of 1
    (torch.tensor([[2.0 + 0j]]), "^scale: expected a float or int tensor"),  # imaginary part dropped, a warning
    # A RuntimeError from deep inside, once
    (torch.tensor([[2.0]], device="meta"), "^scale: expected a tensor with values, got one on the meta device"),
])
def test_refine_lk_names_a_scale_that_is_not_a_real_finite_tensor(scale, expected):
    left, right, points = lk_problem([(0.0, 0.0)])
    with pytest.raises(InputError, match=expected):
        matching.refine_matches_lk(left, right, points, scale.expand(points.valid.shape))


def test_refine_lk_checks_inputs():
    left, right, points = lk_problem([(0.0, 0.0)])
    with pytest.raises(InputError):
        matching.refine_matches_lk(left, right[..., :-1], points)
    with pytest.raises(InputError):
        matching.refine_matches_lk(left, right, points, min_radius_px=0.0)
    empty = matching.MatchedPoints(points.left, points.right, torch.zeros_like(points.valid))
    assert matching.refine_matches_lk(left, right, empty) is empty


def test_gather_matched_points_names_matches_of_another_kind():
    """Found by an audit of the library called by hand: an (idx,) tuple for the matches raised AttributeError on
    .idx, naming no argument."""
    xy = torch.zeros(1, 3, 2)
    with pytest.raises(InputError, match="^matches: expected a Matches, got tuple$"):
        gather_matched_points(xy, xy, (torch.zeros(1, 3, dtype=torch.int64),))


def test_refinement_called_by_hand_names_arguments_of_another_kind():
    """Found by an audit of the library called by hand: points as a plain (left, right, valid) tuple raised
    AttributeError on .left, refine_matched_points given another config a TypeError of unknown keywords, and
    matches of another kind an AttributeError on .valid."""
    from svs_torch.geometry.lk_refinement import MatchRefinementConfig, refine_matched_points
    left, right, points = lk_problem([(0.0, 0.0)])
    matches = Matches(torch.zeros_like(points.valid, dtype=torch.int64), torch.zeros(points.valid.shape))
    with pytest.raises(InputError, match="^points: expected a MatchedPoints, got tuple$"):
        matching.refine_matches_lk(left, right, tuple(points))
    with pytest.raises(InputError, match="^config: expected a MatchRefinementConfig, got dict$"):
        refine_matched_points(left, right, points, matches, None, {"iterations": 8})
    with pytest.raises(InputError, match="^matches: expected a Matches, got tuple$"):
        refine_matched_points(left, right, points, (matches.idx, matches.cost), None, MatchRefinementConfig())
    assert refine_matched_points(left, right, points, matches, None, MatchRefinementConfig())[0].valid.shape == (1, 30)


def test_pipeline_refinement_makes_real_matches_more_precise(data_dir):
    """On a real Middlebury pair at 320 px, the default pipeline's refined matches are closer to GT disparity
    than the same matches unrefined, and dropped rows leave the matches and points consistent."""
    from dataclasses import replace

    from svs_torch.data import load_middlebury_eval3, resize_stereo_batch
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    batch = resize_stereo_batch(load_middlebury_eval3(data_dir / "middlebury_eval3_Q" / "Teddy"), (320, 267))
    config = replace(PipelineConfig(), rectify="off")
    refined = estimate_obstacle_depth(batch, config)
    plain = estimate_obstacle_depth(batch, replace(config, refine_matches=None))

    def errors(result):
        points = result.points
        keep = points.valid[0]
        xy_left, xy_right = points.left[0][keep], points.right[0][keep]
        col, row = xy_left[:, 0].round().long(), xy_left[:, 1].round().long()
        truth_valid = batch.disparity_valid[0, 0, row, col]
        truth = batch.disparity_px[0, 0, row, col]
        return ((xy_left[:, 0] - xy_right[:, 0]) - truth)[truth_valid].abs()

    e_refined, e_plain = errors(refined), errors(plain)
    assert len(e_refined) > 100
    assert float((e_refined <= 1).float().mean()) > float((e_plain <= 1).float().mean())
    assert float(e_refined.median()) < 0.8 * float(e_plain.median())
    assert int(refined.num_matches[0]) <= int(plain.num_matches[0])
    assert torch.equal(refined.matches.valid, refined.points.valid)


def test_refinement_config_and_stage_checks():
    with pytest.raises(InputError, match="min_correlation"):
        matching.MatchRefinementConfig(min_correlation=1.5)
    with pytest.raises(InputError, match="iterations"):
        matching.MatchRefinementConfig(iterations=-1)
    points = gather_matched_points(torch.zeros(1, 3, 2), torch.zeros(1, 3, 2),
                                   Matches(idx=torch.tensor([[0, -1, 1]]), cost=torch.zeros(1, 3)))
    matches = Matches(idx=torch.tensor([[0, -1, 1]]), cost=torch.zeros(1, 3))
    same_points, same_matches = matching.refine_matched_points(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 8),
                                                               points, matches, None, None)
    assert same_points is points and same_matches is matches
