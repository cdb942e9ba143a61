"""Data: simulation files (HDF5), graphs, frame samples and the LightningDataModule;
``from_arrays`` imports trajectories from memory (``bgn.data.importing``)."""

from bgn.data.importing import from_arrays

__all__ = ["from_arrays"]
