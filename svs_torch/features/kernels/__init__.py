"""The C kernels of the features stage (the ``.c`` sources beside this file) and their wrappers, each the fast path of
a torch function of the stage that stays its reference: see :mod:`svs_torch.core.kernels` for how they are built,
cached and loaded, and what every wrapper promises."""

from __future__ import annotations

import ctypes

import torch

from ...core.checks import check_shape
from ...core.errors import InputError
from ...core.kernels import FLOAT, INT, POINTER, available, declare, load, on_cpu
from ...core.kernels.checks import canonical_bool, check_nonempty, check_rows

__all__ = [
    "MAX_TABLE_VALUES", "available", "check_border", "hessian_octave", "load", "local_maxima", "padded_integral",
    "refine_maxima", "strongest_maxima", "usurf_describe"
]

declare({
    "hessian_octave": ([POINTER] + [INT] * 5 + [POINTER] + [INT] * 3 + [POINTER] * 2 + [FLOAT]
                       + [POINTER] * 2 + [INT], None),
    "local_maxima": ([POINTER, POINTER] + [INT] * 5 + [FLOAT, POINTER], None),
    "padded_integral": ([POINTER] * 2 + [INT] * 4 + [POINTER, INT], ctypes.c_int),
    "refine_maxima": ([POINTER] * 6 + [INT] + [POINTER] * 2 + [INT] * 2 + [ctypes.c_double] * 2
                      + [POINTER] * 5 + [INT], ctypes.c_int),
    "strongest_maxima": ([POINTER] * 4 + [INT] * 2 + [FLOAT, INT] + [POINTER] * 2 + [INT], ctypes.c_int),
    "usurf_describe": ([POINTER] + [INT] * 4 + [POINTER] * 3 + [INT] * 2 + [POINTER, INT], ctypes.c_int),
})


def hessian_octave(padded: torch.Tensor, pad: int, step: int, sizes: list[int], inverse_lobe_area: list[float],
                   inverse_dxy_area: list[float], dxy_weight: float, det_out: torch.Tensor,
                   trace_out: torch.Tensor) -> bool:
    """Every level of one octave of ``svs_torch.features.hessian._det_trace`` in one call, read straight from the padded
    integral (see the C source): ``padded`` ``(B, 1, PH, PW)`` float32 (:func:`svs_torch.features.integral.pad_integral`
    by ``pad``), grid ``step`` pixels, one filter size and its two box normalisations per level, into
    ``det_out`` / ``trace_out`` ``(B, S, ny, nx)`` float32. Returns False, writing nothing, when the kernel is
    not available or a tensor does not fit (then the caller's torch path runs)."""
    dims = check_shape(det_out, "det_out", ["B", "S", "ny", "nx"])
    b, s, ny, nx = dims["B"], dims["S"], dims["ny"], dims["nx"]
    check_shape(trace_out, "trace_out", [b, s, ny, nx])
    check_shape(padded, "padded", [b, 1, "PH", "PW"])
    if len(sizes) != s or len(inverse_lobe_area) != s or len(inverse_dxy_area) != s:
        raise InputError(f"sizes, inverse_lobe_area, inverse_dxy_area: expected {s} levels each (det_out's S), got "
                         f"{len(sizes)}, {len(inverse_lobe_area)}, {len(inverse_dxy_area)}")
    if not isinstance(step, int) or step < 1 or not isinstance(pad, int) or pad < 0 or min(sizes, default=1) < 1:
        raise InputError(f"step, pad, sizes: expected step >= 1, pad >= 0 and sizes >= 1, got {step!r}, {pad!r}, "
                         f"{sizes!r}")
    if (not on_cpu(torch.float32, padded, det_out, trace_out) or not det_out.is_contiguous()
            or not trace_out.is_contiguous() or ny < 1 or nx < 1 or b < 1):
        return False
    library = load("hessian_octave")
    if library is None:
        return False
    # Every read must stay inside the table: a box reaches half its filter (+ 1 for the integral's corner) around
    # its grid point.
    reach, (height, width) = max(sizes) // 2 + 1, padded.shape[-2:]
    if pad < reach or pad + (ny - 1) * step + reach >= height or pad + (nx - 1) * step + reach >= width:
        return False
    padded = padded.contiguous()
    factors = torch.tensor([inverse_lobe_area, inverse_dxy_area], dtype=torch.float32)
    levels = torch.tensor(sizes, dtype=torch.int64)
    library.hessian_octave(padded.data_ptr(), b, padded.shape[-2], padded.shape[-1], pad, step, levels.data_ptr(), s,
                           ny, nx, factors[0].data_ptr(), factors[1].data_ptr(), dxy_weight, det_out.data_ptr(),
                           trace_out.data_ptr(), torch.get_num_threads())
    return True


