"""Validators of config values, numpy only, so that scenes (``bgn.sim``) and data code share
them without importing torch: a wrong value fails at once with its name, not deep inside."""

from __future__ import annotations

import math
import operator

import numpy as np


def as_int(value: object, name: str, minimum: int = 0) -> int:
    """A Python int from an int-like value (numpy integers too) that is at least ``minimum``.
    Bools and non-integral numbers are refused: in a config they are likely mistakes."""
    if isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be an integer >= {minimum}, got bool {value!r}")
    try:
        out = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"{name} must be an integer >= {minimum}, got "
                         f"{type(value).__name__} {value!r}") from None
    if out < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {out}")
    return out


def as_float(value: object, name: str, minimum: float | None = None,
             strict: bool = False) -> float:
    """A finite Python float from a real number (bools refused), at least ``minimum`` (above
    it with ``strict``)."""
    if isinstance(value, bool | np.bool_) or isinstance(value, str | bytes):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(out):
        raise ValueError(f"{name} must be finite, got {out}")
    if minimum is not None and (out <= minimum if strict else out < minimum):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {minimum}, got {out}")
    return out


def as_real_array(values: object, name: str) -> np.ndarray:
    """A float64 array of finite real numbers (integers are converted; NaN, inf, complex,
    bool or object arrays are refused)."""
    arr = np.asarray(values)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{name} must be real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite (found NaN or inf)")
    return arr
