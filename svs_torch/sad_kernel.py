"""The fused SAD winner-takes-all kernel of the dense stage: C source in ``svs_torch/kernels/sad_wta.c``,
compiled once per machine with the system's C compiler and loaded through ``ctypes``.

Why a C kernel: eager torch pays one memory pass per elementwise op, and the dense stage's cost volume
(B × D × h × w) went through about 25 of them (x-Sobel differences, 2 (K − 1) box-sum adds, masking, the
running minimum, the uniqueness rival, the right view's winner): 35–50 ms a pair at 320×240, most of a
pipeline run. The kernel makes each output row's costs for every disparity and consumes them while they are in
cache, with running window sums; its inputs are whole numbers (``StereoBM``'s 8-bit levels), so every sum is
exact and its results are bit-identical to the torch path's (``tests/test_dense.py``). It is not differentiable; the soft path (``soft_block_match``) stays in torch.

The shared library is cached in ``$SVS_TORCH_CACHE`` (default ``~/.cache/svs_torch``) under a name that hashes
the source, the compiler flags and the CPU, so every later process reuses it; the one compile (about a second)
is announced on stderr. Without a compiler, or with ``SVS_TORCH_KERNELS=torch``, :func:`load` returns None and
the dense stage runs its torch path.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

__all__ = ["available", "cache_dir", "load", "sad_wta"]

SOURCE = Path(__file__).with_name("kernels") / "sad_wta.c"
#: No -ffast-math: it could assume away the +inf costs that mark disparities outside the image.
FLAGS = ["-O3", "-march=native", "-ffp-contract=off", "-fPIC", "-shared", "-pthread"]
#: Rows of output per task: enough to amortise the K − 1 rows each band reads first, small enough that one pair
#: splits across threads (the B = 1 ``guide`` case).
BAND_ROWS = 48

_LIBRARY: ctypes.CDLL | None = None
_TRIED = False


def cache_dir() -> Path:
    """Where compiled kernels live: ``$SVS_TORCH_CACHE`` or ``~/.cache/svs_torch``."""
    configured = os.environ.get("SVS_TORCH_CACHE")
    if configured:
        return Path(configured)
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "svs_torch"


def _cpu_signature() -> str:
    """The CPU's feature flags (``-march=native`` code must not run on another CPU sharing the cache)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _library_path() -> Path:
    digest = hashlib.sha256()
    for part in (SOURCE.read_bytes(), " ".join(FLAGS).encode(), _cpu_signature().encode(),
                 platform.machine().encode()):
        digest.update(part)
    return cache_dir() / f"sad_wta-{digest.hexdigest()[:16]}.so"


def _compile(target: Path) -> bool:
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if compiler is None:
        return False
    print(f"svs_torch: compiling the dense-stage kernel once for this machine into {target.parent} "
          "(about a second; later runs reuse it)", file=sys.stderr)
    target.parent.mkdir(parents=True, exist_ok=True)
    # Built under a temporary name and renamed: a concurrent process never loads a half-written library.
    handle, temporary = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(handle)
    try:
        done = subprocess.run([compiler, *FLAGS, str(SOURCE), "-o", temporary, "-lm"], capture_output=True,
                              timeout=120)
        if done.returncode != 0:
            print("svs_torch: the kernel did not compile; the dense stage runs its torch path:\n"
                  + done.stderr.decode(errors="replace")[-2000:], file=sys.stderr)
            return False
        os.replace(temporary, target)
        return True
    except (OSError, subprocess.SubprocessError) as error:
        print(f"svs_torch: the kernel did not compile ({error}); the dense stage runs its torch path",
              file=sys.stderr)
        return False
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


def load() -> ctypes.CDLL | None:
    """The compiled kernel, compiling it on first use; None when kernels are off (``SVS_TORCH_KERNELS=torch``)
    or cannot be built or loaded (then the caller's torch path runs)."""
    global _LIBRARY, _TRIED
    if os.environ.get("SVS_TORCH_KERNELS", "").lower() == "torch":
        return None
    if _TRIED:
        return _LIBRARY
    _TRIED = True
    try:
        path = _library_path()
        if not path.exists() and not _compile(path):
            return None
        library = ctypes.CDLL(str(path))
    except OSError as error:
        print(f"svs_torch: the kernel could not be loaded ({error}); the dense stage runs its torch path",
              file=sys.stderr)
        return None
    function = library.sad_wta
    pointer, integer = ctypes.c_void_p, ctypes.c_int64
    function.argtypes = [pointer, pointer] + [integer] * 5 + [pointer] * 4 + [pointer] * 6 + [integer] * 2
    function.restype = ctypes.c_int
    _LIBRARY = library
    return library


def available() -> bool:
    """Whether :func:`sad_wta` can run here."""
    return load() is not None


def sad_wta(left_crop: torch.Tensor, right_crop: torch.Tensor, window_size: int, num_disparities: int,
            x0: torch.Tensor, min_disparity: torch.Tensor, image_w: torch.Tensor, counts: torch.Tensor
            ) -> tuple[torch.Tensor, ...] | None:
    """Winner-takes-all over the SAD costs of the crops, the kernel's contract (see the C source):
    ``left_crop`` ``(B, HL, WL)`` and ``right_crop`` ``(B, HL, WL + D − 1)`` float32 holding whole numbers in
    [−255, 255] (:func:`svs_torch.dense.quantize_levels`: then every sum is exact and the result is the torch
    path's bit for bit); per pair ``x0`` (the crop's column in the image), ``min_disparity``, ``image_w``,
    ``counts`` ``(B,)`` int64.

    Returns ``(best_cost, best, before, after, rival, right_best)``, each ``(B, H, W)`` with ``H = HL − K + 1``,
    ``W = WL − K + 1`` (float32, or int64 for the indices), or None when the kernel is not available."""
    library = load()
    if library is None:
        return None
    b, hl, wl = left_crop.shape
    height, width = hl - window_size + 1, wl - window_size + 1
    left_crop, right_crop = left_crop.contiguous(), right_crop.contiguous()
    per_pair = [v.to(torch.int64).contiguous() for v in (x0, min_disparity, image_w, counts)]
    floats = [left_crop.new_empty(b, height, width) for _ in range(4)]
    best, right_best = (torch.empty(b, height, width, dtype=torch.int64) for _ in range(2))
    best_cost, before, after, rival = floats
    status = library.sad_wta(
        left_crop.data_ptr(), right_crop.data_ptr(), b, hl, wl, num_disparities, window_size,
        *(v.data_ptr() for v in per_pair), best_cost.data_ptr(), best.data_ptr(), before.data_ptr(),
        after.data_ptr(), rival.data_ptr(), right_best.data_ptr(), torch.get_num_threads(), BAND_ROWS)
    if status != 0:
        return None
    return best_cost, best, before, after, rival, right_best
