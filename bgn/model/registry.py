"""Every model by name: ``build_model(config, meta, stats, history)``.

A model is a ``bgn.model.base.PhysicsModel`` subclass with a ``name`` and a ``config_class``
(a dataclass of its options). To add one, write its module, list its class in ``MODELS``
below and add ``conf/model/<name>.yaml`` on its ``<name>_base`` schema (``bgn.training.config``;
README, "Adding a model"). The optimiser is not a model option (``conf/optimizer/``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from bgn.model.base import PhysicsModel, config_from_params
from bgn.model.baselines import GNS, CranmerGN
from bgn.model.bgn import BGN
from bgn.model.newton import Newton
from bgn.sim.scene import SceneMeta

MODELS: dict[str, type[PhysicsModel]] = {cls.name: cls for cls in (BGN, CranmerGN, GNS, Newton)}


def build_model(config: Mapping[str, Any], meta: SceneMeta, stats: Mapping[str, Any],
                history: int) -> PhysicsModel:
    """The model named ``config["name"]`` (default ``bgn``) for a scene; unknown names and
    unknown options are errors that list what exists."""
    config = dict(config)
    name = config.pop("name", "bgn")
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; known: {sorted(MODELS)}")
    cls = MODELS[name]
    return cls(meta, stats, history, config_from_params(cls.config_class, config, name))
