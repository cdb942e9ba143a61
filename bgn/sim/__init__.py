"""Scenes: simulators plus the metadata record the rest of bgn is built from."""

from __future__ import annotations

from typing import Any

from bgn.sim.collisions import CollisionScene
from bgn.sim.imported import ImportedScene
from bgn.sim.nbody import NBodyScene
from bgn.sim.scene import Scene, SceneMeta, State, Trajectory

# name -> (class, fixed arguments). Everything else is a config value.
SCENES: dict[str, tuple[type, dict[str, Any]]] = {
    "collisions": (CollisionScene, {}),
    "spring": (NBodyScene, {"potential": "spring"}),
    "gravity_r1": (NBodyScene, {"potential": "r1"}),
    "gravity_r2": (NBodyScene, {"potential": "r2"}),
    # trajectories from outside bgn (bgn.data.importing): no simulator, fields from the files
    "imported": (ImportedScene, {}),
}


def make_scene(name: str, /, **params: Any) -> Scene:
    """Build scene ``name`` from config values; unknown names or parameters are errors."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose one of {sorted(SCENES)}")
    cls, fixed = SCENES[name]
    try:
        return cls(**fixed, **params)
    except TypeError as err:  # a wrong key in conf/dataset/<name>.yaml
        raise ValueError(f"bad parameters for scene {name!r}: {err}") from err


__all__ = ["SCENES", "Scene", "SceneMeta", "State", "Trajectory", "make_scene", "CollisionScene",
           "ImportedScene", "NBodyScene"]
