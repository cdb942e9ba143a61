"""The law read back and compared with the truth (``read_law`` -> ``LawReport``).

``read_law`` -> ``LawReport``: the formula, how masses enter (the head's ``mass_law``),
relative errors in quantile bands of the data's distances (formula against the learned
law, and both against the true law where the scene is a built-in one of ``bgn.sim``);
``against_truth`` scores a fine-tuned formula against the truth. ``bgn.laws.report``
presents them.
"""

from __future__ import annotations

import copy
import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy
import torch
from scipy.stats import gaussian_kde

from bgn.laws.options import DEFAULTS
from bgn.laws.sample import calibrate_scale, pair_distances, pair_force_head, sample_law
from bgn.laws.terms import (
    Formula,
    Term,
    fit_formula,
    law_scale,
    refine_constants,
    relative_residual,
)

TRUE_LAWS = {"spring": "-2*(s - 1)", "r1": "-1/s", "r2": "-1/s**2"}  # f = -dphi/ds, s = r + eps


def true_law(scene: Any) -> tuple[sympy.Expr, str] | None:
    """The built-in scene's law in the head's convention (force on a unit mass from a unit
    mass, along u_ij) as a sympy expression of r, and how masses enter it; None for a scene
    without a simulator (``bgn.sim.imported``)."""
    from bgn.sim.nbody import NBodyScene

    if not isinstance(scene, NBodyScene):
        return None
    r = sympy.Symbol("r", positive=True)
    expr = sympy.sympify(TRUE_LAWS[scene.potential]).subs(
        "s", r + sympy.nsimplify(scene.softening))
    # how masses enter: the receiver's acceleration with a heavier source, a heavier receiver
    pos = np.array([[[0.0] * scene.dim, [1.5] + [0.0] * (scene.dim - 1)]])
    unit = scene.accelerations(pos, np.ones(2))[0, 1, 0]
    heavy_source = scene.accelerations(pos, np.array([2.0, 1.0]))[0, 1, 0] / unit
    heavy_receiver = scene.accelerations(pos, np.array([1.0, 2.0]))[0, 1, 0] / unit
    masses = ("source" if np.isclose(heavy_source, 2) and np.isclose(heavy_receiver, 1)
              else "inertial" if np.isclose(heavy_source, 1) and np.isclose(heavy_receiver, 0.5)
              else "other")
    return expr, masses


MASS_TEXT = {"inertial": "none: the force does not depend on the masses, a_i = sum_j f(r_ij) "
                         "u_ij / m_i",
             "source": "both: the force is m_i m_j f(r_ij), so a_i = sum_j m_j f(r_ij) u_ij "
                       "(the receiver's own mass cancels)",
             "type": "none: the force does not depend on the masses, a_i = sum_j f(r_ij) "
                     "u_ij / m_i, one mass per particle type (learned)",
             "other": "neither law of bgn.model.newton"}


SCALE_TEXT = {
    "physical": "physical: the head was trained with the recorded masses (the law loss); the "
                "recorded masses reproduce the training targets with the law times {}",
    "calibrated": "free in the model (the window's mass fit absorbs it): put in physical units "
                  "by least squares against the recorded masses of training frames, factor {}",
    "unit masses": "free in the model, and the data record no masses: put in the units of "
                   "unit masses (physical where every mass is 1) by least squares against "
                   "the training frames, factor {}",
}


@dataclass
class PairLaw:
    """The law of one pair of types: the grid, the learned law (physical scale), the
    formula, the truth (or None), the data's distance histogram and the band errors."""

    types: tuple[int, int]
    r: np.ndarray
    learned: np.ndarray
    formula: Formula
    truth: np.ndarray | None
    density: np.ndarray        # the data's density of log r on the grid: the fit's weights
    hist_edges: np.ndarray
    hist_counts: np.ndarray
    bands: list[dict[str, Any]]
    n_distances: int
    truth_in_form: dict[str, Any] | None = None
    # the training distances at DEFAULTS.distance_quantiles: where the data reach (negligible_term)
    reach: np.ndarray | None = None


@dataclass
class LawReport:
    """What ``read_law`` finds; ``markdown`` and ``write_report`` present it."""

    scene: str
    model: str
    mass_law: str
    scale: str                 # "physical" | "calibrated" | "unit masses" (SCALE_TEXT)
    scale_factor: float        # applied to the raw law ("calibrated"), else the check's value
    calibration_error: float   # mean relative squared error with the recorded masses
    length_scale: float
    pairs: list[PairLaw]
    truth_text: str | None = None
    truth_masses: str | None = None


