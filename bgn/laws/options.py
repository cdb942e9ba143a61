"""The laws' options, typed: every setting of the law search (``SearchOptions``), the report
and the fine-tuning in frozen dataclasses (``LawOptions``, its ``search`` field the search's),
their defaults the values the figures in docs/results.md were made with. ``python -m
bgn.laws``'s keys (``conf/laws.yaml``: ``max_terms``, ``tolerance``, ``finetune_<key>``) set
the fields of the same names (``from_keys``; ``max_terms`` is the search's), and the formula
stage (``bgn.laws.stage``) reads them; the modules' other settings read ``DEFAULTS``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from bgn.law_table import ZERO_CROSSING_WIDTH


@dataclass(frozen=True)
class SearchOptions:
    """Every setting of the law search (``bgn.laws.search``); the same for every dataset."""

    max_terms: int = 3               # additive terms of the sum at most
    # sums of single primitives: screened on a grid of their constants (linear least squares
    # of every pair and every triple of grid columns), then refined
    exponent_step: float = 0.5       # the grid's exponents: this apart over exponent_range
    grid_shifts: tuple[float, ...] = (-0.6, -0.3, -0.1, 0.03, 0.1, 0.3, 1.0, 3.0)  # c / s
    grid_rates: int = 32             # rates per sign, log-spaced over rate_range
    grid_exponents_shifted: tuple[float, ...] = (-12.0, -6.0, -3.0, -2.0, -1.5, -1.0, -0.5,
                                                 0.5, 1.0, 2.0)  # of shifted powers
    collinear: float = 1e-4          # a pair of grid columns this near collinear is skipped
    refine_per_size: int = 30        # screened sums of each size refined (Levenberg-Marquardt)
    # forms with a product or a common factor: grown a term at a time from the best fits
    product_terms: int = 2           # terms of such a form at most
    beam: int = 3                    # forms of each size grown by one more term
    fixed_starts: int = 4            # fixed starts of a one-term form's constants at most
    child_starts: int = 2            # ... of a grown form's (the parent's fit and the new term's)
    random_starts: int = 6           # starts drawn at random, for the best forms of each size
    random_forms: int = 3            # ... that many of each size (by error), and each front member
    evaluations: int = 40            # residual evaluations per inner constant, per start
    max_exponent: float = 30.0       # a fit with an exponent beyond +-this is refused
    seed: int = 0                    # of the random starts
    potentials: bool = True          # search potentials U(r) too, the law read as -dU/dr
    snap_step: float = 0.5           # exponents rounded to multiples of this ...
    snap_distance: float = 0.15      # ... when within this distance of one
    clean_factor: float = 1.05       # a clean-up step kept while the error stays within this x
    front_margin: float = 0.999      # a more complex member joins the front below this x error
    # a member is chosen only if its error is within the tolerance also on distances held out:
    # this many contiguous ranges of r of equal weight, each predicted by the form refitted
    # on the others
    holdout_blocks: int = 8
    same_form_tolerance: float = 1e-6  # RMS relative residual of one family fitted to the other
    same_form_starts: int = 4        # starts of that fit (the expression's own, then perturbed)
    # ranges the random starts are drawn from (scales: the data's median distance s)
    exponent_range: tuple[float, float] = (-14.0, 4.0)
    rate_range: tuple[float, float] = (0.1, 20.0)   # |k| s (exp, sin); k s^2 (Gaussian)
    shift_range: tuple[float, float] = (-0.9, 2.0)  # c / s (shifted r), c / s^2 (shifted r^2)


SEARCH_DEFAULTS = SearchOptions()


@dataclass(frozen=True)
class LawOptions:
    """The laws' settings (``bgn.laws``): the search (``search``) and the term list's fit
    (``terms``, the baseline it replaced), the sampled law and its comparison (``sample``,
    ``compare``), the report (``report``), the fine-tuning (``finetune``)."""

    # ------------------------------------------------------------- the search (search)
    search: SearchOptions = SEARCH_DEFAULTS
    # a formula within this RMS relative error of the learned law is taken as it (the
    # discrepancy principle: the network's law is no more exact than that); none within it:
    # "no formula fits", and the network law is kept
    tolerance: float = 0.02

    # ------------------------------------------- relative residuals (terms.law_scale)
    # relative residuals: |f| floored near a zero crossing by the change of f over this
    # fraction of r (a spring's law crosses zero at s = 1, where a relative error is undefined)
    zero_crossing_width: float = ZERO_CROSSING_WIDTH
    size_floor: float = 0.01           # of the law's size at the median point: residuals' floor
    significant: int = 4               # digits of the constants in the printed formula
    # the term list's fit (terms.fit_formula: the baseline of examples/heldout_laws)
    c_grid: int = 41                   # values of a nonlinear constant tried before refinement
    c_grid_pair: int = 25              # ... per constant, where a formula has two
    refine_per_complexity: int = 4     # candidates of each complexity refined jointly

    # ------------------------------------------------------- the law on a grid (sample, compare)
    grid_points: int = 240             # log-spaced distances per pair of types
    # "every distance the data reach", robustly: the 1st to 99th percentiles
    distance_quantiles: np.ndarray = field(
        default_factory=lambda: np.linspace(0.01, 0.99, 99))
    kde_points: int = 20_000           # distances the density of log r is estimated from
    band_quantiles: tuple[float, ...] = (0.0, 0.01, 0.1, 0.5, 0.9, 0.99, 1.0)  # error bands
    calibration_frames: int = 256      # training frames that put a free scale in physical units
    max_distances: int = 2_000_000     # pair distances read from the train split (frames thinned)

    # ------------------------------------------------------- the formula as the law (finetune)
    finetune_members: int = 6          # front members tuned on the frames (the chosen first)
    finetune_steps: int = 80           # loss evaluations (Nelder-Mead) per form's constants
    finetune_restarts: int = 1         # ... then as many more from a fresh simplex, this often
    finetune_substeps: int = 16        # model.substeps while the forms are tuned (and written)
    polish_factor: int = 4             # the chosen form polished through this times finer substeps
    finetune_batch_size: int = 512     # training frames of the fixed batch (closest ones first)
    finetune_horizon: int = 50         # validation rollout steps (as bgn.studies.auto's horizon)
    finetune_val_sims: int | None = None  # validation simulations rolled out (None: all)
    finetune_val_rollouts: int = 100   # ... from as many start frames each as give this many
    amplitude_step: float = 0.1        # the first simplex's step in each amplitude (relative)
    c_step: float = 2.0                # ... and its factor on each constant c
    form_tolerance: float = 0.02       # a simpler form is kept while its loss is within this
    negligible: float = 0.01           # a term this small against the law everywhere goes
    # particles per batch of validation rollouts: the job's deadline is checked between
    # batches; a force scene's whole validation split (200 x 4 bodies) is one batch
    rollout_chunk: int = 4096
    typical_floor: float = 1e-9        # added to each error before the geometric mean (exact ones)
    close_share: float = 0.25          # of the tuning batch: the frames with the closest pairs
    robust_scale: float = 0.1          # relative error at which the law loss's Cauchy loss bends
    turn_quantile: float = 1e-3        # of the training distances: below it the law may not turn
    # the distances turning_term checks, times its floor
    below_floor: np.ndarray = field(default_factory=lambda: np.geomspace(1e-3, 1.0, 61))


DEFAULTS = LawOptions()

# the fields python -m bgn.laws sets by their names (conf/laws.yaml; max_terms: the search's)
COMMAND_KEYS = ("max_terms", "tolerance", "finetune_steps", "finetune_substeps",
                "finetune_batch_size", "finetune_horizon", "finetune_val_sims",
                "finetune_val_rollouts")


def from_keys(values: dict[str, Any]) -> LawOptions:
    """``DEFAULTS`` with the given fields set (a key given as None keeps its default); a key
    that names a field of ``SearchOptions`` and none of ``LawOptions`` sets the search's; a
    key that names no field is refused (``ValueError``)."""
    names = {f.name for f in fields(LawOptions)}
    searched = {f.name for f in fields(SearchOptions)} - names
    unknown = sorted(set(values) - names - searched)
    if unknown:
        raise ValueError(f"no law option {unknown[0]!r}: the options are "
                         f"{sorted(names | searched)}")
    given = {k: v for k, v in values.items() if v is not None}
    search = replace(DEFAULTS.search, **{k: v for k, v in given.items() if k in searched})
    return replace(DEFAULTS, search=search, **{k: v for k, v in given.items() if k in names})
