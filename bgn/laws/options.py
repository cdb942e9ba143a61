"""The laws' options, typed: every setting of the fit, the report and the fine-tuning in one
frozen dataclass (``LawOptions``), its defaults the values the figures in docs/results.md were
made with. ``python -m bgn.laws``'s keys (``conf/laws.yaml``: ``max_terms``, ``tolerance``,
``parsimony``, ``finetune_<key>``) set the fields of the same names (``from_keys``), and the
formula stage (``bgn.laws.stage``) reads them; the modules' other settings read ``DEFAULTS``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np


@dataclass(frozen=True)
class LawOptions:
    """The laws' settings (``bgn.laws``): the fit (``terms``), the sampled law and its
    comparison (``sample``, ``compare``), the report (``report``), the fine-tuning
    (``finetune``)."""

    # ------------------------------------------------------------------ the fit (terms)
    # relative residuals: |f| floored near a zero crossing by the change of f over this
    # fraction of r (a spring's law crosses zero at s = 1, where a relative error is undefined)
    zero_crossing_width: float = 0.1
    size_floor: float = 0.01           # of the law's size at the median point: residuals' floor
    c_grid: int = 41                   # values of a nonlinear constant tried before refinement
    c_grid_pair: int = 25              # ... per constant, where a formula has two
    refine_per_complexity: int = 4     # candidates of each complexity refined jointly
    significant: int = 4               # digits of the constants in the printed formula
    max_terms: int = 3                 # terms of a formula at most (the command's max_terms)
    # a formula within this RMS relative error of the learned law is taken as it (the
    # discrepancy principle: the network's law is no more exact than that)
    tolerance: float = 0.02
    parsimony: float = 1.5             # else PySR's rule among those within this factor of the best

    # ------------------------------------------------------- the law on a grid (sample, compare)
    grid_points: int = 240             # log-spaced distances per pair of types
    # "every distance the data reach", robustly: the 1st to 99th percentiles
    distance_quantiles: np.ndarray = field(
        default_factory=lambda: np.linspace(0.01, 0.99, 99))
    kde_points: int = 20_000           # distances the density of log r is estimated from
    band_quantiles: tuple[float, ...] = (0.0, 0.01, 0.1, 0.5, 0.9, 0.99, 1.0)  # error bands
    calibration_frames: int = 256      # training frames that put a free scale in physical units
    max_distances: int = 2_000_000     # pair distances read from the train split (frames thinned)
    truth_form: float = 1e-3           # the truth fitted in a formula's terms leaves less: its form

    # ------------------------------------------------------- the formula as the law (finetune)
    finetune_steps: int = 80           # loss evaluations (Nelder-Mead) per form's constants
    finetune_substeps: int = 16        # model.substeps while the forms are tuned (and written)
    polish_factor: int = 4             # the chosen form polished through this times finer substeps
    finetune_batch_size: int = 512     # training frames of the fixed batch (closest ones first)
    finetune_horizon: int = 50         # validation rollout steps (as bgn.studies.auto's horizon)
    finetune_val_sims: int | None = None  # validation simulations rolled out (None: all)
    amplitude_step: float = 0.1        # the first simplex's step in each amplitude (relative)
    c_step: float = 2.0                # ... and its factor on each constant c
    form_tolerance: float = 0.02       # a simpler form is kept while its loss is within this
    negligible: float = 0.01           # a term this small against the law everywhere goes
    # particles per batch of validation rollouts: the job's deadline is checked between
    # batches; a force scene's whole validation split (200 x 4 bodies) is one batch
    rollout_chunk: int = 4096
    typical_floor: float = 1e-9        # added to each error before the geometric mean (exact ones)
    cancelling: float = 0.01           # a term twice whose amplitudes cancel to this: a derivative
    close_share: float = 0.25          # of the tuning batch: the frames with the closest pairs
    robust_scale: float = 0.1          # relative error at which the law loss's Cauchy loss bends
    turn_quantile: float = 1e-3        # of the training distances: below it the law may not turn
    # the distances turning_term checks, times its floor
    below_floor: np.ndarray = field(default_factory=lambda: np.geomspace(1e-3, 1.0, 61))


DEFAULTS = LawOptions()

# the fields python -m bgn.laws sets by their names (conf/laws.yaml)
COMMAND_KEYS = ("max_terms", "tolerance", "parsimony", "finetune_steps", "finetune_substeps",
                "finetune_batch_size", "finetune_horizon", "finetune_val_sims")


def from_keys(values: dict[str, Any]) -> LawOptions:
    """``DEFAULTS`` with the given fields set (a key given as None keeps its default); a key
    that names no field is refused (``ValueError``)."""
    names = {f.name for f in fields(LawOptions)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"no law option {unknown[0]!r}: the options are {sorted(names)}")
    return replace(DEFAULTS, **{k: v for k, v in values.items() if v is not None})
