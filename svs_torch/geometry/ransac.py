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

Not differentiable: sampling, arg-min and thresholds are discrete. Refit the returned inliers with
:func:`svs_torch.geometry.epipolar.fundamental_8point` for gradients.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from ..core.checks import InputError, check_dtype, check_shape
from .epipolar import (_denormalize, _design_matrix, _eight_point_from_design, _epipolar_terms,
                       _fix_sign_and_scale, _safe_ratio, _sampson_coefficients, _sampson_monomials,
                       _seven_point_from_design, normalize_points_hartley)
from ..core.types import FundamentalResult, FundamentalStatus

__all__ = ["SCORINGS", "draw_minimal_samples", "estimate_fundamental_ransac"]

#: ``"ransac"``: most inliers (the paper), ties broken by the MSAC cost; ``"msac"``: truncated quadratic cost
#: ``Σ min(d², t²)`` (Torr & Zisserman 2000); ``"lmeds"``: least median of squared Sampson distances (MATLAB's
#: default method; inliers are then those within the threshold, as MATLAB's DistanceThreshold).
SCORINGS = ("ransac", "msac", "lmeds")
#: Refits per local optimisation, their Tukey window (× threshold) and the relative gain below which a pair
#: stops. Measured on 64 synthetic pairs (0.5 px noise, 30–50 % outliers): 8 rounds instead of 4 gain 1 % in
#: accuracy; windows of 2–3 thresholds beat a hard threshold (1) by 10–30 %.
LOCAL_OPTIMIZATION_STEPS = 4
LOCAL_OPTIMIZATION_WINDOW = 3.0
LOCAL_OPTIMIZATION_TOLERANCE = 1e-3
#: Final refits of the winner (kept while the truncated cost at the window drops) and their window: about −10 %
#: error on the same benchmark.
POLISH_STEPS = 8
POLISH_WINDOW = 2.0
#: Pre-verification (Matas & Chum's T(d,d) test, batched): models are first scored on this many random valid
#: rows per pair, and only the best 1 in PREVERIFY_KEEP_RATIO of a chunk is scored on every row. A good model
#: has about w·32 inliers among them, a wrong one almost none, so the best model survives; scoring costs ~5× less.
PREVERIFY_POINTS = 32
PREVERIFY_KEEP_RATIO = 8
#: Added to the float32 Sampson denominator (a sum of squares, expanded into monomials whose rounding can make it
#: slightly negative near an epipole): bounds the float32 rounding error of the expansion for normalised points,
#: so scores are never negative. It shrinks d² by a relative 1e-4/den, i.e. only near an epipole; the reported
#: inliers use the exact float64 distance.
_DENOMINATOR_GUARD = 1e-4
#: Scoring blocks hold about this many (hypothesis, point) entries: 4 MB float32 temporaries stay in cache;
#: larger blocks were slower on a 2-core machine, smaller ones pay Python overhead.
_SCORE_BLOCK_ENTRIES = 1 << 20
_SAMPLE_SIZE = 7

# SplitMix64 constants as signed int64 (torch has no uint64 arithmetic; int64 multiplication wraps mod 2⁶⁴).
_GAMMA = 0x9E3779B97F4A7C15 - (1 << 64)
_MIX1 = 0xBF58476D1CE4E5B9 - (1 << 64)
_MIX2 = 0x94D049BB133111EB - (1 << 64)


class _ScoringSet(NamedTuple):
    """Rows that models are scored on (all valid rows, or the pre-verification subset)."""

    numerator: torch.Tensor  # (B, 9, R) float32 monomials: x'ᵀFx = f · m
    denominator: torch.Tensor  # (B, 12, R) float32 monomials: Sampson denominator = g(F) · m
    median_offsets: torch.Tensor  # (B, 1, R) float32, LMedS only: 0 on valid rows, ±inf on padding
    median_rank: int  # LMedS only: the 1-based rank that is each pair's median after the offsets


class _Problem(NamedTuple):
    """One batch, prepared once: normalised points (float64), transforms and scoring sets."""

    design: torch.Tensor  # (B, K, 9) float64 rows a with x'ᵀFx = a · f (normalised points), zero in padding
    quadratic: torch.Tensor  # (B, K, 12) float64 Sampson-denominator monomials (padding: exactly 1)
    transform_left: torch.Tensor  # (B, 3, 3), x_normalised = T x_px
    transform_right: torch.Tensor  # (B, 3, 3)
    valid: torch.Tensor  # (B, K) bool
    num_valid: torch.Tensor  # (B,) int64; the valid rows are the first num_valid rows of each pair
    threshold_sq: torch.Tensor  # (B,) float64, threshold² in normalised units
    full: _ScoringSet
    subset: _ScoringSet  # PREVERIFY_POINTS random valid rows per pair


