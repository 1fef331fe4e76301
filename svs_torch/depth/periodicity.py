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
from .pooling import mean_pool

__all__ = ["MAX_PERIOD_PX", "repeated_along_rows", "repeated_at_working_width", "row_autocorrelation"]

#: Longest period looked for, pixels of the image given.
MAX_PERIOD_PX = 32
#: How far the correlation must rise again from its least value at a shorter lag to count as a period's peak: a
#: grate's horizontal bars keep it above 0 at every lag (0.1 between its peaks of 0.99).
MIN_RISE = 0.4


def row_autocorrelation(image: torch.Tensor, mask: torch.Tensor, max_lag_px: int = MAX_PERIOD_PX) -> torch.Tensor:
    """``(B, max_lag_px)``: the normalised autocorrelation of ``image`` ``(B, 1, H, W)`` along its rows at lags
    1 … ``max_lag_px`` pixels, over the pixel pairs both inside ``mask`` ``(B, 1, H, W)`` bool, each pair's values
    centred on their mean over the mask; 0 at a lag with no such pair. Not differentiable (a test).

    Three row correlations by FFT, zero-padded past the longest lag so that none wraps: the centred values with
    themselves, and their squares with the mask both ways (each lag's norm over its own pairs). Shifted products
    of the whole image, lag by lag, took 14 ms a 320 × 240 pair; this takes about 3."""
    check_image(image, "image")
    check_shape(mask, "mask", list(image.shape))
    check_dtype(mask, "mask", "bool")
    check_count(max_lag_px, "max_lag_px", 1)
    x, inside = image.detach().to(torch.float64), mask.to(torch.float64)
    count = inside.sum((1, 2, 3), keepdim=True).clamp_min(1)
    centred = (x - (x * inside).sum((1, 2, 3), keepdim=True) / count) * inside
    length = x.shape[-1] + max_lag_px

    def correlated(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # Σ over rows and i of a[i] · b[i + lag]
        spectrum = torch.fft.rfft(a, n=length).conj() * torch.fft.rfft(b, n=length)
        return torch.fft.irfft(spectrum, n=length)[..., 1:max_lag_px + 1].sum((1, 2))

    squares = centred * centred
    products = correlated(centred, centred)
    norm = (correlated(squares, inside) * correlated(inside, squares)).clamp_min(0).sqrt()
    return torch.where(norm > 1e-12, products / norm.clamp_min(1e-12), 0.0)


def repeated_along_rows(image: torch.Tensor, mask: torch.Tensor, min_peak: float, max_lag_px: int = MAX_PERIOD_PX
                        ) -> torch.Tensor:
    """``(B,)`` bool: the pairs whose ``image`` ``(B, 1, H, W)`` repeats itself along the rows over ``mask``: its
    :func:`row_autocorrelation` rises again, by :data:`MIN_RISE` or more from its least value at a shorter lag, to a
    local peak of at least ``min_peak`` at a lag of 3 pixels or more. Not differentiable."""
    check_real(min_peak, "min_peak", 0.0, 1.0)
    r = row_autocorrelation(image, mask, max_lag_px)
    if r.shape[1] < 4:
        return torch.zeros(r.shape[0], dtype=torch.bool, device=r.device)
    lowest = torch.cummin(r, dim=1).values  # the least correlation up to each lag
    peak = (r[:, 1:-1] >= r[:, :-2]) & (r[:, 1:-1] >= r[:, 2:]) & (r[:, 1:-1] >= min_peak)  # lags 2 … max − 1
    risen = r[:, 1:-1] - lowest[:, :-2] >= MIN_RISE
    lag = torch.arange(2, r.shape[1], device=r.device)
    return (peak & risen & (lag >= 3)).any(dim=1)


def repeated_at_working_width(left: torch.Tensor, mask: torch.Tensor, min_peak: float,
                              config: DenseConfig = DenseConfig()) -> torch.Tensor:
    """:func:`repeated_along_rows` of the left views ``(B, 1, H, W)`` over ``mask`` ``(B, 1, H, W)`` bool, both
    reduced to the dense stage's working width (``config``; the mask to its blocks wholly inside): the periods the
    dense matcher sees. ``(B,)`` bool. Not differentiable."""
    check_shape(mask, "mask", list(left.shape))
    check_dtype(mask, "mask", "bool")
    factor = working_factor(left.shape[-1], config, left.shape[-2])
    if factor > 1:
        left = mean_pool(left.detach(), factor)
        mask = mean_pool(mask.to(left.dtype), factor) >= 1
    return repeated_along_rows(left, mask, min_peak)
