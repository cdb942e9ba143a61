"""The law read back and compared with the truth (``read_law`` -> ``LawReport``).

``read_law`` -> ``LawReport``: each pair of types' learned law read back by the law search
(``bgn.laws.search.search_law``: its front and the member chosen within the tolerance, or
"no formula fits"), how masses enter (the head's ``mass_law``), relative errors in quantile
bands of the data's distances (the pair's formula against the learned law, and both against
the true law where the scene is a built-in one of ``bgn.sim``); ``against_truth`` scores the
laws and a fine-tuned formula against the truth (``same_form``: the same form up to
constants). ``bgn.laws.report`` presents them.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy
import torch
from scipy.stats import gaussian_kde

from bgn.laws.options import DEFAULTS, LawOptions
from bgn.laws.sample import calibrate_scale, pair_distances, pair_force_head, sample_law
from bgn.laws.search import Member, R, SearchResult, constant_difference, same_form, search_law
from bgn.laws.terms import law_scale

# f = -dphi/ds, s = r + eps: each law's family, its amplitude A (the softening eps a constant
# of the family where the scene has one), and A's value
TRUE_LAWS = {"spring": "-A*(s - 1)", "r1": "-A/s", "r2": "-A/s**2"}
TRUE_AMPLITUDES = {"spring": 2, "r1": 1, "r2": 1}
_A, _EPS = sympy.Symbol("A", real=True), sympy.Symbol("eps", real=True)


def true_family(scene: Any) -> tuple[sympy.Expr, dict[str, float]] | None:
    """The built-in scene's law (``true_law``) as a family in ``R``: its constants as symbols
    (the amplitude ``A``; the softening ``eps`` where the scene has one) and their values by
    name; None for a scene without a simulator. ``same_form`` judges a law against it."""
    from bgn.sim.nbody import NBodyScene

    if not isinstance(scene, NBodyScene):
        return None
    soft = float(scene.softening)
    expr = sympy.sympify(TRUE_LAWS[scene.potential], locals={"A": _A}).subs(
        "s", R + (_EPS if soft else 0))
    values = {"A": float(TRUE_AMPLITUDES[scene.potential])}
    if soft:
        values["eps"] = soft
    return expr, values


def true_law(scene: Any) -> tuple[sympy.Expr, str] | None:
    """The built-in scene's law in the head's convention (force on a unit mass from a unit
    mass, along u_ij) as a sympy expression of r, and how masses enter it; None for a scene
    without a simulator (``bgn.sim.imported``)."""
    from bgn.sim.nbody import NBodyScene

    if not isinstance(scene, NBodyScene):
        return None
    expr = sympy.sympify(TRUE_LAWS[scene.potential], locals={"A": _A}).subs(
        {"s": R + sympy.nsimplify(scene.softening)}).subs(_A, TRUE_AMPLITUDES[scene.potential])
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
             "coupling": "couplings of either sign: the force is q_i q_j f(r_ij), so a_i = "
                         "(q_i / m_i) sum_j q_j f(r_ij) u_ij, the couplings fitted per "
                         "simulation",
             "other": "neither law of bgn.model.newton"}


SCALE_TEXT = {
    "physical": "physical: the head was trained with the recorded masses (the law loss); the "
                "recorded masses reproduce the training targets with the law times {}",
    "calibrated": "free in the model (the window's mass fit absorbs it): put in physical units "
                  "by least squares against the recorded masses of training frames, factor {}",
    "unit masses": "free in the model, and the data record no masses: put in the units of "
                   "unit masses (physical where every mass is 1) by least squares against "
                   "the training frames, factor {}",
    "unit couplings": "free in the model, shared with the couplings it fits per simulation "
                      "(mass_law=coupling, no recorded ones): in the units of couplings of unit "
                      "root-mean-square per simulation, factor {}",
}


@dataclass
class PairLaw:
    """The law of one pair of types: the grid, the learned law (physical scale), the law
    search's result (``search``: its front and the member chosen, or none), the truth (or
    None), the data's distance histogram and the band errors. ``formula`` is the pair's ONE
    formula, which the report, the figure, the bands and ``against_truth`` all read."""

    types: tuple[int, int]
    r: np.ndarray
    learned: np.ndarray
    search: SearchResult
    truth: np.ndarray | None
    density: np.ndarray        # the data's density of log r on the grid: the search's weights
    hist_edges: np.ndarray
    hist_counts: np.ndarray
    bands: list[dict[str, Any]]
    n_distances: int
    # the formula against the truth's family (``judge_form``), where the truth is known
    truth_in_form: dict[str, Any] | None = None
    # the training distances at DEFAULTS.distance_quantiles: where the data reach (negligible_term)
    reach: np.ndarray | None = None

    @property
    def chosen(self) -> bool:
        """Whether a formula fits: the search chose a member within its tolerance."""
        return self.search.chosen is not None

    @property
    def formula(self) -> Member:
        """The member chosen, or where no formula fits the front's most accurate member (not
        chosen: ``chosen`` is False, and the report says so)."""
        return self.search.chosen if self.search.chosen is not None else self.search.front[-1]


@dataclass
class LawReport:
    """What ``read_law`` finds; ``markdown`` and ``write_report`` present it."""

    scene: str
    model: str
    mass_law: str
    scale: str                 # "physical" | "calibrated" | "unit masses" | "unit couplings"
    scale_factor: float        # applied to the raw law ("calibrated"), else the check's value
    calibration_error: float   # mean relative squared error with the recorded masses
    length_scale: float
    pairs: list[PairLaw]
    truth_text: str | None = None
    truth_masses: str | None = None
    # the truth's family (``true_family``) as text in r and its constants, and their values
    truth_family: str | None = None
    truth_constants: dict[str, float] | None = None

    @property
    def outcome(self) -> str:
        """"formula" where every pair of types' law has a formula, else "no formula fits"."""
        return "formula" if all(p.chosen for p in self.pairs) else "no formula fits"


