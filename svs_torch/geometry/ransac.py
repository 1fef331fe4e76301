"""Batched robust estimation of the fundamental matrix (paper Sec. 3.3 (3)).

The paper draws random samples of 7 correspondences, solves each with the 7-point algorithm and keeps the
solution with the most inliers; LMedS is named as an alternative. Here B pairs run at once, each with M
hypotheses per chunk: sampling, solving and scoring are tensor operations over ``(B, M, …)``. Python loops
run over chunks, sample slots, scoring blocks and refit rounds, never over pairs or hypotheses.

Design, and what it guarantees:

* **Randomness.** Each pair has its own 64-bit seed (``pair_seeds``, or drawn from ``generator``); sample
  slot s of hypothesis h of a pair is the SplitMix64 hash of ``seed + (7h + s + 1)·γ`` (Steele et al., OOPSLA
  2014), i.e. a counter-based stream. A pair's draws therefore never depend on the other pairs or on the
  chunking: a batched call equals per-pair calls given the same per-pair seeds, and the same seeds give the same
  result. Samples are 7 distinct ranks among the pair's valid rows (Floyd's algorithm), so padding is never
  drawn and extra padded rows change nothing.
* **Scoring** in Hartley-normalised coordinates (one similarity per image with a shared scale s, so the
  Sampson distance scales exactly: ``d_normalised = s · d_px``), in float32 as two small matrix products per
  block of hypotheses: ``x'ᵀFx`` from 9 bilinear monomials and the Sampson denominator from 11 quadratic
  monomials of the points. Solving, local optimisation and the final inliers use float64.
* **Pre-verification** (T(d,d), Matas & Chum 2002, batched): each chunk's models are scored on 32 random
  valid rows first; only the best eighth is scored on every row.
* **Stopping.** After each chunk a pair stops once it has drawn ``log(1 − p) / log(1 − w⁷)`` hypotheses (w its
  best inlier ratio, p ``confidence``) or ``max_iterations``; a stopped pair is frozen and no longer computed.
  The loop ends when every pair has stopped; a pair may draw up to ``chunk_size − 1`` more than it needs.
* **Local optimisation** (LO-RANSAC, Chum et al., DAGM 2003): a hypothesis that beats the pair's best raw
  score is refitted by iteratively re-weighted 8-point least squares (Tukey weights of the Sampson distance
  over the Sampson denominator: a robust first-order geometric error), kept while its score improves; a final
  polish runs the same refit a few more times on the winner (as MAGSAC++'s last σ-consensus step).

Only the valid rows are processed (moved to the front): the cost follows the widest pair's number of matches,
not K. ``experiments/bench_ransac.py`` times it against ``cv2.findFundamentalMat``. ``torch.compile`` of the
scoring block was measured and not adopted: 1.7× on that block (≈ 8 % of a run), losses that differ from eager
in the 5th digit, and a compile on every new block shape.

**The C kernel.** For MSAC and RANSAC scoring on CPU, :func:`estimate_fundamental_ransac` runs each pair start to
finish in ``kernels/ransac_fundamental.c``, step for step the algorithm above (the same samples, rows, solver,
scores, refits and stopping; :func:`svs_torch.geometry.kernels.ransac_fundamental`): this torch path batches well
but is about 1 900 small operations for one pair, whose dispatch was nearly all of its time (one pair of 340
matches 4.2 → 0.3 ms; 1.0 → 0.35 ms a pair at B = 8, one thread). Its LU, eigenvectors and sums run in their own
order, so it is not bit for bit: on drawn scenes with outliers 959 of 960 pairs get the same inliers and F to
1e-17 (the other a float32 tie between two hypotheses' scores), and the 58 shared real pairs at 320×240 the same
results (``experiments/kernel_parity.py``). LMedS, other devices and ``SVS_TORCH_KERNELS=torch`` take this path,
which stays the reference.

Not differentiable: sampling, arg-min and thresholds are discrete. Refit the returned inliers with
:func:`svs_torch.geometry.epipolar.fundamental_8point` for gradients.
"""

from __future__ import annotations

import math

import torch

from ..core.checks import InputError, check_count, check_dtype, check_generator, check_shape
from ..core.types import FundamentalResult, FundamentalStatus
from . import kernels
from .epipolar_distance import _epipolar_terms, _safe_ratio
from .minimal_solvers import (_FAST_PIVOT_RATIO, DEGENERATE_PIVOT_RATIO, MAX_ROOT_DETERMINANT, SIGN_TIE_TOLERANCE,
                              _denormalize, _fix_sign_and_scale)
