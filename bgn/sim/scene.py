"""What every scene shares: its metadata record and the trajectory it produces.

A scene knows numpy and scipy only (no torch, no files, no config): the data layer turns its
trajectories into files and graphs, and the model is assembled from its ``SceneMeta``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

# "unknown": imported data (bgn.sim.imported), whose pair forces bgn does not know
Interaction = Literal["contact", "pairwise", "unknown"]
TargetKind = Literal["velocity", "acceleration"]
GraphKind = Literal["full", "radius"]


@dataclass(frozen=True)
class SceneMeta:
    """What the rest of the code needs to know about a scene (docs/design.md#the-scene-record).

    ``box`` is the side length of the reflecting box ``[0, box]^dim`` when the scene has walls,
    else ``None``. ``period`` holds the box length of each dimension with periodic boundaries
    (0 for a non-periodic one), or is ``None`` for a scene without any: edges, edge vectors
    and distances then follow the minimum image. ``graph == "radius"`` means edges join pairs
    closer than ``r_i + r_j + margin``; ``"full"`` means every ordered pair ``i != j``.
    """

    name: str
    dim: int
    n_particles: int
    n_types: int
    interaction: Interaction
    target: TargetKind
    graph: GraphKind
    box: float | None = None
    # False for imported data whose source gives no masses (ones stand in): the inverse model
    # still reports its posterior, but no metric scores it against them
    masses_known: bool = True
    period: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.period is None:
            return
        # lists from JSON (dataset files, checkpoints) -> a tuple: the record stays hashable
        period = tuple(float(p) for p in self.period)
        if len(period) != self.dim or not all(np.isfinite(p) and p >= 0 for p in period):
            raise ValueError(f"SceneMeta.period={self.period}: give one finite length >= 0 per "
                             f"dimension (dim={self.dim}; 0: not periodic), or None")
        object.__setattr__(self, "period", period if any(period) else None)

    @property
    def has_walls(self) -> bool:
        return self.box is not None

    @property
    def periodic(self) -> bool:
        """Whether any dimension has periodic boundaries."""
        return self.period is not None


@dataclass
class Trajectory:
    """One simulation sampled at ``times`` (float64 throughout).

    positions, velocities: (T, N, D), instantaneous (exact) values at the frame times.
    accelerations: (T, N, D) from the force law at the recorded positions, or None (contact
    scenes). masses, radii: (N,); types: (N,) int. contacts: (M, 3) int rows
    ``(frame, i, j)`` with ``i < j`` for every pair that touches in ``(times[frame],
    times[frame + 1]]``; None for scenes without contacts. charges: (N,) where the state
    carried them (``State.charges``), else None.
    """

    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    masses: np.ndarray
    types: np.ndarray
    radii: np.ndarray
    accelerations: np.ndarray | None = None
    contacts: np.ndarray | None = None
    charges: np.ndarray | None = None


@dataclass
class State:
    """An initial state to simulate from (``Scene.simulate_from``), float64.

    positions, velocities: (N, D); masses: (N,). radii (N,) and types (N,) int matter for
    contact scenes only (None: zeros). charges (N,), of either sign: couplings in place of the
    masses where a scene's potential takes them (``bgn.sim.nbody``); None: none.
    """

    positions: np.ndarray
    velocities: np.ndarray
    masses: np.ndarray
    radii: np.ndarray | None = None
    types: np.ndarray | None = None
    charges: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.positions = np.array(self.positions, dtype=np.float64, ndmin=2)
        self.velocities = np.array(self.velocities, dtype=np.float64, ndmin=2)
        self.masses = np.array(self.masses, dtype=np.float64, ndmin=1)
        n = self.positions.shape[0]
        self.radii = (np.zeros(n) if self.radii is None
                      else np.array(self.radii, dtype=np.float64, ndmin=1))
        self.types = (np.zeros(n, dtype=np.int64) if self.types is None
                      else np.array(self.types, dtype=np.int64, ndmin=1))
        if self.positions.ndim != 2 or self.velocities.shape != self.positions.shape:
            raise ValueError(f"positions and velocities must both be (N, D); got "
                             f"{self.positions.shape} and {self.velocities.shape}")
        if self.charges is not None:
            self.charges = np.array(self.charges, dtype=np.float64, ndmin=1)
        for name in ("masses", "radii", "types") + (("charges",) if self.charges is not None
                                                     else ()):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} must be (N,) = ({n},); got "
                                 f"{getattr(self, name).shape}")


class Scene(Protocol):
    """A simulator plus its metadata. Parameters are dataclass fields (config, not code)."""

    n_particles: int
    dim: int

    @property
    def meta(self) -> SceneMeta: ...

    def simulate(self, rng: np.random.Generator, times: np.ndarray) -> Trajectory:
        """Draw initial conditions and masses from ``rng``; return the state at ``times``.

        ``times`` is increasing, starts at 0. The physical trajectory must not depend on
        ``times`` (integration accuracy is independent of the frame rate), so sampling the
        same ``rng`` state at every 5th time gives every 5th frame bit for bit.
        """
        ...

    def draw_state(self, rng: np.random.Generator) -> State:
        """The initial state ``simulate`` draws from ``rng``."""
        ...

    def simulate_from(self, state: State, times: np.ndarray) -> Trajectory:
        """Simulate from a given state at time 0; ``simulate(rng, times)`` is
        ``simulate_from(draw_state(rng), times)`` bit for bit."""
        ...

    def energy(self, positions: np.ndarray, velocities: np.ndarray,
               masses: np.ndarray) -> np.ndarray:
        """Total energy per frame for (T, N, D) arrays (float64)."""
        ...