def relative_error(a: np.ndarray, b: np.ndarray, r: np.ndarray) -> np.ndarray:
    return np.abs(a - b) / law_scale(r, b, smooth=False)


def _bands(head: Any, dim: int, types: tuple[int, int], distances: np.ndarray, factor: float,
           formula: Formula, truth: sympy.Expr | None) -> list[dict[str, Any]]:
    """Median and largest relative errors in quantile bands of the data's distances, on 48
    log-spaced points in each band."""
    edges = np.quantile(distances, DEFAULTS.band_quantiles)
    truth_f = None if truth is None else sympy.lambdify(sympy.Symbol("r", positive=True),
                                                        truth, "numpy")
    rows = []
    for (q0, q1), (lo, hi) in zip(itertools.pairwise(DEFAULTS.band_quantiles),
                                  itertools.pairwise(edges)):
        r = np.geomspace(lo, max(hi, lo * (1 + 1e-9)), 48)
        learned = factor * sample_law(head, r, dim, types)
        fitted = formula(r)
        row = {"quantiles": [q0, q1], "r": [float(lo), float(hi)],
               "formula_vs_learned": _stats(relative_error(fitted, learned, r))}
        if truth_f is not None:
            true = np.broadcast_to(np.asarray(truth_f(r), np.float64), r.shape)
            row["learned_vs_truth"] = _stats(relative_error(learned, true, r))
            row["formula_vs_truth"] = _stats(relative_error(fitted, true, r))
        rows.append(row)
    return rows


def _stats(err: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(err)), "max": float(np.max(err))}


