"""Input checks for public entry points.

Every check raises :class:`InputError` (a ``ValueError``) whose message names the argument and what was
expected, e.g. ``left: expected (B, 1, H, W), got (4, 3, 240, 320)``. Checks run once at the public entry of
a stage; the tensor maths inside trusts its inputs. A pipeline that calls one public stage after another on the
same images checks them once and names them :func:`checked_images`: the stages do not range them again.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from collections.abc import Iterator, Sequence

import torch

from .errors import InputError

__all__ = [
    "InputError",
    "nesting_depth",
    "check_device",
    "check_shape",
    "check_dtype",
    "check_dtypes",
    "check_image",
    "check_instance",
    "check_same_shape",
    "all_finite",
    "check_finite",
    "check_finite_where",
    "check_flag",
    "check_count",
    "check_real",
    "check_generator",
    "check_percentiles",
    "check_positive_scalar",
    "check_float_dtype",
    "check_stereo_views",
    "checked_images",
    "real_or_nan",
    "FLOAT32_MAX",
]


#: The memory and layout of the images :func:`checked_images` names, in the block it opens (per thread and task).
_CHECKED: contextvars.ContextVar[frozenset[tuple]] = contextvars.ContextVar("svs_torch_checked_images",
                                                                           default=frozenset())


def _layout(tensor: torch.Tensor) -> tuple:
    return tensor.data_ptr(), tuple(tensor.shape), tensor.stride(), tensor.dtype, tensor.device


@contextlib.contextmanager
def checked_images(*images: torch.Tensor) -> Iterator[None]:
    """Within the block, :func:`check_image` does not range ``images`` again and :func:`all_finite` takes them as
    finite: the caller has checked them (values in [0, 1]) and does not write into them. Any tensor of the same
    memory, shape, strides and dtype counts (``.detach()``, ``.contiguous()`` of a contiguous one). Why: the
    pipeline's stages each ranged the same two views again, five or six times a batch (4.2 ms of 8 pairs' scans at
    320 × 240, 1.8 now: 0.3 ms a pair)."""
    token = _CHECKED.set(_CHECKED.get() | {_layout(image) for image in images})
    try:
        yield
    finally:
        _CHECKED.reset(token)


def _was_checked(tensor: torch.Tensor) -> bool:
    checked = _CHECKED.get()
    if not checked or tensor.layout != torch.strided or tensor.is_meta:
        return False
    try:
        return _layout(tensor) in checked
    except RuntimeError:  # no storage to point at (a functorch wrapper): not one of them
        return False


def _format_spec(spec: Sequence[str | int]) -> str:
    return "(" + ", ".join(str(s) for s in spec) + ")"


def check_shape(tensor: torch.Tensor, name: str, spec: Sequence[str | int]) -> dict[str, int]:
    """Check ``tensor`` against a shape spec such as ``["B", 1, "H", "W"]``.

    Letters bind to sizes (the same letter must bind to the same size everywhere in the spec); integers must
    match exactly. Returns the bindings, so callers can check sizes across arguments.

    Example:
        >>> check_shape(torch.zeros(2, 1, 4, 5), "left", ["B", 1, "H", "W"])
        {'B': 2, 'H': 4, 'W': 5}
    """
    if not isinstance(tensor, torch.Tensor):
        raise InputError(f"{name}: expected a torch.Tensor of shape {_format_spec(spec)}, "
                         f"got {type(tensor).__name__}")
    shape = tuple(tensor.shape)
    bindings: dict[str, int] = {}
    ok = len(shape) == len(spec)
    if ok:
        for size, want in zip(shape, spec):
            if isinstance(want, int):
                ok = ok and size == want
            elif want in bindings:
                ok = ok and bindings[want] == size
            else:
                bindings[want] = size
    if not ok:
        raise InputError(f"{name}: expected {_format_spec(spec)}, got {_format_spec(shape)}")
    return bindings


#: The floating-point dtypes the pipeline computes in. Half precision is refused: the integral image of a 64 x 64
#: image sums past 2048, where float16 stops holding whole numbers, and CPU kernels such as cdist do not exist for it.
FLOAT_DTYPES = (torch.float32, torch.float64)
#: The integer dtypes the checks take as "int": torch.uint16, uint32 and uint64 have no comparison nor sort on the
#: CPU ('"gt_cpu" not implemented for 'UInt64''), the quantized ones (qint8) no plain op at all.
INT_DTYPES = (torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64)
#: The largest float32: a setting that becomes a float32 tensor's value is bounded by it (1e39 passed its check,
#: then made every pair an ERROR row, "value cannot be converted to type float without overflow"; an audit of --set).
FLOAT32_MAX = float(torch.finfo(torch.float32).max)


def check_float_dtype(dtype: object, name: str = "dtype") -> None:
    """Check a ``dtype`` argument (what a loader or a renderer makes its tensors in): one of :data:`FLOAT_DTYPES`."""
    if dtype not in FLOAT_DTYPES:
        raise InputError(f"{name}: expected torch.float32 or torch.float64, got {dtype!r}")


def _a(word: str) -> str:
    """The article an error's "expected ..." takes before ``word``: "an int tensor", "an ObjectDepths"."""
    return "an" if word[:1].lower() in "aeio" else "a"


