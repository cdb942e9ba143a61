"""Symmetries of the scenes: the same motion offset in space or seen at another length scale.

``offset(state, shift)`` adds ``shift`` to every coordinate (n-body scenes have no walls, so
their motion is translation invariant). ``scaled(scene, state, factor)`` multiplies every length
by ``factor`` at the same time unit: velocities scale with the lengths, and the scene's
parameters follow so that the new motion is the old one times ``factor`` (collisions: box and
radii; gravity: softening, and masses by ``factor**3`` (1/r^2 force) or ``factor**2``
(1/r force), so that accelerations scale like lengths, and the integrator's absolute
tolerance, so that its error control is the same). The spring's rest length (1) is not a
parameter, so it has no scaled twin. numpy only.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from bgn.sim.collisions import CollisionScene
from bgn.sim.nbody import NBodyScene
from bgn.sim.scene import Scene, State

# how masses scale with lengths so that accelerations scale like lengths
_MASS_POWER = {"r1": 2, "r2": 3}


def offset(state: State, shift: float) -> State:
    """``state`` with ``shift`` added to every coordinate."""
    return dataclasses.replace(state, positions=state.positions + shift)


def scaled(scene: Scene, state: State, factor: float) -> tuple[Scene, State]:
    """The scene and state whose motion is ``factor`` times that of ``(scene, state)``."""
    if not factor > 0:
        raise ValueError(f"factor={factor} must be > 0")
    new_state = dataclasses.replace(state, positions=state.positions * factor,
                                    velocities=state.velocities * factor,
                                    radii=state.radii * factor)
    if isinstance(scene, CollisionScene):
        types = [dataclasses.replace(t, radius=t.radius * factor) for t in scene.types]
        return (dataclasses.replace(scene, box=scene.box * factor, types=tuple(types),
                                    velocity_std=scene.velocity_std * factor), new_state)
    if isinstance(scene, NBodyScene):
        if scene.potential not in _MASS_POWER:
            raise ValueError(f"the {scene.meta.name} scene has no length parameter (its rest "
                             "length is 1), so it has no scaled twin")
        power = _MASS_POWER[scene.potential]
        new_state = dataclasses.replace(new_state, masses=state.masses * factor ** power)
        return (dataclasses.replace(scene, softening=scene.softening * factor,
                                    atol=scene.atol * factor,
                                    position_std=scene.position_std * factor,
                                    velocity_std=scene.velocity_std * factor,
                                    mass_log_mean=scene.mass_log_mean + power * np.log(factor)),
                new_state)
    raise ValueError(f"no scaling rule for {type(scene).__name__}")


__all__ = ["offset", "scaled"]
