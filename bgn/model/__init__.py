"""Model layer: BGN (and later the baselines). Uses torch, zuko and the Graph/SceneMeta types
only; no files, Lightning or Hydra (DESIGN section 0)."""

from bgn.model.bgn import BGN, LOSS_KEYS, BGNOutput, ModelConfig
from bgn.model.normalizer import Normalizer
from bgn.model.registry import build_model

__all__ = ["BGN", "BGNOutput", "ModelConfig", "Normalizer", "LOSS_KEYS", "build_model"]
