"""The shared config validators: integers, finite floats, real arrays."""

from __future__ import annotations

import numpy as np
import pytest

from bgn.coerce import as_float, as_int, as_real_array


def test_as_int() -> None:
    assert as_int(np.int32(4), "n") == 4 and type(as_int(np.int64(4), "n")) is int
    assert as_int(2, "n", minimum=2) == 2
    for bad in (True, np.bool_(False), 2.0, 2.5, "3", None):
        with pytest.raises(ValueError, match="n must be an integer >= 0"):
            as_int(bad, "n")
    with pytest.raises(ValueError, match=r"n_particles must be an integer >= 2, got 1"):
        as_int(1, "n_particles", minimum=2)


def test_as_float() -> None:
    assert as_float(np.float32(0.5), "x") == 0.5 and as_float(3, "x") == 3.0
    assert as_float(0.0, "x", minimum=0.0) == 0.0
    for bad, match in ((True, "real number"), ("1.0", "real number"), (None, "real number"),
                       (np.nan, "finite"), (-np.inf, "finite")):
        with pytest.raises(ValueError, match=match):
            as_float(bad, "x")
    with pytest.raises(ValueError, match="x must be >= 1"):
        as_float(0.5, "x", minimum=1.0)
    with pytest.raises(ValueError, match="x must be > 0"):
        as_float(0.0, "x", minimum=0.0, strict=True)


def test_as_real_array() -> None:
    out = as_real_array([[1, 2]], "positions")
    assert out.dtype == np.float64 and out.tolist() == [[1.0, 2.0]]
    with pytest.raises(ValueError, match="real numbers"):
        as_real_array(np.array(["a"]), "positions")
    with pytest.raises(ValueError, match="finite"):
        as_real_array([0.0, np.nan], "radii")