def relative_error(a: np.ndarray, b: np.ndarray, r: np.ndarray) -> np.ndarray:
    return np.abs(a - b) / law_scale(r, b, smooth=False)


def _bands(law: Callable[[np.ndarray], np.ndarray], distances: np.ndarray, formula: Member,
           truth: sympy.Expr | None) -> list[dict[str, Any]]:
    """Median and largest relative errors in quantile bands of the data's distances, on 48
    log-spaced points in each band: the formula against the learned ``law``, and both
    against the ``truth`` (numbers for its constants) where known."""
    edges = np.quantile(distances, DEFAULTS.band_quantiles)
    truth_f = None if truth is None else sympy.lambdify(R, truth, "numpy")
    rows = []
    for (q0, q1), (lo, hi) in zip(itertools.pairwise(DEFAULTS.band_quantiles),
                                  itertools.pairwise(edges)):
        r = np.geomspace(lo, max(hi, lo * (1 + 1e-9)), 48)
        learned = law(r)
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


def _truth_symbols(constants: dict[str, float]) -> dict[str, Any]:
    return {"r": R, **{name: sympy.Symbol(name, real=True) for name in constants}}


def judge_form(found: sympy.Expr, family: sympy.Expr, constants: dict[str, float],
               r: np.ndarray) -> dict[str, Any]:
    """A found law (constants as numbers) against the truth's ``family`` (its ``constants``
    by name) over the distances ``r``: whether it is the same form up to constants
    (``same_form``), and where it is, the largest relative difference of its constants from
    the truth's in its own family (``constant_difference``: the found family fitted to the
    truth); NaN where the form differs (another form's constants are not the truth's)."""
    symbols = {sympy.Symbol(name, real=True): v for name, v in constants.items()}
    same = same_form(found, family, r, symbols)
    return {"same_form": bool(same),
            "constants_vs_truth": (constant_difference(found, family.subs(symbols), r) if same
                                   else math.nan)}


def read_pair(types: tuple[int, int], distances: np.ndarray,
              law: Callable[[np.ndarray], np.ndarray], options: LawOptions = DEFAULTS,
              truth: tuple[sympy.Expr, dict[str, float]] | None = None) -> PairLaw:
    """One pair of types' learned ``law`` (a function of physical distances, in physical
    units) read back over the data's ``distances`` of that pair: sampled on
    ``options.grid_points`` log-spaced distances over them, each weighted by the data's
    density of log r, and searched (``search_law`` within ``options.tolerance``, with
    ``options.search``); ``truth``: the true law's family and constants (``true_family``),
    which the formula is judged against (``judge_form``)."""
    r = np.geomspace(distances.min(), distances.max(), options.grid_points)
    density = log_density(distances, r)
    learned = law(r)
    found = search_law(r, learned, density, options.tolerance, options.search)
    true, numeric = None, None
    if truth is not None:
        numeric = truth[0].subs({sympy.Symbol(k, real=True): v for k, v in truth[1].items()})
        true = np.broadcast_to(np.asarray(sympy.lambdify(R, numeric, "numpy")(r), np.float64),
                               r.shape).copy()
    edges = np.geomspace(distances.min(), distances.max(), 61)
    pair = PairLaw(types, r, learned, found, true, density, edges,
                   np.histogram(distances, edges)[0], [], len(distances), None,
                   np.quantile(distances, DEFAULTS.distance_quantiles))
    pair.bands = _bands(law, distances, pair.formula, numeric)
    if truth is not None:
        pair.truth_in_form = judge_form(pair.formula.expr, truth[0], truth[1], r)
    return pair


