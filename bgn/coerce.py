"""Validators of config values, numpy only, so that scenes (``bgn.sim``), data code and the
commands' config checks (``bgn.training.validate``) share them without importing torch: a wrong
value fails at once with its name, not deep inside. ``as_*`` raise a ``ValueError``;
``need_*`` a ``ConfigError`` naming the key, the value and what is accepted."""

from __future__ import annotations

import math
import operator
from collections.abc import Mapping
from datetime import timedelta
from typing import Any

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


class ConfigError(ValueError):
    """A config value bgn cannot use; the message names the key, the value and what is
    accepted (or is given whole as ``message``)."""

    def __init__(self, key: str, value: Any = None, accepted: str = "",
                 message: str | None = None) -> None:
        self.key, self.value = key, value
        shown = repr(value) if isinstance(value, str) else f"{value}"
        super().__init__(message or f"{key}={shown}: {accepted}")


def need_int(value: Any, key: str, minimum: int, maximum: int | None = None,
             optional: bool = False, why: str = "") -> int | None:
    """``value`` as an int in ``[minimum, maximum]`` (``None`` allowed when ``optional``)."""
    if value is None and optional:
        return None
    span = f"an integer >= {minimum}" if maximum is None else \
        f"an integer in {minimum}..{maximum}"
    accepted = f"must be {span}{' (or null)' if optional else ''}{why}"
    try:
        out = as_int(value, key, minimum)
    except ValueError:
        raise ConfigError(key, value, accepted) from None
    if maximum is not None and out > maximum:
        raise ConfigError(key, value, accepted)
    return out


def need_float(value: Any, key: str, low: float | None = None, high: float | None = None,
               strict_low: bool = True, strict_high: bool = False, why: str = "") -> float:
    """``value`` as a finite float above ``low`` (at least, unless ``strict_low``) and below
    ``high`` (at most, unless ``strict_high``)."""
    parts = []
    if low is not None:
        parts.append(f"{'>' if strict_low else '>='} {low:g}")
    if high is not None:
        parts.append(f"{'<' if strict_high else '<='} {high:g}")
    accepted = f"must be a finite number{' ' + ' and '.join(parts) if parts else ''}{why}"
    try:
        out = as_float(value, key)
    except ValueError:
        raise ConfigError(key, value, accepted) from None
    if low is not None and (out <= low if strict_low else out < low):
        raise ConfigError(key, value, accepted)
    if high is not None and (out >= high if strict_high else out > high):
        raise ConfigError(key, value, accepted)
    return out


def seconds(max_time: Any) -> float | None:
    """Lightning's ``max_time`` (``"DD:HH:MM:SS"``, a dict of timedelta fields, a timedelta
    or None) in seconds."""
    if max_time is None:
        return None
    if isinstance(max_time, timedelta):
        return max_time.total_seconds()
    if isinstance(max_time, Mapping):
        return timedelta(**{str(k): float(v) for k, v in max_time.items()}).total_seconds()
    days, hours, minutes, secs = (float(p) for p in str(max_time).split(":"))
    return timedelta(days=days, hours=hours, minutes=minutes, seconds=secs).total_seconds()


def clock(total: float) -> str:
    """Whole seconds as Lightning's ``"DD:HH:MM:SS"``."""
    s = int(total)
    return f"{s // 86400:02d}:{s // 3600 % 24:02d}:{s // 60 % 60:02d}:{s % 60:02d}"
