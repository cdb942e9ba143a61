"""Benchmarks, run as modules: ``python -m bgn.benchmarks.<name> --help``."""
