"""Fused C kernels for the memory-bound hot spots, compiled once per machine with the system's C compiler and loaded
through ``ctypes``: the runs of each mask row that the segmentation's connected components start from (``find_runs.c``)
and their labelling (``label_runs.c``), its gray levels and their histogram (``gray_levels.c``), the dense stage's SAD
block matching (``block_match.c``), its row fill of invalid pixels (``fill_invalid_rows.c``), its order statistics by
label (``labelled_select.c``: the search range's percentiles) and each object's depth statistics, every pair read once
at its own box (``object_depths.c``), SURF's padded integral table (``padded_integral.c``), a whole octave of its
box-filter Hessian (``hessian_octave.c``), its scale-space maxima (``local_maxima.c``) and the strongest of them over
all the octaves of an image (``strongest_maxima.c``), the quadratic fit that makes them keypoints (``refine_maxima.c``),
its upright descriptor (``usurf_describe.c``), the SAD nearest-neighbour search of descriptor matching
(``sad_nearest.c``) and the Lucas–Kanade refinement of matched points (``lk_refine.c``). Each is the no-gradient path of
a torch function that stays the reference, the fallback and the differentiable path. Eleven give that torch path's
values bit for bit: the first ten, and the strongest maxima ``torch.topk``'s values and indices (equal values in index
order, which ``torch.topk`` leaves open). Four do not: the fit solves its 3 × 3 systems by its own elimination, not
LAPACK's LU (offsets to about 1e-15: the same float32 keypoints on the shared scenes); the matching kernel sums each
distance in its own order (on real descriptors: the same matches, the same costs); the refinement takes the same steps
with its sums in double and in its own order, so its points agree to about 1e-4 px; the U-SURF descriptor
(``usurf_describe.c``) builds each image's integral and describes its keypoints in double, equal to the float64 torch
path to 1e-6 and to the float32 one within its round-off (5e-4), except where a response near 0 takes the other sign
there (the extended descriptor's halves then move by up to 0.08). On the 58 shared real pairs at 320×240, 6 pipeline
results differ from the torch paths' by 1–2 matches or inliers, from the last two (``experiments/kernel_parity.py``;
the README's "Compiled kernels" says the same).

Each wrapper below checks what its C code assumes (shapes, one row per pair, sizes and boxes within the buffers,
non-empty images, finite parameters in range) and raises :class:`~svs_torch.InputError` naming the argument
(:mod:`svs_torch.kernels.checks`); the C code then trusts its inputs. A wrapper answers None, for the torch path to
run, for inputs of another dtype or device, for cases the kernel leaves to it (NaN values to select among, an octave
without interior points, a table too small to read), or when the kernel is not built. ``tests/test_kernel_fuzz.py`` feeds
drawn inputs through every public function that reaches a kernel; ``tests/sanitize/run.sh`` runs it against builds
with AddressSanitizer and UBSan.

Why a C kernel for the dense stage: eager torch pays one memory pass per elementwise op, and the dense stage's
cost volume (B × D × h × w) went through about 25 of them (x-Sobel differences, 2 (K − 1) box-sum adds, masking,
the running minimum, the uniqueness rival, the right view's winner): 35–50 ms a pair at 320×240, most of a
pipeline run. The kernel makes each output row's costs for every disparity and consumes them while they are in
cache, with running window sums, then gives each finished row the rejections and the sub-pixel fit and writes it
into the disparity map; each pair is matched at its own box and over its own range, where the torch path pads
every pair to the batch's largest (on 64 real pairs at 320×240, one thread: the dense stage 9.3 → 6.5 ms a pair
against the earlier kernel that returned winner statistics for torch to judge). Its inputs are whole numbers
(``StereoBM``'s 8-bit levels), so every sum is exact and its results are bit-identical to the torch path's
(``tests/test_dense.py``). It is not differentiable; the soft path (``soft_block_match``) stays in torch. Each
Hessian level reads 32 integral-image corner views and made about 40 elementwise passes in eager torch, after a
contiguous copy of the table per sub-lattice of the octave; the kernel makes a whole octave in one call, reading
each grid point's corners from the padded table at the octave's step and doing the same float32 operations in
the same order, its rows split over ``torch.get_num_threads()`` threads (16 images of 320×240, one thread,
interleaved: ``hessian_octaves`` 54–75 → 42–43 ms, the copies and views it no longer makes); the padded integral
table it reads is made in one pass per image (5.3 → 2.1 ms for the same 16 images). The maxima took a dozen
passes (three running maxima of 3, compare, mask, select) for a few hundred survivors; the kernel tests each
point once, most stopping at the threshold (on 16 real images at 320×240, octave 0: 20 → 3 ms); the detector then
concatenated the maps (−inf at all but a few hundred of ~200 000 points an image) and partially sorted each whole
row with ``torch.topk``, where the strongest-maxima kernel collects an image's maxima and sorts only them (the three
octaves of 16 real images: about 19 → 12 ms). The refinement
sampled every patch of the batch 14 times with ``grid_sample`` and reduced it in about 100 passes; the kernel
refines one match at a time in L1 (on the 1 900 matches of 16 real pairs: 95 → 19 ms). Matching wrote the whole
masked distance matrix and read it three times (topk, argmin); the kernel consumes each row of distances as it
makes it (16 real pairs: 110 → 29 ms). The objects' depth statistics cropped every pair to the batch's largest
box (three gathers, the fill, the depth, a selection and a count per object over it, so that a pair of B = 128
cost twice a pair of B = 32); the kernel reads each pair once at its own box (64 real pairs at B = 8, one thread:
1.84 → 0.7 ms a pair). The runs took about eight passes over the batch's masks and two ``nonzero``; the kernel
reads each row twice, skipping eight pixels at a time (16 masks of 320×240: 3.0 → 0.6 ms).

The shared libraries are built and cached by :mod:`svs_torch.kernels.loader`: in a private folder
(``$SVS_TORCH_CACHE``, default ``~/.cache/svs_torch``; one others can write to is refused), under a name that
hashes the source, the shared headers, the flags actually used, the compiler and the CPU; a failed build is
remembered there. Without a working compiler, or with ``SVS_TORCH_KERNELS=torch``, :func:`load` returns None
(the first with one line on stderr) and the callers run their torch paths.
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

import torch

from ..checks import check_shape
from ..errors import InputError
from . import loader
from .checks import check_boxes, check_counts, check_image_hw, check_nonempty, check_number, check_rows
from .loader import FLAGS, HEADERS, cache_dir  # noqa: F401  (re-exported: the loader's public names)

__all__ = ["available", "block_match", "cache_dir", "fill_invalid_rows", "find_runs", "gray_levels", "hessian_octave",
           "label_runs", "labelled_select", "lk_refine", "load", "local_maxima", "object_depths", "padded_integral",
           "refine_maxima", "sad_nearest", "strongest_maxima", "usurf_describe"]

_POINTER, _INT, _FLOAT = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
#: Each kernel's (argument types, return type), as declared in its C source.
_SIGNATURES = {
    "block_match": ([_POINTER] * 3 + [_INT, _FLOAT] + [_INT] * 5 + [_POINTER] * 5 + [_FLOAT] * 3 + [_INT]
                    + [_POINTER, _INT] + [_POINTER] * 2 + [_INT] * 2, ctypes.c_int),
    "hessian_octave": ([_POINTER] + [_INT] * 5 + [_POINTER] + [_INT] * 3 + [_POINTER] * 2 + [_FLOAT]
                       + [_POINTER] * 2 + [_INT], None),
    "local_maxima": ([_POINTER, _POINTER] + [_INT] * 5 + [_FLOAT, _POINTER], None),
    "lk_refine": ([_POINTER, _POINTER] + [_INT] * 4 + [_POINTER] * 4 + [_INT, _FLOAT, _POINTER, _POINTER, _INT],
                  None),
    "sad_nearest": ([_POINTER] * 8 + [_FLOAT] + [_INT] * 4 + [_POINTER] * 4 + [_INT], ctypes.c_int),
    "labelled_select": ([_POINTER] * 4 + [_INT] * 4 + [_POINTER] * 3 + [_INT], ctypes.c_int),
    "find_runs": ([_POINTER] * 2 + [_INT] * 2 + [_POINTER] * 3 + [_INT], ctypes.c_int),
    "label_runs": ([_POINTER] * 2 + [_INT] * 5 + [_POINTER] * 3 + [_INT], ctypes.c_int),
    "gray_levels": ([_POINTER] + [_INT] * 2 + [_POINTER] * 2 + [_INT], ctypes.c_int),
    "refine_maxima": ([_POINTER] * 6 + [_INT] + [_POINTER] * 2 + [_INT] * 2 + [ctypes.c_double] * 2
                      + [_POINTER] * 5 + [_INT], ctypes.c_int),
    "fill_invalid_rows": ([_POINTER] * 2 + [_INT] * 2 + [_POINTER] * 2 + [_INT], ctypes.c_int),
    "object_depths": ([_POINTER] * 3 + [_INT] * 3 + [_POINTER] * 2 + [_INT] + [_POINTER] * 3 + [_INT, _POINTER, _INT]
                      + [_POINTER] * 5 + [_INT], ctypes.c_int),
    "padded_integral": ([_POINTER] * 2 + [_INT] * 4 + [_POINTER, _INT], ctypes.c_int),
    "strongest_maxima": ([_POINTER] * 4 + [_INT] * 2 + [_FLOAT, _INT] + [_POINTER] * 2 + [_INT], ctypes.c_int),
    "usurf_describe": ([_POINTER] + [_INT] * 4 + [_POINTER] * 3 + [_INT] * 2 + [_POINTER, _INT], ctypes.c_int),
}
#: Each kernel's C source, named after it.
SOURCES = {name: Path(__file__).with_name(f"{name}.c") for name in _SIGNATURES}
#: Rows of output per task: enough to amortise the K rows each band sums before its window can slide, small
#: enough that one pair splits across threads (the B = 1 ``guide`` case).
BAND_ROWS = 48

_LIBRARIES: dict[str, ctypes.CDLL | None] = {}


def load(name: str = "block_match") -> ctypes.CDLL | None:
    """The compiled kernel ``name`` (a key of :data:`SOURCES`), compiling it on first use; None
    when kernels are off (``SVS_TORCH_KERNELS=torch``) or it cannot be built or loaded (then the caller's torch
    path runs; :func:`svs_torch.kernels.loader.open_library` says why once)."""
    if os.environ.get("SVS_TORCH_KERNELS", "").lower() == "torch":
        return None
    if name not in _LIBRARIES:
        library = loader.open_library(name)
        if library is not None:
            function = getattr(library, name)
            function.argtypes, function.restype = _SIGNATURES[name]
        _LIBRARIES[name] = library
    return _LIBRARIES[name]


def available(name: str = "block_match") -> bool:
    """Whether the kernel ``name`` can run here."""
    return load(name) is not None


def _on_cpu(dtype: torch.dtype, *tensors: torch.Tensor) -> bool:
    """Whether every tensor is a CPU tensor of ``dtype``: the kernels read raw memory of one element type."""
    return all(t.dtype == dtype and t.device.type == "cpu" for t in tensors)


#: Where :func:`block_match` takes its levels from (the C source's SOURCE_ constants).
BLOCK_MATCH_SOURCES = {"levels": 0, "raw": 1, "xsobel": 2}


def block_match(left: torch.Tensor, right: torch.Tensor, texture: torch.Tensor | bool | None, window_size: int,
                boxes: torch.Tensor, min_disparity: torch.Tensor, counts: torch.Tensor, image_hw: torch.Tensor,
                lower_is_limit: torch.Tensor, uniqueness_ratio: float, lr_max_diff_px: float | None,
                texture_min: float, whole_range_in_view: bool, source: str = "levels",
                prefilter_cap: float = 0.0, mask: torch.Tensor | None = None, mask_margin_px: int = 0
                ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``svs_torch.dense._match_box`` of every pair at its own box and range, the kernel's contract (see the C
    source). With ``source="levels"``: ``left``, ``right`` ``(B, H, W)`` float32 pre-filtered images holding
    whole numbers in [−255, 255] (:func:`svs_torch.dense.quantize_levels`: then every cost is exact and the
    result is the torch path's bit for bit); ``texture`` ``(B, H, W)`` float32 |x-Sobel| of the left image, or
    None (no texture rule). With ``source="raw"`` or ``"xsobel"``: ``left``, ``right`` are the images themselves
    and the kernel makes the levels a row at a time, ``quantize_levels`` of the image or of its
    ``prefilter_xsobel`` at ``prefilter_cap``, the same values without whole pre-filtered images in memory, and
    ``texture`` is True (the texture rule, on the left image's clipped x-Sobel) or False / None;
    ``boxes`` ``(B, 4)`` x0, y0, width, height; ``min_disparity``, ``counts`` ``(B,)``; ``image_hw`` ``(B, 2)``;
    ``lower_is_limit`` ``(B,)`` bool; the rules' parameters as in :class:`svs_torch.dense.DenseConfig`
    (``texture_min`` is the least window sum); ``mask`` ``(B, H, W)`` bool or None: where depth is wanted, then
    only the pixels within ``mask_margin_px`` columns of their row's mask span are computed
    (:func:`svs_torch.dense.wanted_pixels`), each with the value the whole box gives it.

    Returns the disparity ``(B, H, W)`` float32 (0 where not valid) and ``valid`` ``(B, H, W)`` bool; None when
    the kernel is not available or the inputs do not fit its contract."""
    if source not in BLOCK_MATCH_SOURCES:
        raise ValueError(f"source: expected one of {sorted(BLOCK_MATCH_SOURCES)}, got {source!r}")
    levels = source == "levels"
    if (texture is True) if levels else isinstance(texture, torch.Tensor):
        raise ValueError("texture: expected a tensor or None with source 'levels', a bool with the raw sources")
    tensors = (left, right, texture) if isinstance(texture, torch.Tensor) else (left, right)
    if not _on_cpu(torch.float32, *tensors) or mask is not None and not _on_cpu(torch.bool, mask):
        return None
    b, h, w = _check_block_match(left, right, texture, mask, window_size, boxes, min_disparity, counts, image_hw,
                                 lower_is_limit, uniqueness_ratio, lr_max_diff_px, texture_min, prefilter_cap,
                                 mask_margin_px)
    library = load("block_match")
    if library is None:
        return None
    left, right = left.contiguous(), right.contiguous()
    textured = texture is not None and texture is not False
    texture = texture.contiguous() if isinstance(texture, torch.Tensor) else None
    per_pair = [v.to(torch.int64).contiguous() for v in (boxes, min_disparity, counts, image_hw)]
    lower = lower_is_limit.to(torch.uint8).contiguous()
    if mask is not None:
        mask = mask.contiguous().view(torch.uint8)  # bool is one byte of 0 or 1: read as it is
    disparity = torch.zeros(b, h, w)
    valid = torch.zeros(b, h, w, dtype=torch.uint8)
    # The factors are made in double and rounded to float32, as torch does with a Python scalar.
    status = library.block_match(
        left.data_ptr(), right.data_ptr(), None if texture is None else texture.data_ptr(),
        BLOCK_MATCH_SOURCES[source], prefilter_cap, int(textured), b, h, w, window_size,
        *(v.data_ptr() for v in per_pair), lower.data_ptr(),
        1 + uniqueness_ratio if uniqueness_ratio > 0 else 0.0, -1.0 if lr_max_diff_px is None else lr_max_diff_px,
        texture_min, int(whole_range_in_view), None if mask is None else mask.data_ptr(), mask_margin_px,
        disparity.data_ptr(), valid.data_ptr(), torch.get_num_threads(), BAND_ROWS)
    if status != 0:
        return None
    return disparity, valid.bool()


