"""Hydra's ConfigStore entries of the model configs: each model's dataclass is the schema
and the base of ``conf/model/<name>.yaml``.

The dataclasses (``cls.config_class`` of every model in ``bgn.model.registry.MODELS``) are the
one source of the model defaults; a model yaml only names its base (``defaults: [<name>_base,
_self_]``) and the model. A composed ``model`` node is then typed: ``model.hidden=64`` is
checked against the field's type and a typo (``model.hiden=3``) is an error at composition.

Call ``register_configs()`` before composing ``conf/train.yaml`` (``bgn.train`` does it at
import, the tests in ``compose_config``); calling it again does nothing.
"""

from __future__ import annotations

from dataclasses import field, make_dataclass

from hydra.core.config_store import ConfigStore

from bgn.model.registry import MODELS

_registered = False


def model_schema(model: type) -> type:
    """The model's config dataclass plus its ``name`` (the registry key), for Hydra."""
    cfg = model.config_class
    return make_dataclass(f"{cfg.__name__}Node", [("name", str, field(default=model.name))],
                          bases=(cfg,))


def register_configs() -> None:
    """Store ``model/<name>_base`` for every registered model (idempotent)."""
    global _registered
    if _registered:
        return
    cs = ConfigStore.instance()
    for name, model in MODELS.items():
        cs.store(group="model", name=f"{name}_base", node=model_schema(model))
    _registered = True
