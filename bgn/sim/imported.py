"""A scene bgn did not simulate: trajectories imported from another engine
(docs/design.md#imported-scenes).

``ImportedScene`` carries what the rest of bgn needs to know of the imported data (sizes, types,
graph rule, target, box) and nothing of their physics: there is no simulator to draw or
continue a trajectory, and the pair force law is unknown (``interaction="unknown"``: BGN builds
no force-magnitude contact head for it, the files' edge contact targets are zero). The fields
are written by ``bgn.data.importing`` into the files' generating config, so a dataset file
rebuilds its scene like a generated one (``bgn.data.dataset.scene_from_file``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from bgn.sim.scene import SceneMeta, State, Trajectory

GRAPHS = ("full", "radius")
TARGETS = ("acceleration", "velocity")


class NoSimulatorError(RuntimeError):
    """Asked an imported scene to simulate."""


@dataclass(frozen=True)
class ImportedScene:
    """Imported trajectories' scene record. ``graph="radius"`` joins pairs closer than
    ``r_i + r_j + connectivity_radius`` (radii are zero unless the source gives them: then
    GNS's rule ``|x_i - x_j| <= R``); ``box`` is the side of reflecting walls ``[0, box]^dim``
    declared by the source, else None. ``periodic`` (per dimension) and ``bounds`` are the
    source's: the imported positions are unwrapped, and the periodic dimensions' box lengths
    become ``SceneMeta.period`` (minimum-image edges and edge vectors). ``kinematic_types`` are
    particle types moved by the source (inputs, never predicted or scored); ``masses_known``
    False: the source gave no masses (ones stand in). ``source`` names
    the file or folder imported ("" from memory), ``data_sha256`` hashes the imported arrays
    of every split (so the checkpoints' provenance tells two imports under one name apart)."""

    name: str = "imported"
    n_particles: int = 1
    dim: int = 2
    n_types: int = 1
    graph: str = "full"
    target: str = "acceleration"
    interaction: str = "unknown"
    box: float | None = None
    connectivity_radius: float | None = None
    periodic: tuple[bool, ...] = ()
    bounds: tuple[tuple[float, float], ...] = ()
    kinematic_types: tuple[int, ...] = ()
    masses_known: bool = True
    source: str = ""
    data_sha256: str = ""
    # no exact simulator: tools that re-simulate (the predictability limit, the stability
    # suite's exact runs) skip a scene whose has_simulator is False
    has_simulator: ClassVar[bool] = False

    def __post_init__(self) -> None:
        for key in ("n_particles", "dim", "n_types"):
            if int(getattr(self, key)) < 1:
                raise ValueError(f"{key}={getattr(self, key)} must be >= 1")
        if self.graph not in GRAPHS:
            raise ValueError(f"graph={self.graph!r}; choose one of {GRAPHS}")
        if self.target not in TARGETS:
            raise ValueError(f"target={self.target!r}; choose one of {TARGETS}")
        if self.graph == "radius" and not (self.connectivity_radius or 0) > 0:
            raise ValueError("graph='radius' needs a connectivity_radius > 0")
        # lists from JSON or config -> tuples (the dataclass is frozen and hashable)
        object.__setattr__(self, "periodic", tuple(bool(p) for p in self.periodic))
        object.__setattr__(self, "bounds", tuple(tuple(float(v) for v in b)
                                                 for b in self.bounds))
        object.__setattr__(self, "kinematic_types", tuple(int(t) for t in self.kinematic_types))
        if any(self.periodic) and (len(self.periodic) != self.dim
                                   or len(self.bounds) != self.dim):
            raise ValueError(f"periodic={self.periodic} needs one flag and one (low, high) bound "
                             f"per dimension (dim={self.dim}); got bounds={self.bounds}")

    @property
    def meta(self) -> SceneMeta:
        return SceneMeta(name=self.name, dim=int(self.dim), n_particles=int(self.n_particles),
                         n_types=int(self.n_types), interaction=self.interaction,  # type: ignore
                         target=self.target, graph=self.graph,  # type: ignore[arg-type]
                         box=None if self.box is None else float(self.box),
                         masses_known=bool(self.masses_known), period=self.period)

    @property
    def period(self) -> tuple[float, ...] | None:
        """The box length of each periodic dimension (0 elsewhere) from the source's bounds, or
        None when no dimension is periodic (``SceneMeta.period``)."""
        if not any(self.periodic):
            return None
        return tuple(hi - lo if p else 0.0 for p, (lo, hi) in zip(self.periodic, self.bounds))

    @property
    def margin(self) -> float:
        """The radius graph's margin (``bgn.data.edges.scene_edges``); 0 for full graphs."""
        return float(self.connectivity_radius) if self.graph == "radius" else 0.0

    def _no_simulator(self, what: str) -> NoSimulatorError:
        return NoSimulatorError(
            f"{what}: the imported dataset {self.name!r} ({self.source or 'arrays'}) has no "
            "simulator in bgn; only its recorded frames exist")

    def simulate(self, rng: np.random.Generator, times: np.ndarray) -> Trajectory:
        raise self._no_simulator("simulate")

    def draw_state(self, rng: np.random.Generator) -> State:
        raise self._no_simulator("draw_state")

    def simulate_from(self, state: State, times: np.ndarray) -> Trajectory:
        raise self._no_simulator("simulate_from")

    def energy(self, positions: np.ndarray, velocities: np.ndarray,
               masses: np.ndarray) -> np.ndarray:
        """KINETIC energy ``0.5 sum_i m_i |v_i|^2`` per frame of (T, N, D) arrays: the
        potential of an engine bgn did not write is unknown, so this is not the total energy
        and need not be conserved."""
        v = np.asarray(velocities, dtype=np.float64)
        return 0.5 * np.einsum("n,tnd,tnd->t", np.asarray(masses, dtype=np.float64), v, v)

    def pair_force_magnitude(self, positions: np.ndarray, masses: np.ndarray,
                             senders: np.ndarray, receivers: np.ndarray) -> np.ndarray:
        raise NotImplementedError(
            f"the pair force law of the imported dataset {self.name!r} is unknown "
            "(interaction='unknown'): there is no force-magnitude target")