def log_density(distances: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The density of log r of ``distances`` at ``r`` (a Gaussian KDE of at most
    ``DEFAULTS.kde_points`` of them, evenly picked), mean 1 over ``r``."""
    pick = distances[np.unique(np.linspace(0, len(distances) - 1, DEFAULTS.kde_points).astype(int))]
    logs = np.log(pick)
    if np.ptp(logs) == 0:
        return np.ones_like(r)
    density = gaussian_kde(logs)(np.log(r))
    return density / density.mean()


def read_law(module_or_model: Any, dataset: Any, max_terms: int = DEFAULTS.max_terms,
             tolerance: float = DEFAULTS.tolerance, parsimony: float = DEFAULTS.parsimony,
             ) -> LawReport:
    """The learned pair law of a model with a pair-force head as a formula, over the
    distances of ``dataset`` (a ``FrameDataset``: the training split); see the module doc."""
    model, head = pair_force_head(module_or_model)
    head = copy.deepcopy(head).double().eval()  # the law in float64: smooth to the last digit
    dim = dataset.meta.dim
    pinned = "law" in getattr(model, "heads", ())
    scale = ("physical" if pinned else "calibrated" if dataset.meta.masses_known
             else "unit masses")
    k, error = calibrate_scale(head, _as_double(dataset))
    factor = 1.0 if pinned else k  # the scale the head does not pin, from the data
    truth = true_law(dataset.scene)
    pairs = []
    for types, distances in pair_distances(dataset).items():
        r = np.geomspace(distances.min(), distances.max(), DEFAULTS.grid_points)
        density = log_density(distances, r)
        learned = factor * sample_law(head, r, dim, types)
        formula = fit_formula(r, learned, density, max_terms=max_terms, tolerance=tolerance,
                              parsimony=parsimony)
        true = None
        in_form = None
        if truth is not None:
            truth_f = sympy.lambdify(sympy.Symbol("r", positive=True), truth[0], "numpy")
            true = np.broadcast_to(np.asarray(truth_f(r), np.float64), r.shape).copy()
            in_form = _in_form(formula, r, density, true)
        edges = np.geomspace(distances.min(), distances.max(), 61)
        pairs.append(PairLaw(
            types, r, learned, formula, true, density, edges, np.histogram(distances, edges)[0],
            _bands(head, dim, types, distances, factor, formula,
                   None if truth is None else truth[0]), len(distances), in_form,
            np.quantile(distances, DEFAULTS.distance_quantiles)))
    return LawReport(
        scene=dataset.meta.name, model=getattr(model, "name", type(model).__name__),
        mass_law=head.mass_law, scale=scale,
        scale_factor=k, calibration_error=error, length_scale=float(head.length_scale),
        pairs=pairs, truth_text=None if truth is None else sympy.sstr(truth[0]),
        truth_masses=None if truth is None else truth[1])


def _as_double(dataset: Any) -> Any:
    """``dataset`` whose graphs come in float64 (for the float64 copy of the head)."""

    class Double:
        def __len__(self) -> int:
            return len(dataset)

        def __getitem__(self, index: int) -> Any:
            g = dataset[index]
            return type(g)(**{name: (v.double() if isinstance(v, torch.Tensor)
                                     and v.is_floating_point() else v)
                              for name, v in vars(g).items()})

    return Double()


def _in_form(formula: Formula, r: np.ndarray, density: np.ndarray, y: np.ndarray,
             ) -> dict[str, Any]:
    """The truth ``y`` (at ``r``) fitted in the formula's own terms (same weights): its
    constants beside the formula's and its relative residual there (about 0: the form is the
    truth's)."""
    w = np.sqrt(density / density.mean()) / law_scale(r, y, smooth=False)
    values, _ = refine_constants(formula.terms, r, y, w, formula.values)
    res = relative_residual(formula.terms, r, y, w, values)
    return {"values": [float(v) for v in values],
            "relative_difference": [float(abs(a - b) / abs(b)) if b else float("inf")
                                    for a, b in zip(formula.values, values)],
            "residual_rms": float(np.sqrt(np.mean(res * res))),
            "residual_max": float(np.max(np.abs(res)))}


def spec_formula(pair: dict[str, Any]) -> Formula:
    """One pair of types of a ``model.law_formula`` spec (``pair_spec``'s entry) as a
    ``Formula`` (no error estimates)."""
    terms = [Term(t["kind"], t["power"]) for t in pair["terms"]]
    values = np.array([t["a"] for t in pair["terms"]]
                      + [t["c"] for t in pair["terms"] if Term(t["kind"], t["power"]).nonlinear],
                      dtype=np.float64)
    zeros = np.zeros_like(values)
    return Formula(terms, values, zeros, zeros, 0.0, len(values))


def against_truth(report: LawReport, tuned: list[dict[str, Any]] | None = None,
                  ) -> dict[str, Any]:
    """How far the laws are from the scene's true law at every training distance (empty
    where the truth is unknown): the largest relative error (``relative_error``) of the network's
    law, of the formula read back from it and of the ``tuned`` spec (the formula fitted to
    the frames, ``finetune_formula``'s ``tuned``) over the grid of the training pairs'
    distances (``<law>_max``: all of them; ``<law>_max_1_99``: between their 1st and 99th
    percentiles), the worst over the pairs of types. For the tuned formula also whether its
    form is the truth's (``tuned_form_is_truth``: the truth fitted in its terms leaves a
    relative residual below ``DEFAULTS.truth_form``; 1 or 0) and the largest relative difference of
    its constants from the truth's in that form (``tuned_constants_vs_truth``)."""
    if report.truth_text is None:
        return {}
    tuned_by_types = {tuple(p["types"]): spec_formula(p) for p in tuned or []}
    out: dict[str, Any] = {}

    def worst(key: str, value: float) -> None:
        out[key] = max(out.get(key, -math.inf), value)

    for pair in report.pairs:
        r, true = pair.r, pair.truth  # the truth on the grid (read_law)
        lo, hi = (pair.reach[0], pair.reach[-1]) if pair.reach is not None else (r[0], r[-1])
        inner = (r >= lo) & (r <= hi)
        laws = {"network": pair.learned, "read_back": pair.formula(r)}
        formula = tuned_by_types.get(tuple(pair.types))
        if formula is not None:
            laws["tuned"] = formula(r)
            in_form = _in_form(formula, r, pair.density, true)
            worst("tuned_form_is_truth_residual", in_form["residual_max"])
            worst("tuned_constants_vs_truth", max(in_form["relative_difference"]))
        for name, values in laws.items():
            err = relative_error(values, true, r)
            worst(f"{name}_max", float(err.max()))
            worst(f"{name}_max_1_99", float(err[inner].max()) if inner.any() else math.nan)
    if "tuned_form_is_truth_residual" in out:
        out["tuned_form_is_truth"] = float(out["tuned_form_is_truth_residual"]
                                           < DEFAULTS.truth_form)
        if not out["tuned_form_is_truth"]:  # constants of another form are not the truth's
            out["tuned_constants_vs_truth"] = math.nan
    return out
