"""bgn: a graph network that learns particle physics forward (dynamics) and inverse (mass)."""

import os

# Transparent huge pages for PyTorch's large CPU tensors. Per-edge tensors of a big graph are
# hundreds of MB, freed and allocated again every step; with 4 KiB pages each allocation pays
# for its page faults again, and that dominated steps on large graphs
# (docs/notes/2026-11-26-results-history.md, "Moved here from code comments and configs";
# docs/design.md#performance-choices). PyTorch reads the
# variable at its first allocation, so it is set here, before anything imports torch; an explicit
# setting in the environment wins.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

__version__ = "0.1.0"


def __getattr__(name: str):
    """``bgn.load`` and ``bgn.Model`` (the Python API, ``bgn.api``), imported on first use so
    that ``import bgn`` stays light and no lower layer imports the API."""
    if name in ("load", "Model", "MassPosterior", "PairLaw"):
        from bgn import api

        return getattr(api, name)
    raise AttributeError(f"module 'bgn' has no attribute {name!r}")
