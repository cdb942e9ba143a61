"""Frames of a dataset file as graph samples (one torch ``Graph`` per frame)."""

from __future__ import annotations

import json

import numpy as np
import torch
from torch.utils.data import Dataset

from bgn.data.edges import full_graph, pair_codes, scene_edges
from bgn.data.files import DatasetFile
from bgn.data.targets import backward_velocities, targets
from bgn.graph import Graph, window_graph
from bgn.sim import Scene, SceneMeta, make_scene


def scene_from_file(file: DatasetFile) -> Scene:
    """Rebuild the generating scene from the config stored in the file."""
    config = json.loads(file.attrs["config"])
    return make_scene(config["scene"], **config["params"])


class FrameDataset(Dataset):
    """Sample ``(sim, t)`` for t in ``[k+1, T-2]``: the window needs ``x[t-k-1]`` and the
    target needs ``x[t+1]``.

    ``sims`` restricts the simulations used (e.g. the first 3 for a sample-efficiency run).
    ``unroll`` S > 0 adds the true velocities of the S frames after the target's to every
    graph (``Graph.future_vel``, for unrolled training: ``bgn.training.unroll``); the last S
    frames of each simulation then start no sample.
    """

    def __init__(self, file: DatasetFile, history: int = 5, sims: list[int] | None = None,
                 in_memory: bool = True, unroll: int = 0) -> None:
        if history < 0:
            raise ValueError(f"dataset.history={history} must be >= 0")
        if isinstance(unroll, bool) or not isinstance(unroll, int) or unroll < 0:
            raise ValueError(f"dataset.unroll={unroll!r} must be an integer >= 0")
        if file.n_frames < history + 3 + unroll:
            raise ValueError(f"{file.path}: {file.n_frames} frames are too few for history "
                             f"{history} and unroll {unroll}; need at least "
                             f"{history + 3 + unroll}")
        self.file = file
        self.meta = file.meta
        self.scene = scene_from_file(file)
        if getattr(self.scene.meta, "period", None) != self.meta.period:
            # a file imported before SceneMeta recorded periodic boundaries
            raise ValueError(f"{file.path}: the source's periodic boundaries "
                             f"{self.scene.meta.period} are missing from the file's scene "
                             "record; import the data again (python -m bgn.data.import ...)")
        self.history, self.unroll = history, unroll
        self.sims = list(range(file.n_sims)) if sims is None else list(sims)
        if not self.sims or max(self.sims) >= file.n_sims or min(self.sims) < 0:
            raise ValueError(f"simulations {sims} not in the file's 0..{file.n_sims - 1}")
        self.in_memory = in_memory
        self.frames_per_sim = file.n_frames - history - 2 - unroll
        self.dt = file.dt
        self.margin = file.margin
        self._full_edges = (full_graph(self.meta.n_particles)
                            if self.meta.graph == "full" else None)  # built once
        self._contacts: dict[tuple[int, int], np.ndarray] | None = None
        # imported data whose source has kinematic types: the particles it moves
        self.has_kinematic = bool(getattr(self.scene, "kinematic_types", ())) \
            and "kinematic" in self.file.handle

    def __len__(self) -> int:
        return len(self.sims) * self.frames_per_sim

    def locate(self, index: int) -> tuple[int, int]:
        """Dataset index -> (simulation, frame t)."""
        if not 0 <= index < len(self):
            raise IndexError(index)
        return self.sims[index // self.frames_per_sim], self.history + 1 + index % \
            self.frames_per_sim

    def _contact_codes(self, sim: int, frame: int) -> np.ndarray:
        if self._contacts is None:  # built lazily per worker: (sim, frame) -> sorted i*N+j
            n = self.meta.n_particles
            table = self.file.read("contacts", ...)
            codes = pair_codes(table[:, 2], table[:, 3], n)
            order = np.lexsort((codes, table[:, 1], table[:, 0]))
            self._contacts = {}
            for (s, f), c in zip(map(tuple, table[order, :2].tolist()), codes[order]):
                self._contacts.setdefault((s, f), []).append(c)
            self._contacts = {k: np.asarray(v) for k, v in self._contacts.items()}
        return self._contacts.get((sim, frame), np.empty(0, dtype=np.int64))

    def __getitem__(self, index: int) -> Graph:
        if self.in_memory and not self.file.loaded:
            self.file.load_all()
        sim, t = self.locate(index)
        k = self.history
        x = self.file.read("positions", (sim, slice(t - k - 1, t + 2 + self.unroll)))
        contacts = self._contact_codes(sim, t) if self.meta.interaction == "contact" else None
        g = self.graph(x[:k + 2], sim, t, next_position=x[k + 2], contact_codes=contacts)
        if self.unroll:  # v[t+2] .. v[t+S+1], differences in the file's float64
            future = backward_velocities(x[k + 2:], self.dt).transpose(1, 0, 2)
            g.future_vel = torch.as_tensor(future, dtype=g.vel.dtype)
        return g

    def graph(self, window: np.ndarray, sim: int, frame: int,
              next_position: np.ndarray | None = None,
              contact_codes: np.ndarray | None = None) -> Graph:
        """The graph of frame ``frame`` of simulation ``sim`` from positions ``window``
        (frames t-k-1 .. t, shape (k+2, N, D)); rollouts pass predicted positions here.

        Without ``next_position`` the target is zero (unknown).
        """
        return frame_graph(window, self.dt, self.meta, self.scene,
                           masses=self.file.read("masses", sim),
                           radii=self.file.read("radii", sim),
                           types=self.file.read("types", sim), margin=self.margin,
                           sim=sim, frame=frame, next_position=next_position,
                           contact_codes=contact_codes, edges=self._full_edges,
                           kinematic=self.kinematic(sim))

    def kinematic(self, sim: int) -> np.ndarray | None:
        """(N,) bool: the particles of simulation ``sim`` that the source moves (imported
        data with kinematic types), else None."""
        if not self.has_kinematic:
            return None
        return self.file.read("kinematic", sim)


def frame_graph(window: np.ndarray, dt: float, meta: SceneMeta, scene: Scene,
                masses: np.ndarray, radii: np.ndarray, types: np.ndarray, margin: float,
                sim: int = 0, frame: int = 0, next_position: np.ndarray | None = None,
                contact_codes: np.ndarray | None = None, edges: np.ndarray | None = None,
                kinematic: np.ndarray | None = None) -> Graph:
    """Inputs, edges and targets of one frame (docs/design.md#frames-and-targets,
    docs/design.md#graphs). The inputs are ``bgn.graph.window_graph``'s, which the learned simulator
    builds in rollouts."""
    pos = window[-1]
    if edges is None:
        edges = scene_edges(meta.graph, pos, radii, margin, meta.period)
    g = window_graph(torch.as_tensor(window, dtype=torch.float64)[None], dt,
                     torch.as_tensor(edges, dtype=torch.long),
                     torch.as_tensor(masses)[None], torch.as_tensor(radii)[None],
                     torch.as_tensor(types)[None], meta.box, torch.tensor([sim]),
                     torch.tensor([frame]),
                     kinematic=None if kinematic is None else torch.as_tensor(kinematic)[None],
                     period=meta.period)
    if next_position is not None:
        target = targets(np.concatenate([window[-2:], next_position[None]]), dt, meta.target)[0]
        g.target = torch.as_tensor(target, dtype=torch.float32)
    snd, rcv = edges
    if meta.interaction == "contact":
        codes = pair_codes(snd, rcv, len(pos))
        known = contact_codes if contact_codes is not None else np.empty(0, np.int64)
        contact = np.isin(codes, known).astype(np.float32)
    elif meta.interaction == "unknown":  # imported data: the pair force law is not known
        contact = np.zeros(len(snd), dtype=np.float32)
    else:
        contact = scene.pair_force_magnitude(pos, masses, snd, rcv)
    g.edge_contact = torch.as_tensor(contact, dtype=torch.float32)
    return g