#: The most values a padded integral table may hold (8 GiB as float32; a 320×240 view's widest border is under
#: 200 px): past it a border is an error, not a C size computation that overflows (a pad of 2^62 crashed the
#: descriptor kernel) or a torch allocation failing deep inside.
MAX_TABLE_VALUES = 2**31


def check_border(pad: int, height: int, width: int) -> None:
    """InputError naming ``pad`` unless it is a non-negative int whose ``(H + 1 + 2·pad) × (W + 1 + 2·pad)`` table
    holds at most :data:`MAX_TABLE_VALUES` values."""
    if not isinstance(pad, int) or isinstance(pad, bool) or pad < 0:
        raise InputError(f"pad: expected a non-negative int, got {pad!r}")
    values = (height + 1 + 2 * pad) * (width + 1 + 2 * pad)
    if values > MAX_TABLE_VALUES:
        raise InputError(f"pad: a border of {pad} px around a {height}x{width} image asks for an integral table of "
                         f"{values} values (at most {MAX_TABLE_VALUES}); a keypoint's reach is far smaller")


def padded_integral(image: torch.Tensor, means: torch.Tensor | None, pad: int) -> torch.Tensor | None:
    """``pad_integral(integral_image(image − means), pad)`` of ``svs_torch.features.hessian`` in one pass per image (see
    the C source), bit for bit: ``image`` ``(B, 1, H, W)`` float32, ``means`` ``(B,)`` float32 (each image's
    own, subtracted from its pixels; None: ``image_means(image)``, taken by the kernel). Returns the table
    ``(B, 1, H + 1 + 2·pad, W + 1 + 2·pad)``, or None when the kernel is not available or the inputs do not fit
    its contract."""
    dims = check_shape(image, "image", ["B", 1, "H", "W"])
    if means is not None:
        check_shape(means, "means", [dims["B"]])
    check_border(pad, dims["H"], dims["W"])
    if not on_cpu(torch.float32, image, *([] if means is None else [means])):
        return None
    library = load("padded_integral")
    if library is None:
        return None
    b, _, h, w = image.shape
    image, means = image.contiguous(), None if means is None else means.contiguous()
    out = torch.empty(b, 1, h + 1 + 2 * pad, w + 1 + 2 * pad)
    status = library.padded_integral(image.data_ptr(), None if means is None else means.data_ptr(), b, h, w, pad,
                                     out.data_ptr(), torch.get_num_threads())
    return None if status != 0 else out


def _check_support(support: torch.Tensor, name: str, b: int, inner: tuple[int, int, int]) -> None:
    """A maxima support ``(B or 1, S − 2, ny − 2, nx − 2)``: one for every pair or one shared."""
    rows = support.shape[0] if isinstance(support, torch.Tensor) and support.dim() == 4 else b
    check_shape(support, name, [rows if rows in (1, b) else b, *inner])


def local_maxima(det: torch.Tensor, support: torch.Tensor, threshold: float) -> torch.Tensor | None:
    """``svs_torch.features.hessian._interior_maxima`` in one pass: ``det`` ``(B, S, ny, nx)`` float32 where it is a
    3 × 3 × 3 maximum above ``threshold`` with ``support`` (``(B or 1, S − 2, ny − 2, nx − 2)`` bool), −inf
    elsewhere; ``(B, S − 2, ny − 2, nx − 2)``. None when the kernel is not available or the inputs do not fit
    its contract (then the caller's torch path runs)."""
    dims = check_shape(det, "det", ["B", "S", "ny", "nx"])
    b, s, ny, nx = dims["B"], dims["S"], dims["ny"], dims["nx"]
    inner = (s - 2, ny - 2, nx - 2)
    if min(inner) < 1:  # no interior point: the torch path's empty map
        return None
    _check_support(support, "support", b, inner)
    if not (on_cpu(torch.float32, det) and on_cpu(torch.bool, support)):
        return None
    library = load("local_maxima")
    if library is None:
        return None
    det, support = det.contiguous(), support.contiguous()
    out = det.new_empty(b, *inner)
    library.local_maxima(det.data_ptr(), support.data_ptr(), 0 if support.shape[0] == 1 else support[0].numel(),
                         b, s, ny, nx, threshold, out.data_ptr())
    return out