def read_law(module_or_model: Any, dataset: Any, options: LawOptions = DEFAULTS) -> LawReport:
    """The learned pair law of a model with a pair-force head read back by the law search,
    over the distances of ``dataset`` (a ``FrameDataset``: the training split), each pair of
    types by ``read_pair``; see the module doc."""
    model, head = pair_force_head(module_or_model)
    head = copy.deepcopy(head).double().eval()  # the law in float64: smooth to the last digit
    dim = dataset.meta.dim
    pinned = "law" in getattr(model, "heads", ())
    scale = ("physical" if pinned else "unit couplings" if head.mass_law == "coupling"
             else "calibrated" if dataset.meta.masses_known else "unit masses")
    k, error = calibrate_scale(head, _as_double(dataset))
    factor = 1.0 if pinned else k  # the scale the head does not pin, from the data
    truth = true_law(dataset.scene)
    family = true_family(dataset.scene)
    pairs = [read_pair(types, distances,
                       lambda r, types=types: factor * sample_law(head, r, dim, types),
                       options, family)
             for types, distances in pair_distances(dataset).items()]
    return LawReport(
        scene=dataset.meta.name, model=getattr(model, "name", type(model).__name__),
        mass_law=head.mass_law, scale=scale,
        scale_factor=k, calibration_error=error, length_scale=float(head.length_scale),
        pairs=pairs, truth_text=None if truth is None else sympy.sstr(truth[0]),
        truth_masses=None if truth is None else truth[1],
        truth_family=None if family is None else sympy.sstr(family[0]),
        truth_constants=None if family is None else dict(family[1]))


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


def spec_law(pair: dict[str, Any]) -> Callable[[np.ndarray], np.ndarray]:
    """One pair of a ``model.law_formula`` spec as a function of distances (numpy)."""
    from bgn.model.formula_law import pair_expression

    fn = sympy.lambdify(R, pair_expression(pair), "numpy")
    return lambda r: np.broadcast_to(np.asarray(fn(r), np.float64), np.shape(r))


def against_truth(report: LawReport, tuned: list[dict[str, Any]] | None = None,
                  ) -> dict[str, Any]:
    """How far the laws are from the scene's true law at every training distance (empty
    where the truth is unknown): the largest relative error (``relative_error``) of the
    network's law, of the formula read back from it (``PairLaw.formula``) and of the ``tuned``
    spec (the formula fitted to the frames, ``finetune_formula``'s ``tuned``) over the grid of
    the training pairs' distances (``<law>_max``: all of them; ``<law>_max_1_99``: between
    their 1st and 99th percentiles), the worst over the pairs of types. For the read-back and
    the tuned formula also whether the form is the truth's (``<law>_form_is_truth``: the same
    form up to constants, ``judge_form``, for every pair of types; 1 or 0) and where it is,
    the largest relative difference of its constants from the truth's in its own family
    (``<law>_constants_vs_truth``; NaN where the form is not the truth's)."""
    if report.truth_text is None or report.truth_family is None:
        return {}
    constants = report.truth_constants or {}
    family = sympy.sympify(report.truth_family, locals=_truth_symbols(constants))
    tuned_by_types = {tuple(sorted(p["types"])): p for p in tuned or []}
    out: dict[str, Any] = {}

    def worst(key: str, value: float) -> None:
        out[key] = max(out.get(key, -math.inf), value)

    for pair in report.pairs:
        r, true = pair.r, pair.truth  # the truth on the grid (read_law)
        lo, hi = (pair.reach[0], pair.reach[-1]) if pair.reach is not None else (r[0], r[-1])
        inner = (r >= lo) & (r <= hi)
        laws = {"network": pair.learned, "read_back": pair.formula(r)}
        forms = {"read_back": pair.formula.expr}
        spec = tuned_by_types.get(tuple(sorted(pair.types)))
        if spec is not None:
            from bgn.model.formula_law import pair_expression

            laws["tuned"] = spec_law(spec)(r)
            forms["tuned"] = pair_expression(spec)
        for name, expr in forms.items():
            judged = judge_form(expr, family, constants, r)
            out[f"{name}_form_is_truth"] = min(out.get(f"{name}_form_is_truth", 1.0),
                                               float(judged["same_form"]))
            worst(f"{name}_constants_vs_truth", judged["constants_vs_truth"])
        for name, values in laws.items():
            err = relative_error(values, true, r)
            worst(f"{name}_max", float(err.max()))
            worst(f"{name}_max_1_99", float(err[inner].max()) if inner.any() else math.nan)
    for name in ("read_back", "tuned"):  # another form's constants are not the truth's
        if out.get(f"{name}_form_is_truth") == 0.0:
            out[f"{name}_constants_vs_truth"] = math.nan
    return out
