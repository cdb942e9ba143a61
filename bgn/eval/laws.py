"""The learned pair law as a formula: ``python -m bgn.laws <run folder or checkpoint>
[finetune=true] ...`` (``main``; ``--help`` lists the keys).

A pair-force head (``bgn.model.newton``: ``model=newton``, or BGN with
``model.dynamics=newton``) learns a scene's interaction as an MLP ``f(r)`` of the pair's
distance (and types): the force on particle i from j is ``f(r_ij) u_ij``, ``u_ij`` the unit
vector from j to i (positive: repulsive). This module reads that law back:

1. ``sample_law``: ``f`` on a log-spaced grid over the distances of the training split's pairs
   (per pair of types where the law reads types), through the head's own ``pair_terms``; r in
   the data's units. The law's scale is physical where the head was trained with the recorded
   masses (BGN's ``law`` loss); where the window's mass fit absorbs it (``model=newton``, BGN
   without the law loss) only the shape is learned, and ``calibrate_scale`` puts it in physical
   units by least squares against the recorded masses of training frames (said in the report).
2. ``fit_formula``: sparse regression over a library of candidate terms (``default_library``:
   powers ``r^p`` (Lennard-Jones' among them), ``log r``, ``exp(-r/c)``, softened ``(r + c)^p``
   and ``(r^2 + c^2)^(p/2)``, a constant): every subset of up to ``max_terms`` terms with at
   most one nonlinear term, or one such term twice with two constants (Morse's force is two
   exponentials), each c on a grid with the amplitudes solved by linear least squares; the
   best few of each complexity (number of constants) refined jointly by
   ``scipy.optimize.least_squares``. Residuals are relative (``law_scale``), each distance
   weighted by the training data's density of log r: the loss is the mean squared relative
   error over the training pairs, so sparsely visited distances (a close encounter) do not
   steer the form, and the band table shows how the formula extrapolates there. The formula
   chosen is the simplest whose RMS relative error is within ``tolerance`` of the learned law
   (the discrepancy principle: the network's law is no more exact than that), else PySR's
   rule for the "best" model (Cranmer 2023, arXiv:2305.01582): on the front of loss against
   complexity, the largest drop of log-loss per added constant among the models within
   ``parsimony`` times the lowest loss. Constants get standard errors from the Jacobian
   (covariance scaled by the residual variance) and from a bootstrap over the sampled points;
   both say how well the learned curve pins them, not how far the network's law is from the
   truth, which the band table shows.
3. ``read_law`` -> ``LawReport``: the formula, how masses enter (the head's ``mass_law``),
   relative errors in quantile bands of the data's distances (formula against the learned
   law, and both against the true law where the scene is a built-in one of ``bgn.sim``);
   ``write_report`` writes report.md, law.csv, law.json and law.png; ``law_section`` gives
   the markdown for an evaluation report.
4. ``finetune=true`` (``finetune_formula``): the formula as the model's law (``model.law=formula``,
   ``model.law_formula``: ``formula_spec``'s JSON, ``bgn.model.formula_law``). Every form on
   the fit's front, every one-term form of the library and every nonlinear term twice
   (``candidate_specs``) has its constants fitted to the frames (``tune_constants``:
   Nelder-Mead on the head's law loss under a Cauchy loss, ``law_objective``, through
   ``model.substeps``: a frame's finite-difference target averages the force over the frame)
   and is pruned of the terms the frames do not need (``prune_terms``); the lowest loss wins,
   and its constants are polished through finer substeps (``polish_constants``). The network
   law and the formula are then scored on the validation rollouts (``bgn.studies.auto``'s
   protocol) and the better chosen; ``<run>/laws/formula.ckpt`` (with its
   ``train_config.yaml``) loads as any checkpoint. ``model.law=auto`` runs this after training
   (``law_stage``).

Libraries. PySR (symbolic regression, Cranmer's route) downloads and compiles Julia at run
time: not possible without network. PySINDy (installs from PyPI, with scikit-learn) fits
libraries linear in their coefficients only: the softening ``c`` of ``(r + c)^p`` must be a
fixed grid of columns, nearly collinear with each other and with the plain powers. Tried on
this library (c on a grid) with the noisy laws of tests/test_laws.py, its STLSQ and SR3 kept
tens of terms at any threshold tried, not the one or two of the law
(docs/notes/2026-11-26-results-history.md, "Laws read back as formulas"). An
exhaustive search over subsets of up to three terms is exact where a sparse relaxation is a
heuristic, and takes seconds: numpy, scipy and sympy (already dependencies) suffice.
"""

from __future__ import annotations

import copy
import csv
import io
import itertools
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import sympy
import torch
from scipy.optimize import least_squares, minimize
from scipy.signal import savgol_filter
from scipy.stats import gaussian_kde

from bgn.training.budget import NO_DEADLINE, Deadline, OutOfTime, check, clock_text
from bgn.training.validate import cli

log = logging.getLogger("bgn.train")

# relative residuals: |f| floored near a zero crossing by the change of f over this fraction
# of r (a spring's law crosses zero at s = 1, where a plain relative error is undefined)
ZERO_CROSSING_WIDTH = 0.1
SIZE_FLOOR = 0.01                 # of the law's size at the median point (fit_formula)
GRID_POINTS = 240                 # log-spaced distances per pair of types
DISTANCE_QUANTILES = np.linspace(0.01, 0.99, 99)  # "every distance the data reach", robustly
KDE_POINTS = 20_000               # distances the density of log r is estimated from
BAND_QUANTILES = (0.0, 0.01, 0.1, 0.5, 0.9, 0.99, 1.0)  # bands of the error table
C_GRID = 41                       # values of a nonlinear constant tried before refinement
C_GRID_PAIR = 25                  # ... per constant, where a formula has two
REFINE_PER_COMPLEXITY = 4         # candidates of each complexity refined jointly
CALIBRATION_FRAMES = 256          # training frames that put a free scale in physical units
MAX_DISTANCES = 2_000_000         # pair distances read from the train split (frames thinned)
SIGNIFICANT = 4                   # digits of the constants in the printed formula
# a formula within this RMS relative error of the learned law is taken as it (module doc)
TOLERANCE = 0.02

# ----------------------------------------------------------------------------- library

TERM_KINDS = ("const", "power", "log", "exp", "shifted", "plummer")


@dataclass(frozen=True)
class Term:
    """A candidate term: ``const``, ``power`` r^p, ``log`` log r, and with a constant c > 0,
    ``exp`` exp(-r / c), ``shifted`` (r + c)^p, ``plummer`` (r^2 + c^2)^(p/2)."""

    kind: str
    power: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in TERM_KINDS:
            raise ValueError(f"term kind {self.kind!r}; choose one of {TERM_KINDS}")

    @property
    def nonlinear(self) -> bool:
        return self.kind in ("exp", "shifted", "plummer")

    def __call__(self, r: np.ndarray, c: float = 1.0) -> np.ndarray:
        p = self.power
        if self.kind == "const":
            return np.ones_like(r)
        if self.kind == "power":
            return r**p
        if self.kind == "log":
            return np.log(r)
        if self.kind == "exp":
            return np.exp(-r / c)
        if self.kind == "shifted":
            return (r + c) ** p
        return (r * r + c * c) ** (p / 2)

    def expr(self, r: sympy.Symbol, c: Any) -> sympy.Expr:
        p = sympy.nsimplify(self.power)
        return {"const": lambda: sympy.Integer(1), "power": lambda: r**p,
                "log": lambda: sympy.log(r), "exp": lambda: sympy.exp(-r / c),
                "shifted": lambda: (r + c) ** p,
                "plummer": lambda: (r**2 + c**2) ** (p / 2)}[self.kind]()

    @property
    def label(self) -> str:
        return str(self.expr(sympy.Symbol("r"), sympy.Symbol("c")))


def default_library() -> list[Term]:
    """The candidate terms (see the module doc): also the powers of Lennard-Jones' force (-13,
    -7) and its potential (-12, -6). Shifted powers 1, 2, 3 are left out: they are polynomials
    the plain powers already span, and would only make c arbitrary."""
    powers = (-13, -12, -7, -6, -4, -3, -2.5, -2, -1.5, -1, -0.5, 0.5, 1, 1.5, 2, 3)
    return ([Term("const"), Term("log")] + [Term("power", p) for p in powers]
            + [Term("exp")] + [Term("shifted", p) for p in (-3, -2, -1.5, -1, -0.5, 0.5)]
            + [Term("plummer", p) for p in (-3, -2, -1)])


# ----------------------------------------------------------------------------- fitting


def law_scale(r: np.ndarray, y: np.ndarray, smooth: bool = True) -> np.ndarray:
    """The size relative errors are taken against: ``sqrt(f^2 + (w r f')^2)``, w =
    ``ZERO_CROSSING_WIDTH``: |f| within a few % for power laws, finite where f crosses zero.
    ``smooth``: f is smoothed first (Savitzky-Golay along the sorted grid), for noisy points."""
    y = np.asarray(y, dtype=np.float64)
    if smooth and len(y) >= 7:
        y = savgol_filter(y, min(21, len(y) - 1 + len(y) % 2), 3)  # an odd window
    slope = np.gradient(y, np.log(r))
    size = np.sqrt(y * y + (ZERO_CROSSING_WIDTH * slope) ** 2)
    return np.maximum(size, 1e-12 * (size.max() + 1e-300))


@dataclass
class Formula:
    """A fitted law ``sum_k a_k term_k(r; c_k)``; ``values`` holds the amplitudes, then one
    constant c per nonlinear term (in the terms' order); ``stderr`` from the Jacobian,
    ``boot_std`` from a bootstrap over the points; ``loss`` the weighted mean squared relative
    residual; ``front`` the best formula of each complexity (number of constants)."""

    terms: list[Term]
    values: np.ndarray
    stderr: np.ndarray
    boot_std: np.ndarray
    loss: float
    complexity: int
    front: list[dict[str, Any]] = field(default_factory=list)
    # (terms, values) of each formula on the front: forms the fine-tuning may prefer on the
    # frames themselves (finetune_formula), where the network's law is off
    alternatives: list[tuple[list[Term], np.ndarray]] = field(default_factory=list)

    @property
    def cs(self) -> list[float]:
        return [float(v) for v in self.values[len(self.terms):]]

    @property
    def names(self) -> list[str]:
        n = len(self.cs)
        return ([f"a{k + 1}" for k in range(len(self.terms))]
                + (["c"] if n == 1 else [f"c{k + 1}" for k in range(n)]))

    def __call__(self, r: np.ndarray) -> np.ndarray:
        return design(self.terms, np.asarray(r, np.float64), self.cs) @ self.values[
            :len(self.terms)]

    def expr(self, digits: int = SIGNIFICANT) -> sympy.Expr:
        r = sympy.Symbol("r", positive=True)
        cs = iter(self.cs)
        return sum((sympy.Float(a, digits) * t.expr(r, sympy.Float(next(cs), digits)
                                                    if t.nonlinear else None)
                    for a, t in zip(self.values, self.terms)), sympy.Integer(0))

    @property
    def text(self) -> str:
        return sympy.sstr(self.expr())

    def constants(self) -> list[dict[str, Any]]:
        """One row per constant: name, the term it belongs to, value, errors."""
        owners = [t.label for t in self.terms if t.nonlinear]
        labels = [t.label for t in self.terms] + [f"c of {o}" for o in owners]
        return [{"name": n, "term": lab, "value": float(v), "stderr": float(s),
                 "bootstrap_std": float(b)}
                for n, lab, v, s, b in zip(self.names, labels, self.values, self.stderr,
                                           self.boot_std)]


