"""The term library and the sparse fit of a formula (``fit_formula``), and the relative scale
of a law's residuals (``law_scale``, ``floored_scale``), which the law search uses too.

The formula stage reads a law with the law search (``bgn.laws.search``), not with this list:
``fit_formula`` stays as the baseline the search is measured against
(examples/heldout_laws/search_trial.py), and ``Term``, ``Formula``, ``default_library`` with it.

``fit_formula``: sparse regression over a library of candidate terms (``default_library``:
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

Libraries. PySR (symbolic regression, Cranmer's route) downloads and compiles Julia at run
time: not possible without network. PySINDy (installs from PyPI, with scikit-learn) fits
libraries linear in their coefficients only: the softening ``c`` of ``(r + c)^p`` must be a
fixed grid of columns, nearly collinear with each other and with the plain powers. Tried on
this library (c on a grid) with the noisy laws of tests/laws/test_terms.py, its STLSQ and SR3 kept
tens of terms at any threshold tried, not the one or two of the law
(docs/notes/2026-11-26-results-history.md, "Laws read back as formulas"). An
exhaustive search over subsets of up to three terms is exact where a sparse relaxation is a
heuristic, and takes seconds: numpy, scipy and sympy (already dependencies) suffice.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import sympy
from scipy.optimize import least_squares
from scipy.signal import savgol_filter

from bgn.law_table import law_size
from bgn.laws.options import DEFAULTS

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
    ``DEFAULTS.zero_crossing_width``: |f| within a few % for power laws, finite where f
    crosses zero.
    ``smooth``: f is smoothed first (Savitzky-Golay along the sorted grid), for noisy points."""
    y = np.asarray(y, dtype=np.float64)
    if smooth and len(y) >= 7:
        y = savgol_filter(y, min(21, len(y) - 1 + len(y) % 2), 3)  # an odd window
    size = law_size(y, np.log(r), DEFAULTS.zero_crossing_width)
    return np.maximum(size, 1e-12 * (size.max() + 1e-300))


def floored_scale(r: np.ndarray, y: np.ndarray, share: np.ndarray) -> np.ndarray:
    """``law_scale`` floored at ``DEFAULTS.size_floor`` of its value at the weights' median
    point (r sorted, ``share`` each point's weight): a law far weaker than where most points
    are (beyond a cut-off) counts in absolute terms, since its relative error there would be
    the network's noise over nothing."""
    scale = law_scale(r, y)
    middle = scale[np.searchsorted(np.cumsum(share), share.sum() / 2)]
    return np.maximum(scale, DEFAULTS.size_floor * middle)


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

    def expr(self, digits: int = DEFAULTS.significant) -> sympy.Expr:
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


def relative_residual(terms: list[Term], r: np.ndarray, y: np.ndarray, w: np.ndarray,
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
    ranking; the models kept are solved again by ``_solve`` and ``refine_constants``)."""
    norm = np.linalg.norm(cols, axis=0)
    unit = cols / np.where(norm > 0, norm, 1)
    gram, proj = unit.T @ unit, unit.T @ b
    g = gram[subsets[:, :, None], subsets[:, None, :]]             # (m, k, k)
    v = proj[subsets]                                               # (m, k)
    g = g + 1e-10 * np.eye(subsets.shape[1])                        # collinear subsets
    explained = (v * np.linalg.solve(g, v[..., None])[..., 0]).sum(1)
    return np.maximum(b @ b - explained, 0) / len(b)


def refine_constants(terms: list[Term], r: np.ndarray, y: np.ndarray, w: np.ndarray, x0: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray | None]:
    """Joint least squares of the amplitudes and the log of each constant from ``x0``
    (amplitudes, constants); (values, Jacobian in those values), or the start and None where
    the fit fails."""
    k = len(terms)

    def residual(theta: np.ndarray) -> np.ndarray:
        with np.errstate(over="ignore"):
            return relative_residual(terms, r, y, w, np.concatenate([theta[:k], np.exp(theta[k:])]))

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
        grid = np.geomspace(r[0] * 1e-2, r[-1] * 2,
                            DEFAULTS.c_grid if n_nl < 2 else DEFAULTS.c_grid_pair)
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
                for i in np.argsort(best)[:DEFAULTS.refine_per_complexity]:
                    keep(n_nl, float(best[i]), [*(linear[j] for j in subsets[i][:k]), *extra],
                         tuple(best_cs[i]))
    return found


def fit_formula(r: np.ndarray, y: np.ndarray, weight: np.ndarray | None = None,
                max_terms: int = 3, max_constants: int = 2,
                tolerance: float = DEFAULTS.tolerance, parsimony: float = 1.5,
                library: list[Term] | None = None,
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
        scale = floored_scale(r, y, share)
    w = np.sqrt(share / share.mean()) / scale
    b = y * w
    candidates = _candidates(r, b, w, default_library() if library is None else library,
                             max_terms, max_constants)
    refined: dict[int, tuple[float, list[Term], np.ndarray, np.ndarray | None]] = {}
    for (complexity, _), found in candidates.items():
        for _, terms, x0 in sorted(found, key=lambda e: e[0])[:DEFAULTS.refine_per_complexity]:
            loss0 = float(np.mean(relative_residual(terms, r, y, w, x0) ** 2))
            values, jac = refine_constants(terms, r, y, w, x0)
            loss = float(np.mean(relative_residual(terms, r, y, w, values) ** 2))
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
        boots.append(refine_constants(terms, r[pick], y[pick], w[pick], values)[0])
    boot_std = np.std(boots, axis=0) if boots else np.full(p, np.nan)
    alternatives = [(refined[e["complexity"]][1], np.asarray(refined[e["complexity"]][2],
                                                             np.float64)) for e in front]
    return Formula(terms, np.asarray(values, np.float64), stderr, boot_std, loss, chosen, front,
                   alternatives)


