"""Data: simulation files (HDF5), graphs, frame samples and the LightningDataModule."""