def check_dtype(tensor: torch.Tensor, name: str, kinds: str) -> None:
    """Check the dtype family: ``"float"`` (float32 or float64), ``"bool"``, ``"int"`` (any integer), or several
    joined by ``|``."""
    allowed = kinds.split("|")
    if not isinstance(tensor, torch.Tensor):  # a list or a number failed on .is_meta below (an audit)
        kind = "float32 or float64" if allowed == ["float"] else " or ".join(allowed)
        raise InputError(f"{name}: expected {_a(kind)} {kind} tensor, got {type(tensor).__name__}")
    if tensor.is_meta:  # shapes without values: every check that reads a value (bool(), item()) failed deep in torch
        raise InputError(f"{name}: expected a tensor with values, got one on the meta device")
    # A sparse (or mkldnn) tensor failed in the first op without such a kernel (a kernel wrapper's .contiguous():
    # "unsupported memory format option Contiguous"), naming no argument (an audit of hostile calls).
    if tensor.layout != torch.strided:
        raise InputError(f"{name}: expected a dense tensor, got layout {tensor.layout} (call .to_dense())")
    dtype = tensor.dtype
    family = ("bool" if dtype == torch.bool else
              "float" if dtype in FLOAT_DTYPES else
              "half" if dtype.is_floating_point else
              "complex" if dtype.is_complex else
              "int" if dtype in INT_DTYPES else "other")
    if family == "half" and "float" in allowed:
        raise InputError(f"{name}: expected a float32 or float64 tensor, got {dtype}")
    if family == "other" and "int" in allowed:  # torch.uint64, torch.qint8: torch's comparisons refuse them
        raise InputError(f"{name}: expected an int tensor (int8, int16, int32, int64 or uint8), got {dtype}")
    if family not in allowed:
        raise InputError(f"{name}: expected {_a(allowed[0])} {' or '.join(allowed)} tensor, got {dtype}")


def check_dtypes(**arguments: tuple[torch.Tensor, str]) -> None:
    """:func:`check_dtype` of each argument given as ``name=(tensor, kinds)``, in order: one line for a function's
    arguments."""
    for name, (tensor, kinds) in arguments.items():
        check_dtype(tensor, name, kinds)


def check_image(tensor: torch.Tensor, name: str, check_range: bool = True) -> dict[str, int]:
    """Check a grayscale image batch: float ``(B, 1, H, W)`` with values in [0, 1] and no NaN.

    The range check costs one reduction and one host sync; it runs once per public call.
    """
    bindings = check_shape(tensor, name, ["B", 1, "H", "W"])
    if tensor.is_meta:  # shapes without values (a model traced on the meta device): nothing to range
        raise InputError(f"{name}: expected an image with values, got a tensor on the meta device")
    if tensor.layout != torch.strided:  # a sparse image: aminmax raised NotImplementedError from deep inside
        raise InputError(f"{name}: expected a dense image tensor, got layout {tensor.layout} (call .to_dense())")
    check_dtype(tensor, name, "float")
    if check_range and tensor.numel() > 0 and not _was_checked(tensor):
        # One pass: aminmax propagates NaN, so a NaN anywhere shows in the extremes.
        lo, hi = (float(v) for v in torch.aminmax(tensor.detach()))
        if math.isnan(lo) or math.isnan(hi):
            raise InputError(f"{name}: expected values in [0, 1], got NaN{_in_pairs(tensor.isnan())}")
        if not (lo >= 0.0 and hi <= 1.0):
            # Nine digits tell a float32 one ulp above 1 (1.00000012) from 1 itself.
            raise InputError(f"{name}: expected values in [0, 1], got min {lo:.9g}, max {hi:.9g}"
                             f"{_in_pairs((tensor < 0) | (tensor > 1))}")
    return bindings