def _shift_right(value: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 (torch's ``>>`` is arithmetic)."""
    return (value >> bits) & ((1 << (64 - bits)) - 1)


def _splitmix64(state: torch.Tensor) -> torch.Tensor:
    """The SplitMix64 output function of an int64 state (bit-exact with the uint64 reference)."""
    z = (state ^ _shift_right(state, 30)) * _MIX1
    z = (z ^ _shift_right(z, 27)) * _MIX2
    return z ^ _shift_right(z, 31)


def draw_minimal_samples(pair_seeds: torch.Tensor, first_hypothesis: int, num_hypotheses: int,
                         num_valid: torch.Tensor, sample_size: int = _SAMPLE_SIZE) -> torch.Tensor:
    """Ranks of random minimal samples: ``(B, M, sample_size)`` distinct ranks in ``[0, num_valid)`` per pair.

    Hypothesis h (global index, ``first_hypothesis ≤ h < first_hypothesis + M``) of pair b depends only on
    ``pair_seeds[b]``, h and ``num_valid[b]`` (counter-based SplitMix64, then Floyd's algorithm, which draws a
    uniform subset). Pairs with fewer than ``sample_size`` valid rows get ranks that must be ignored.
    """
    device = pair_seeds.device
    hypotheses = torch.arange(first_hypothesis, first_hypothesis + num_hypotheses, device=device)
    counter = hypotheses.unsqueeze(-1) * sample_size + torch.arange(1, sample_size + 1, device=device)  # (M, s)
    bits = _shift_right(_splitmix64(pair_seeds.view(-1, 1, 1) + counter * _GAMMA), 11)  # (B, M, s), 53 bits
    population = num_valid.clamp(min=sample_size).view(-1, 1)  # (B, 1)
    chosen: list[torch.Tensor] = []
    for slot in range(sample_size):
        # Floyd: pick t in [0, j] with j = n − s + slot; if t is taken, take j (never taken yet) instead.
        top = population - sample_size + slot
        pick = bits[..., slot] % (top + 1)
        if chosen:
            taken = (torch.stack(chosen, -1) == pick.unsqueeze(-1)).any(-1)
            pick = torch.where(taken, top.expand_as(pick), pick)
        chosen.append(pick)
    return torch.stack(chosen, -1)


def _scoring_set(numerator: torch.Tensor, denominator: torch.Tensor, valid: torch.Tensor) -> _ScoringSet:
    """A scoring set over rows with validity ``(B, R)``; LMedS offsets make one rank the median of every pair.

    Padding scores exactly 0; giving the first ``p_b`` padding rows −inf and the rest +inf shifts pair b's
    median (rank ``(n_b − 1)//2 + 1`` among its n_b valid rows) to the common rank ``k = max_b`` of those ranks
    when ``p_b = k − rank_b`` (always ≤ the pair's padding count), so one ``kthvalue`` serves the batch.
    """
    count = valid.sum(-1)
    rank = (count - 1).clamp(min=0) // 2 + 1
    common = int(rank.max()) if rank.numel() else 1
    padding_rank = (~valid).cumsum(-1) - 1
    below = (~valid) & (padding_rank < (common - rank).unsqueeze(-1))
    offsets = torch.where(valid, 0.0, torch.where(below, -math.inf, math.inf)).float().unsqueeze(1)
    return _ScoringSet(numerator, denominator, offsets, common)


def _normalize_shared_scale(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Hartley normalisation with one scale s for both images of a pair (so ``d_normalised = s·d_px``)."""
    work = torch.float64
    mask = valid.unsqueeze(-1)
    left_px = torch.where(mask, points_left.to(work), 0.0)
    right_px = torch.where(mask, points_right.to(work), 0.0)
    _, t_left = normalize_points_hartley(left_px, valid.to(work))
    _, t_right = normalize_points_hartley(right_px, valid.to(work))
    scale = (t_left[:, 0, 0] * t_right[:, 0, 0]).sqrt()  # (B,)
    normalised, transforms = [], []
    for points, t in ((left_px, t_left), (right_px, t_right)):
        shift = t[:, :2, 2] / t[:, :1, 0] * scale.unsqueeze(-1)  # −centroid · s
        t = t.clone()
        t[:, :2, 2] = shift
        t[:, 0, 0] = t[:, 1, 1] = scale
        transforms.append(t)
        normalised.append(torch.where(mask, points * scale.view(-1, 1, 1) + shift.unsqueeze(1), 0.0))
    return normalised[0], normalised[1], transforms[0], transforms[1], scale


def _preverification_rows(pair_seeds: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """PREVERIFY_POINTS rows per pair ``(B, P)``: a uniform random subset of the valid rows, chosen by rank.

    Each valid row's key hashes its rank among the valid rows (not its index), so padding rows, wherever they
    are, never change the subset; padding fills the subset only when a pair has fewer valid rows.
    """
    rank = valid.cumsum(-1) - 1
    subset_seed = _splitmix64(pair_seeds + _GAMMA).unsqueeze(-1)  # a stream apart from the samples'
    keys = _splitmix64(subset_seed + (rank + 1) * _GAMMA)
    keys = torch.where(valid, keys, torch.iinfo(torch.int64).max)
    size = min(PREVERIFY_POINTS, valid.shape[1])
    return keys.topk(size, dim=-1, largest=False, sorted=True).indices


def _prepare(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor, threshold_px: float,
             pair_seeds: torch.Tensor) -> _Problem:
    """Normalise each pair and build the monomials and scoring sets, once per call; rows ``(B, K, 2)`` hold
    each pair's valid correspondences first."""
    left, right, t_left, t_right, scale = _normalize_shared_scale(points_left, points_right, valid)
    mask = valid.unsqueeze(-1)
    design = torch.where(mask, _design_matrix(left, right), 0.0)  # (B, K, 9)
    padding_row = torch.zeros(12, dtype=design.dtype, device=design.device)
    padding_row[11] = 1.0
    quadratic = torch.where(mask, _sampson_monomials(left, right), padding_row)  # (B, K, 12)
    numerator = design.transpose(1, 2).float().contiguous()  # (B, 9, K) for the float32 scoring products
    denominator = quadratic.transpose(1, 2).float().contiguous()  # (B, 12, K)
    rows = _preverification_rows(pair_seeds, valid)
    subset = _scoring_set(numerator.gather(2, rows.unsqueeze(1).expand(-1, 9, -1)),
                          denominator.gather(2, rows.unsqueeze(1).expand(-1, 12, -1)), valid.gather(1, rows))
    return _Problem(design=design, quadratic=quadratic, transform_left=t_left, transform_right=t_right,
                    valid=valid, num_valid=valid.sum(-1),
                    threshold_sq=(threshold_px * scale).square(),
                    full=_scoring_set(numerator, denominator, valid), subset=subset)


def _score(rows: _ScoringSet, fundamental: torch.Tensor, usable: torch.Tensor, threshold_sq: torch.Tensor,
           scoring: str) -> torch.Tensor:
    """Loss of each model ``(B, S, 3, 3)`` (normalised coordinates) on ``rows`` → ``(B, S)`` float64, lower is
    better; inf where ``usable`` is False.

    Blocks of models are scored by two matrix products and a few in-place passes, never materialising more
    than about ``_SCORE_BLOCK_ENTRIES`` distances.
    """
    b, s = usable.shape
    r = rows.numerator.shape[-1]
    coefficients_num = fundamental.flatten(-2).float()  # (B, S, 9)
    coefficients_den = _sampson_coefficients(fundamental, _DENOMINATOR_GUARD).float()  # (B, S, 12)
    threshold_sq = threshold_sq.float().view(-1, 1, 1)
    block = max(1, _SCORE_BLOCK_ENTRIES // max(1, b * r))
    losses = [torch.zeros(b, 0, dtype=torch.float64, device=usable.device)]
    for start in range(0, s, block):
        distance_sq = torch.bmm(coefficients_num[:, start:start + block], rows.numerator)  # (B, s', R)
        distance_sq = distance_sq.mul_(distance_sq).div_(
            torch.bmm(coefficients_den[:, start:start + block], rows.denominator))
        if scoring == "lmeds":
            loss = distance_sq.add_(rows.median_offsets).kthvalue(rows.median_rank, dim=-1).values
        elif scoring == "ransac":
            count = (distance_sq <= threshold_sq).sum(-1, dtype=torch.float32)
            # MSAC cost / t² < R + 1: the fraction only breaks ties between equal counts.
            tie = torch.minimum(distance_sq, threshold_sq, out=distance_sq).sum(-1) / threshold_sq.view(-1, 1)
            loss = tie.double() / (r + 1) - count.double()
        else:
            loss = torch.minimum(distance_sq, threshold_sq, out=distance_sq).sum(-1)
        losses.append(loss.double())
    return torch.where(usable, torch.cat(losses, 1), math.inf)


def _solve_chunk(problem: _Problem, pair_seeds: torch.Tensor, first: int,
                 count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Draw ``count`` samples per pair and solve them: models ``(B, 3·count, 3, 3)`` and validity ``(B, 3·count)``."""
    b = problem.valid.shape[0]
    ranks = draw_minimal_samples(pair_seeds, first, count, problem.num_valid)  # (B, M, 7), rank = row
    rows = ranks.flatten(1).unsqueeze(-1).expand(-1, -1, 9)  # (B, M·7, 9)
    design = problem.design.gather(1, rows).view(b, count, _SAMPLE_SIZE, 9)
    models, usable = _seven_point_from_design(design)  # (B, M, 3, 3, 3), (B, M, 3)
    return models.flatten(1, 2), usable.flatten(1)


def _sampson_sq(problem: _Problem, fundamental: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared Sampson distances ``(B, K)`` (normalised units, float64) of models ``(B, 3, 3)``, and the
    denominators; only meaningful on valid rows."""
    algebraic = (problem.design @ fundamental.flatten(-2).unsqueeze(-1)).squeeze(-1)
    denominator = (problem.quadratic @ _sampson_coefficients(fundamental).unsqueeze(-1)).squeeze(-1)
    denominator = denominator.clamp(min=0.0)  # a sum of squares; the expansion may round to −1e-16
    return _safe_ratio(algebraic.square(), denominator), denominator


def _select_pairs(problem: _Problem, index: torch.Tensor) -> _Problem:
    """The pairs at ``index`` (int64) of a prepared batch; scoring sets keep their common LMedS rank."""
    def pick(value):
        if isinstance(value, _ScoringSet):
            return value._replace(numerator=pick(value.numerator), denominator=pick(value.denominator),
                                  median_offsets=pick(value.median_offsets))
        return value.index_select(0, index)

    return _Problem(*(pick(value) for value in problem))


def _reweighted_refit(problem: _Problem, model: torch.Tensor, window: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One iteratively re-weighted least-squares step from models ``(b, 3, 3)``: the refit and whether each
    model had the 8 inliers a fit needs ``(b,)``.

    Weights are Tukey's biweight of the Sampson distance within ``window × threshold``, divided by the Sampson
    denominator, so the algebraic least squares minimises a robust first-order geometric error (a soft inlier
    set: it takes noise beyond the threshold into account without letting far points pull).
    """
    distance_sq, denominator = _sampson_sq(problem, model)
    threshold_sq = problem.threshold_sq.unsqueeze(-1)
    window_sq = window * window * threshold_sq
    near = problem.valid & (distance_sq <= window_sq) & (denominator > 0)
    enough = (near & (distance_sq <= threshold_sq)).sum(-1) >= 8
    tukey = (1.0 - distance_sq / window_sq).clamp(min=0.0).square()
    weights = torch.where(near, tukey / torch.where(near, denominator, 1.0), 0.0)
    return _eight_point_from_design(problem.design, weights), enough


def _local_optimization(problem: _Problem, best: torch.Tensor, best_loss: torch.Tensor, improved: torch.Tensor,
                        scoring: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Re-fit the improved pairs by :func:`_reweighted_refit`, keeping each refit that scores better.

    Only the improved pairs are computed. A pair stops once a refit gains less than
    LOCAL_OPTIMIZATION_TOLERANCE and is frozen, so the other pairs' iterations never change it.
    """
    index = improved.nonzero().squeeze(-1)
    part = _select_pairs(problem, index)
    part_best, part_loss = best.index_select(0, index), best_loss.index_select(0, index)
    running = torch.ones_like(part_loss, dtype=torch.bool)
    for _ in range(LOCAL_OPTIMIZATION_STEPS):
        refit, enough = _reweighted_refit(part, part_best, LOCAL_OPTIMIZATION_WINDOW)
        refit_loss = _score(part.full, refit.unsqueeze(1), (enough & running).unsqueeze(1), part.threshold_sq,
                            scoring).squeeze(1)
        better = refit_loss < part_loss
        part_best = torch.where(better.view(-1, 1, 1), refit, part_best)
        running = better & (refit_loss < part_loss - LOCAL_OPTIMIZATION_TOLERANCE * part_loss.abs())
        part_loss = torch.where(better, refit_loss, part_loss)
        if not bool(running.any()):
            break
    return best.index_copy(0, index, part_best), best_loss.index_copy(0, index, part_loss)


def _polish(problem: _Problem, best: torch.Tensor, found: torch.Tensor) -> torch.Tensor:
    """The final model of each found pair after up to POLISH_STEPS re-weighted refits (an M-estimator from the
    RANSAC model, as MAGSAC++'s final σ-consensus step).

    A refit is kept only if it lowers the truncated quadratic cost at the polish window (the cost the Tukey
    weights approximate), so a weak, nearly degenerate pair can never be polished away from its inliers.
    """
    window_sq = POLISH_WINDOW * POLISH_WINDOW * problem.threshold_sq
    loss = _score(problem.full, best.unsqueeze(1), found.unsqueeze(1), window_sq, "msac").squeeze(1)
    running = found
    for _ in range(POLISH_STEPS):
        refit, enough = _reweighted_refit(problem, best, POLISH_WINDOW)
        refit_loss = _score(problem.full, refit.unsqueeze(1), (enough & running).unsqueeze(1), window_sq,
                            "msac").squeeze(1)
        better = refit_loss < loss
        best = torch.where(better.view(-1, 1, 1), refit, best)
        running = better & (refit_loss < loss - LOCAL_OPTIMIZATION_TOLERANCE * loss.abs())  # then frozen
        loss = torch.where(better, refit_loss, loss)
        if not bool(running.any()):
            break
    return best


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
    check_shape(valid, "valid", [dims["B"], dims["K"]])
    check_dtype(valid, "valid", "bool")
    if pair_seeds is not None:
        if generator is not None:
            raise InputError("pair_seeds: expected either pair_seeds or generator, not both")
        check_shape(pair_seeds, "pair_seeds", [dims["B"]])
        check_dtype(pair_seeds, "pair_seeds", "int")
    rules = {"threshold_px": (lambda v: math.isfinite(v) and v > 0, "a finite positive number of pixels"),
             "confidence": (lambda v: 0 < v <= 1, "a probability in (0, 1]"),
             "max_iterations": (lambda v: isinstance(v, int) and v >= 1, "an int ≥ 1"),
             "chunk_size": (lambda v: isinstance(v, int) and v >= 1, "an int ≥ 1"),
             "min_inliers": (lambda v: isinstance(v, int) and v >= 0, "an int ≥ 0"),
             "scoring": (lambda v: v in SCORINGS, f"one of {', '.join(SCORINGS)}")}
    for name, (ok, expected) in rules.items():
        try:
            passed = bool(ok(settings[name]))
        except (TypeError, ValueError, RuntimeError):  # e.g. a string or a tensor of several values
            passed = False
        if not passed:
            raise InputError(f"{name}: expected {expected}, got {settings[name]!r}")
    both = torch.cat([points_left, points_right], -1)
    if not bool(torch.where(valid.unsqueeze(-1), both, 0.0).isfinite().all()):
        raise InputError("points_left: expected finite coordinates in valid rows (NaN or inf found)")


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
    inliers = valid & found.unsqueeze(-1) & (distance_sq <= torch.tensor(float(threshold_px), dtype=work, device=distance_sq.device).square())
    num_inliers = inliers.sum(-1)
    status = torch.full_like(num_inliers, FundamentalStatus.OK)
    status = torch.where(num_inliers < min_inliers, FundamentalStatus.TOO_FEW_INLIERS, status)
    status = torch.where(~found, FundamentalStatus.DEGENERATE, status)
    status = torch.where(problem.num_valid < _SAMPLE_SIZE, FundamentalStatus.TOO_FEW_MATCHES, status)
    ok = status == FundamentalStatus.OK
    return FundamentalResult(F=torch.where(ok.view(-1, 1, 1), fundamental, 0.0).to(points_left.dtype),
                             inliers=inliers, num_inliers=num_inliers, status=status, iterations=iterations)


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
            e.g. from :func:`svs_torch.geometry.matching.gather_matched_points`).
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
        generator: draws the per-pair seeds when ``pair_seeds`` is None (None: torch's global generator).
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
