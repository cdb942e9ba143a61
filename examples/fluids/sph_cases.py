"""Two SPH problems set up on JAX-SPH's solver: a 2D Taylor-Green vortex and a 2D dam break.

The set-ups (geometry, initial fields, walls, gravity) are ours, written for this benchmark;
the physics (kernel, equation of state, weakly compressible momentum and density equations,
transport-velocity integrator, wall boundary condition) is JAX-SPH's, unchanged. Runs in the
peer environment (setup_peer.sh), never inside bgn.

- ``tgv``: periodic unit square, u = -U cos(2 pi x) sin(2 pi y), v = U sin(2 pi x) cos(2 pi y),
  Re = U L / nu = 100; the kinetic energy decays as exp(-16 pi^2 nu t), a check of the engine
  (make_sph.py records it). Trajectories differ by the vortex grid's offset against the
  particle lattice and by jittered initial positions.
- ``dam``: a water column released in a closed tank (5.366 x 2, three layers of wall particles),
  gravity 1, free surface (no background pressure), density evolution and artificial viscosity
  (alpha 0.1) for a stable free surface, Adami's generalised wall condition. Trajectories differ
  by the column's shape (drawn per trajectory, its area and particle count fixed) and jittered
  initial positions.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax_sph.case_setup import SimulationSetup
from jax_sph.defaults import set_defaults
from jax_sph.utils import Tag, pos_box_2d, pos_init_cartesian_2d
from omegaconf import DictConfig

TANK = np.array([5.366, 2.0])     # the dam break's tank, inner size (SPHERIC benchmark 2)
DAM_FLUID_AREA = 1.92             # the water column's area (1 200 particles at dx 0.04)


class TGV(SimulationSetup):
    """Taylor-Green vortex in the periodic unit square."""

    def __init__(self, cfg: DictConfig):
        super().__init__(cfg)
        self.phase = jnp.asarray(cfg.case.special.phase, dtype=float)
        # tiles x tiles periods of the vortex in a box as many units wide (the same flow,
        # tiles^2 times the particles: speed.py's scaling)
        self.tiles = int(cfg.case.special.get("tiles", 1))
        self.offset_vec = np.zeros(2)

    def _box_size2D(self, n_walls):
        return np.array([1.0, 1.0]) * self.tiles

    def _box_size3D(self, n_walls):
        raise NotImplementedError("2D only")

    def _init_walls_2d(self):
        return jnp.zeros((0, 2))

    def _init_walls_3d(self):
        raise NotImplementedError("2D only")

    def _init_velocity2D(self, r):
        x, y = 2.0 * jnp.pi * (r - self.phase)
        u_ref = self.case.u_ref
        return jnp.array([-u_ref * jnp.cos(x) * jnp.sin(y), u_ref * jnp.sin(x) * jnp.cos(y)])

    def _init_velocity3D(self, r):
        raise NotImplementedError("2D only")

    def _external_acceleration_fn(self, r):
        return jnp.zeros_like(r)

    def _boundary_conditions_fn(self, state):
        return state


class DAM(SimulationSetup):
    """Dam break: a water column of cfg.case.special.column (width, height) in a closed tank."""

    def __init__(self, cfg: DictConfig):
        super().__init__(cfg)
        self.column = np.asarray(cfg.case.special.column, dtype=float)
        dxn = cfg.solver.n_walls * cfg.case.dx
        self.offset_vec = np.full(2, dxn)

    def _box_size2D(self, n_walls):
        return TANK + 2 * n_walls * self.case.dx

    def _box_size3D(self, n_walls):
        raise NotImplementedError("2D only")

    def _init_walls_2d(self):
        return pos_box_2d(TANK, self.case.dx, self.cfg.solver.n_walls)

    def _init_walls_3d(self):
        raise NotImplementedError("2D only")

    def _init_pos2D(self, box_size, dx, n_walls):
        fluid = pos_init_cartesian_2d(self.column, dx) + self.offset_vec
        walls = self._init_walls_2d()
        r = jnp.concatenate([walls, fluid])
        tag = jnp.concatenate([jnp.full(len(walls), Tag.SOLID_WALL, dtype=int),
                               jnp.full(len(fluid), Tag.FLUID, dtype=int)])
        return r, tag

    def _init_velocity2D(self, r):
        return jnp.zeros_like(r)

    def _init_velocity3D(self, r):
        raise NotImplementedError("2D only")

    def _external_acceleration_fn(self, r):
        return jnp.zeros_like(r).at[:, 1].set(-self.case.g_ext_magnitude)

    def _boundary_conditions_fn(self, state):
        wall = (state["tag"] == Tag.SOLID_WALL)[:, None]
        for key in ("u", "v", "dudt", "dvdt"):
            state[key] = jnp.where(wall, 0.0, state[key])
        return state


CASES = {"tgv": TGV, "dam": DAM}


def config(case: str, seed: int, dx: float, rng: np.random.Generator,
           tiles: int = 1) -> DictConfig:
    """JAX-SPH's configuration for one trajectory of ``case``; what varies per trajectory is
    drawn from ``rng``. ``tiles`` > 1 (tgv only): the periodic box that many units wide."""
    if tiles != 1 and case != "tgv":
        raise ValueError(f"tiles={tiles}: only the periodic tgv case tiles")
    cfg = set_defaults()
    cfg.config = f"{case}.yaml"            # JAX-SPH names the case after its config file
    cfg.seed = seed
    cfg.case.source = f"{case}.py"
    cfg.case.dim = 2
    cfg.case.dx = dx
    cfg.case.r0_noise_factor = 0.05        # jitter of the initial lattice, in units of dx
    cfg.io.print_props = []
    if case == "tgv":
        cfg.case.viscosity = 0.01          # Re = 100 with U = L = 1
        cfg.case.u_ref = 1.0
        cfg.case.special.phase = rng.uniform(0.0, 1.0, 2).tolist()
        cfg.case.special.tiles = int(tiles)
        cfg.solver.tvf = 1.0
        cfg.solver.t_end = 5.0
        cfg.solver.n_walls = 0
    elif case == "dam":
        # the column's shape varies, its particle count does not (one count for every
        # trajectory, as both loaders require): DAM_FLUID particles in nx x ny, nx one of the
        # divisors that keep the width within 1.6-2.4 (heights 1.25-0.8 at dx 0.04)
        n = round(DAM_FLUID_AREA / dx**2)
        widths = [k for k in range(1, n + 1) if n % k == 0 and 1.6 <= k * dx <= 2.4]
        nx = int(rng.choice(widths))
        cfg.case.special.column = [nx * dx, n // nx * dx]
        cfg.case.viscosity = 0.0
        cfg.case.u_ref = float(np.sqrt(2.0 * 1.0 * TANK[1] / 2))   # sqrt(2 g H), H = 1
        cfg.case.g_ext_magnitude = 1.0
        cfg.solver.density_evolution = True
        cfg.solver.artificial_alpha = 0.1
        cfg.solver.is_bc_trick = True
        cfg.solver.t_end = 6.0
        cfg.solver.n_walls = 3
        cfg.eos.p_bg_factor = 0.0          # free surface
    else:
        raise ValueError(f"unknown case {case!r}; one of {sorted(CASES)}")
    return cfg
