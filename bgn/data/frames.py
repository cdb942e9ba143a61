"""Fixed subsets of frames: evenly spaced indices, so a subset covers every simulation of a
split the same way each time (validation frames, evaluated test frames, edge statistics)."""

from __future__ import annotations

import numpy as np


def evenly_spaced(n: int, k: int | None) -> list[int]:
    """``k`` distinct indices spread evenly over ``range(n)``, first and last included (all
    of them when ``k`` is None or at least ``n``)."""
    if k is None or k >= n:
        return list(range(n))
    return np.unique(np.linspace(0, n - 1, k).round().astype(int)).tolist()
