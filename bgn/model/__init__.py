"""Model layer: BGN, the baselines and the contract they share (``PhysicsModel``). Uses torch,
zuko, the graph type and scene metadata only; no files, Lightning or Hydra
(docs/design.md#layers)."""

from bgn.model.base import LOSS_KEYS, ModelOutput, PhysicsModel
from bgn.model.bgn import BGN, ModelConfig
from bgn.model.normalizer import Normalizer
from bgn.model.registry import MODELS, build_model

__all__ = ["BGN", "LOSS_KEYS", "MODELS", "ModelConfig", "ModelOutput", "Normalizer",
           "PhysicsModel", "build_model"]