#: The dense kernel keeps disparity indices in its 16-bit cost type (block_match.c): at most 65534 disparities.
MAX_DISPARITIES = 65534


def _check_block_match(left, right, texture, mask, window_size, boxes, min_disparity, counts, image_hw,
                       lower_is_limit, uniqueness_ratio, lr_max_diff_px, texture_min, prefilter_cap,
                       mask_margin_px) -> tuple[int, int, int]:
    """:func:`block_match`'s contract (see there), raising :class:`InputError`: returns B, H, W."""
    dims = check_shape(left, "left", ["B", "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    for tensor, name in ((right, "right"), (texture, "texture"), (mask, "mask")):
        if isinstance(tensor, torch.Tensor):
            check_shape(tensor, name, [b, h, w])
    check_nonempty(left, "left")
    if not isinstance(window_size, int) or window_size < 1 or window_size % 2 == 0:
        raise InputError(f"window_size: expected a positive odd int, got {window_size!r}")
    check_boxes(boxes, b, h, w)
    check_rows(min_disparity, "min_disparity", b)
    check_counts(counts, "counts", b, MAX_DISPARITIES)
    check_image_hw(image_hw, b, h, w)
    check_rows(lower_is_limit, "lower_is_limit", b, kinds="bool")
    check_number(uniqueness_ratio, "uniqueness_ratio", 0.0)
    if lr_max_diff_px is not None:
        check_number(lr_max_diff_px, "lr_max_diff_px", 0.0)
    check_number(texture_min, "texture_min")
    check_number(prefilter_cap, "prefilter_cap", 0.0)
    if not isinstance(mask_margin_px, int) or mask_margin_px < 0:
        raise InputError(f"mask_margin_px: expected a non-negative int, got {mask_margin_px!r}")
    return b, h, w


def hessian_octave(padded: torch.Tensor, pad: int, step: int, sizes: list[int], inverse_lobe_area: list[float],
                   inverse_dxy_area: list[float], dxy_weight: float, det_out: torch.Tensor,
                   trace_out: torch.Tensor) -> bool:
    """Every level of one octave of ``svs_torch.hessian._det_trace`` in one call, read straight from the padded
    integral (see the C source): ``padded`` ``(B, 1, PH, PW)`` float32 (:func:`svs_torch.integral.pad_integral`
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
    if (not _on_cpu(torch.float32, padded, det_out, trace_out) or not det_out.is_contiguous()
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


def padded_integral(image: torch.Tensor, means: torch.Tensor, pad: int) -> torch.Tensor | None:
    """``pad_integral(integral_image(image − means), pad)`` of ``svs_torch.hessian`` in one pass per image (see
    the C source), bit for bit: ``image`` ``(B, 1, H, W)`` float32, ``means`` ``(B,)`` float32 (each image's
    own, subtracted from its pixels). Returns the table ``(B, 1, H + 1 + 2·pad, W + 1 + 2·pad)``, or None when
    the kernel is not available or the inputs do not fit its contract."""
    b = check_shape(image, "image", ["B", 1, "H", "W"])["B"]
    check_shape(means, "means", [b])
    if not isinstance(pad, int) or pad < 0:
        raise InputError(f"pad: expected a non-negative int, got {pad!r}")
    if not _on_cpu(torch.float32, image, means):
        return None
    library = load("padded_integral")
    if library is None:
        return None
    b, _, h, w = image.shape
    image, means = image.contiguous(), means.contiguous()
    out = torch.empty(b, 1, h + 1 + 2 * pad, w + 1 + 2 * pad)
    status = library.padded_integral(image.data_ptr(), means.data_ptr(), b, h, w, pad, out.data_ptr(),
                                     torch.get_num_threads())
    return None if status != 0 else out


def _check_support(support: torch.Tensor, name: str, b: int, inner: tuple[int, int, int]) -> None:
    """A maxima support ``(B or 1, S − 2, ny − 2, nx − 2)``: one for every pair or one shared."""
    rows = support.shape[0] if isinstance(support, torch.Tensor) and support.dim() == 4 else b
    check_shape(support, name, [rows if rows in (1, b) else b, *inner])


def local_maxima(det: torch.Tensor, support: torch.Tensor, threshold: float) -> torch.Tensor | None:
    """``svs_torch.hessian._interior_maxima`` in one pass: ``det`` ``(B, S, ny, nx)`` float32 where it is a
    3 × 3 × 3 maximum above ``threshold`` with ``support`` (``(B or 1, S − 2, ny − 2, nx − 2)`` bool), −inf
    elsewhere; ``(B, S − 2, ny − 2, nx − 2)``. None when the kernel is not available or the inputs do not fit
    its contract (then the caller's torch path runs)."""
    dims = check_shape(det, "det", ["B", "S", "ny", "nx"])
    b, s, ny, nx = dims["B"], dims["S"], dims["ny"], dims["nx"]
    inner = (s - 2, ny - 2, nx - 2)
    if min(inner) < 1:  # no interior point: the torch path's empty map
        return None
    _check_support(support, "support", b, inner)
    if not (_on_cpu(torch.float32, det) and _on_cpu(torch.bool, support)):
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
        if not _on_cpu(torch.float32, det):
            return None
        inner = (det.shape[1] - 2, det.shape[2] - 2, det.shape[3] - 2)
        if min(inner) < 1:  # no interior point (the kernel reads nothing of it)
            pointers.append((det.shape[1:], 0, 0, 0))
            continue
        _check_support(support, f"supports[{octave}]", b, inner)
        if not _on_cpu(torch.bool, support):
            return None
        det, support = det.contiguous(), support.contiguous()
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
    """The keypoints of :func:`svs_torch.detector.detect_surf_keypoints` from its strongest maxima, one keypoint at
    a time (see the C source): ``dets[o]``, ``traces[o]`` ``(B, S, ny, nx)`` float32 with the octave's grid step
    and filter sizes; ``score`` ``(B, K)`` float32 and ``index`` ``(B, K)`` int64 (:func:`strongest_maxima`);
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
    if (not _on_cpu(torch.float32, score, *dets, *traces) or not _on_cpu(torch.int64, index)
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


def lk_refine(left: torch.Tensor, right: torch.Tensor, left_xy: torch.Tensor, right_xy: torch.Tensor,
              radius: torch.Tensor, active: torch.Tensor, iterations: int, max_shift_px: float
              ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``svs_torch.matching._refine_lk``'s Gauss–Newton refinement, one match at a time (see the C source):
    ``left``, ``right`` ``(B, 1, H, W)`` float32; ``left_xy``, ``right_xy`` ``(B, K, 2)``, ``radius`` ``(B, K)``
    float32; ``active`` ``(B, K)`` bool, the rows to refine. Returns the refined right points ``(B, K, 2)`` and
    the weighted NCC at them ``(B, K)`` (0 for inactive rows), or None when the kernel is not available or the
    inputs do not fit its contract."""
    tensors = (left, right, left_xy, right_xy, radius)
    dims = check_shape(left, "left", ["B", 1, "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    check_shape(right, "right", [b, 1, h, w])
    k = check_shape(left_xy, "left_xy", [b, "K", 2])["K"]
    check_shape(right_xy, "right_xy", [b, k, 2])
    check_shape(radius, "radius", [b, k])
    check_rows(active, "active", b, k, kinds="bool")
    check_nonempty(left, "left")
    if not isinstance(iterations, int) or iterations < 0:
        raise InputError(f"iterations: expected a non-negative int, got {iterations!r}")
    check_number(max_shift_px, "max_shift_px", 0.0)
    if (not (_on_cpu(torch.float32, *tensors) and _on_cpu(torch.bool, active))
            or h * w >= 2**31):  # the kernel indexes an image with 32-bit offsets
        return None
    library = load("lk_refine")
    if library is None:
        return None
    left, right, left_xy, right_xy, radius, active = (t.contiguous() for t in (*tensors, active))
    refined, correlation = torch.empty(b, k, 2), torch.empty(b, k)
    library.lk_refine(left.data_ptr(), right.data_ptr(), b, h, w, k, left_xy.data_ptr(), right_xy.data_ptr(),
                      radius.data_ptr(), active.data_ptr(), iterations, max_shift_px, refined.data_ptr(),
                      correlation.data_ptr(), torch.get_num_threads())
    return refined, correlation


def sad_nearest(desc_left: torch.Tensor, desc_right: torch.Tensor, valid_left: torch.Tensor,
                valid_right: torch.Tensor, sign_left: torch.Tensor | None = None,
                sign_right: torch.Tensor | None = None, y_left: torch.Tensor | None = None,
                y_right: torch.Tensor | None = None, band_px: float | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Nearest neighbours by SAD (see the C source): ``desc_left`` ``(B, K, D)``, ``desc_right`` ``(B, K2, D)``
    float32; a candidate pair needs ``valid_left`` ``(B, K)`` and ``valid_right`` ``(B, K2)`` (bool), equal
    ``sign_left`` / ``sign_right`` (int64, optional) and, given ``band_px``, ``|y_left − y_right| ≤ band_px``
    (float32 ``(B, K)``, ``(B, K2)``), as :func:`svs_torch.matching._allowed`. Returns ``(best, second,
    best_index, back)``: each left row's smallest and second-smallest allowed distance ``(B, K)`` (+inf if
    none), the index of the smallest, and each right descriptor's nearest left row ``(B, K2)``; None when the
    kernel is not available or the inputs do not fit its contract."""
    signs = sign_left is not None
    band = band_px is not None
    dims = check_shape(desc_left, "desc_left", ["B", "K", "D"])
    b, k, d = dims["B"], dims["K"], dims["D"]
    k2 = check_shape(desc_right, "desc_right", [b, "K2", d])["K2"]
    check_rows(valid_left, "valid_left", b, k, kinds="bool")
    check_rows(valid_right, "valid_right", b, k2, kinds="bool")
    if signs != (sign_right is not None) or band and (y_left is None or y_right is None):
        raise InputError("sign_left, sign_right, y_left, y_right: expected both signs or neither, and both rows "
                         "given a band_px")
    for tensor, name, rows in ((sign_left, "sign_left", k), (sign_right, "sign_right", k2)):
        if signs:
            check_rows(tensor, name, b, rows)
    for tensor, name, rows in ((y_left, "y_left", k), (y_right, "y_right", k2)):
        if band:
            check_rows(tensor, name, b, rows, kinds="float")
    if band:
        check_number(band_px, "band_px", 0.0)
    if (not (_on_cpu(torch.float32, desc_left, desc_right) and _on_cpu(torch.bool, valid_left, valid_right))
            or signs and not _on_cpu(torch.int64, sign_left, sign_right)
            or band and not _on_cpu(torch.float32, y_left, y_right)):
        return None
    library = load("sad_nearest")
    if library is None:
        return None
    inputs = [t.contiguous() if t is not None else None for t in (
        desc_left, desc_right, valid_left, valid_right, sign_left if signs else None, sign_right if signs else None,
        y_left if band else None, y_right if band else None)]
    pointers = [0 if t is None else t.data_ptr() for t in inputs]
    best, second = torch.empty(b, k), torch.empty(b, k)
    best_index, back = torch.empty(b, k, dtype=torch.int64), torch.empty(b, k2, dtype=torch.int64)
    status = library.sad_nearest(*pointers, band_px if band else 0.0, b, k, k2, d, best.data_ptr(),
                                 second.data_ptr(), best_index.data_ptr(), back.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (best, second, best_index, back)


def labelled_select(values: torch.Tensor, labels: torch.Tensor, slots: torch.Tensor, q: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The order statistics of :func:`svs_torch.depth.labelled_quantile` by selection (see the C source):
    ``values`` ``(B, P)`` float32 without NaN, ``labels`` ``(B, P)`` and ``slots`` ``(B, N)`` int64, quantiles
    ``q`` ``(Q,)`` float32. Returns ``(count, below, above)``: each slot's member count ``(B, N)`` and the
    members of rank ``floor`` / ``ceil`` of ``q · (count − 1)`` ``(B, N, Q)`` (0 for an empty slot); None when
    the kernel is not available or the inputs do not fit its contract."""
    dims = check_shape(values, "values", ["B", "P"])
    b, p = dims["B"], dims["P"]
    check_rows(labels, "labels", b, p)
    n = check_rows(slots, "slots", b, "N").shape[1]
    k = check_shape(q, "q", ["Q"])["Q"]
    if q.numel() and not bool(((q >= 0) & (q <= 1)).all()):  # NaN too: the kernel casts q · (count − 1) to int
        raise InputError(f"q: expected quantiles in [0, 1], got {q.tolist()}")
    if not (_on_cpu(torch.float32, values, q) and _on_cpu(torch.int64, labels, slots)):
        return None
    if bool(values.isnan().any()):  # the selection orders by <, which NaN breaks: the torch path sorts them last
        return None
    library = load("labelled_select")
    if library is None:
        return None
    values, labels, slots, q = (t.contiguous() for t in (values, labels, slots, q))
    count = torch.empty(b, n, dtype=torch.int64)
    below, above = torch.empty(b, n, k), torch.empty(b, n, k)
    status = library.labelled_select(values.data_ptr(), labels.data_ptr(), slots.data_ptr(), q.data_ptr(), b, p, n,
                                     k, count.data_ptr(), below.data_ptr(), above.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (count, below, above)


def _rows(tensor: torch.Tensor) -> tuple[int, int]:
    """A ``(..., W)`` tensor as rows for a row kernel: (number of rows, W)."""
    width = tensor.shape[-1]
    return (tensor.numel() // width if width else 0), width


def fill_invalid_rows(disparity: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`svs_torch.dense.fill_invalid_rows` in two passes per row (see the C source), bit for bit:
    ``disparity`` ``(..., W)`` float32, ``valid`` of its shape, bool. Returns the filled disparity and where a
    fill was possible; None when the kernel is not available or the inputs do not fit its contract."""
    if disparity.dim() < 1:
        raise InputError(f"disparity: expected (..., W), got {tuple(disparity.shape)}")
    check_shape(valid, "valid", list(disparity.shape))
    if not (_on_cpu(torch.float32, disparity) and _on_cpu(torch.bool, valid)):
        return None
    library = load("fill_invalid_rows")
    if library is None:
        return None
    rows, width = _rows(disparity)
    disparity, valid = disparity.contiguous(), valid.contiguous()
    filled, reachable = torch.empty_like(disparity), torch.empty_like(valid)
    status = library.fill_invalid_rows(disparity.data_ptr(), valid.data_ptr(), rows, width, filled.data_ptr(),
                                       reachable.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (filled, reachable)


def find_runs(foreground: torch.Tensor, value: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`svs_torch.components._find_runs` in two passes per row (see the C source): the flat start and end
    (inclusive) positions ``(R,)`` int64 of the runs of ``foreground`` ``(..., W)`` bool in raster order, a run also
    ending where ``value`` (int64, its shape) changes. None when the kernel is not available or the inputs do not
    fit its contract."""
    if foreground.dim() < 1:
        raise InputError(f"foreground: expected (..., W), got {tuple(foreground.shape)}")
    if value is not None:
        check_shape(value, "value", list(foreground.shape))
    if not _on_cpu(torch.bool, foreground) or value is not None and not _on_cpu(torch.int64, value):
        return None
    library = load("find_runs")
    if library is None:
        return None
    rows, width = _rows(foreground)
    foreground = foreground.contiguous()
    value = None if value is None else value.contiguous()
    value_ptr = 0 if value is None else value.data_ptr()
    counts = torch.empty(rows, dtype=torch.int64)
    threads = torch.get_num_threads()
    library.find_runs(foreground.data_ptr(), value_ptr, rows, width, counts.data_ptr(), 0, 0, threads)
    total = int(counts.sum())
    first = counts.cumsum(0) - counts  # each row's first output slot
    start, end = torch.empty(total, dtype=torch.int64), torch.empty(total, dtype=torch.int64)
    library.find_runs(foreground.data_ptr(), value_ptr, rows, width, first.data_ptr(), start.data_ptr(),
                      end.data_ptr(), threads)
    return start, end


def gray_levels(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`svs_torch.threshold.gray_levels` and :func:`~svs_torch.threshold.gray_histogram` in one read of each
    image (see the C source): ``image`` ``(B, 1, H, W)`` float32 in [0, 1] → the uint8 levels ``(B, 1, H, W)``
    and the histograms ``(B, 256)`` int64, the torch path's values. None when the kernel is not available or
    the input does not fit its contract."""
    check_shape(image, "image", ["B", 1, "H", "W"])
    if not _on_cpu(torch.float32, image):
        return None
    library = load("gray_levels")
    if library is None:
        return None
    image = image.detach().contiguous()
    b = image.shape[0]
    levels = torch.empty(image.shape, dtype=torch.uint8)
    histogram = torch.empty(b, 256, dtype=torch.int64)
    status = library.gray_levels(image.data_ptr(), b, image[0].numel() if b else 0, levels.data_ptr(),
                                 histogram.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (levels, histogram)


def _check_runs(start: torch.Tensor, end: torch.Tensor, batch: int, height: int, width: int,
                connectivity: int) -> None:
    """:func:`label_runs`' contract: runs inside the grid, in raster order, each within one row (as
    :func:`find_runs` gives them); the two int64 ``(R,)`` checks cost a few passes over R runs, not the grid."""
    if connectivity not in (4, 8):
        raise InputError(f"connectivity: expected 4 or 8, got {connectivity!r}")
    if not all(isinstance(v, int) and v >= 0 for v in (batch, height, width)):
        raise InputError(f"batch, height, width: expected non-negative ints, got {batch!r}, {height!r}, {width!r}")
    r = check_shape(start, "start", ["R"])["R"]
    check_rows(end, "end", r)
    if r == 0 or not _on_cpu(torch.int64, start, end):  # other dtypes are left to the torch path
        return
    row_start = start - start % width if width else start
    bad = ((start < 0) | (end < start) | (end >= batch * height * width) | (end >= row_start + width)).any()
    if bool(bad) or bool((start[1:] <= end[:-1]).any()):
        raise InputError(f"start, end: expected runs in raster order inside one row each of the {batch} x {height} x "
                         f"{width} grid (as find_runs gives them)")


def label_runs(start: torch.Tensor, end: torch.Tensor, batch: int, height: int, width: int, connectivity: int
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """:func:`svs_torch.components._label_runs` and ``_paint`` by one union-find sweep per image (see the C
    source): from the runs' flat ``start`` and ``end`` ``(R,)`` int64 of a ``(batch, height, width)`` grid, each
    run's label ``(R,)``, each image's number of labels ``(batch,)`` and the label image ``(batch, 1, height,
    width)``, all int64. None when the kernel is not available or the inputs do not fit its contract."""
    _check_runs(start, end, batch, height, width, connectivity)
    if not _on_cpu(torch.int64, start, end):
        return None
    library = load("label_runs")
    if library is None:
        return None
    start, end = start.contiguous(), end.contiguous()
    run_label = torch.empty_like(start)
    num_labels = torch.empty(batch, dtype=torch.int64)
    labels = torch.empty(batch, 1, height, width, dtype=torch.int64)
    status = library.label_runs(start.data_ptr(), end.data_ptr(), start.numel(), batch, height, width, connectivity,
                                run_label.data_ptr(), num_labels.data_ptr(), labels.data_ptr(),
                                torch.get_num_threads())
    return None if status != 0 else (run_label, num_labels, labels)


def _check_box_rows(boxes: torch.Tensor, name: str, b: int) -> None:
    """Boxes ``(B, 4)`` int that :func:`object_depths` reads at any place (its columns and rows outside the frame
    repeat the border), within 2³¹ so that no corner's arithmetic overflows."""
    check_rows(boxes, name, b, 4)
    if boxes.numel() and bool((boxes.abs() >= 2**31).any()):
        raise InputError(f"{name}: expected (x0, y0, width, height) within ±2^31, got {boxes.tolist()}")


def object_depths(disparity: torch.Tensor, valid: torch.Tensor, labels: torch.Tensor, boxes: torch.Tensor,
                  slots: torch.Tensor, scale: torch.Tensor, doffs: torch.Tensor, in_view_from: torch.Tensor,
                  fill: bool, q: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The statistics of :func:`svs_torch.dense_depth.dense_object_depths`, each pair read once at its own box
    (see the C source): ``disparity`` ``(B, H, W)`` float32, ``valid`` ``(B, H, W)`` bool, ``labels``
    ``(B, H, W)`` int64; ``boxes`` ``(B, 4)`` x0, y0, width, height; ``slots`` ``(B, N)`` int64; ``scale``
    (focal · baseline) and ``doffs`` ``(B,)`` float32; ``in_view_from`` ``(B,)`` int64, the first frame column
    where the pair's whole disparity range lands inside the right image; ``fill``: fill invalid pixels from their
    row first; quantiles ``q`` ``(Q,)`` float32. Returns ``(count, measured, in_view, below, above)``: each
    slot's member count, its members that were valid before the fill and those of them at columns from
    ``in_view_from`` on ``(B, N)``, and the members of rank ``floor`` / ``ceil`` of
    ``q · (count − 1)`` ``(B, N, Q)``; None when the kernel is not available or the inputs do not fit its
    contract."""
    dims = check_shape(disparity, "disparity", ["B", "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    check_shape(valid, "valid", [b, h, w])
    check_shape(labels, "labels", [b, h, w])
    check_nonempty(disparity, "disparity")
    _check_box_rows(boxes, "boxes", b)
    check_rows(slots, "slots", b, "N")
    check_shape(scale, "scale", [b])
    check_shape(doffs, "doffs", [b])
    check_rows(in_view_from, "in_view_from", b)
    check_shape(q, "q", ["Q"])
    if q.numel() and not bool(((q >= 0) & (q <= 1)).all()):  # NaN too: the kernel casts q · (count − 1) to int
        raise InputError(f"q: expected quantiles in [0, 1], got {q.tolist()}")
    if not (_on_cpu(torch.float32, disparity, scale, doffs, q) and _on_cpu(torch.bool, valid)
            and _on_cpu(torch.int64, labels, boxes, slots, in_view_from)):
        return None
    library = load("object_depths")
    if library is None:
        return None
    n, k = slots.shape[1], q.numel()
    disparity, labels, boxes, slots, scale, doffs, in_view_from, q = (
        t.contiguous() for t in (disparity, labels, boxes, slots, scale, doffs, in_view_from, q))
    valid = valid.contiguous().view(torch.uint8)
    count, measured, in_view = (torch.empty(b, n, dtype=torch.int64) for _ in range(3))
    below, above = torch.empty(b, n, k), torch.empty(b, n, k)
    status = library.object_depths(disparity.data_ptr(), valid.data_ptr(), labels.data_ptr(), b, h, w,
                                   boxes.data_ptr(), slots.data_ptr(), n, scale.data_ptr(), doffs.data_ptr(),
                                   in_view_from.data_ptr(), int(fill), q.data_ptr(), k, count.data_ptr(),
                                   measured.data_ptr(), in_view.data_ptr(), below.data_ptr(), above.data_ptr(),
                                   torch.get_num_threads())
    return None if status != 0 else (count, measured, in_view, below, above)


def usurf_describe(image: torch.Tensor, pad: int, xy: torch.Tensor, scale: torch.Tensor, valid: torch.Tensor,
                   extended: bool) -> torch.Tensor | None:
    """:func:`svs_torch.descriptor._describe_upright` from the images (see the C source): ``image``
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
    if not isinstance(pad, int) or pad < 0:
        raise InputError(f"pad: expected a non-negative int, got {pad!r}")
    if not (_on_cpu(torch.float32, image, xy, scale) and _on_cpu(torch.bool, valid)):
        return None
    # A NaN position would be cast to an index (undefined in C); ±inf and huge ones are clamped to the border.
    if bool((xy.isnan().any(-1) & valid).any()):
        raise InputError("xy: expected no NaN at valid keypoints")
    library = load("usurf_describe")
    if library is None:
        return None
    image, xy, scale = image.contiguous(), xy.contiguous(), scale.contiguous()
    mask = valid.to(torch.uint8).contiguous()
    out = torch.zeros(b, k, 128 if extended else 64)
    status = library.usurf_describe(image.data_ptr(), b, h, w, pad, xy.data_ptr(), scale.data_ptr(),
                                    mask.data_ptr(), k, int(extended), out.data_ptr(), torch.get_num_threads())
    return None if status != 0 else out