def check_stereo_views(left: torch.Tensor, right: torch.Tensor) -> dict[str, int]:
    """:func:`check_image` of both views of a batch of pairs, of one shape and one dtype (with two, what came out
    took one view's dtype and its values moved with which view was which); returns the bindings."""
    dims = check_image(left, "left")
    check_image(right, "right")
    check_same_shape(left, "left", right, "right")
    if right.dtype != left.dtype:
        raise InputError(f"right: expected the left view's dtype {left.dtype}, got {right.dtype}")
    return dims


def _in_pairs(bad: torch.Tensor) -> str:
    """`` (image 2 of 3)``: which of a batch's images hold the ``bad`` values, so a bulk run can find the file."""
    images = bad.detach().flatten(1).any(1).nonzero().flatten().tolist()
    return f" (image{'s' if len(images) > 1 else ''} {', '.join(map(str, images[:8]))} of {bad.shape[0]})"


def check_instance(value: object, name: str, kind: type, fields: tuple[str, ...] = ()) -> None:
    """Check that ``value`` is a ``kind`` (a container or a configuration), e.g.
    ``config: expected a PipelineConfig, got dict``. With ``fields``, any object that has them passes too (a
    function that reads only those fields also takes a stand-in, as hand-made test cases are)."""
    if isinstance(value, kind) or (fields and all(hasattr(value, field) for field in fields)):
        return
    raise InputError(f"{name}: expected {_a(kind.__name__)} {kind.__name__}, got {type(value).__name__}")


def check_same_shape(a: torch.Tensor, name_a: str, b: torch.Tensor, name_b: str) -> None:
    """Check that two tensors have the same shape (e.g. a left and a right image)."""
    if a.shape != b.shape:
        raise InputError(f"{name_b}: expected the shape of {name_a} {_format_spec(tuple(a.shape))}, "
                         f"got {_format_spec(tuple(b.shape))}")


def all_finite(tensor: torch.Tensor) -> bool:
    """Whether every value of ``tensor`` is finite (no NaN, no ±inf), in one pass without a temporary: a real float
    tensor's extremes by ``aminmax``, which propagates NaN (an infinity is an extreme). Why: ``isfinite(x).all()``
    writes a bool tensor and reads it again, 1.65 ms for 8 images of 320 x 240 at one thread against 0.13 ms, and
    the pipeline's own checks of its images and descriptors took 4 % of ``estimate --pairs``' time."""
    values = tensor.detach()
    if _was_checked(values):
        return True
    if values.is_complex() or values.numel() == 0 or values.layout != torch.strided:
        return bool(torch.isfinite(values).all())
    if not values.is_floating_point():  # bool and integers are finite
        return True
    low, high = torch.aminmax(values)
    return bool(torch.isfinite(low) & torch.isfinite(high))


def check_finite(tensor: torch.Tensor, name: str, positive: bool = False) -> None:
    """Check that every value is finite (no NaN, no ±inf) and, with ``positive``, greater than zero.

    Raises :class:`InputError` naming the argument and the first offending value, e.g.
    ``focal_px: expected finite positive values, got inf``.
    """
    values = tensor.detach()
    if not positive and all_finite(values):
        return
    bad = ~torch.isfinite(values)
    if positive:
        bad = bad | ~(values > 0)
    if bool(bad.any()):
        first = float(values[bad].flatten()[0])
        raise InputError(f"{name}: expected finite{' positive' if positive else ''} values, got {first}")


def check_device(tensor: torch.Tensor, name: str, like: torch.Tensor, whose: str) -> None:
    """Check that ``tensor`` is on ``like``'s device (``whose``: how the message names it, e.g. ``"the image's"``): one
    on another device, or the meta device, failed deep inside torch at its first use or ``bool()``."""
    if tensor.device != like.device:
        raise InputError(f"{name}: expected a tensor on {whose} device {like.device}, got {tensor.device}")


def check_finite_where(tensor: torch.Tensor, name: str, where: torch.Tensor, where_name: str) -> None:
    """Check that ``tensor`` ``(B, ...)`` is finite wherever the bool ``where`` holds, naming the pairs that are
    not. A ground truth of inf or NaN marked known (a PFM's "unknown" left valid) was taken, then failed a whole
    batch's scoring, naming an argument its caller never passed."""
    if all_finite(tensor):
        return
    bad = (~torch.isfinite(tensor.detach()) & where).flatten(1).any(1)
    if bool(bad.any()):
        raise InputError(f"{name}: expected finite values where {where_name} holds, got NaN or inf for pair(s) "
                         f"{bad.nonzero().flatten().tolist()[:8]} of {bad.shape[0]}")


