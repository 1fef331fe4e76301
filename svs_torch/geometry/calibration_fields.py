"""The fields of a calibration file (:mod:`svs_torch.geometry.calibration`), read one by one: each refused with a
one-line error naming it and what was expected, never taken as another type (numpy would read ``"500"`` as 500)."""

from __future__ import annotations

import math

import numpy as np

from ..core.checks import InputError

__all__ = ["coefficients_field", "finite_or_none", "matrix_field", "number_field", "numbers_only"]


def finite_or_none(value):
    """``value`` with each NaN or inf, in nested dicts and lists, as None (JSON's null: a file without its errors)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [finite_or_none(v) for v in value]
    return value


def numbers_only(value) -> bool:
    """Nested lists of JSON numbers (numpy would take ``"500"`` as 500)."""
    if isinstance(value, list):
        return all(numbers_only(v) for v in value)
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def matrix_field(record: dict, key: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    """``record[key]``, a ``shape`` array of finite numbers; refused naming ``where`` and ``key``."""
    value = record.get(key)
    try:
        array = np.asarray(value, dtype=np.float64) if numbers_only(value) else None
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer of hundreds of digits
        array = None
    if array is None or array.shape != shape or not np.isfinite(array).all():
        raise InputError(f"{where}: expected '{key}' as {'x'.join(map(str, shape))} finite numbers")
    return array


def coefficients_field(record: dict, key: str, where: str) -> np.ndarray:
    """``record[key]``, OpenCV's 4, 5, 8, 12 or 14 distortion coefficients; refused naming ``where`` and ``key``."""
    value = record.get(key)
    try:
        array = np.asarray(value, dtype=np.float64).ravel() if numbers_only(value) else None
    except (TypeError, ValueError, OverflowError):
        array = None
    if array is None or array.size not in (4, 5, 8, 12, 14) or not np.isfinite(array).all():
        raise InputError(f"{where}: expected '{key}' as 4, 5, 8, 12 or 14 finite distortion coefficients")
    return array


def number_field(record: dict, key: str) -> float:
    """``record[key]`` as a float; NaN where it is missing or no JSON number (an optional value)."""
    value = record.get(key)  # an integer beyond a float's range (400 digits) is as unknown as a string
    number = isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) <= 1e300
    return float(value) if number else math.nan