from .ransac_refine import (LOCAL_OPTIMIZATION_STEPS, LOCAL_OPTIMIZATION_TOLERANCE, LOCAL_OPTIMIZATION_WINDOW,
                            POLISH_STEPS, POLISH_WINDOW, _local_optimization, _polish)
from .ransac_sampling import _SAMPLE_SIZE, PREVERIFY_POINTS, draw_minimal_samples
from .ransac_scoring import (_DENOMINATOR_GUARD, _Problem, _prepare, _sampson_sq, _score, _select_pairs,
                             _solve_chunk)

__all__ = ["SCORINGS", "draw_minimal_samples", "estimate_fundamental_ransac"]


#: ``"ransac"``: most inliers (the paper), ties broken by the MSAC cost; ``"msac"``: truncated quadratic cost
#: ``Σ min(d², t²)`` (Torr & Zisserman 2000); ``"lmeds"``: least median of squared Sampson distances (MATLAB's
#: default method; inliers are then those within the threshold, as MATLAB's DistanceThreshold).
SCORINGS = ("ransac", "msac", "lmeds")
PREVERIFY_KEEP_RATIO = 8
#: The largest ``min_inliers``: inlier counts are int64.
MAX_MIN_INLIERS = 2**62


def _best_of_chunk(problem: _Problem, models: torch.Tensor, usable: torch.Tensor, scoring: str,
                   preverification: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """The best model of a chunk ``(B, S, 3, 3)`` per pair: its loss ``(B,)`` and the model ``(B, 3, 3)``.

    With pre-verification, only the best ``⌈S / PREVERIFY_KEEP_RATIO⌉`` models on the subset are fully scored,
    kept in hypothesis order so ties still go to the earliest hypothesis.
    """
    keep = -(-models.shape[1] // PREVERIFY_KEEP_RATIO)
    if preverification and keep < models.shape[1]:
        rough = _score(problem.subset, models, usable, problem.threshold_sq, scoring)
        kept = rough.topk(keep, dim=-1, largest=False).indices.sort(-1).values  # (B, keep)
        models = models.gather(1, kept[..., None, None].expand(-1, -1, 3, 3))
        usable = usable.gather(1, kept)
    loss = _score(problem.full, models, usable, problem.threshold_sq, scoring)
    pick = loss.argmin(-1, keepdim=True)  # the first best on ties
    best = models.gather(1, pick[..., None, None].expand(-1, 1, 3, 3)).squeeze(1)
    return loss.gather(-1, pick).squeeze(-1), best


def _run_chunk(part: _Problem, pair_seeds: torch.Tensor, first: int, count: int, best: torch.Tensor,
               losses: torch.Tensor, settings: dict, local_optimization: bool, preverification: bool
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One chunk for the running pairs: draw, solve, score, optimise locally, keep the best, test stopping.

    ``losses (b, 2)`` holds each pair's best loss and its best raw (un-optimised) hypothesis loss. As in
    LO-RANSAC, a hypothesis triggers local optimisation when it beats the best *raw* loss: comparing raw
    7-point models with an already optimised one would let a poor local optimum block every better start.
    Returns the updated best models ``(b, 3, 3)``, ``losses (b, 2)`` and which pairs stop now ``(b,)``.
    """
    scoring = settings["scoring"]
    models, usable = _solve_chunk(part, pair_seeds, first, count)  # (b, 3·count, 3, 3)
    chunk_loss, candidate = _best_of_chunk(part, models, usable, scoring, preverification)
    new_raw = chunk_loss < losses[:, 1]
    raw = torch.where(new_raw, chunk_loss, losses[:, 1])
    if local_optimization and bool(new_raw.any()):
        candidate, chunk_loss = _local_optimization(part, candidate, chunk_loss, new_raw, scoring)
    better = chunk_loss < losses[:, 0]
    best = torch.where(better.view(-1, 1, 1), candidate, best)
    best_loss = torch.where(better, chunk_loss, losses[:, 0])
    distance_sq, _ = _sampson_sq(part, best)
    inliers = part.valid & (distance_sq <= part.threshold_sq.unsqueeze(-1)) & best_loss.isfinite().unsqueeze(-1)
    needed = _required_iterations(inliers.sum(-1), part.num_valid, settings["confidence"],
                                  settings["max_iterations"])
    return best, torch.stack([best_loss, raw], -1), needed <= first + count


def _required_iterations(num_inliers: torch.Tensor, num_valid: torch.Tensor, confidence: float,
                         max_iterations: int) -> torch.Tensor:
    """``log(1 − p) / log(1 − w⁷)`` hypotheses for confidence p at inlier ratio w, capped: ``(B,)`` int64."""
    ratio = num_inliers.double() / num_valid.clamp(min=1).double()
    all_good = ratio.pow(_SAMPLE_SIZE)
    if confidence >= 1.0:
        return torch.full_like(num_inliers, max_iterations)
    per_draw = torch.log1p(-all_good.clamp(max=1.0))  # −inf at w = 1 (then 0 hypotheses are needed)
    needed = torch.where(all_good > 0, math.log1p(-confidence) / per_draw, math.inf)
    return needed.clamp(max=max_iterations).ceil().long()


def _search(problem: _Problem, pair_seeds: torch.Tensor, settings: dict, local_optimization: bool,
            preverification: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The chunk loop: best models ``(B, 3, 3)`` (normalised), losses ``(B, 2)`` and hypotheses drawn ``(B,)``.

    Each chunk works on the running pairs only; a pair that has stopped is never touched again, so its result
    does not depend on how long the others run.
    """
    b, device = problem.valid.shape[0], problem.valid.device
    best = torch.zeros(b, 3, 3, dtype=torch.float64, device=device)
    losses = torch.full((b, 2), math.inf, dtype=torch.float64, device=device)  # best, best raw
    iterations = torch.zeros(b, dtype=torch.int64, device=device)
    done = problem.num_valid < _SAMPLE_SIZE
    part, active = problem, torch.arange(b, device=device)
    chunk_size, max_iterations = settings["chunk_size"], settings["max_iterations"]
    for first in range(0, max_iterations, chunk_size):
        if bool(done.all()):  # one host sync per chunk: the loop ends when every pair has stopped
            break
        if len(active) != int((~done).sum()):
            active = (~done).nonzero().squeeze(-1)
            part = _select_pairs(problem, active)
        count = min(chunk_size, max_iterations - first)
        part_best, part_losses, stop = _run_chunk(part, pair_seeds.index_select(0, active), first, count,
                                                  best.index_select(0, active), losses.index_select(0, active),
                                                  settings, local_optimization, preverification)
        best, losses = best.index_copy(0, active, part_best), losses.index_copy(0, active, part_losses)
        iterations = iterations.index_fill(0, active, first + count)
        done = done.index_copy(0, active, stop)
    return best, losses, iterations


def _check_arguments(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor,
                     pair_seeds: torch.Tensor | None, generator: torch.Generator | None, settings: dict) -> None:
    dims = check_shape(points_left, "points_left", ["B", "K", 2])
    check_dtype(points_left, "points_left", "float")
    check_shape(points_right, "points_right", [dims["B"], dims["K"], 2])
    check_dtype(points_right, "points_right", "float")
    if points_right.dtype != points_left.dtype:  # taken before: F came in the promoted dtype, float32 points' F too
        raise InputError(f"points_right: expected points_left's dtype {points_left.dtype}, got {points_right.dtype}")
    check_shape(valid, "valid", [dims["B"], dims["K"]])
    check_dtype(valid, "valid", "bool")
    check_generator(generator)
    if pair_seeds is not None:
        if generator is not None:
            raise InputError("pair_seeds: expected either pair_seeds or generator, not both")
        check_shape(pair_seeds, "pair_seeds", [dims["B"]])
        check_dtype(pair_seeds, "pair_seeds", "int")
    rules = {"threshold_px": (lambda v: math.isfinite(v) and v > 0, "a finite positive number of pixels"),
             "confidence": (lambda v: 0 < v <= 1, "a probability in (0, 1]"),
             "scoring": (lambda v: v in SCORINGS, f"one of {', '.join(SCORINGS)}")}
    for name, (ok, expected) in rules.items():
        try:
            passed = bool(ok(settings[name]))
        except (TypeError, ValueError, RuntimeError):  # e.g. a string or a tensor of several values
            passed = False
        if not passed:
            raise InputError(f"{name}: expected {expected}, got {settings[name]!r}")
    # Whole numbers, not bools (True was taken as 1); min_inliers bounded as the int64 counts it is compared with
    # (10**30 raised OverflowError inside torch): an audit.
    check_count(settings["max_iterations"], "max_iterations", 1, most=kernels.MAX_HYPOTHESES)
    check_count(settings["chunk_size"], "chunk_size", 1)
    check_count(settings["min_inliers"], "min_inliers", 0, most=MAX_MIN_INLIERS)
    for name, points in (("points_left", points_left), ("points_right", points_right)):
        if not bool(torch.where(valid.unsqueeze(-1), points, 0.0).isfinite().all()):
            raise InputError(f"{name}: expected finite coordinates in valid rows (NaN or inf found)")


def _finish(problem: _Problem, points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor,
            best: torch.Tensor, best_loss: torch.Tensor, iterations: torch.Tensor, threshold_px: float,
            min_inliers: int) -> FundamentalResult:
    """Pixel F, inliers by the exact Sampson distance (float64, pixels) and per-pair status."""
    work = torch.float64
    fundamental = _fix_sign_and_scale(_denormalize(best, problem.transform_left, problem.transform_right))
    algebraic, grad_right, grad_left = _epipolar_terms(points_left.to(work), points_right.to(work), fundamental)
    distance_sq = _safe_ratio(algebraic.square(), grad_right + grad_left)
    found = best_loss.isfinite()
    # Squared in float64 tensors: a huge finite threshold squares to inf here instead of raising OverflowError.
    threshold_sq = torch.tensor(float(threshold_px), dtype=work, device=distance_sq.device).square()
    inliers = valid & found.unsqueeze(-1) & (distance_sq <= threshold_sq)
    return _result(fundamental, found, inliers, problem.num_valid, iterations, min_inliers, points_left.dtype)


def _result(fundamental: torch.Tensor, found: torch.Tensor, inliers: torch.Tensor, num_valid: torch.Tensor,
            iterations: torch.Tensor, min_inliers: int, dtype: torch.dtype) -> FundamentalResult:
    """The :class:`FundamentalResult` of pixel models ``(B, 3, 3)`` float64, each pair's status from its counts."""
    num_inliers = inliers.sum(-1)
    status = torch.full_like(num_inliers, FundamentalStatus.OK)
    status = torch.where(num_inliers < min_inliers, FundamentalStatus.TOO_FEW_INLIERS, status)
    status = torch.where(~found, FundamentalStatus.DEGENERATE, status)
    status = torch.where(num_valid < _SAMPLE_SIZE, FundamentalStatus.TOO_FEW_MATCHES, status)
    ok = status == FundamentalStatus.OK
    return FundamentalResult(F=torch.where(ok.view(-1, 1, 1), fundamental, 0.0).to(dtype),
                             inliers=inliers, num_inliers=num_inliers, status=status, iterations=iterations)


def _kernel_settings(settings: dict, local_optimization: bool, preverification: bool, polish: bool) -> dict:
    """The settings of :func:`svs_torch.geometry.kernels.ransac_fundamental`: the call's and this module's
    constants (one source for both paths)."""
    return {"threshold_px": settings["threshold_px"], "confidence": settings["confidence"],
            # A chunk past every iteration is the one chunk it would be: chunk_size=10**9 made the kernel ask for
            # 27 doubles a sample per thread up front (216 GB), then fall back to the torch path (an audit).
            "max_iterations": settings["max_iterations"],
            "chunk_size": min(settings["chunk_size"], settings["max_iterations"]),
            "scoring": float(settings["scoring"] == "ransac"), "local_optimization": float(local_optimization),
            "preverification": float(preverification), "polish": float(polish), "lo_steps": LOCAL_OPTIMIZATION_STEPS,
            "lo_window": LOCAL_OPTIMIZATION_WINDOW, "lo_tolerance": LOCAL_OPTIMIZATION_TOLERANCE,
            "polish_steps": POLISH_STEPS, "polish_window": POLISH_WINDOW, "degenerate_pivot": DEGENERATE_PIVOT_RATIO,
            "fast_pivot": _FAST_PIVOT_RATIO, "max_root_determinant": MAX_ROOT_DETERMINANT,
            "guard": _DENOMINATOR_GUARD, "preverify_points": PREVERIFY_POINTS,
            "preverify_keep_ratio": PREVERIFY_KEEP_RATIO, "sign_tie": SIGN_TIE_TOLERANCE}


def estimate_fundamental_ransac(
    points_left: torch.Tensor,
    points_right: torch.Tensor,
    valid: torch.Tensor,
    *,
    threshold_px: float = 1.0,
    confidence: float = 0.99,
    max_iterations: int = 1024,
    chunk_size: int = 96,
    scoring: str = "msac",
    local_optimization: bool = True,
    preverification: bool = True,
    polish: bool = True,
    min_inliers: int = 8,
    generator: torch.Generator | None = None,
    pair_seeds: torch.Tensor | None = None,
) -> FundamentalResult:
    """Robust F for every pair by RANSAC over random 7-point samples (paper Sec. 3.3 (3)), batched.

    Args:
        points_left, points_right: ``(B, K, 2)`` matched points in pixels (row k of both is one correspondence,
            e.g. from :func:`svs_torch.geometry.matched_points.gather_matched_points`).
        valid: ``(B, K)`` bool; padding rows are never sampled, scored or reported as inliers.
        threshold_px: inlier threshold on the Sampson distance (not squared), pixels. MATLAB's default
            DistanceThreshold 0.01 is on the squared distance (0.1 px); OpenCV's FM_RANSAC threshold is on the
            distance to the epipolar lines, about √2 × the Sampson distance.
        confidence: probability that an all-inlier sample was drawn before stopping (MATLAB/OpenCV 0.99);
            1.0 always draws ``max_iterations``.
        max_iterations: hypotheses (7-point samples) per pair at most; each gives up to 3 models.
        chunk_size: samples per pair drawn, solved and scored at once; stopping is checked between chunks.
        scoring: one of :data:`SCORINGS`.
        local_optimization: re-fit improved models on their inliers (see the module docstring).
        preverification: score each chunk's models on PREVERIFY_POINTS random rows first and fully score only
            the best 1 in PREVERIFY_KEEP_RATIO (about 5× less scoring; False scores every model on every row).
        polish: refit the winning model a few more times (see the module docstring).
        min_inliers: a found model with fewer inliers gives ``TOO_FEW_INLIERS``. The default 8: any 7
            correspondences fit some F exactly, so only the 8th inlier is evidence.
        generator: draws the per-pair seeds when ``pair_seeds`` is None (None: torch's global generator), in
            batch order, so a pair's samples then depend on its row (``pair_seeds`` do not; the pipeline's).
        pair_seeds: optional ``(B,)`` int64 seeds, one per pair; pair b's result depends only on its own rows
            and ``pair_seeds[b]``, so ``estimate(points[b:b+1], …, pair_seeds=seeds[b:b+1])`` equals row b
            of the batched call.

    Returns:
        :class:`FundamentalResult`: ``F (B, 3, 3)`` (pixels, ``x_rightᵀ F x_left = 0``, unit norm, rank 2,
        zeros unless OK), ``inliers (B, K)`` (Sampson distance ≤ threshold_px under F, over the input rows),
        ``num_inliers (B,)``, ``status (B,)`` (:class:`FundamentalStatus`; a pair never raises: < 7 valid rows
        → TOO_FEW_MATCHES, no non-degenerate sample → DEGENERATE, < min_inliers → TOO_FEW_INLIERS with its
        inliers still reported), ``iterations (B,)`` samples drawn. F has the input's dtype.

    Not differentiable (discrete sampling and selection).

    Raises:
        InputError: wrong shapes or dtypes, non-finite valid points, out-of-range settings.
    """
    settings = {"threshold_px": threshold_px, "confidence": confidence, "max_iterations": max_iterations,
                "chunk_size": chunk_size, "min_inliers": min_inliers, "scoring": scoring}
    _check_arguments(points_left, points_right, valid, pair_seeds, generator, settings)
    b = points_left.shape[0]
    if pair_seeds is None:
        pair_seeds = torch.randint(0, 1 << 62, (b,), generator=generator, device=points_left.device)
    pair_seeds = pair_seeds.to(torch.int64)
    if scoring != "lmeds":
        compiled = kernels.ransac_fundamental(
            points_left.to(torch.float64), points_right.to(torch.float64), valid, pair_seeds,
            _kernel_settings(settings, local_optimization, preverification, polish))
        if compiled is not None:
            fundamental, found, iterations, inliers = compiled
            return _result(fundamental, found, inliers, valid.sum(-1), iterations, min_inliers, points_left.dtype)
    # The valid rows only, moved to the front (stable, so samples drawn by rank are unchanged).
    order = torch.argsort((~valid).to(torch.uint8), dim=-1, stable=True)
    rows = order[:, :int(valid.sum(-1).max()) if b else 0]
    problem = _prepare(points_left.gather(1, rows.unsqueeze(-1).expand(-1, -1, 2)),
                       points_right.gather(1, rows.unsqueeze(-1).expand(-1, -1, 2)), valid.gather(1, rows),
                       threshold_px, pair_seeds)
    best, losses, iterations = _search(problem, pair_seeds, settings, local_optimization, preverification)
    if polish:
        best = _polish(problem, best, losses[:, 0].isfinite())
    return _finish(problem, points_left, points_right, valid, best, losses[:, 0], iterations, threshold_px,
                   min_inliers)
