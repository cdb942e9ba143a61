"""Build a model by name from a plain config dict (what ``conf/model/*.yaml`` holds).

Every model takes ``(meta, stats, history, ...)`` and exposes ``forward(g)``,
``loss_terms(g, out)``, ``total_loss(terms)``, ``predict(g)`` (physical units),
``denormalize_target``, ``heads`` (the loss keys it produces) and, with an inverse head,
``sample_mass(g, n)``. Baselines register in ``bgn.model.baselines.MODELS`` as
``name -> callable(meta, stats, history, params: dict) -> nn.Module``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
from typing import Any

from torch import nn

from bgn.model.bgn import BGN, ModelConfig
from bgn.sim.scene import SceneMeta

# Config keys that belong to the optimiser, not to the model.
TRAINING_KEYS = frozenset({"name", "lr", "weight_decay", "lr_min_ratio"})


def model_config(params: Mapping[str, Any]) -> ModelConfig:
    """``ModelConfig`` from a dict; unknown keys are an error (a typo in a yaml file)."""
    names = {f.name for f in fields(ModelConfig)}
    unknown = set(params) - names - TRAINING_KEYS
    if unknown:
        raise ValueError(f"unknown BGN model options {sorted(unknown)}; known: {sorted(names)}")
    values = {k: v for k, v in params.items() if k in names}
    if "loss_weights" in values:
        values["loss_weights"] = {str(k): float(v) for k, v in dict(values["loss_weights"]).items()}
    return ModelConfig(**values)


def build_model(config: Mapping[str, Any], meta: SceneMeta, stats: Mapping[str, Any],
                history: int) -> nn.Module:
    """The model named ``config["name"]`` (default ``bgn``) for a scene."""
    config = dict(config)
    name = config.get("name", "bgn")
    if name == "bgn":
        return BGN(meta, stats, history, model_config(config))
    try:
        from bgn.model.baselines import MODELS  # added later by the baselines' author
    except ImportError:
        MODELS = {}
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; known: {['bgn', *sorted(MODELS)]}")
    params = {k: v for k, v in config.items() if k not in TRAINING_KEYS}
    return MODELS[name](meta, stats, history, params)
