"""The one loader of every stage's C kernels, and what they share.

Each stage keeps its kernels beside its torch code, in its own ``kernels/`` folder: the C sources and a
``kernels/__init__.py`` of wrappers (``svs_torch.segmentation.kernels``, ``svs_torch.features.kernels``,
``svs_torch.geometry.kernels``, ``svs_torch.depth.kernels``); each wrapper module declares its kernels'
signatures (:func:`declare`) and calls them through :func:`load`. This folder holds what they share: the loader
(``loader.py``: build, cache, open; ``elf.py``: a cached library cut short is built again, never mapped),
the argument checks (``checks.py``) and the header every source includes
(``common.h``: thread count, scratch allocation), the quickselect the stages' order statistics share
(``select_rank.h``) and the LU of their small linear systems (``small_lu.h``).

Fused C kernels for the memory-bound hot spots, compiled once per machine with the system's C compiler and loaded
through ``ctypes``: the runs of each mask row that the segmentation's connected components start from (``find_runs.c``)
and their labelling (``label_runs.c``), its gray levels and their histogram (``gray_levels.c``), the dense stage's SAD
block matching (``block_match.c``), its row fill of invalid pixels (``fill_invalid_rows.c``), its order statistics by
label (``labelled_select.c``: the search range's and the nearness map's percentiles), each region's lower median
(``region_medians.c``: the nearness segmenter's ranking), the nearness map's median filter (``median_filter.c``)
and its split into near and far (``nearness_split.c``), the kept regions moved into the right view
(``shift_regions.c``) and cut to their interior (``region_interiors.c``),
the floor's plane found in the nearness map (``ground_plane_fit.c``), and each object's depth statistics, every pair
read once at its own box (``object_depths.c``), SURF's padded integral table (``padded_integral.c``), a whole octave
of its box-filter Hessian (``hessian_octave.c``), its scale-space maxima (``local_maxima.c``) and the strongest of
them over all the octaves of an image (``strongest_maxima.c``), the quadratic fit that makes them keypoints
(``refine_maxima.c``),
its upright descriptor (``usurf_describe.c``), the SAD nearest-neighbour search of descriptor matching
(``sad_nearest.c``), the Lucas–Kanade refinement of matched points (``lk_refine.c``), the MSAC costs of the row
alignment's hypotheses (``row_alignment_cost.c``) and its whole similarity fit (``row_alignment_fit.c``), the whole
RANSAC search for F, one pair at a time (``ransac_fundamental.c``), and Hartley's rectifying homographies with the
parallel x row (``rectify_parallel.c``). Each is the no-gradient path of a torch function that stays the
reference, the fallback and the differentiable path. Sixteen give that torch path's values bit for bit: those
named before the strongest maxima but the floor's plane, and the strongest maxima ``torch.topk``'s values and
indices (equal values in index order, which ``torch.topk`` leaves open). Nine do not (RANSAC's: its LU,
eigenvectors and sums in its own order, the same inliers but where two hypotheses' float32 scores tie;
:mod:`svs_torch.geometry.ransac`). Eight of them: the fit solves its 3 × 3 systems by its own elimination, not
LAPACK's LU (offsets to about 1e-15: the same float32 keypoints on the shared scenes); the matching kernel sums each
distance in its own order (on real descriptors: the same matches, the same costs); the refinement takes the same steps
with its sums in double and in its own order, so its points agree to about 1e-4 px; the U-SURF descriptor
(``usurf_describe.c``) builds each image's integral and describes its keypoints in double, equal to the float64 torch
path to 1e-6 and to the float32 one within its round-off (5e-4), except where a response near 0 takes the other sign
there (the extended descriptor's halves then move by up to 0.08); the row alignment sums each hypothesis's truncated
row errors in match order, not torch's (the same alignments: ``tests/core/test_kernel_fuzz.py``), and its whole fit
also solves its samples and refits by its own LU (the same inliers, acceptances and keystone readings, homographies
to 1e-9: ``tests/geometry/test_row_alignment.py``); the rectification makes the adjugate's cross products, the
norms and the area test's determinant its own way (homographies and epipoles to their last bits, statuses the same:
``tests/geometry/test_rectification.py``); the ground plane solves its samples and refits by its own LU (the same
planes and masks bit for bit on the tests' maps and the pipeline's frames: ``tests/segmentation/test_ground_plane.py``).
On the 58 shared
real pairs at 320×240, the Middlebury and KITTI scenes' results equal the torch paths'; 10 of the 13 chessboard pairs
differ by a few matches or inliers (and through their rectification, their depths), all from the refinement and the
descriptor (``experiments/kernel_parity.py``; the README's "Compiled kernels" says the same).

Each wrapper checks what its C code assumes (shapes, one row per pair, sizes and boxes within the buffers,
non-empty images, finite parameters in range) and raises :class:`~svs_torch.InputError` naming the argument
(:mod:`svs_torch.core.kernels.checks`); the C code then trusts its inputs. A wrapper answers None, for the torch path to
run, for inputs of another dtype or device, for cases the kernel leaves to it (NaN values to select among, an octave
without interior points, a table too small to read), or when the kernel is not built. ``tests/core/test_kernel_fuzz.py``
feeds drawn inputs through every public function that reaches a kernel; ``tests/sanitize/run.sh`` runs it against builds
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
(``tests/depth/test_dense.py``). It is not differentiable; the soft path (``soft_block_match``) stays in torch. Each
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
reads each row twice, skipping eight pixels at a time (16 masks of 320×240: 3.0 → 0.6 ms). The row alignment scored
its 256 hypotheses against every match in six float64 passes over a ``(B, 256, K)`` array, K the batch's largest
match count, so its time a pair grew with the batch; the kernel sums each hypothesis in one pass over its own pair's
matches (synthetic pairs, one thread: 1.2 / 5.7 / 9.2 → 0.38 / 0.31 / 0.21 ms a pair at B = 8 / 32 / 128). At
B = 1, guide's call, the cost is torch's dispatch, not memory: the rectification and the row alignment's fit were
each 130–180 small operations on 3 × 3 matrices and a few hundred matches (3.0 and 3.2 ms a frame), where their
kernels take 0.3 and 0.35 ms (the stage 6.8 → 1.6 ms a frame on the bench's camera frames); the ground plane's fit,
about 150 operations on the map's grid, 3.2 ms a frame where no floor is found and 5.8 where one is, 0.7 and 1.2.

The shared libraries are built and cached by :mod:`svs_torch.core.kernels.loader`: in a private folder
(``$SVS_TORCH_CACHE``, default ``~/.cache/svs_torch``; one others can write to is refused), under a name that
hashes the source, the shared headers, the flags actually used, the compiler and the CPU; a failed build is
remembered there. Without a working compiler, or with ``SVS_TORCH_KERNELS=torch``, :func:`load` returns None
(the first with one line on stderr) and the callers run their torch paths.
"""