def strongest_maxima(dets: list[torch.Tensor], supports: list[torch.Tensor | None], threshold: float, k: int
                     ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The ``k`` strongest scale-space maxima of each image over all its octaves, in one pass (see the C source):
    ``torch.topk`` of the concatenated, flattened :func:`local_maxima` maps of the octaves, the same k values,
    largest first, equal values in index order; past an image's last maximum, −inf at index 0. ``dets[o]``
    ``(B, S, ny, nx)`` float32; ``supports[o]`` ``(B or 1, S − 2, ny − 2, nx − 2)`` bool, or None for an octave
    without interior points. None when the kernel is not available or the inputs do not fit its contract."""
    if not dets or len(supports) != len(dets):
        raise InputError(f"supports: expected one per octave of dets ({len(dets)}, at least 1), got {len(supports)}")
    b, total = check_shape(dets[0], "dets[0]", ["B", "S", "ny", "nx"])["B"], 0
    kept, pointers = [], []  # kept: the contiguous tensors, alive until the call returns
    for octave, (det, support) in enumerate(zip(dets, supports)):
        check_shape(det, f"dets[{octave}]", [b, "S", "ny", "nx"])
        if not on_cpu(torch.float32, det):
            return None
        inner = (det.shape[1] - 2, det.shape[2] - 2, det.shape[3] - 2)
        if min(inner) < 1:  # no interior point (the kernel reads nothing of it)
            pointers.append((det.shape[1:], 0, 0, 0))
            continue
        _check_support(support, f"supports[{octave}]", b, inner)
        if not on_cpu(torch.bool, support):
            return None
        # The C code ands each support byte with the threshold's 0 / 1: a mask viewed from other bytes (2) kept
        # no maximum at all (an audit of hostile calls); nonzero is True, as torch reads a bool.
        det, support = det.contiguous(), canonical_bool(support).contiguous()
        kept += [det, support]
        pointers.append((det.shape[1:], det.data_ptr(), support.data_ptr(),
                         0 if support.shape[0] == 1 else support[0].numel()))
        total += inner[0] * inner[1] * inner[2]
    if not isinstance(k, int) or not 0 <= k <= total:
        raise InputError(f"k: expected an int in [0, {total}] (the octaves' interior points), got {k!r}")
    library = load("strongest_maxima")
    if library is None:
        return None
    shape = torch.tensor([list(p[0]) for p in pointers], dtype=torch.int64)
    det_ptr, support_ptr, stride = (torch.tensor([p[i] for p in pointers], dtype=torch.int64) for i in (1, 2, 3))
    values, index = torch.empty(b, k), torch.empty(b, k, dtype=torch.int64)
    status = library.strongest_maxima(det_ptr.data_ptr(), support_ptr.data_ptr(), stride.data_ptr(),
                                      shape.data_ptr(), len(pointers), b, threshold, k, values.data_ptr(),
                                      index.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (values, index)


def refine_maxima(dets: list[torch.Tensor], traces: list[torch.Tensor], steps: list[int], sizes: list[list[int]],
                  score: torch.Tensor, index: torch.Tensor, factor: float, max_offset: float
                  ) -> tuple[torch.Tensor, ...] | None:
    """The keypoints of :func:`svs_torch.features.detector.detect_surf_keypoints` from its strongest maxima, one
    keypoint at a time (see the C source): ``dets[o]``, ``traces[o]`` ``(B, S, ny, nx)`` float32 with the octave's grid
    step and filter sizes; ``score`` ``(B, K)`` float32 and ``index`` ``(B, K)`` int64 (:func:`strongest_maxima`);
    ``factor`` the detector's upsampling. Returns ``valid`` ``(B, K)`` bool, ``xy`` ``(B, K, 2)``, ``size``,
    ``peak`` ``(B, K)`` float64 and the trace's sign ``(B, K)`` int64; None when the kernel is not available or
    the inputs do not fit its contract (an octave without an interior, for one)."""
    if not dets or len(traces) != len(dets) or len(steps) != len(dets) or len(sizes) != len(dets):
        raise InputError(f"traces, steps, sizes: expected one per octave of dets ({len(dets)}, at least 1), got "
                         f"{len(traces)}, {len(steps)}, {len(sizes)}")
    dims = check_shape(score, "score", ["B", "K"])
    b, k = dims["B"], dims["K"]
    check_rows(index, "index", b, k)
    total = 0
    for octave, (det, trace, levels, step) in enumerate(zip(dets, traces, sizes, steps)):
        check_shape(det, f"dets[{octave}]", [b, "S", "ny", "nx"])
        check_shape(trace, f"traces[{octave}]", list(det.shape))
        if len(levels) != det.shape[1] or len(levels) < 2 or not isinstance(step, int) or step < 1:
            raise InputError(f"sizes[{octave}], steps[{octave}]: expected S >= 2 filter sizes (dets' S) and a grid "
                             f"step >= 1, got {len(levels)} sizes for {tuple(det.shape)}, step {step!r}")
        total += max(0, det.shape[1] - 2) * max(0, det.shape[2] - 2) * max(0, det.shape[3] - 2)
    if (not on_cpu(torch.float32, score, *dets, *traces) or not on_cpu(torch.int64, index)
            or min(min(det.shape[1:]) for det in dets) < 3):  # an octave without an interior: the torch path
        return None
    if index.numel() and bool(((index < 0) | (index >= total)).any()):
        raise InputError(f"index: expected indices in [0, {total}) (the octaves' interior points)")
    library = load("refine_maxima")
    if library is None:
        return None
    kept = [t.contiguous() for t in (*dets, *traces)]  # alive until the call returns
    det_ptr = torch.tensor([t.data_ptr() for t in kept[:len(dets)]], dtype=torch.int64)
    trace_ptr = torch.tensor([t.data_ptr() for t in kept[len(dets):]], dtype=torch.int64)
    shape = torch.tensor([list(d.shape[1:]) for d in dets], dtype=torch.int64)
    step = torch.tensor(steps, dtype=torch.int64)
    size0 = torch.tensor([levels[0] for levels in sizes], dtype=torch.int64)
    size_inc = torch.tensor([levels[1] - levels[0] for levels in sizes], dtype=torch.int64)
    score, index = score.contiguous(), index.contiguous()
    xy = torch.empty(b, k, 2, dtype=torch.float64)
    size, peak = torch.empty(b, k, dtype=torch.float64), torch.empty(b, k, dtype=torch.float64)
    sign, valid = torch.empty(b, k, dtype=torch.int64), torch.empty(b, k, dtype=torch.bool)
    status = library.refine_maxima(det_ptr.data_ptr(), trace_ptr.data_ptr(), shape.data_ptr(), step.data_ptr(),
                                   size0.data_ptr(), size_inc.data_ptr(), len(dets), score.data_ptr(),
                                   index.data_ptr(), b, k, float(factor), float(max_offset), xy.data_ptr(),
                                   size.data_ptr(), peak.data_ptr(), sign.data_ptr(), valid.data_ptr(),
                                   torch.get_num_threads())
    return None if status != 0 else (valid, xy, size, peak, sign)


def usurf_describe(image: torch.Tensor, pad: int, xy: torch.Tensor, scale: torch.Tensor, valid: torch.Tensor,
                   extended: bool) -> torch.Tensor | None:
    """:func:`svs_torch.features.descriptor._describe_upright` from the images (see the C source): ``image``
    ``(B, 1, H, W)`` float32, read through its integral with a replicate border of ``pad`` pixels; ``xy``
    ``(B, K, 2)``, ``scale`` ``(B, K)`` float32; ``valid`` ``(B, K)`` bool. Returns ``(B, K, 64 or 128)``
    float32 unit descriptors, zero rows where not valid; None when the kernel is not available or the inputs
    do not fit its contract."""
    dims = check_shape(image, "image", ["B", 1, "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    k = check_shape(xy, "xy", [b, "K", 2])["K"]
    check_shape(scale, "scale", [b, k])
    check_rows(valid, "valid", b, k, kinds="bool")
    check_nonempty(image, "image")
    check_border(pad, h, w)
    if not (on_cpu(torch.float32, image, xy, scale) and on_cpu(torch.bool, valid)):
        return None
    # A NaN position would be cast to an index (undefined in C); ±inf and huge ones are clamped to the border. So
    # would an infinite position at an infinite scale (inf − inf is NaN; a NaN scale reads as the least one).
    if bool((xy.isnan().any(-1) & valid).any()):
        raise InputError("xy: expected no NaN at valid keypoints")
    if bool((scale.isinf() & valid).any()):
        raise InputError("scale: expected finite scales at valid keypoints (describe_surf's are positive)")
    library = load("usurf_describe")
    if library is None:
        return None
    image, xy, scale = image.contiguous(), xy.contiguous(), scale.contiguous()
    mask = valid.to(torch.uint8).contiguous()
    out = torch.zeros(b, k, 128 if extended else 64)
    status = library.usurf_describe(image.data_ptr(), b, h, w, pad, xy.data_ptr(), scale.data_ptr(),
                                    mask.data_ptr(), k, int(extended), out.data_ptr(), torch.get_num_threads())
    return None if status != 0 else out

