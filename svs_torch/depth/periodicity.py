"""Does a region repeat itself along the rows (a fence, a railing, a grate, a checkerboard)?

The block matcher's cost over such a region has a minimum at the true disparity and one a period away on either
side. Measured on a coarser grid the period shrinks with the pixels, and a pattern of 8-24 px becomes one of 4-12,
where the aliases lie closer and the sub-pixel fit locks onto the pattern's edges: on rendered panels as the board's
camera frames, the pipeline with the coarse retry told a wrong distance for 10 of 36 (a period off, or 6-8 %
near); kept at the working width, for none of them, 32 ranged within 5 % (``experiments/repeated_patterns.md``).

The test is the row autocorrelation of the left view over the region: a natural texture's falls from 1 and stays
low; a repeated pattern's falls, then rises again to a peak one period away.
"""

from __future__ import annotations

import torch

from ..core.checks import check_count, check_dtype, check_image, check_real, check_shape
from .dense import working_factor
from .dense_config import DenseConfig
from .depth_types import DepthConfig
from .pooling import mean_pool

__all__ = ["MAX_PERIOD_PX", "object_periods", "period_along_rows", "period_at_working_width", "repeated_along_rows",
           "repeated_at_working_width", "row_autocorrelation"]

#: Longest period looked for by default, pixels of the image given (the pipeline's alias check's:
#: ``DepthConfig.alias_check_max_period_px``; its coarse grid's gate looks further).
MAX_PERIOD_PX = DepthConfig.alias_check_max_period_px
#: How far the correlation must rise again from its least value at a shorter lag to count as a period's peak: a
#: grate's horizontal bars keep it above 0 at every lag (0.1 between its peaks of 0.99).
MIN_RISE = 0.4
#: Fewest pixel pairs at a period's lag for its peak to count; 0, off. At 64 it cleared blank noisy views as the spread
#: floor below does, and cost rendered panels (seed 9, a loose rig's camera frames) one grate told a wrong distance
#: in place of one left unranged (experiments/blank_views.md).
MIN_PERIOD_PAIRS = 0
#: Least spread (standard deviation) of the image over the region, in its [0, 1] levels, for a pattern to be looked
#: for: 4 of 255. A small region of a blank, noisy view (a covered lens, a grey wall as the board's camera frames)
#: correlates to 0.5-1.0 by chance over its few pixel pairs: guide said "Repeated pattern ahead" there, and never
#: "Cannot see ahead" (an audit). Its noise spreads less than this; no rendered panel does (the same experiment).
MIN_PATTERN_SPREAD = 4 / 255


def row_autocorrelation(image: torch.Tensor, mask: torch.Tensor, max_lag_px: int = MAX_PERIOD_PX) -> torch.Tensor:
    """``(B, max_lag_px)``: the normalised autocorrelation of ``image`` ``(B, 1, H, W)`` along its rows at lags
    1 … ``max_lag_px`` pixels, over the pixel pairs both inside ``mask`` ``(B, 1, H, W)`` bool, each pair's values
    centred on their mean over the mask; 0 at a lag with no such pair. Not differentiable (a test).

    Four row correlations by FFT, zero-padded past the longest lag so that none wraps: the centred values with
    themselves, their squares with the mask both ways (each lag's norm over its own pairs) and the mask with
    itself (the pairs' count). Shifted products of the whole image, lag by lag, took 14 ms a 320 × 240 pair; an
    inverse transform of every row 1.2-2.7; this, about 0.8-1.2."""
    return _row_statistics(image, mask, max_lag_px)[0]


