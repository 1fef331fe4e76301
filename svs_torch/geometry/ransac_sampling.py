"""RANSAC's random draws, the same for a pair whatever its batch: the minimal samples of each hypothesis
(:func:`draw_minimal_samples`, SplitMix64 from the pair's seed and the hypothesis index) and the
pre-verification rows.
"""

from __future__ import annotations

import torch

__all__ = ["PREVERIFY_POINTS", "draw_minimal_samples"]


#: Pre-verification (Matas & Chum's T(d,d) test, batched): models are first scored on this many random valid
#: rows per pair, and only the best 1 in PREVERIFY_KEEP_RATIO of a chunk is scored on every row. A good model
#: has about w·32 inliers among them, a wrong one almost none, so the best model survives; scoring costs ~5× less.
PREVERIFY_POINTS = 32
_SAMPLE_SIZE = 7
# SplitMix64 constants as signed int64 (torch has no uint64 arithmetic; int64 multiplication wraps mod 2⁶⁴).
_GAMMA = 0x9E3779B97F4A7C15 - (1 << 64)
_MIX1 = 0xBF58476D1CE4E5B9 - (1 << 64)
_MIX2 = 0x94D049BB133111EB - (1 << 64)


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
    uniform subset). Pairs with fewer than ``sample_size`` valid rows get ranks that must be ignored. Not
    differentiable (integer ranks).
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