from __future__ import annotations

import ctypes
import os

import torch

from . import loader
from .loader import FLAGS, HEADERS, SOURCES, cache_dir  # noqa: F401  (re-exported: the loader's public names)

__all__ = ["FLOAT", "INT", "POINTER", "available", "cache_dir", "declare", "load", "on_cpu", "rows_of"]

#: The C types of the kernels' arguments: pointers to tensor data, int64 sizes, float parameters.
POINTER, INT, FLOAT = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
#: Each kernel's (argument types, return type), as declared in its C source; filled by each stage's wrappers.
_SIGNATURES: dict[str, tuple[list, object]] = {}
_LIBRARIES: dict[str, ctypes.CDLL | None] = {}


def declare(signatures: dict[str, tuple[list, object]]) -> None:
    """Record kernels' (argument types, return type), as their C sources declare them: each stage's wrapper
    module does so for its own kernels when it is imported."""
    _SIGNATURES.update(signatures)
    for name in signatures:
        if _LIBRARIES.get(name) is not None:  # loaded before its stage declared it
            _bind(_LIBRARIES[name], name)


def _bind(library: ctypes.CDLL, name: str) -> None:
    if name in _SIGNATURES:
        function = getattr(library, name)
        function.argtypes, function.restype = _SIGNATURES[name]


def load(name: str = "block_match") -> ctypes.CDLL | None:
    """The compiled kernel ``name`` (a key of :data:`SOURCES`), compiling it on first use; None
    when kernels are off (``SVS_TORCH_KERNELS=torch``) or it cannot be built or loaded (then the caller's torch
    path runs; :func:`svs_torch.core.kernels.loader.open_library` says why once)."""
    if os.environ.get("SVS_TORCH_KERNELS", "").lower() == "torch":
        return None
    if name not in _LIBRARIES:
        library = loader.open_library(name)
        if library is not None:
            _bind(library, name)
        _LIBRARIES[name] = library
    return _LIBRARIES[name]


def available(name: str = "block_match") -> bool:
    """Whether the kernel ``name`` can run here."""
    return load(name) is not None


def on_cpu(dtype: torch.dtype, *tensors: torch.Tensor) -> bool:
    """Whether every tensor is a CPU tensor of ``dtype`` whose memory holds its values: the kernels read raw memory
    of one element type. A negative view (``z.conj().imag``) holds the negated values, and ``.contiguous()`` keeps
    it as it is where it is contiguous (one element): a (1,) baseline read as its negation ranged Teddy at 0 m, and
    a quantile [0.5] as -0.5 read before the sorted members (an audit of hostile calls). Such tensors take the
    torch path, which reads them right."""
    return all(t.dtype == dtype and t.device.type == "cpu" and not t.is_neg() for t in tensors)


def rows_of(tensor: torch.Tensor) -> tuple[int, int]:
    """A ``(..., W)`` tensor as rows for a row kernel: (number of rows, W)."""
    width = tensor.shape[-1]
    return (tensor.numel() // width if width else 0), width
