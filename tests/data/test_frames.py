"""Evenly spaced frame indices: first and last included, distinct, all when asked for more."""

from __future__ import annotations

from bgn.data.frames import evenly_spaced


def test_evenly_spaced() -> None:
    assert evenly_spaced(10, 4) == [0, 3, 6, 9]
    assert evenly_spaced(3, 10) == [0, 1, 2]
    assert evenly_spaced(5, None) == [0, 1, 2, 3, 4]
    assert evenly_spaced(0, 3) == []
    picked = evenly_spaced(1000, 100)
    assert len(picked) == 100 and picked[0] == 0 and picked[-1] == 999
