"""LightningDataModule: generates or finds the files (imported data: finds them only), splits
by simulation, batches graphs."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
from torch.utils.data import DataLoader, Subset

from bgn.data.dataset import FrameDataset
from bgn.data.files import DatasetFile
from bgn.data.frames import evenly_spaced
from bgn.data.generate import ensure_splits
from bgn.data.spec import IMPORTED, DatasetSpec, LoaderOptions
from bgn.graph import collate
from bgn.sim import SceneMeta


class ParticleDataModule(L.LightningDataModule):
    """Train, val and test are separate simulations (separate files): no frame of a test
    simulation is ever seen in training.

    ``dataset`` is the ``dataset`` config node (scene parameters, sizes, loading options).
    ``train_sims`` limits training to the first n simulations (sample-efficiency studies).
    ``val_samples`` caps validation at that many frames spread evenly over all validation
    simulations (every epoch the same ones): a prefix of the split, which ``limit_val_batches``
    would take, is one or two simulations, and with heavy-tailed targets its error says little
    about the others. ``test_samples`` does the same for the test split (null: whole).
    """

    def __init__(self, dataset: Any, fps: float, data_dir: str | Path = "data",
                 generate_workers: int | None = None, show_progress: bool = True,
                 spec: DatasetSpec | None = None) -> None:
        super().__init__()
        # ``spec``: the train split's, where the caller built it already (bgn.training.validate);
        # imported data (dataset=imported): the spec comes from the files under data_dir
        self.spec = spec or DatasetSpec.from_config(dataset, fps, "train", data_dir)
        if self.spec.scene == IMPORTED:
            logging.getLogger("bgn.data").info(
                f"dataset=imported ({self.spec.params['name']}): frames are "
                f"{self.spec.dt:g} apart as recorded ({self.spec.fps:g} per time unit); the "
                f"top-level fps={float(fps):g} is ignored")
        loader = LoaderOptions.from_config(dataset, self.spec.n_sims)  # checked: ConfigError
        self.history, self.unroll = loader.history, loader.unroll  # unroll: bgn.training.unroll
        self.batch_size, self.num_workers = loader.batch_size, loader.num_workers
        self.in_memory, self.train_sims = loader.in_memory, loader.train_sims
        self.samples: dict[str, int | None] = {"val": loader.val_samples,
                                               "test": loader.test_samples}
        self.data_dir = Path(data_dir)
        self.generate_workers = generate_workers
        self.show_progress = show_progress
        self.paths: dict[str, Path] = {}
        self.datasets: dict[str, FrameDataset] = {}

    def prepare_data(self) -> None:
        self.paths = ensure_splits(self.spec, self.data_dir, self.generate_workers,
                                   self.show_progress)

    def setup(self, stage: str | None = None) -> None:
        if not self.paths:
            self.paths = {s: self.spec.with_split(s).path(self.data_dir)
                          for s in ("train", "val", "test")}
        for split, path in self.paths.items():
            if split in self.datasets:
                continue
            file = DatasetFile(path, self.spec.with_split(split))
            sims = list(range(self.train_sims)) if split == "train" and self.train_sims else None
            self.datasets[split] = FrameDataset(file, self.history, sims, self.in_memory,
                                                unroll=self.unroll if split == "train" else 0)

    @property
    def meta(self) -> SceneMeta:
        return self.spec.build_scene().meta

    @property
    def dt(self) -> float:
        return self.spec.dt

    def stats(self) -> dict[str, dict[str, np.ndarray]]:
        """Normalisation statistics of the training split (computed once, at generation)."""
        self.setup()
        return self.datasets["train"].file.stats()

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        self.setup()
        data = self.datasets[split]
        cap = self.samples.get(split)
        if cap is not None and cap < len(data):
            data = Subset(data, evenly_spaced(len(data), cap))
        return DataLoader(data, batch_size=self.batch_size, shuffle=shuffle,
                          num_workers=self.num_workers, collate_fn=collate,
                          persistent_workers=self.num_workers > 0)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)