def design(terms: list[Term], r: np.ndarray, cs: list[float] | tuple[float, ...] = ()
           ) -> np.ndarray:
    """(n, K) the terms' values at r; ``cs``: the constants of the nonlinear terms, in order."""
    it = iter(cs)
    return np.stack([t(r, next(it)) if t.nonlinear else t(r) for t in terms], axis=1)


def _residual(terms: list[Term], r: np.ndarray, y: np.ndarray, w: np.ndarray,
              values: np.ndarray) -> np.ndarray:
    """Weighted residual of ``values`` (amplitudes, then constants); huge where not finite."""
    k = len(terms)
    with np.errstate(all="ignore"):
        out = (design(terms, r, values[k:]) @ values[:k] - y) * w
    return np.where(np.isfinite(out), out, 1e6)


def _solve(cols: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted linear least squares: amplitudes and the mean squared residual."""
    amps = np.linalg.lstsq(cols, b, rcond=None)[0]
    res = cols @ amps - b
    return amps, float(np.mean(res * res))


def _subset_losses(cols: np.ndarray, b: np.ndarray, subsets: np.ndarray) -> np.ndarray:
    """(m,) mean squared residual of the least-squares fit of ``b`` by each subset (m, k) of
    the columns (n, K), all at once through the normal equations of unit-norm columns (a
    ranking; the models kept are solved again by ``_solve`` and ``_refine``)."""
    norm = np.linalg.norm(cols, axis=0)
    unit = cols / np.where(norm > 0, norm, 1)
    gram, proj = unit.T @ unit, unit.T @ b
    g = gram[subsets[:, :, None], subsets[:, None, :]]             # (m, k, k)
    v = proj[subsets]                                               # (m, k)
    g = g + 1e-10 * np.eye(subsets.shape[1])                        # collinear subsets
    explained = (v * np.linalg.solve(g, v[..., None])[..., 0]).sum(1)
    return np.maximum(b @ b - explained, 0) / len(b)


def _refine(terms: list[Term], r: np.ndarray, y: np.ndarray, w: np.ndarray, x0: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray | None]:
    """Joint least squares of the amplitudes and the log of each constant from ``x0``
    (amplitudes, constants); (values, Jacobian in those values), or the start and None where
    the fit fails."""
    k = len(terms)

    def residual(theta: np.ndarray) -> np.ndarray:
        with np.errstate(over="ignore"):
            return _residual(terms, r, y, w, np.concatenate([theta[:k], np.exp(theta[k:])]))

    theta0 = np.concatenate([x0[:k], np.log(x0[k:])])
    try:
        sol = least_squares(residual, theta0, method="lm" if len(r) > len(theta0) else "trf",
                            x_scale="jac")
    except (ValueError, np.linalg.LinAlgError):
        return x0, None
    with np.errstate(over="ignore"):
        values = np.concatenate([sol.x[:k], np.exp(sol.x[k:])])
    if not np.isfinite(values).all() or (values[k:] <= 0).any():
        return x0, None  # a constant ran off to 0 or infinity: keep the start
    jac = sol.jac.copy()
    jac[:, k:] = jac[:, k:] / values[k:]  # d/dc = d/dlog c / c
    return values, jac


def _candidates(r: np.ndarray, b: np.ndarray, w: np.ndarray, library: list[Term],
                max_terms: int, max_constants: int,
                ) -> dict[tuple[int, int], list[tuple[float, list[Term], np.ndarray]]]:
    """The best few formulas of each complexity (constants: amplitudes and c's) and number
    of nonlinear terms, by their weighted loss: every subset of up to ``max_terms`` terms
    with at most ``max_constants`` nonlinear terms (two: the same term twice), each c on a
    grid; (loss, terms, amplitudes then c's)."""
    linear = [t for t in library if not t.nonlinear]
    nonlinear = [t for t in library if t.nonlinear]
    lin_cols = np.stack([t(r) * w for t in linear], 1)
    n_lin = len(linear)
    found: dict[tuple[int, int], list[tuple[float, list[Term], np.ndarray]]] = {}

    def keep(n_nl: int, loss: float, terms: list[Term], cs: tuple[float, ...]) -> None:
        if not np.isfinite(loss):
            return
        amps = _solve(design(terms, r, cs) * w[:, None], b)[0]
        found.setdefault((len(terms) + len(cs), n_nl), []).append(
            (loss, terms, np.concatenate([amps, cs])))

    for n_nl in range(min(max_constants, max_terms) + 1):
        grid = np.geomspace(r[0] * 1e-2, r[-1] * 2, C_GRID if n_nl < 2 else C_GRID_PAIR)
        for k in range(max_terms - n_nl + 1):
            if k + n_nl == 0:
                continue
            subsets = np.array([(*s, *range(n_lin, n_lin + n_nl))
                                for s in itertools.combinations(range(n_lin), k)],
                               dtype=np.intp).reshape(-1, k + n_nl)
            for extra in itertools.combinations_with_replacement(nonlinear, n_nl):
                if len(set(extra)) > 1:
                    continue  # two constants: one term twice (Morse: two exponentials)
                best = np.full(len(subsets), np.inf)
                best_cs = np.zeros((len(subsets), n_nl))
                for cs in itertools.combinations(grid, n_nl):
                    with np.errstate(all="ignore"):
                        cols = [t(r, c) * w for t, c in zip(extra, cs)]
                    if not all(np.isfinite(col).all() for col in cols):
                        continue
                    losses = _subset_losses(np.column_stack([lin_cols, *cols]), b, subsets)
                    better = losses < best
                    best[better], best_cs[better] = losses[better], cs
                for i in np.argsort(best)[:REFINE_PER_COMPLEXITY]:
                    keep(n_nl, float(best[i]), [*(linear[j] for j in subsets[i][:k]), *extra],
                         tuple(best_cs[i]))
    return found


def fit_formula(r: np.ndarray, y: np.ndarray, weight: np.ndarray | None = None,
                max_terms: int = 3, max_constants: int = 2, tolerance: float = TOLERANCE,
                parsimony: float = 1.5, library: list[Term] | None = None,
                scale: np.ndarray | None = None, n_boot: int = 100, seed: int = 0) -> Formula:
    """The sparse formula of ``y(r)`` (see the module doc). ``r`` > 0; ``weight``: how much
    each point counts (default alike); ``max_constants``: nonlinear terms (each with its c)
    at most; ``scale``: the size residuals are relative to (default ``law_scale`` of the
    data). The loss is the weighted mean squared relative residual; the formula chosen is the
    simplest whose RMS relative residual is within ``tolerance``, else PySR's rule with
    ``parsimony``."""
    order = np.argsort(r)
    r, y = np.asarray(r, np.float64)[order], np.asarray(y, np.float64)[order]
    share = np.ones_like(r) if weight is None else np.asarray(weight, np.float64)[order]
    if not (np.isfinite(share).all() and (share >= 0).all() and share.sum() > 0):
        raise ValueError("the weights of a formula's points must be finite, >= 0, not all 0")
    if scale is not None:
        scale = np.asarray(scale, np.float64)[order]
    kept = share > 0  # points of weight 0 take no part, not even in the relative scale
    r, y, share = r[kept], y[kept], share[kept]
    scale = None if scale is None else scale[kept]
    if len(r) < 8 or not (r > 0).all() or not np.isfinite(y).all():
        raise ValueError(f"a formula needs >= 8 finite points at r > 0 of weight > 0; got "
                         f"{len(r)} points, {int((r <= 0).sum())} at r <= 0, "
                         f"{int((~np.isfinite(y)).sum())} not finite")
    if scale is None:
        scale = law_scale(r, y)
        # a law far weaker than where most points are (beyond a cut-off) counts in absolute
        # terms: its relative error there would be the network's noise over nothing
        middle = scale[np.searchsorted(np.cumsum(share), share.sum() / 2)]
        scale = np.maximum(scale, SIZE_FLOOR * middle)
    w = np.sqrt(share / share.mean()) / scale
    b = y * w
    candidates = _candidates(r, b, w, default_library() if library is None else library,
                             max_terms, max_constants)
    refined: dict[int, tuple[float, list[Term], np.ndarray, np.ndarray | None]] = {}
    for (complexity, _), found in candidates.items():
        for _, terms, x0 in sorted(found, key=lambda e: e[0])[:REFINE_PER_COMPLEXITY]:
            loss0 = float(np.mean(_residual(terms, r, y, w, x0) ** 2))
            values, jac = _refine(terms, r, y, w, x0)
            loss = float(np.mean(_residual(terms, r, y, w, values) ** 2))
            if loss > loss0:
                values, jac, loss = x0, None, loss0
            if complexity not in refined or loss < refined[complexity][0]:
                refined[complexity] = (loss, terms, values, jac)
    # PySR's "best": on the front of loss against complexity, the largest drop of log-loss
    # per constant among the models within `parsimony` times the lowest loss
    floor = 1e-300
    last_loss, last_c = float(np.mean(b * b)) + floor, 0  # the zero law
    best_loss = min(v[0] for v in refined.values())
    front: list[dict[str, Any]] = []
    chosen, chosen_score = None, -np.inf
    for complexity in sorted(refined):
        loss, terms, values, jac = refined[complexity]
        if loss >= last_loss:
            continue
        score = -(math.log(loss + floor) - math.log(last_loss)) / (complexity - last_c)
        front.append({"complexity": complexity, "loss": loss, "score": score,
                      "terms": [t.label for t in terms]})
        if loss <= parsimony * best_loss + floor and score > chosen_score:
            chosen, chosen_score = complexity, score
        last_loss, last_c = loss, complexity
    assert chosen is not None  # the lowest loss is on the front
    # the discrepancy principle: the simplest formula as close to the points as they are
    # trusted to be (the network's law is not exact either)
    good = [e["complexity"] for e in front if math.sqrt(e["loss"]) <= tolerance]
    chosen = good[0] if good else chosen
    loss, terms, values, jac = refined[chosen]
    n, p = len(r), len(values)
    stderr = np.full(p, np.nan)
    if jac is not None and n > p:
        # columns scaled to unit norm first: constants of very different sizes (Morse's
        # amplitudes and decay lengths) would otherwise fall below pinv's cut-off
        norm = np.linalg.norm(jac, axis=0)
        norm = np.where(norm > 0, norm, 1)
        unit = jac / norm
        cov = np.linalg.pinv(unit.T @ unit) / np.outer(norm, norm) * loss * n / (n - p)
        stderr = np.sqrt(np.clip(np.diag(cov), 0, None))
    rng = np.random.default_rng(seed)
    boots = []
    for _ in range(n_boot):
        pick = np.sort(rng.integers(0, n, n))
        boots.append(_refine(terms, r[pick], y[pick], w[pick], values)[0])
    boot_std = np.std(boots, axis=0) if boots else np.full(p, np.nan)
    alternatives = [(refined[e["complexity"]][1], np.asarray(refined[e["complexity"]][2],
                                                             np.float64)) for e in front]
    return Formula(terms, np.asarray(values, np.float64), stderr, boot_std, loss, chosen, front,
                   alternatives)


# ----------------------------------------------------------------------------- the model's law


def pair_force_head(module_or_model: Any) -> tuple[Any, Any]:
    """(model, its ``PairForceHead``) of a LightningModule or model; a model without one is
    refused in one line."""
    from bgn.model.newton import pair_force_head_of

    model = getattr(module_or_model, "model", module_or_model)
    head = pair_force_head_of(model)
    if head is None:
        name = getattr(model, "name", type(model).__name__)
        scene = getattr(getattr(model, "meta", None), "name", "?")
        raise ValueError(f"the {name} model of {scene} has no pair-force head, so it has no "
                         "law to read: train model=newton, or model=bgn model.dynamics=newton, "
                         "on a pairwise-force scene")
    return model, head


@torch.no_grad()
def sample_law(head: Any, r: np.ndarray, dim: int, types: tuple[int, int] = (0, 0),
               ) -> np.ndarray:
    """The head's law ``f(r)`` at physical distances ``r`` between a particle of type
    ``types[0]`` (the source) and one of ``types[1]``, through the head's own ``pair_terms``
    (a two-particle graph, one edge): whatever inputs the law reads, they are read so."""
    param = next(head.parameters())
    pos = torch.zeros(2, len(r), dim, dtype=param.dtype, device=param.device)
    pos[1, :, 0] = torch.as_tensor(np.asarray(r), dtype=param.dtype)
    g = SimpleNamespace(edge_index=torch.tensor([[0], [1]], device=param.device),
                        types=torch.tensor(types, device=param.device))
    return head.pair_terms(g, pos)[0, :, 0].double().cpu().numpy()


def pair_distances(dataset: Any) -> dict[tuple[int, int], np.ndarray]:
    """The distances of every pair of particles at the frames of ``dataset``'s simulations
    (a ``FrameDataset``; frames thinned evenly beyond ``MAX_DISTANCES``), per pair of types
    (sorted; all (0, 0) where the scene has one type). On a radius graph only the pairs within
    its reach: beyond it a pair has no edge, and the law no force to learn."""
    from bgn.data.edges import minimum_image

    file, sims = dataset.file, list(dataset.sims)
    n = dataset.meta.n_particles
    reach = np.inf
    if dataset.meta.graph == "radius":
        reach = float(dataset.margin) + 2 * float(np.max(file.read("radii", ...), initial=0.0))
    i, j = np.triu_indices(n, k=1)
    stride = max(1, math.ceil(len(sims) * file.n_frames * len(i) / MAX_DISTANCES))
    found: dict[tuple[int, int], list[np.ndarray]] = {}
    for s in sims:
        x = np.asarray(file.read("positions", (s, slice(None, None, stride))), np.float64)
        r = np.sqrt((minimum_image(x[:, i] - x[:, j], dataset.meta.period) ** 2).sum(-1))
        types = (np.asarray(file.read("types", s)) if dataset.meta.n_types > 1
                 else np.zeros(n, dtype=np.int64))
        lo, hi = np.minimum(types[i], types[j]), np.maximum(types[i], types[j])
        for a, b in sorted(set(zip(lo.tolist(), hi.tolist()))):
            found.setdefault((a, b), []).append(r[:, (lo == a) & (hi == b)].ravel())
    # coincident particles (r = 0) have no direction, and no place on a log-r grid
    kept = {k: d[(d > 0) & (d <= reach)] for k, v in found.items() if (d := np.concatenate(v)).size}
    return {k: d for k, d in kept.items() if d.size}


@torch.no_grad()
def calibrate_scale(head: Any, dataset: Any, frames: int = CALIBRATION_FRAMES,
                    ) -> tuple[float, float]:
    """(k, relative error): the factor that puts the law in physical units, by least squares
    of the head's prediction with the recorded masses against the training targets (relative,
    as ``newton.law_loss``), and the mean relative squared error of ``k`` times the prediction
    (how well the recorded masses and the law explain the targets)."""
    from bgn.data.frames import evenly_spaced
    from bgn.graph import collate

    idx = evenly_spaced(len(dataset), frames)
    pred, target = [], []
    for start in range(0, len(idx), 64):
        g = collate([dataset[k] for k in idx[start:start + 64]])
        pred.append(head(g, known_masses=True)[0].double())
        target.append(g.target.double())
    p, t = torch.cat(pred), torch.cat(target)
    size = (t * t).sum(-1)
    w = 1 / (size + 1e-4 * size.mean() + 1e-300)
    k = float((w * (p * t).sum(-1)).sum() / (w * (p * p).sum(-1)).sum().clamp_min(1e-300))
    error = float((w * ((k * p - t) ** 2).sum(-1)).mean())
    return k, error


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
    # the training distances at DISTANCE_QUANTILES: where the data reach (negligible_term)
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


def _rel_error(a: np.ndarray, b: np.ndarray, r: np.ndarray) -> np.ndarray:
    return np.abs(a - b) / law_scale(r, b, smooth=False)


def _bands(head: Any, dim: int, types: tuple[int, int], distances: np.ndarray, factor: float,
           formula: Formula, truth: sympy.Expr | None) -> list[dict[str, Any]]:
    """Median and largest relative errors in quantile bands of the data's distances, on 48
    log-spaced points in each band."""
    edges = np.quantile(distances, BAND_QUANTILES)
    truth_f = None if truth is None else sympy.lambdify(sympy.Symbol("r", positive=True),
                                                        truth, "numpy")
    rows = []
    for (q0, q1), (lo, hi) in zip(itertools.pairwise(BAND_QUANTILES), itertools.pairwise(edges)):
        r = np.geomspace(lo, max(hi, lo * (1 + 1e-9)), 48)
        learned = factor * sample_law(head, r, dim, types)
        fitted = formula(r)
        row = {"quantiles": [q0, q1], "r": [float(lo), float(hi)],
               "formula_vs_learned": _stats(_rel_error(fitted, learned, r))}
        if truth_f is not None:
            true = np.broadcast_to(np.asarray(truth_f(r), np.float64), r.shape)
            row["learned_vs_truth"] = _stats(_rel_error(learned, true, r))
            row["formula_vs_truth"] = _stats(_rel_error(fitted, true, r))
        rows.append(row)
    return rows


def _stats(err: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(err)), "max": float(np.max(err))}


def log_density(distances: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The density of log r of ``distances`` at ``r`` (a Gaussian KDE of at most
    ``KDE_POINTS`` of them, evenly picked), mean 1 over ``r``."""
    pick = distances[np.unique(np.linspace(0, len(distances) - 1, KDE_POINTS).astype(int))]
    logs = np.log(pick)
    if np.ptp(logs) == 0:
        return np.ones_like(r)
    density = gaussian_kde(logs)(np.log(r))
    return density / density.mean()


def read_law(module_or_model: Any, dataset: Any, max_terms: int = 3,
             tolerance: float = TOLERANCE, parsimony: float = 1.5) -> LawReport:
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
        r = np.geomspace(distances.min(), distances.max(), GRID_POINTS)
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
            np.quantile(distances, DISTANCE_QUANTILES)))
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
    values, _ = _refine(formula.terms, r, y, w, formula.values)
    res = _residual(formula.terms, r, y, w, values)
    return {"values": [float(v) for v in values],
            "relative_difference": [float(abs(a - b) / abs(b)) if b else float("inf")
                                    for a, b in zip(formula.values, values)],
            "residual_rms": float(np.sqrt(np.mean(res * res))),
            "residual_max": float(np.max(np.abs(res)))}


TRUTH_FORM = 1e-3  # the truth fitted in a formula's terms leaves less: the form is the truth's


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
    where the truth is unknown): the largest relative error (``_rel_error``) of the network's
    law, of the formula read back from it and of the ``tuned`` spec (the formula fitted to
    the frames, ``finetune_formula``'s ``tuned``) over the grid of the training pairs'
    distances (``<law>_max``: all of them; ``<law>_max_1_99``: between their 1st and 99th
    percentiles), the worst over the pairs of types. For the tuned formula also whether its
    form is the truth's (``tuned_form_is_truth``: the truth fitted in its terms leaves a
    relative residual below ``TRUTH_FORM``; 1 or 0) and the largest relative difference of
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
            err = _rel_error(values, true, r)
            worst(f"{name}_max", float(err.max()))
            worst(f"{name}_max_1_99", float(err[inner].max()) if inner.any() else math.nan)
    if "tuned_form_is_truth_residual" in out:
        out["tuned_form_is_truth"] = float(out["tuned_form_is_truth_residual"] < TRUTH_FORM)
        if not out["tuned_form_is_truth"]:  # constants of another form are not the truth's
            out["tuned_constants_vs_truth"] = math.nan
    return out


def truth_markdown(truth: dict[str, Any], truth_text: str | None) -> list[str]:
    """``against_truth``'s figures as a paragraph (none where the truth is unknown)."""
    if not truth:
        return []
    laws = [(k, name) for k, name in (("network", "the network's"),
                                      ("read_back", "the formula read back from it"),
                                      ("tuned", "the fine-tuned formula"))
            if f"{k}_max" in truth]
    text = ("Against the scene's true law `" + str(truth_text) + "`, the largest relative "
            "error over the training distances (between their 1st and 99th percentiles in "
            "brackets): " + "; ".join(f"{name} {_g(truth[f'{k}_max'], 2)} "
                                       f"({_g(truth[f'{k}_max_1_99'], 2)})" for k, name in laws)
            + ".")
    if "tuned_form_is_truth" in truth:
        text += (f" The fine-tuned form is the truth's, its constants within "
                 f"{_g(truth['tuned_constants_vs_truth'], 2)} of the truth's."
                 if truth["tuned_form_is_truth"] else " The fine-tuned form is NOT the truth's.")
    return [text, ""]


# ----------------------------------------------------------------------------- presenting


def _g(x: float, digits: int = 3) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def _pair_name(report: LawReport, types: tuple[int, int]) -> str:
    return "" if len(report.pairs) == 1 else f" (types {types[0]}-{types[1]})"


def markdown(report: LawReport, figure: str | None = None, level: int = 2) -> str:
    """The law as a markdown section (``level``: its heading level): formula, constants,
    masses, scale, band errors and the truth where known."""
    h = "#" * level
    lines = [f"{h} The learned pair law ({report.model} on {report.scene})", ""]
    scale = SCALE_TEXT[report.scale].format(_g(report.scale_factor, 4))
    lines += [f"- Convention: the force on particle i from j is f(r) u_ij, u_ij the unit vector "
              "from j to i (f > 0: repulsive); r in the data's length units (the head reads r / "
              f"{_g(report.length_scale, 4)}); f is the force between unit masses.",
              f"- Masses (the head's mass_law={report.mass_law}): {MASS_TEXT[report.mass_law]}."
              + ("" if report.truth_masses is None else
                 f" The scene's own law: {report.truth_masses}"
                 + (" (the same)." if report.truth_masses == report.mass_law else
                    " (DIFFERENT: the learned law is not comparable with the truth).")),
              f"- Scale: {scale}; relative squared error of the targets then "
              f"{_g(report.calibration_error)}.",
              ""]
    if figure:
        lines += [f"![learned law, formula and truth]({figure})", ""]
    for pair in report.pairs:
        f = pair.formula
        lines += [f"{h}# Formula{_pair_name(report, pair.types)}", "",
                  f"    f(r) = {f.text}", "",
                  f"Fitted on {GRID_POINTS} log-spaced distances over the {pair.n_distances} "
                  f"training pair distances (r = {_g(pair.r[0])} to {_g(pair.r[-1])}), each "
                  "weighted by the data's density of log r: the RMS relative residual "
                  f"{_g(math.sqrt(f.loss))} is the mean over the training pairs. Complexity "
                  f"(constants) {f.complexity}; the best formula of each complexity and its "
                  "residual: "
                  + ", ".join(f"{e['complexity']}: {' + '.join(e['terms'])} "
                              f"({_g(math.sqrt(e['loss']))})" for e in f.front) + ".", ""]
        if report.truth_text is not None:
            lines += [f"Truth (bgn.sim): f(r) = {report.truth_text}."]
            if pair.truth_in_form is not None:
                lines += [f"The truth in the formula's terms: relative residual "
                          f"{_g(pair.truth_in_form['residual_rms'])} (RMS), "
                          f"{_g(pair.truth_in_form['residual_max'])} (max): "
                          + ("the form is the truth's." if pair.truth_in_form["residual_max"]
                             < TRUTH_FORM else "the form is NOT the truth's.")]
            lines += [""]
        header = "| constant | term | value | std. error (Jacobian) | std (bootstrap) |"
        rule = "|---|---|---|---|---|"
        if pair.truth_in_form is not None:
            header += " truth in this form | relative difference |"
            rule += "---|---|"
        lines += [header, rule]
        for i, row in enumerate(f.constants()):
            line = (f"| {row['name']} | `{row['term']}` | {_g(row['value'], 5)} | "
                    f"{_g(row['stderr'], 2)} | {_g(row['bootstrap_std'], 2)} |")
            if pair.truth_in_form is not None:
                line += (f" {_g(pair.truth_in_form['values'][i], 5)} | "
                         f"{_g(pair.truth_in_form['relative_difference'][i], 2)} |")
            lines.append(line)
        lines += ["", "Relative errors (|a - b| / |b|, |b| floored near a zero crossing) in "
                  "bands of the training distances (median / max):", ""]
        cols = ["formula_vs_learned"] + (["learned_vs_truth", "formula_vs_truth"]
                                         if pair.truth is not None else [])
        lines += ["| data quantiles | r | " + " | ".join(c.replace("_", " ") for c in cols)
                  + " |", "|---|---|" + "---|" * len(cols)]
        for band in pair.bands:
            lines.append(f"| {band['quantiles'][0]:g}-{band['quantiles'][1]:g} | "
                         f"{_g(band['r'][0])}-{_g(band['r'][1])} | "
                         + " | ".join(f"{_g(band[c]['median'], 2)} / {_g(band[c]['max'], 2)}"
                                      for c in cols) + " |")
        lines.append("")
    return "\n".join(lines)


def law_section(module: Any, dataset: Any, level: int = 2) -> str:
    """The markdown section of the learned law of ``module`` over ``dataset``'s distances
    (the training split), for an evaluation report (``bgn.eval.evaluate``): models with a
    pair-force head only (``pair_force_head`` refuses the others)."""
    return markdown(read_law(module, dataset), level=level)


def law_figure(report: LawReport, tuned: str | None = None) -> Any:
    """Learned law, formula and truth against r, their relative errors, and the histogram of
    the training distances underneath; one column per pair of types. ``tuned``: a
    ``model.law_formula`` spec drawn too (the formula fitted to the frames)."""
    from matplotlib.ticker import FormatStrFormatter, FuncFormatter, NullFormatter

    from bgn.figures import plt

    n = len(report.pairs)
    fig, axes = plt.subplots(3, n, figsize=(6 * n, 8.5), sharex="col", squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1.4, 1.2]})
    for col, pair in enumerate(report.pairs):
        law_ax, err_ax, hist_ax = axes[:, col]
        curves = {"learned": pair.learned, "formula": pair.formula(pair.r)}
        if tuned is not None:
            curves["formula fitted to the frames"] = spec_values(tuned, pair.types, pair.r)
        if pair.truth is not None:
            curves["truth"] = pair.truth
        signs = {np.sign(c[np.abs(c) > 0]).mean() for c in curves.values()}
        one_sign = all(abs(s) == 1 for s in signs) and len(signs) == 1
        flip = -1.0 if one_sign and signs.pop() < 0 else 1.0
        styles = {"learned": "-", "formula": "--", "formula fitted to the frames": "-.",
                  "truth": ":"}
        for name, c in curves.items():
            law_ax.plot(pair.r, flip * c, styles[name], label=name, lw=2 if name == "learned"
                        else 1.5)
        law_ax.set_xscale("log")
        if one_sign:
            law_ax.set_yscale("log")
        law_ax.set_ylabel(("-f(r)" if flip < 0 else "f(r)") + " (force between unit masses)")
        law_ax.legend(fontsize=8)
        law_ax.set_title(f"{report.scene}{_pair_name(report, pair.types)}: "
                         f"f = {pair.formula.text}", fontsize=9)
        err_ax.plot(pair.r, _rel_error(curves["formula"], pair.learned, pair.r),
                    label="formula vs learned")
        if pair.truth is not None:
            err_ax.plot(pair.r, _rel_error(pair.learned, pair.truth, pair.r),
                        label="learned vs truth")
            err_ax.plot(pair.r, _rel_error(curves["formula"], pair.truth, pair.r), "--",
                        label="formula vs truth")
            if tuned is not None:
                err_ax.plot(pair.r, _rel_error(curves["formula fitted to the frames"],
                                               pair.truth, pair.r), "-.",
                            label="fitted to the frames vs truth")
        err_ax.set_yscale("log")
        err_ax.set_ylabel("relative error")
        err_ax.legend(fontsize=8)
        hist_ax.stairs(pair.hist_counts, pair.hist_edges, fill=True, color="0.6")
        hist_ax.set_yscale("log")
        hist_ax.set_xlabel("r (distance between the pair)")
        hist_ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        # within two decades also 2 and 5 times a power of ten (else the decades alone)
        if pair.r[-1] / pair.r[0] < 100:
            hist_ax.xaxis.set_minor_formatter(FuncFormatter(
                lambda x, _: f"{x:g}" if f"{x:.0e}"[0] in "25" else ""))
        else:
            hist_ax.xaxis.set_minor_formatter(NullFormatter())
        hist_ax.set_ylabel("training pairs")
    fig.tight_layout()
    return fig


def spec_values(spec: str, types: tuple[int, int], r: np.ndarray) -> np.ndarray:
    """The law of a ``model.law_formula`` spec between ``types`` at distances ``r``."""
    from bgn.model.formula_law import FormulaLaw

    n_types = 1 + max(max(p["types"]) for p in json.loads(spec))
    law = FormulaLaw(spec, max(n_types, max(types) + 1))
    pair = torch.full((len(r),), min(types) * law.n_types + max(types))
    with torch.no_grad():
        return law(torch.as_tensor(r, dtype=torch.float64), pair).numpy()


def _jsonable(report: LawReport) -> dict[str, Any]:
    out = {k: v for k, v in asdict(report).items() if k != "pairs"}
    out["pairs"] = []
    for pair in report.pairs:
        f = pair.formula
        out["pairs"].append({
            "types": list(pair.types), "formula": f.text, "complexity": f.complexity,
            "relative_rms": math.sqrt(f.loss), "constants": f.constants(), "front": f.front,
            "r": pair.r.tolist(), "density": pair.density.tolist(),
            "n_distances": pair.n_distances,
            "bands": pair.bands, "truth_in_form": pair.truth_in_form,
            "histogram": {"edges": pair.hist_edges.tolist(),
                          "counts": pair.hist_counts.tolist()}})
    return out


def write_report(report: LawReport, out_dir: str | Path, title: str | None = None) -> Path:
    """report.md, law.csv (r, learned, formula, truth per pair of types), law.json and
    law.png in ``out_dir``; each file written whole or not at all."""
    from bgn.figures import save
    from bgn.training.checkpoints import write_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = [["type_a", "type_b", "r", "learned", "formula", "truth"]]
    for pair in report.pairs:
        fitted = pair.formula(pair.r)
        for k, r in enumerate(pair.r):
            rows.append([*pair.types, f"{r:.9g}", f"{pair.learned[k]:.9g}", f"{fitted[k]:.9g}",
                         "" if pair.truth is None else f"{pair.truth[k]:.9g}"])
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerows(rows)
    record = json.dumps(_jsonable(report), indent=2)
    body = (f"# {title}\n\n" if title else "") + markdown(report, "law.png", level=2) + "\n"
    tmp = out / "law.tmp.png"
    try:  # the figure first: the step most likely to fail, and nothing is written before it
        save(law_figure(report), tmp)
    except Exception:
        tmp.unlink(missing_ok=True)
        raise
    write_atomic(out / "law.csv", text.getvalue())
    write_atomic(out / "law.json", record)
    write_atomic(out / "report.md", body)
    tmp.replace(out / "law.png")
    return out / "report.md"


# ------------------------------------------------------------------- the formula as the law

FINETUNE_STEPS = 80       # evaluations of the loss (Nelder-Mead) on the formula's constants
FINETUNE_SUBSTEPS = 16    # model.substeps while the forms are tuned (and in the written checkpoint)
POLISH_FACTOR = 4         # the chosen form's constants polished through this times finer substeps
FINETUNE_BATCH = 512      # training frames of the fixed batch (closest_frames among them)
AMPLITUDE_STEP = 0.1      # the first simplex's step in each amplitude (relative to its start)
C_STEP = 2.0              # ... and its factor on each constant c
FORM_TOLERANCE = 0.02     # a simpler form is kept while its tuned loss is within this of the best
NEGLIGIBLE = 0.01         # a term this small against the law at every distance goes (prune_terms)
FINETUNE_HORIZON = 50     # validation rollout steps (as auto.horizon)
# particles per batch of validation rollouts (checked_rollouts): the job's deadline is checked
# between batches; a force scene's whole validation split (200 x 4 bodies) is one batch
ROLLOUT_CHUNK = 4096
TYPICAL_FLOOR = 1e-9      # added to each error before the geometric mean (an exact rollout)
CANCELLING = 0.01         # a term twice whose amplitudes cancel to this is one term's derivative
CLOSE_SHARE = 0.25        # of the tuning batch: the frames with the closest pairs
ROBUST_SCALE = 0.1        # relative error at which law_objective's Cauchy loss bends
TURN_QUANTILE = 1e-3      # of the training distances: below it the law may not turn (turning_term)
BELOW_FLOOR = np.geomspace(1e-3, 1.0, 61)  # the distances turning_term checks, times its floor


def formula_spec(report: LawReport) -> str:
    """The report's formulas as ``model.law_formula`` (``bgn.model.formula_law``'s format: a
    JSON list of pairs of types, each with its terms: kind, power, amplitude a, constant c),
    in physical units: the head with ``model.law=formula`` evaluates this law."""
    return json.dumps([pair_spec(pair.types, pair.formula.terms, pair.formula.values)
                       for pair in report.pairs])


def pair_spec(types: tuple[int, int], terms: list[Term], values: np.ndarray) -> dict[str, Any]:
    """One pair of types' entry of a ``model.law_formula`` spec: ``values`` the amplitudes,
    then one constant c per nonlinear term."""
    cs = iter(float(c) for c in values[len(terms):])
    return {"types": [int(t) for t in types], "terms": [
        {"kind": t.kind, "power": float(t.power), "a": float(a),
         "c": next(cs) if t.nonlinear else None}
        for t, a in zip(terms, values[:len(terms)])]}


def formula_module(checkpoint: Path, spec: str, substeps: int) -> Any:
    """The checkpoint's model rebuilt with ``law=formula`` (``spec``) and ``substeps``, every
    weight but the law's copied from the checkpoint; (module, its hyperparameters)."""
    import inspect

    from bgn.training.checkpoints import read
    from bgn.training.module import PhysicsModule

    saved = read(checkpoint)  # once: the fine-tuning rebuilds the model for every form
    hp = dict(saved.get("hyper_parameters") or {})
    hp["model_config"] = {**hp["model_config"], "law": "formula", "law_formula": spec,
                          "law_scale": 1.0, "substeps": int(substeps)}
    keep = inspect.signature(PhysicsModule.__init__).parameters
    module = PhysicsModule(**{k: v for k, v in hp.items() if k in keep})
    old = saved["state_dict"]
    missing, unexpected = module.load_state_dict(
        {k: v for k, v in old.items() if ".force_law." not in k}, strict=False)
    if [k for k in missing if ".force_law." not in k] or unexpected:
        raise ValueError(f"checkpoint {checkpoint}: its weights do not fit the same model with "
                         f"law=formula (missing {missing[:3]}, unexpected {unexpected[:3]})")
    return module, hp


def closest_frames(dataset: Any) -> np.ndarray:
    """Indices of ``dataset``'s frames (a ``FrameDataset``) sorted by their closest pair,
    nearest first: a handful of constants is pinned at small r only by the frames with a close
    encounter, which a random batch rarely holds."""
    from bgn.data.edges import minimum_image

    file, n = dataset.file, dataset.meta.n_particles
    i, j = np.triu_indices(n, k=1)
    nearest = []
    for s in dataset.sims:
        t = dataset.history + 1 + np.arange(dataset.frames_per_sim)
        x = np.asarray(file.read("positions", (s, slice(int(t[0]), int(t[-1]) + 1))), np.float64)
        r = np.sqrt((minimum_image(x[:, i] - x[:, j], dataset.meta.period) ** 2).sum(-1))
        nearest.append(r.min(axis=1) if len(i) else np.full(len(t), np.inf))
    return np.argsort(np.concatenate(nearest), kind="stable")


def tuning_batches(dataset: Any, size: int, seed: int = 0) -> list[tuple[float, Any]]:
    """The fixed batches the constants are tuned on, with their weights in the loss: the
    ``CLOSE_SHARE`` of ``size`` frames with the closest pairs (weight: their share of the
    split), and frames drawn at random from the rest (weight: the rest's share). The weighted
    sum is an unbiased estimate of the loss over the whole split, with far less variance at
    small r than a random batch of the same size."""
    from bgn.graph import collate

    n = len(dataset)
    if size >= n:
        return [(1.0, collate([dataset[i] for i in range(n)]))]
    order = closest_frames(dataset)
    k = max(1, int(round(size * CLOSE_SHARE)))
    rest = np.random.default_rng(seed).choice(order[k:], size - k, replace=False)
    return [(k / n, collate([dataset[int(i)] for i in order[:k]])),
            ((n - k) / n, collate([dataset[int(i)] for i in np.sort(rest)]))]


def checked_rollouts(model: Any, val: Any, sims: list[int], starts: list[int], n_steps: int,
                     deadline: Deadline | None = None) -> Any:
    """Validation rollouts (``bgn.rollout.rollout_many``) in batches of at most
    ``ROLLOUT_CHUNK`` particles, the job's ``deadline`` and SIGTERM checked before each
    (``check``: ``OutOfTime`` past it): one batch of a large scene's validation split can
    take minutes. The formula stage's and ``bgn.studies.auto``'s scoring."""
    from bgn.rollout import rollout_many

    with torch.no_grad():
        return rollout_many(model.eval(), val, sims, starts, n_steps, chunk=ROLLOUT_CHUNK,
                            between=lambda: check(deadline, "the validation rollouts"))


def validation_errors(model: Any, val: Any, history: int, horizon: int = FINETUNE_HORIZON,
                      val_sims: int | None = None,
                      deadline: Deadline | None = None) -> dict[str, Any]:
    """bgn.studies.auto's scoring: every validation simulation (or ``val_sims`` of them)
    rolled out from the shared start frames; after 10 and ``horizon`` steps the mean capped
    error (a failed rollout at the cap) and its geometric mean over the rollouts
    (``typical``, shown beside), and how many failed (``failed``, ``failed_share``).
    ``deadline``: checked between batches (``checked_rollouts``)."""
    from bgn.data.frames import evenly_spaced
    from bgn.metrics import SHORT_HORIZON, failure_capped_errors
    from bgn.rollout import rollout_starts

    n_steps = min(horizon, val.file.n_frames - history - 2)
    horizons = sorted({min(SHORT_HORIZON, n_steps), n_steps})
    sims, starts = evenly_spaced(val.file.n_sims, val_sims), rollout_starts(val, n_steps)
    t = checked_rollouts(model, val, sims, starts, n_steps, deadline)
    capped, failed = failure_capped_errors(t.predicted, t.true, t.first_non_finite,
                                           val.meta.box)
    at = {h: capped[:, h - 1] for h in horizons}
    return {"errors": {h: float(e.mean()) for h, e in at.items()},
            "typical": {h: float(np.exp(np.log(e + TYPICAL_FLOOR).mean())) for h, e in at.items()},
            "failed": int(np.sum(failed >= 0)),
            "failed_share": float(np.mean(failed >= 0)), "horizon": n_steps,
            "rollouts": len(sims) * len(starts)}


def law_objective(model: Any, head: Any, g: Any) -> torch.Tensor:
    """The loss a pair law's constants are tuned on. Where the model trains its law with the
    recorded masses (BGN's ``law`` head): each particle's relative error (``newton.law_loss``)
    under a Cauchy loss, ``log(1 + rel / ROBUST_SCALE^2)``. A frame whose encounter the
    substeps do not resolve misses its target whatever the law; squared, those few frames
    would decide the constants (they favour a law softer than the truth), where the robust loss
    lets the many resolved frames decide (docs/notes/2026-11-26-results-history.md,
    "The formula stage"). Else the
    model's dynamics loss (the law through the window's mass fit). The other tasks' losses are
    left out: the inverse model reads the head's mass fit (``mass_context=fit``), and its
    likelihood would pull the law towards masses that are easy to predict."""
    from bgn.model.newton import law_loss

    if "law" in getattr(model, "heads", ()):
        rel = law_loss(head, g, reduce=False)
        return torch.log1p(rel / ROBUST_SCALE ** 2).mean()
    # the dynamics term of model.loss_terms through the head alone (forward_target): the
    # encoders and the flow, whose losses are left out, need not run for every evaluation
    return model.target_coder.loss(model.forward_target(g), g)


class _Budget(Exception):
    """The fine-tuning's evaluations or seconds are spent."""


def n_constants(spec: str | list[dict[str, Any]]) -> int:
    """Amplitudes and constants c of a ``model.law_formula`` spec."""
    pairs = json.loads(spec) if isinstance(spec, str) else spec
    return sum(1 + (t.get("c") is not None) for p in pairs for t in p["terms"])


def candidate_specs(report: LawReport) -> list[str]:
    """The forms the fine-tuning starts from: the formula read back, then (one pair of types
    only) every other formula on its fit's front, every one-term form of the library with a
    constant c, and every such term twice (``twice_form``), each fitted to the learned law.
    The network's law can be off where the frames pin the form (gravity's close encounters),
    so a form the fit passed over may fit the frames best."""
    specs = [formula_spec(report)]
    if len(report.pairs) != 1:
        return specs
    pair = report.pairs[0]
    forms = list(pair.formula.alternatives)
    nonlinear = [term for term in default_library() if term.nonlinear]
    for term in nonlinear:  # (the fitter needs a linear term beside it: a constant)
        one = fit_formula(pair.r, pair.learned, pair.density, max_terms=1,
                          library=[Term("const"), term], n_boot=0)
        forms += [(t, v) for t, v in one.alternatives if t == [term]]
    forms += [form for term in nonlinear if (form := twice_form(pair, term)) is not None]
    for terms, values in forms:
        spec = json.dumps([pair_spec(pair.types, terms, values)])
        if spec not in specs:
            specs.append(spec)
    return specs


def negligible_term(spec: str, reach: np.ndarray | None) -> int | None:
    """The smallest term of a one-pair ``spec`` whose size stays below ``NEGLIGIBLE`` times
    the law's RMS size at every distance of ``reach`` (where the data reach: the training
    distances at ``DISTANCE_QUANTILES``, ``PairLaw.reach``), or None. Such a term changes no
    prediction the frames can check; the loss may still prefer it a little, where it absorbs
    what the substeps miss at the closest encounters. Dropping it whatever the loss is
    sequential thresholding, as sparse regression does."""
    from bgn.model.formula_law import FormulaLaw

    pairs = json.loads(spec)
    if reach is None or len(reach) == 0 or len(pairs) != 1 or len(pairs[0]["terms"]) < 2:
        return None
    r = torch.as_tensor(reach, dtype=torch.float64)
    with torch.no_grad():
        values = FormulaLaw(spec).values(r).numpy()                      # (R, K)
    size = np.sqrt(np.mean(values.sum(-1) ** 2))
    peak = np.abs(values).max(0) / max(size, 1e-300)
    k = int(np.argmin(peak))
    return k if peak[k] < NEGLIGIBLE else None


def turning_term(spec: str, floor: float | None) -> int | None:
    """The term of a one-pair ``spec`` that turns the law's sign below ``floor`` (the closest
    ``TURN_QUANTILE`` of the training distances), or None: the term pulling against the law's
    sign at the floor that is largest at the closest distance where the law has turned. No
    frame pins the law down there, so a turn there is the fit's extrapolation, not the data's
    (REBOUND's softened attraction read back with a small 1/r^2 repulsion that takes over in
    a close encounter; docs/design.md, "The formula stage"). A core the data reach (Morse,
    Lennard-Jones) turns the law above the floor and is kept."""
    from bgn.model.formula_law import FormulaLaw

    pairs = json.loads(spec)
    if floor is None or not floor > 0 or len(pairs) != 1 or len(pairs[0]["terms"]) < 2:
        return None
    r = torch.as_tensor(floor * BELOW_FLOOR, dtype=torch.float64)
    with torch.no_grad():
        values = FormulaLaw(spec).values(r).numpy()                      # (R, K), r ascending
    law = values.sum(-1)
    sign = np.sign(law[-1])
    turned = np.flatnonzero(np.sign(law) == -sign) if sign != 0 else []
    if len(turned) == 0:
        return None
    against = values[turned[0]] * sign < 0
    return int(np.argmax(np.where(against, np.abs(values[turned[0]]), -np.inf)))


def twice_form(pair: Any, term: Term) -> tuple[list[Term], np.ndarray] | None:
    """``term`` twice, each with its own c (Morse: two exponentials), fitted to ``pair``'s
    learned law in absolute terms: relative residuals are set by the many pairs where the law
    is near zero (beyond a cut-off), as the frames' loss is not, and there the fit collapses
    to one scale. None where the two amplitudes cancel to ``CANCELLING`` of the larger: a
    finite difference of one term (its derivative in c), not two scales of the law."""
    fit = fit_formula(pair.r, pair.learned, pair.density, max_terms=2,
                      library=[Term("const"), term], scale=np.ones_like(pair.r), n_boot=0)
    for terms, values in fit.alternatives:
        a = np.abs(values[:2])
        if terms == [term, term] and abs(values[0] + values[1]) > CANCELLING * a.max():
            return terms, values
    return None


def drop_term(spec: str, k: int) -> str:
    """A one-pair ``spec`` without its term ``k``."""
    pair = json.loads(spec)[0]
    return json.dumps([{**pair, "terms": [t for j, t in enumerate(pair["terms"]) if j != k]}])


def prune_terms(tune: Callable[[str], tuple[float, Any, Any, str]], loss: float, module: Any,
                hp: Any, spec: str, reach: np.ndarray | None = None,
                floor: float | None = None) -> tuple[float, Any, Any, str]:
    """Backward elimination on the frames: a negligible term (``negligible_term``, over the
    distances the data ``reach``) or one that turns the law's sign below the ``floor`` of the
    training distances (``turning_term``) is dropped, the rest tuned again, whatever the loss;
    else a term is dropped while the loss rises by at most ``FORM_TOLERANCE``: a term the
    network's law needed in its tails (where the frames barely pin it) goes."""
    while True:
        pairs = json.loads(spec)
        if len(pairs) != 1 or len(pairs[0]["terms"]) < 2:
            return loss, module, hp, spec
        drop = negligible_term(spec, reach)
        if drop is None:
            drop = turning_term(spec, floor)
        if drop is not None:
            loss, module, hp, spec = tune(drop_term(spec, drop))
            continue
        for k in range(len(pairs[0]["terms"])):
            result = tune(drop_term(spec, k))
            if not result[0] > loss * (1 + FORM_TOLERANCE):
                loss, module, hp, spec = min(result[0], loss), *result[1:]
                break
        else:
            return loss, module, hp, spec


def tune_constants(model: Any, head: Any, batches: list[tuple[float, Any]], steps: int,
                   deadline: Deadline | None) -> tuple[float, int]:
    """The constants of ``head``'s formula law fitted in place to ``law_objective`` on the
    weighted ``batches``, derivative-free (Nelder-Mead, at most ``steps`` evaluations): the
    law's loss through the substeps of the closest encounters is smooth at the scale of the
    constants' errors but rough at a quasi-Newton step's (its gradient jumps), where L-BFGS
    stalls. A trial point where the loss is not finite counts as infinitely worse (a form
    with no finite point returns inf and loses). Returns (the lowest loss, evaluations);
    ``_Budget`` past ``deadline`` (the job's, ``bgn.training.budget``) before any; a
    SIGTERM ends it between evaluations (``check``)."""
    from bgn.model.formula_law import NONLINEAR

    law = head.force_law
    nonlinear = torch.tensor([k in NONLINEAR for k in law.kinds])
    best: list[Any] = [math.inf, None]
    count = [0]

    def place(x: np.ndarray) -> None:
        with torch.no_grad():
            law.amplitude.copy_(torch.as_tensor(x[:len(law.kinds)]))
            law.log_c[nonlinear] = torch.as_tensor(x[len(law.kinds):], dtype=law.log_c.dtype)

    def objective(x: np.ndarray) -> float:
        if count[0] >= steps:
            raise _Budget
        try:
            check(deadline, "the formula stage")  # and SIGTERM, between evaluations
        except OutOfTime:
            raise _Budget from None
        place(x)
        with torch.no_grad():
            loss = float(sum(w * law_objective(model, head, g) for w, g in batches))
        count[0] += 1
        if not math.isfinite(loss):  # constants the law cannot take: a worse point, not a stop
            return math.inf
        if loss < best[0]:
            best[:] = [loss, x.copy()]
        return loss

    x0 = np.concatenate([law.amplitude.detach().numpy(),
                         law.log_c.detach()[nonlinear].numpy()]).astype(np.float64)
    simplex = np.vstack([x0, x0 + np.diag(np.where(np.arange(len(x0)) < len(law.kinds),
                                                   AMPLITUDE_STEP, math.log(C_STEP)))])
    try:
        minimize(objective, x0, method="Nelder-Mead",
                 options={"initial_simplex": simplex, "maxfev": steps, "xatol": 1e-3,
                          "fatol": 1e-6})
    except _Budget:
        if best[1] is None and count[0] == 0:
            raise
    place(x0 if best[1] is None else best[1])  # no finite point: the form loses (loss inf)
    return best[0], count[0]


def polish_constants(model: Any, head: Any, batches: list[tuple[float, Any]], steps: int,
                     deadline: Deadline | None) -> dict[str, Any] | None:
    """The chosen form's constants tuned once more (``steps`` evaluations, as every form)
    through ``POLISH_FACTOR`` times finer substeps: through the coarser substeps the forms
    are compared with, the loss is rough at the scale of a softening constant, and its minimum
    spans a band around the truth (docs/notes/2026-11-26-results-history.md,
    "The formula stage"). The substeps are put back after. None where no time is left."""
    coarse = head.substeps
    head.substeps = fine = POLISH_FACTOR * coarse
    try:
        loss, n = tune_constants(model, head, batches, steps, deadline)
    except _Budget:
        return None
    finally:
        head.substeps = coarse
    return {"substeps": fine, "loss": loss, "evaluations": n}


def failed_rollouts(score: dict[str, Any]) -> int:
    """How many of a ``validation_errors`` score's rollouts failed (from its share where an
    older record lacks the count)."""
    if "failed" in score:
        return int(score["failed"])
    return int(round(score.get("failed_share", 0.0) * score.get("rollouts", 0)))


def law_choice(scores: dict[str, dict[str, Any]], horizon: int) -> str:
    """The law a formula stage keeps, of ``scores`` (law -> ``validation_errors``): the fewest
    failed rollouts first, so a law that fails more never wins; then the lower mean error
    after ``horizon`` steps with each failed rollout at the cap (``model.dynamics=auto``'s
    rule, ``bgn.metrics.capped_step_errors``), in which a failure weighs its cap where a
    geometric mean would let it weigh little; the network law on a tie."""
    return min(scores, key=lambda k: (failed_rollouts(scores[k]),
                                      scores[k]["errors"].get(horizon, math.inf),
                                      k != "network"))


def finetune_formula(checkpoint: Path, train_split: Any, val: Any,
                     report: LawReport | None = None, steps: int = FINETUNE_STEPS,
                     substeps: int = FINETUNE_SUBSTEPS,
                     batch_size: int = FINETUNE_BATCH, horizon: int = FINETUNE_HORIZON,
                     val_sims: int | None = None, out_dir: Path | None = None,
                     seed: int = 0, start: str | None = None,
                     max_seconds: float | None = None,
                     deadline: Deadline | None = None) -> dict[str, Any]:
    """The fitted formula as the model's law, its constants fine-tuned end to end: the
    checkpoint's model with ``law=formula`` (``formula_module``), the law's constants alone
    fitted by Nelder-Mead (``steps`` evaluations) to the head's own loss (``law_objective``)
    on a fixed batch of ``batch_size`` training frames (``tuning_batches``: the closest
    encounters and a random rest, weighted to the split), through ``substeps`` (a frame's
    finite-difference target averages the force over the frame, as the substeps integrate
    it); the chosen form's constants are then polished through finer substeps
    (``polish_constants``). Only the law is fitted: the rest of the model is the
    checkpoint's, validated with the network law, and a handful of constants cannot overfit
    a split. Both laws are then scored on the validation rollouts (``validation_errors``)
    and one is kept (``law_choice``: the fewer failed rollouts, then the lower mean error
    after the horizon, a failed rollout at the cap).
    ``out_dir``: writes ``formula.ckpt`` (loadable as any checkpoint) and ``formula.json``.
    ``start``: a spec to start from in place of the law read back (tests). The fit is
    bounded by its evaluation count (``steps`` per form); ``deadline`` (the job's wall-clock
    cap, ``bgn.training.budget``) and ``max_seconds`` (from now) stop it earlier, and the
    record's ``budget.cut_by`` says so. The validation rollouts check ``deadline`` alone
    between their batches (``checked_rollouts``); past it the network law is kept (the
    run stays usable), ``validation`` is empty and ``budget.cut`` names them. A line per
    tuned form shows its progress. Returns the record (specs before and after, errors,
    choice)."""
    from bgn.training.module import load_model

    network = load_model(checkpoint)
    if start is None and report is None:
        report = read_law(network, train_split)
    batches = tuning_batches(train_split, batch_size, seed)
    reach, floor = _data_reach(report, train_split)
    job = deadline or NO_DEADLINE  # the validation rollouts' (max_seconds bounds the fit)
    deadline = job.sooner(max_seconds)
    began = time.monotonic()
    evaluations = [0, 0]  # loss evaluations, tunings (each at most `steps` evaluations)

    def tune(spec: str) -> tuple[float, Any, Any, str]:
        """(tuned loss, module, hp, tuned spec) of the checkpoint's model with law ``spec``."""
        module, hp = formula_module(checkpoint, spec, substeps)
        model, head = pair_force_head(module)
        model.requires_grad_(False)
        model.eval()  # no dropout in the inverse model: the loss is one function
        loss, n = tune_constants(model, head, batches, steps, deadline)
        evaluations[0] += n
        evaluations[1] += 1
        log.info("formula stage: tuning %d done (%d evaluations, loss %.4g, %s so far)",
                 evaluations[1], n, loss, clock_text(time.monotonic() - began))
        return loss, module, hp, head.force_law.spec()

    starts = [start] if start is not None else candidate_specs(report)
    forms = _tuned_forms(tune, starts, checkpoint, substeps, reach, floor)
    form = _chosen_form(forms)
    module, hp = form["module"], form["hp"]
    model, head = pair_force_head(module)
    polish = polish_constants(model, head, batches, steps, deadline) \
        if math.isfinite(form["loss"]) else None
    if polish:
        evaluations[0] += polish["evaluations"]
        evaluations[1] += 1
    # the fit ended by the cap, not by its evaluation count: another machine fits otherwise
    budget = {"steps_per_form": steps, "evaluations": evaluations[0],
              "cut_by": "max_time" if deadline.passed() else None,
              "cut": ["the fit"] if deadline.passed() else []}
    log.info("formula stage: tuned in %s%s; rolling out both laws on validation",
             clock_text(time.monotonic() - began),
             " (cut short by the job's wall-clock cap)" if budget["cut_by"] else "")
    scale, model_scale = 1.0, 1.0
    if "law" not in getattr(model, "heads", ()):
        # tuned through the window's mass fit, which absorbs the law's scale (law_objective):
        # the constants put back in physical units, as the law read back is (calibrate_scale).
        # The mass flow reads the window's fitted masses (mass_context=fit) in the network
        # law's free scale, which it was trained on: the model keeps the formula in that
        # scale (its rollouts are the same at any scale), the record in physical units
        scale = calibrate_scale(head, train_split)[0]
        model_scale = 1 / calibrate_scale(pair_force_head(network)[1], train_split)[0]
    with torch.no_grad():
        head.force_law.amplitude.mul_(scale)
    spec = head.force_law.spec()
    with torch.no_grad():
        head.force_law.amplitude.mul_(model_scale)
    hp["model_config"] = {**hp["model_config"], "law_formula": head.force_law.spec(),
                          "law_scale": 1 / model_scale}  # its labels in physical units
    history = int(hp["history"])
    try:
        scores, by_substeps = _validated_laws(network, model, head, val, history, horizon,
                                              val_sims, substeps, job)
        choice = law_choice(scores, scores["network"]["horizon"])
    except OutOfTime:  # nothing compared: the law the checkpoint validated with stays
        scores, by_substeps, choice = {}, {}, "network"
        budget["cut_by"] = "max_time"
        budget["cut"].append("the validation rollouts")
        log.warning("formula stage: the validation rollouts reached the job's wall-clock cap "
                    "(trainer.max_time): the network law is kept; raise trainer.max_time to "
                    "compare the formula")
    hp["model_config"] = {**hp["model_config"], "substeps": head.substeps}
    record = {"checkpoint": str(checkpoint), "substeps": substeps,
              "steps": evaluations[0], "tunings": evaluations[1], "batch_size": batch_size,
              "budget": budget,
              "forms": [{k: f[k] for k in ("start", "tuned", "loss", "constants")}
                        for f in forms],
              "rollout_substeps": head.substeps,
              "formula_by_substeps": {str(k): v for k, v in by_substeps.items()},
              "start": form["start"], "tuned": json.loads(spec),
              "scale": scale, "model_scale": model_scale,
              "model_tuned": json.loads(hp["model_config"]["law_formula"]),
              "loss": form["loss"], "polish": polish, "floor": floor,
              "validation": scores, "choice": choice,
              "against_truth": {} if report is None else against_truth(report,
                                                                        json.loads(spec)),
              "truth": None if report is None else report.truth_text}
    if out_dir is not None:
        record["path"] = str(_write_formula(Path(out_dir), checkpoint, module, hp, record))
    return record


def _data_reach(report: LawReport | None, train_split: Any) -> tuple[Any, float | None]:
    """(reach, floor) of the training distances: where the data reach (the report's, for one
    pair of types; else the split's distance quantiles), and the floor below which a law may
    not turn (``TURN_QUANTILE``); None where the split has no pairs."""
    seen = np.concatenate([np.zeros(0), *pair_distances(train_split).values()])
    floor = float(np.quantile(seen, TURN_QUANTILE)) if seen.size else None
    if report is not None and len(report.pairs) == 1:
        reach = report.pairs[0].reach
    else:
        reach = np.quantile(seen, DISTANCE_QUANTILES) if seen.size else None
    return reach, floor


def _tuned_forms(tune: Callable[[str], tuple[float, Any, Any, str]], starts: list[str],
                 checkpoint: Path, substeps: int, reach: Any,
                 floor: float | None) -> list[dict[str, Any]]:
    """Every candidate form, each tuned on the frames (``tune``) and pruned of the terms the
    frames do not need, until the budget runs out; with no time for even one evaluation, the
    form read back, untuned, less the terms that turn it below the data (``turning_term``
    needs no evaluation)."""
    forms = []
    for spec in starts:
        try:
            loss, module, hp, tuned = tune(spec)
            loss, module, hp, tuned = prune_terms(tune, loss, module, hp, tuned, reach, floor)
        except _Budget:
            break
        forms.append({"start": json.loads(spec), "tuned": json.loads(tuned), "loss": loss,
                      "constants": n_constants(tuned), "module": module, "hp": hp})
    if not forms:
        spec = starts[0]
        while (drop := turning_term(spec, floor)) is not None:
            spec = drop_term(spec, drop)
        module, hp = formula_module(checkpoint, spec, substeps)
        forms.append({"start": json.loads(starts[0]), "tuned": json.loads(spec),
                      "loss": math.nan, "constants": n_constants(spec),
                      "module": module, "hp": hp})
    return forms


def _chosen_form(forms: list[dict[str, Any]]) -> dict[str, Any]:
    """The lowest loss wins, the fewest constants among those within ``FORM_TOLERANCE``."""
    lowest = min(f["loss"] for f in forms)
    near = [f for f in forms if not f["loss"] > lowest * (1 + FORM_TOLERANCE)] or forms
    return min(near, key=lambda f: (f["constants"], f["loss"]))


def _validated_laws(network: Any, model: Any, head: Any, val: Any, history: int, horizon: int,
                    val_sims: int | None, substeps: int, deadline: Deadline | None = None,
                    ) -> tuple[dict[str, Any], dict[int, Any]]:
    """Validation rollouts of the network law and of the formula (``scores``), the formula
    rolled out with the substeps it was tuned through and with the network's own
    (``by_substeps``); ``head.substeps`` is left at the better of the two on the mean error:
    the shooting's velocity estimate can cost more over a rollout than the substeps gain
    (docs/notes/2026-11-26-results-history.md, "The formula stage"), and substeps are there
    for the rare close encounters, which a typical (geometric-mean) error discounts.
    ``deadline``: the job's, checked between rollout batches (``OutOfTime``, with
    ``head.substeps`` put back)."""
    scores = {"network": validation_errors(network.model, val, history, horizon, val_sims,
                                           deadline)}
    n = scores["network"]["horizon"]
    by_substeps = {}
    for k in sorted({substeps, pair_force_head(network)[1].substeps}):
        head.substeps = k
        try:
            by_substeps[k] = validation_errors(model, val, history, horizon, val_sims,
                                               deadline)
        except OutOfTime:
            head.substeps = substeps
            raise
    head.substeps = min(by_substeps, key=lambda k: by_substeps[k]["errors"].get(n, math.inf))
    scores["formula"] = by_substeps[head.substeps]
    return scores, by_substeps


def _write_formula(out: Path, checkpoint: Path, module: Any, hp: dict[str, Any],
                   record: dict[str, Any]) -> Path:
    """``formula.ckpt`` (the checkpoint with the formula law: loadable as any checkpoint) and
    ``formula.json`` (the record) in ``out``; returns the checkpoint's path."""
    from bgn.training.checkpoints import read, write_atomic

    out.mkdir(parents=True, exist_ok=True)
    ckpt = read(checkpoint)
    # the run's optimiser settings kept for bgn.train ckpt_path, its moments dropped: they
    # belonged to the network law's weights; one parameter group, the first's settings
    # (a matched network law trained in a slower second group: the formula is not matched)
    n_params = len(list(module.parameters()))
    for state in ckpt.get("optimizer_states", []):
        state["param_groups"] = state.get("param_groups", [{}])[:1]
        state["state"], state["param_groups"][0]["params"] = {}, list(range(n_params))
    for state in ckpt.get("lr_schedulers", []):
        for key in ("min_lrs", "_last_lr"):
            if isinstance(state.get(key), list):
                state[key] = state[key][:1]
    ckpt["hyper_parameters"], ckpt["state_dict"] = hp, module.state_dict()
    tmp = out / ".formula.ckpt.tmp"  # then a rename: never a half-written checkpoint
    torch.save(ckpt, tmp)
    tmp.replace(out / "formula.ckpt")
    write_atomic(out / "formula.json", json.dumps(record, indent=2, default=float))
    return out / "formula.ckpt"


def finetune_markdown(record: dict[str, Any], level: int = 2) -> str:
    """The comparison table of ``finetune_formula``'s record."""
    h = "#" * level
    v = record["validation"]
    if not v:  # the validation rollouts were cut (finetune_formula)
        return (f"{h} The formula as the law, fine-tuned\n\nThe fitted formula as the model's "
                f"pair law, its constants fitted in {record['steps']} evaluations: "
                f"`{spec_text(record['tuned'])}`. Not compared: the job's wall-clock cap "
                "(trainer.max_time) was reached before the validation rollouts finished "
                f"({', '.join((record.get('budget') or {}).get('cut', []))} cut), so the "
                "network law is kept.\n")
    horizons = sorted(v["network"]["errors"], key=int)
    lines = [f"{h} The formula as the law, fine-tuned",
             "",
             f"The fitted formula as the model's pair law (model.law=formula), its constants "
             f"fitted in {record['steps']} evaluations of the law's loss on "
             f"{record.get('batch_size', '?')} training frames with model.substeps="
             f"{record['substeps']}, the rest of the model the checkpoint's; both scored on "
             f"the validation split's rollouts ({v['network']['rollouts']} rollouts, a failed "
             "one at the cap): the mean error and the typical one (the geometric mean over "
             "the rollouts).",
             "",
             "| law | formula | " + " | ".join(f"mean @{k} | typical @{k}" for k in horizons)
             + " | failed |",
             "|---|---|" + "---|---|" * len(horizons) + "---|"]
    rows = [("network", "(MLP)", v["network"])] + [
        (f"formula, substeps {k}", spec_text(record["tuned"]), s)
        for k, s in record["formula_by_substeps"].items()]
    for name, text, s in rows:
        typical = s.get("typical", {})
        lines.append(f"| {name} | `{text}` | " + " | ".join(
            f"{_g(s['errors'][k])} | {_g(typical[k]) if k in typical else ''}"
            for k in horizons) + f" | {s['failed_share']:.0%} |")
    if record.get("forms"):
        lines += ["", "Forms tried (the fit's front, the library's one-term forms and each "
                  "nonlinear term twice: each form's constants fitted to the law's loss on the "
                  "frames, then pruned of terms the frames do not need; the lowest loss wins, "
                  f"the fewest constants within {FORM_TOLERANCE:.0%} of it):",
                  "", "| from | tuned and pruned | constants | loss |", "|---|---|---|---|"]
        lines += [f"| `{spec_text(f['start'])}` | `{spec_text(f['tuned'])}` | "
                  f"{f['constants']} | {_g(f['loss'])} |" for f in record["forms"]]
    lines += ["", f"Fitted before fine-tuning: `{spec_text(record['start'])}`; the formula "
              f"rolls out with substeps {record['rollout_substeps']} (the lower mean error: "
              "substeps are for the rare close encounters).", ""]
    if record.get("polish"):
        lines += [f"The chosen form's constants then polished through "
                  f"{record['polish']['substeps']} substeps ({record['polish']['evaluations']} "
                  f"evaluations; loss {_g(record['polish']['loss'])}).", ""]
    if record.get("scale", 1.0) != 1.0:
        lines += [f"The tuned constants put in physical units by the factor {_g(record['scale'])} "
                  "(the loss through the window's mass fit leaves the law's scale free; "
                  "the forms above are before it). The model keeps the formula times "
                  f"{_g(record.get('model_scale', 1.0))}, the network law's scale, in which "
                  "its mass flow reads the window's fitted masses.", ""]
    lines += truth_markdown(record.get("against_truth") or {}, record.get("truth"))
    lines += [f"Chosen: **{record['choice']}** (the fewer failed validation rollouts, then "
              f"the lower mean error after {horizons[-1]} steps, a failed one at the cap)."]
    if record.get("path"):
        lines += ["", f"Checkpoint with the formula law: `{record['path']}`."]
    return "\n".join(lines) + "\n"


def spec_text(pairs: list[dict[str, Any]]) -> str:
    """A ``model.law_formula`` spec (parsed) as text: each pair of types' law in r."""
    r = sympy.Symbol("r", positive=True)
    out = []
    for p in pairs:
        expr = sum((sympy.Float(t["a"], SIGNIFICANT) * Term(t["kind"], t["power"]).expr(
            r, None if t["c"] is None else sympy.Float(t["c"], SIGNIFICANT))
            for t in p["terms"]), sympy.Integer(0))
        out.append((f"{p['types'][0]}-{p['types'][1]}: " if len(pairs) > 1 else "")
                   + sympy.sstr(expr))
    return "; ".join(out)


# ----------------------------------------------------------------------------- command line

FINETUNE_KEYS = ("steps", "substeps", "batch_size", "horizon", "val_sims")  # finetune_<key>


def _options(cfg: Any) -> tuple[Path, dict[str, Any]]:
    """``python -m bgn.laws``'s keys (``conf/laws.yaml``) checked before any data or model is
    read: (the checkpoint, ``run``'s options). The checkpoint is the one ``python -m
    bgn.evaluate`` scores (``bgn.eval.evaluate.resolve_run``: a run folder's chosen one)."""
    from bgn.eval.evaluate import resolve_run
    from bgn.training.validate import ConfigError, need_float, need_int

    if not cfg.get("ckpt"):
        raise ConfigError("ckpt", None, "give a run folder or checkpoint: python -m bgn.laws "
                          "outputs/train/runs/<run> [finetune=true]")
    if not isinstance(cfg.finetune, bool):
        raise ConfigError("finetune", cfg.finetune, "true or false")
    need_int(cfg.max_terms, "max_terms", 1, 4)
    need_float(cfg.tolerance, "tolerance", 0.0, strict_low=False)
    need_float(cfg.parsimony, "parsimony", 1.0, strict_low=False)
    for key, high in (("steps", None), ("substeps", 64), ("batch_size", None),
                      ("horizon", None), ("val_sims", None)):
        need_int(cfg[f"finetune_{key}"], f"finetune_{key}", 1, high, optional=True)
    ckpt, _, config = resolve_run(str(cfg.ckpt), cfg.get("run_config"))
    options: dict[str, Any] = {"config": str(config), "finetune": cfg.finetune,
                               "max_terms": int(cfg.max_terms), "tolerance": cfg.tolerance,
                               "parsimony": cfg.parsimony}
    if cfg.paths.data_dir:
        options["data_dir"] = str(cfg.paths.data_dir)
    if cfg.out_dir:
        options["out_dir"] = str(cfg.out_dir)
    for key in FINETUNE_KEYS:
        if cfg[f"finetune_{key}"] is not None:
            options[f"finetune.{key}"] = int(cfg[f"finetune_{key}"])
    return ckpt, options


def formula_stage(checkpoint: Path, train_split: Any, val: Any, config: Any,
                  out_dir: Path, finetune: bool = True, **options: Any) -> dict[str, Any]:
    """The law of ``checkpoint`` read back over ``train_split`` (``read_law``) and written to
    ``out_dir`` (report.md, law.csv, law.json, law.png); with ``finetune`` the formula also
    fine-tuned as the law and scored against the network law on ``val``'s rollouts
    (``finetune_formula``): ``formula.ckpt`` with its ``train_config.yaml`` (``config``, the
    run's, with the formula's model options) and a section of report.md. ``options``:
    ``read_law``'s (max_terms, tolerance, parsimony) and ``finetune.<key>``. Returns the
    fine-tuning record (``{}`` without ``finetune``) with ``report`` (report.md's path)."""
    from omegaconf import OmegaConf, open_dict

    from bgn.training.checkpoints import read, write_atomic
    from bgn.training.module import load_model

    report = read_law(load_model(checkpoint), train_split,
                      **{k: options[k] for k in ("max_terms", "tolerance", "parsimony")
                         if k in options})
    path = write_report(report, out_dir, title=f"Learned law of {checkpoint}")
    if not finetune:
        return {"report": str(path)}
    tuned = {k.split(".", 1)[1]: v for k, v in options.items() if k.startswith("finetune.")}
    record = finetune_formula(checkpoint, train_split, val, report, out_dir=out_dir, **tuned)
    section = finetune_markdown(record)
    print(section)
    write_atomic(path, path.read_text() + "\n" + section)
    from bgn.figures import save

    tmp = Path(out_dir) / "law.tmp.png"  # the figure again, with the formula fitted to frames
    save(law_figure(report, json.dumps(record["tuned"])), tmp)
    tmp.replace(Path(out_dir) / "law.png")
    # the run's config with the formula model's options beside formula.ckpt: bgn.evaluate
    # takes the folder of a checkpoint outside checkpoints/ for its run
    tuned_cfg = copy.deepcopy(config)
    hp = read(record["path"])["hyper_parameters"]["model_config"]
    with open_dict(tuned_cfg):
        for key in ("law", "law_formula", "law_scale", "substeps"):
            tuned_cfg.model[key] = hp[key]
    write_atomic(Path(out_dir) / "train_config.yaml", OmegaConf.to_yaml(tuned_cfg))
    return {**record, "report": str(path)}


def law_stage(cfg: Any, best: Path, datamodule: Any, output_dir: Path,
              world_size: int, deadline: Deadline | None = None) -> dict[str, Any]:
    """``model.law=auto``'s stage (``bgn.training.run.train``'s ``law_stage``): the best
    checkpoint's network law read back as a formula, the formula fine-tuned as the law and
    kept where it validates better on rollouts (``formula_stage``, in ``<run>/laws/``); run
    before the test, on the training and validation splits only. Returns its record
    (``choice``: network or formula; ``path``: formula.ckpt). Bounded by its evaluation
    count (``FINETUNE_STEPS`` per form), so the same run fits the same formula on any
    machine; ``deadline`` (the job's wall-clock cap) stops it earlier, and its record's
    ``budget`` says so (docs/design.md#budgets)."""
    if world_size > 1:  # one process would tune while the others wait at the test's barrier
        log.info("model.law=auto: the formula stage runs in a single process; run python -m "
                 f"bgn.laws {best} finetune=true after this DDP run")
        return {}
    log.info("model.law=auto: reading the learned law back as a formula and fine-tuning it")
    record = formula_stage(best, datamodule.datasets["train"], datamodule.datasets["val"],
                           cfg, output_dir / "laws", **{"finetune.deadline": deadline})
    log.info(f"model.law=auto: the {record['choice']} law validates better "
             f"(report: {record['report']})")
    return record


def run(checkpoint: Path, options: dict[str, Any]) -> Path:
    """Read the law of ``checkpoint`` over its training split and write the report; with
    ``finetune=true`` also the fitted formula as the law, fine-tuned (``formula_stage``):
    ``formula.ckpt``, ``formula.json`` and a section of report.md in the same folder."""
    from omegaconf import OmegaConf

    from bgn.data.datamodule import ParticleDataModule
    from bgn.training.checkpoints import run_config
    from bgn.training.module import load_model

    pair_force_head(load_model(checkpoint))  # refused before any data are read
    config = Path(options["config"]) if "config" in options else run_config(checkpoint)
    cfg = OmegaConf.load(config)
    data_dir = options.get("data_dir") or OmegaConf.select(cfg, "paths.data_dir",
                                                           default="data")
    datamodule = ParticleDataModule(cfg.dataset, cfg.fps, data_dir, show_progress=False)
    datamodule.prepare_data()
    datamodule.setup()
    out = Path(options.get("out_dir") or checkpoint.resolve().parent.parent / "laws")
    record = formula_stage(checkpoint, datamodule.datasets["train"],
                           datamodule.datasets["val"], cfg, out,
                           finetune=bool(options.get("finetune", False)),
                           **{k: v for k, v in options.items()
                              if k not in ("config", "data_dir", "out_dir", "finetune")})
    return Path(record["report"])


@cli("laws", positional="ckpt")  # bad input: one line, exit 2 (bgn.training.validate)
def main(cfg: Any) -> Path:
    """``python -m bgn.laws <run folder or checkpoint> [finetune=true] ...``; a model without
    a pair-force head or an unusable checkpoint: one line, exit code 2."""
    from bgn.data.files import DatasetFileError
    from bgn.training.checkpoints import CheckpointError
    from bgn.training.validate import CONFIG_EXIT, DATA_EXIT, fail, full_error

    checkpoint, options = _options(cfg)
    try:
        path = run(checkpoint, options)
    except DatasetFileError as err:
        if full_error():
            raise
        fail(err, DATA_EXIT)
    except (CheckpointError, ValueError, FileNotFoundError) as err:
        if full_error():
            raise
        fail(err, CONFIG_EXIT)
    print(f"law: {path}")
    return path