# ---------------------------------------------------------------------------------------------------------------
# Settings of the configuration dataclasses: checked when a configuration is built, so that a sweep's absurd value
# is refused by its field's name rather than failing late, or silently changing nothing (a string taken as true).


def check_flag(value: object, name: str) -> None:
    """A bool setting (``True`` / ``False``; a string such as ``"no"`` would be truthy)."""
    if value is not True and value is not False:
        raise InputError(f"{name}: expected a bool, got {value!r}")


def check_count(value: object, name: str, least: int = 0, optional: bool = False, most: int | None = None) -> None:
    """A whole-number setting of at least ``least`` and at most ``most`` (``None`` allowed with ``optional``)."""
    if optional and value is None:
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < least or (most is not None and value > most):
        bound = f">= {least}" if most is None else f"from {least} to {most}"
        raise InputError(f"{name}: expected an int {bound}{' or None' if optional else ''}, got {value!r}")


def check_real(value: object, name: str, low: float = -math.inf, high: float = math.inf, low_open: bool = False,
               high_open: bool = False, optional: bool = False) -> None:
    """A finite real setting in the interval from ``low`` to ``high`` (each end closed unless ``*_open``;
    ``None`` allowed with ``optional``), e.g. ``max_offset: expected a finite number in [0, inf), got nan``."""
    if optional and value is None:
        return
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan
    if not (math.isfinite(number) and (low < number if low_open else low <= number)
            and (number < high if high_open else number <= high)):
        opening = "(" if low_open or math.isinf(low) else "["
        interval = f"{opening}{low:g}, {high:g}{')' if high_open or math.isinf(high) else ']'}"
        raise InputError(f"{name}: expected a finite number in {interval}{' or None' if optional else ''}, "
                         f"got {value!r}")


def check_positive_scalar(value: object, name: str, noun: str = "number") -> None:
    """One positive number: an int or float (not a bool) or a one-element tensor with a value (not on the meta
    device), e.g. a soft function's temperature. Why: a (B,) tensor raised "Boolean value of Tensor with more than
    one value is ambiguous", a string or None a TypeError from the comparison and a meta tensor a RuntimeError from
    its bool(), none naming the argument (audits); a bool is a flag passed in the wrong place. ``noun``: what the
    message calls the value (``expected a positive {noun}``)."""
    if isinstance(value, torch.Tensor) and value.numel() != 1:
        raise InputError(f"{name}: expected one positive number, got a tensor of shape {tuple(value.shape)}")
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number or isinstance(value, torch.Tensor) and not value.is_meta) or not value > 0:
        raise InputError(f"{name}: expected a positive {noun}, got {value!r}")


def real_or_nan(value: object) -> float:
    """``value`` where it is a real number (not a bool), else NaN, for a setting's range check: every comparison
    with NaN fails, so the setting's own message names it (a string compared raised a TypeError, "'<=' not supported
    between instances of 'int' and 'str'", that named no field: an audit of hostile configuration values)."""
    return value if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


def check_percentiles(value: object, name: str, optional: bool = False) -> None:
    """A ``(low, high)`` pair of percentiles with ``0 <= low <= high <= 100`` (``None`` allowed with ``optional``),
    e.g. ``percentiles: expected (low, high) with 0 <= low <= high <= 100, got (90, 10)``."""
    if optional and value is None:
        return
    real = (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v))
    if not (isinstance(value, (tuple, list)) and len(value) == 2 and all(real(v) for v in value)
            and 0 <= value[0] <= value[1] <= 100):
        raise InputError(f"{name}: expected (low, high) with 0 <= low <= high <= 100{' or None' if optional else ''}"
                         f", got {value!r}")


def check_generator(generator: object, name: str = "generator") -> None:
    """``None`` or a :class:`torch.Generator` (every random draw goes through one), e.g. not a seed."""
    if generator is not None and not isinstance(generator, torch.Generator):
        raise InputError(f"{name}: expected a torch.Generator or None (seed one with manual_seed), got "
                         f"{type(generator).__name__}")


def nesting_depth(value: object) -> int:
    """How many levels of non-empty dicts and lists nest in ``value`` (a parsed TOML or JSON document), counted a
    level at a time, without recursion: a recursive walk of a file nested thousands deep ended in a RecursionError,
    "internal error" on the command line (an audit)."""
    depth, level = 0, [value]
    while level := [item for node in level if isinstance(node, (dict, list))
                    for item in (node.values() if isinstance(node, dict) else node)]:
        depth += 1
    return depth