def _row_statistics(image: torch.Tensor, mask: torch.Tensor, max_lag_px: int
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`row_autocorrelation`, with the pixel pairs at each lag ``(B, max_lag_px)`` and the image's standard
    deviation over the mask ``(B,)`` (0 where the mask is empty); the arguments checked here, for both callers."""
    check_image(image, "image")
    check_shape(mask, "mask", list(image.shape))
    check_dtype(mask, "mask", "bool")
    check_count(max_lag_px, "max_lag_px", 1)
    # In float32 (a fifth of float64's time; the correlations within 1e-5 of numpy's float64). The three images are
    # written into one zero-padded buffer and transformed in one call, at a length of small prime factors (the 344
    # of 320 + 24 has 43 and took 6.7× as long as 352). The sums over rows are taken of the spectra's products,
    # before the inverse transform (it is linear): one inverse a pair, in float64, not one a row. The pairs' counts
    # stay within 0.04 of the exact ones on a 2900 × 2000 image (0.0003 at 320 × 240), well inside the 0.5 below.
    x, width = image.detach().to(torch.float32), image.shape[-1]
    length = _fft_length(width + max_lag_px)
    padded = x.new_empty((3, *x.shape[:-1], length))
    padded[..., width:] = 0
    centred, centred_squared, inside = padded[..., :width].unbind(0)
    inside.copy_(mask)
    count = inside.sum((1, 2, 3), keepdim=True).clamp_min(1)
    x_inside = x * inside
    torch.mul(x - x_inside.sum((1, 2, 3), keepdim=True) / count, inside, out=centred)
    torch.mul(centred, centred, out=centred_squared)
    values, squares, weights = torch.fft.rfft(padded).unbind(0)

    def inverse(spectrum: torch.Tensor) -> torch.Tensor:  # (B, F) summed spectrum → lags 1 … max_lag_px
        return torch.fft.irfft(spectrum.to(torch.complex128), n=length)[..., 1:max_lag_px + 1]

    def power(a: torch.Tensor) -> torch.Tensor:  # Σ over rows of conj(a) · a, real
        parts = torch.view_as_real(a).flatten(-2)  # (B, 1, H, 2F): real and imaginary parts side by side
        return (parts * parts).sum((1, 2)).view(*a.shape[:1], -1, 2).sum(-1)

    # Σ over rows and i of a[i] · b[i + lag] is the inverse of Σ over rows of conj(A) · B; squares against weights
    # both ways are one product and its conjugate.
    squares_weights = (squares.conj() * weights).sum((1, 2))
    products = inverse(power(values))
    norm = (inverse(squares_weights) * inverse(squares_weights.conj())).clamp_min(0).sqrt()
    # float32 rounding is not 0 where the sums are: a lag with no pixel pair inside the mask (a mask of every other
    # square of a checker has none at its side) is told by the pairs' count, exact to well under 0.5; a region
    # without texture (the bright squares alone, all one level) by its centred energy against its values' (a level
    # of texture on mid grey: 6e-5); a lag's norm against the FFTs' rounding of that energy.
    energy = centred_squared.sum((1, 2, 3)).to(torch.float64).view(-1, 1)
    textured = energy > 1e-8 * (x_inside * x_inside).sum((1, 2, 3)).to(torch.float64).view(-1, 1)
    pairs = inverse(power(weights))
    paired = (pairs >= 0.5) & (norm > 1e-6 * energy) & textured
    spread = (energy.view(-1) / count.view(-1).to(torch.float64)).sqrt()
    return torch.where(paired, products / norm.clamp_min(1e-30), 0.0).clamp(-1.0, 1.0), pairs.round(), spread


def _fft_length(least: int) -> int:
    """The shortest even length of ``least`` or more whose prime factors are all 2, 3, 5 or 11: measured the fast
    ones of the real FFT here (320 + 24 = 344 has 43 and took 6.7× as long as 352; 350, with 7, 3×)."""
    length = least + least % 2
    while True:
        rest = length
        for factor in (2, 3, 5, 11):
            while rest % factor == 0:
                rest //= factor
        if rest == 1:
            return length
        length += 2


def period_along_rows(image: torch.Tensor, mask: torch.Tensor, min_peak: float, max_lag_px: int = MAX_PERIOD_PX
                      ) -> torch.Tensor:
    """``(B,)`` int64: the period, pixels, at which ``image`` ``(B, 1, H, W)`` repeats itself along the rows over
    ``mask``: the shortest lag of 3 pixels or more where its :func:`row_autocorrelation` rises again, by
    :data:`MIN_RISE` or more from its least value at a shorter lag, to a local peak of at least ``min_peak`` over
    :data:`MIN_PERIOD_PAIRS` pixel pairs or more; 0 where it does not repeat, or where the image spreads less than
    :data:`MIN_PATTERN_SPREAD` over the mask (a blank view's noise). Not differentiable."""
    check_real(min_peak, "min_peak", 0.0, 1.0)
    r, pairs, spread = _row_statistics(image, mask, max_lag_px)
    if r.shape[1] < 4:
        return torch.zeros(r.shape[0], dtype=torch.int64, device=r.device)
    lowest = torch.cummin(r, dim=1).values  # the least correlation up to each lag
    peak = (r[:, 1:-1] >= r[:, :-2]) & (r[:, 1:-1] >= r[:, 2:]) & (r[:, 1:-1] >= min_peak)  # lags 2 … max − 1
    risen = r[:, 1:-1] - lowest[:, :-2] >= MIN_RISE
    lag = torch.arange(2, r.shape[1], device=r.device)
    found = peak & risen & (lag >= 3) & (pairs[:, 1:-1] >= MIN_PERIOD_PAIRS) & (spread >= MIN_PATTERN_SPREAD)[:, None]
    shortest = torch.where(found, lag, r.shape[1] + 1).amin(dim=1)
    return torch.where(found.any(dim=1), shortest, 0)


def repeated_along_rows(image: torch.Tensor, mask: torch.Tensor, min_peak: float, max_lag_px: int = MAX_PERIOD_PX
                        ) -> torch.Tensor:
    """``(B,)`` bool: the pairs whose ``image`` ``(B, 1, H, W)`` repeats itself along the rows over ``mask``
    (:func:`period_along_rows` found a period). Not differentiable."""
    return period_along_rows(image, mask, min_peak, max_lag_px) > 0


def period_at_working_width(left: torch.Tensor, mask: torch.Tensor, min_peak: float,
                            config: DenseConfig = DenseConfig(), max_lag_px: int = MAX_PERIOD_PX) -> torch.Tensor:
    """:func:`period_along_rows` of the left views ``(B, 1, H, W)`` over ``mask`` ``(B, 1, H, W)`` bool, both
    reduced to the dense stage's working width (``config``; the mask to its blocks wholly inside), up to a lag of
    ``max_lag_px`` working pixels: the periods the dense matcher sees, given in input pixels (the working period
    times the reduction factor), 0 where none. ``(B,)`` int64. Not differentiable."""
    check_shape(mask, "mask", list(left.shape))
    check_dtype(mask, "mask", "bool")
    factor = working_factor(left.shape[-1], config, left.shape[-2])
    if factor > 1:
        left = mean_pool(left.detach(), factor)
        mask = mean_pool(mask.to(left.dtype), factor) >= 1
    return period_along_rows(left, mask, min_peak, max_lag_px) * factor


def repeated_at_working_width(left: torch.Tensor, mask: torch.Tensor, min_peak: float,
                              config: DenseConfig = DenseConfig(), max_lag_px: int = MAX_PERIOD_PX) -> torch.Tensor:
    """``(B,)`` bool: :func:`period_at_working_width` found a period. Not differentiable."""
    return period_at_working_width(left, mask, min_peak, config, max_lag_px) > 0


def object_periods(left: torch.Tensor, objects: torch.Tensor, min_peak: float, config: DenseConfig = DenseConfig(),
                   max_lag_px: int = MAX_PERIOD_PX) -> torch.Tensor:
    """``(B, N)`` int64: each object's period (:func:`period_at_working_width` of the left view ``(B, 1, H, W)``
    over the object's own mask, ``objects`` ``(B, N, H, W)`` bool), input pixels; 0 where it does not repeat.
    Only the pairs whose objects' union repeats are looked at object by object. The union alone is not enough:
    two like regions side by side correlate at the lag that separates them (the tuned Piano at half contrast,
    JPEG digit 8 with noise σ 8: two regions 26 and 52 px wide, a union period of 48 px that neither has, with
    lags up to 64). Not differentiable."""
    check_dtype(objects, "objects", "bool")
    check_shape(objects, "objects", [left.shape[0], "N", *left.shape[-2:]])
    periods = torch.zeros(objects.shape[:2], dtype=torch.int64, device=objects.device)
    union = objects.any(dim=1, keepdim=True)
    index = (period_at_working_width(left, union, min_peak, config, max_lag_px) > 0).nonzero().flatten()
    if len(index) == 0:
        return periods
    n, (height, width) = objects.shape[1], objects.shape[-2:]
    each = objects[index].reshape(-1, 1, height, width)
    views = left[index].unsqueeze(1).expand(-1, n, -1, -1, -1).reshape(-1, 1, height, width)
    found = period_at_working_width(views, each, min_peak, config, max_lag_px).view(-1, n)
    return periods.index_put((index,), found)
