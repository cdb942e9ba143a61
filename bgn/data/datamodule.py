"""LightningDataModule: generates or finds the files (imported data: finds them only), splits
by simulation, batches graphs."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Sampler, Subset

from bgn.coerce import ConfigError, need_int
from bgn.data.dataset import FrameDataset
from bgn.data.files import DatasetFile
from bgn.data.frames import evenly_spaced
from bgn.data.generate import ensure_dataset, ensure_splits
from bgn.data.spec import IMPORTED, SPLITS, DatasetSpec, LoaderOptions
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
    ``sims_per_batch``: each training batch holds windows of that many simulations only, an
    equal share each (``SimulationBatches``; a model that fits per-simulation quantities over
    a batch's windows, ``mass_law=coupling``, needs many windows of each); None: windows drawn
    at random.
    """

    def __init__(self, dataset: Any, fps: float, data_dir: str | Path = "data",
                 generate_workers: int | None = None, show_progress: bool = True,
                 spec: DatasetSpec | None = None, sims_per_batch: int | None = None) -> None:
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
        if sims_per_batch is not None and sims_per_batch < 1:
            raise ValueError(f"sims_per_batch={sims_per_batch} must be at least 1")
        self.sims_per_batch = sims_per_batch
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

    def larger_split(self, split: str, n_sims: int) -> FrameDataset:
        """Split ``split`` with ``n_sims`` simulations instead of the run's, generated on first
        use: its first simulations are the run's (each is a pure function of the seed, the
        split and its index), the rest new ones from the same scene, never seen in training or
        choices; a radius-graph scene keeps the run's training file and its margin. More
        particles for a metric whose spread is the split's size (coverage over ten
        simulations moves in tenths). Generated scenes only."""
        if self.spec.scene == IMPORTED:
            raise ConfigError("sims", n_sims, "imported data hold the simulations they hold: "
                              "import more, or leave sims unset")
        n_sims = need_int(n_sims, "sims", 1)
        base = self.spec.with_split(split)
        # every other split keeps the run's size: the train file (and its margin) is the run's
        sizes = tuple((int(n_sims) if s == split else base.n_sims, base.n_frames)
                      for s in SPLITS)
        spec = replace(base, n_sims=int(n_sims), sizes=sizes)
        path = ensure_dataset(spec, self.data_dir, self.generate_workers, None)
        return FrameDataset(DatasetFile(path, spec), self.history, None, self.in_memory)

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
        if self.sims_per_batch is None:
            return self._loader("train", shuffle=True)
        self.setup()
        data = self.datasets["train"]
        sampler = SimulationBatches(len(data.sims), data.frames_per_sim, self.batch_size,
                                    self.sims_per_batch)
        return DataLoader(data, batch_sampler=sampler, num_workers=self.num_workers,
                          collate_fn=collate, persistent_workers=self.num_workers > 0)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)


class SimulationBatches(Sampler[list[int]]):
    """Batches of ``batch_size`` windows from ``per_batch`` simulations each (an equal share,
    the first ones one more where it does not divide): every epoch each simulation's windows
    shuffled, the simulations taken ``per_batch`` at a time in a shuffled order, round after
    round, until every window was drawn once (about). A dataset index is ``sim *
    frames_per_sim + frame`` (``FrameDataset.locate``). Seeded by torch's global generator,
    as the default shuffle is."""

    def __init__(self, n_sims: int, frames_per_sim: int, batch_size: int, per_batch: int
                 ) -> None:
        self.n_sims, self.frames, self.batch_size = n_sims, frames_per_sim, batch_size
        self.per_batch = min(per_batch, n_sims)

    def __len__(self) -> int:
        return max(1, (self.n_sims * self.frames) // self.batch_size)

    def __iter__(self) -> Iterator[list[int]]:
        shares = [len(s) for s in np.array_split(np.arange(self.batch_size), self.per_batch)]
        queues = [torch.randperm(self.frames).tolist() for _ in range(self.n_sims)]
        order: list[int] = []
        for _ in range(len(self)):
            batch: list[int] = []
            for share in shares:
                if not order:
                    order = torch.randperm(self.n_sims).tolist()
                sim = order.pop()
                if len(queues[sim]) < share:
                    queues[sim] += torch.randperm(self.frames).tolist()
                batch += [sim * self.frames + queues[sim].pop() for _ in range(share)]
            yield batch
