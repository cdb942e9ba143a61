"""bgn: a graph network that learns particle physics forward (dynamics) and inverse (mass)."""

__version__ = "0.1.0"
