"""A symbolic search for a pair law ``f(r)`` over expression trees (``search_law``).

The grammar (docs/design.md, "The law search"): a law is a normal form

    f(r) = F(r) * (a_1 T_1(r) + ... + a_m T_m(r)),   m <= ``max_terms``,

each term ``T`` the constant 1, a primitive, or a product of two primitives of different kinds,
``F`` an optional common factor (a primitive). The primitives are the operators
``pow exp log sin`` applied to the simplest parametric argument in r, each constant fitted:
``r^k``, ``|r + c|^k``, ``|r^2 + c|^k`` (pow of r, of a shifted r and of a shifted r^2; ``/``
and ``sqrt`` are powers), ``exp(k r)``, ``exp(k r^2)``, ``log|r + c|``, ``sin(k r)``. Nothing
in the grammar names a law: every law it holds is one of these trees with its constants fitted.

Constants by variable projection: the amplitudes ``a`` by linear least squares for any value of
the inner constants, those by ``scipy.optimize.least_squares`` (Levenberg-Marquardt) from
fixed starts (each primitive's, spread in units of the data's median distance, and the parent
form's fit) and from starts drawn at random with a fixed seed. The loss is the weighted mean
squared RELATIVE residual, the residual relative to ``bgn.laws.terms.law_scale`` and each
point weighted as ``fit_formula`` weights the sampled distances; the error of a form is the
root of its loss.

The search, in two parts. Sums of up to ``max_terms`` single primitives (and the constant)
are screened: every primitive's constants on a grid (``_grid``), the amplitudes of every pair
and of every triple of grid columns by linear least squares; the best of each combination of
kinds is refined. Forms with a product or a common
factor grow a term at a time (a beam): every one-term form (a product started also from the
best point of its grid), then from the best ``beam`` fits of each size every such form with
one more term (a product's factor may become the common factor of the new sum), up to
``product_terms`` terms. Each form's complexity is its node count (``complexity``); the front
of complexity against error is kept (with ``potentials``, the forms of a second search, run
alike on potentials ``U(r)`` of the same grammar whose force ``-dU/dr`` is fitted, in the same
pool, each counted on the potential's tree): the best fit of each complexity of each search
cleaned up (``clean_up``: drop terms, round exponents within ``snap_distance`` of a multiple
of ``snap_step``, each step kept only while the refitted error stays within ``clean_factor``
times the member's), and the front formed of the cleaned fits. The law chosen is the
simplest front member whose error is within the caller's ``tolerance`` (the learned law's own
uncertainty) both as fitted and held out (``holdout_error``: each of ``holdout_blocks``
contiguous ranges of r predicted by the form refitted on the rest), else none: "no formula
fits", and the front is returned anyway.
``same_form`` says whether two expressions are the same form up to constants (sympy), and
``constant_difference`` how far one's constants are from the other's in its family;
``expression_spec`` writes a member as a ``model.law_formula`` pair (``bgn.model.formula_law``).
The formula stage reads each pair of types' learned law with ``search_law``
(``bgn.laws.compare.read_law``) and fine-tunes the front's members (``bgn.laws.finetune``).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import sympy
from scipy.optimize import least_squares

from bgn.laws.options import DEFAULTS, SEARCH_DEFAULTS, SearchOptions
from bgn.laws.terms import floored_scale, law_scale

R = sympy.Symbol("r", positive=True)


# ----------------------------------------------------------------------------- the grammar


@dataclass(frozen=True)
class Primitive:
    """A parametric primitive: ``fn(r, constants)`` in numpy, ``expr(r, constants)`` in
    sympy, ``dfn`` and ``dexpr`` its derivative in r (written with ``Abs`` and no ``sign``, so
    that ``bgn.model.formula_law`` evaluates it: d|x|^k/dx = k x |x|^(k-2)); ``nodes`` its
    node count (each constant a node); ``starts`` its fixed starts, in units of the data's
    median distance ``s`` by each constant's kind (``kinds``: exponent, shift of r or of r^2,
    rate of r or of r^2); ``exponent``: which constant is a power (rounded by the clean-up),
    or None."""

    name: str
    fn: Callable[[np.ndarray, np.ndarray], np.ndarray]
    expr: Callable[[Any, list[Any]], sympy.Expr]
    dfn: Callable[[np.ndarray, np.ndarray], np.ndarray]
    dexpr: Callable[[Any, list[Any]], sympy.Expr]
    nodes: int
    starts: tuple[tuple[float, ...], ...]
    kinds: tuple[str, ...]
    exponent: int | None = None

    @property
    def n(self) -> int:
        return len(self.kinds)


def _exp(x: np.ndarray) -> np.ndarray:
    return np.exp(np.minimum(x, 700.0))


# starts: exponent as is; a shift in units of s (or s^2 for r^2); a rate in units of 1/s (1/s^2)
PRIMITIVES: tuple[Primitive, ...] = (
    Primitive("power", lambda r, k: r ** k[0], lambda r, k: r ** k[0],
              lambda r, k: k[0] * r ** (k[0] - 1), lambda r, k: k[0] * r ** (k[0] - 1), 3,
              ((-1.0,), (1.0,), (-6.0,)), ("exponent",), 0),
    Primitive("shifted power", lambda r, k: np.abs(r + k[1]) ** k[0],
              lambda r, k: sympy.Abs(r + k[1]) ** k[0],
              lambda r, k: k[0] * (r + k[1]) * np.abs(r + k[1]) ** (k[0] - 2),
              lambda r, k: k[0] * (r + k[1]) * sympy.Abs(r + k[1]) ** (k[0] - 2), 5,
              ((-1.0, 0.1), (-2.0, 0.1), (-6.0, -0.5)), ("exponent", "shift"), 0),
    Primitive("softened power", lambda r, k: np.abs(r * r + k[1]) ** k[0],
              lambda r, k: sympy.Abs(r**2 + k[1]) ** k[0],
              lambda r, k: 2 * k[0] * r * (r * r + k[1]) * np.abs(r * r + k[1]) ** (k[0] - 2),
              lambda r, k: 2 * k[0] * r * (r**2 + k[1]) * sympy.Abs(r**2 + k[1]) ** (k[0] - 2),
              7, ((-1.5, 0.1), (-0.5, 1.0)), ("exponent", "shift2"), 0),
    Primitive("exponential", lambda r, k: _exp(k[0] * r), lambda r, k: sympy.exp(k[0] * r),
              lambda r, k: k[0] * _exp(k[0] * r), lambda r, k: k[0] * sympy.exp(k[0] * r), 4,
              ((-1.0,), (-5.0,)), ("rate",)),
    Primitive("gaussian", lambda r, k: _exp(k[0] * r * r), lambda r, k: sympy.exp(k[0] * r**2),
              lambda r, k: 2 * k[0] * r * _exp(k[0] * r * r),
              lambda r, k: 2 * k[0] * r * sympy.exp(k[0] * r**2),
              6, ((-1.0,),), ("rate2",)),
    Primitive("log", lambda r, k: np.log(np.abs(r + k[0]) + 1e-300),
              lambda r, k: sympy.log(sympy.Abs(r + k[0])),
              lambda r, k: 1.0 / (r + k[0]), lambda r, k: 1 / (r + k[0]), 4,
              ((0.1,),), ("shift",)),
    Primitive("sine", lambda r, k: np.sin(k[0] * r), lambda r, k: sympy.sin(k[0] * r),
              lambda r, k: k[0] * np.cos(k[0] * r), lambda r, k: k[0] * sympy.cos(k[0] * r), 4,
              ((1.0,), (2.5,)), ("rate",)),
)

# the units of each kind of constant in powers of the median distance s
_UNIT = {"exponent": 0, "shift": 1, "shift2": 2, "rate": -1, "rate2": -2}

Term = tuple[int, ...]  # indices into PRIMITIVES: () the constant 1, (i,), or (i, j) with i < j
TERMS: tuple[Term, ...] = ((), *((i,) for i in range(len(PRIMITIVES))),
                           *itertools.combinations(range(len(PRIMITIVES)), 2))


@dataclass(frozen=True)
class Form:
    """``F * sum_k a_k T_k``: ``factor`` the index of F (None: 1), ``terms`` the T's;
    ``fixed``: inner constants held at a value (slot, value), the exponents the clean-up
    rounded; ``potential``: the tree is a potential U(r) and the law its force ``-dU/dr``."""

    factor: int | None
    terms: tuple[Term, ...]
    fixed: tuple[tuple[int, float], ...] = ()
    potential: bool = False

    @property
    def primitives(self) -> list[int]:
        """The primitive of each inner constant block, in slot order."""
        return ([] if self.factor is None else [self.factor]) + [p for t in self.terms for p in t]

    @property
    def n_inner(self) -> int:
        return sum(PRIMITIVES[p].n for p in self.primitives)

    @property
    def exponent_slots(self) -> list[int]:
        """The slots of the inner constants that are exponents."""
        out, i = [], 0
        for p in self.primitives:
            if PRIMITIVES[p].exponent is not None:
                out.append(i + PRIMITIVES[p].exponent)
            i += PRIMITIVES[p].n
        return out

    @property
    def key(self) -> tuple[Any, ...]:
        return (self.factor, tuple(sorted(self.terms)), self.fixed, self.potential)


def complexity(form: Form) -> int:
    """The node count of the form's tree: a primitive's nodes (every constant, fitted or
    rounded, one node); a term ``a T``: the amplitude and a product node, and one more for a
    product of two primitives; the constant term ``a``: 1; ``m`` terms: ``m - 1`` sum nodes;
    a common factor: its nodes and a product node. A potential's form is counted on the
    potential's tree (the force ``-dU/dr`` is read from it, not written)."""
    def term_nodes(t: Term) -> int:
        return 1 if not t else 1 + len(t) + sum(PRIMITIVES[p].nodes for p in t)

    n = sum(term_nodes(t) for t in form.terms) + len(form.terms) - 1
    return n if form.factor is None else n + 1 + PRIMITIVES[form.factor].nodes


def _columns(form: Form, inner: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(n, m) each term (times the common factor) at r for the inner constants ``inner``; of
    a potential's form, each term's force ``-d/dr (F T)`` (the product rule)."""
    blocks, i = [], 0
    for p in form.primitives:
        blocks.append(inner[i:i + PRIMITIVES[p].n])
        i += PRIMITIVES[p].n
    it = iter(blocks)
    # each factor as (value, derivative)
    if form.factor is None:
        common = (np.ones_like(r), np.zeros_like(r))
    else:
        k = next(it)
        common = (PRIMITIVES[form.factor].fn(r, k), PRIMITIVES[form.factor].dfn(r, k))
    out = np.empty((len(r), len(form.terms)))
    for j, t in enumerate(form.terms):
        val, der = common
        for p in t:
            k = next(it)
            v, d = PRIMITIVES[p].fn(r, k), PRIMITIVES[p].dfn(r, k)
            val, der = val * v, der * v + val * d
        out[:, j] = -der if form.potential else val
    return out


# ----------------------------------------------------------------------------- the fit


@dataclass
class Fit:
    """A form with its constants: ``inner`` every inner constant (fixed ones included) in slot
    order, ``amplitudes`` the a's; ``loss`` the weighted mean squared relative residual."""

    form: Form
    inner: np.ndarray
    amplitudes: np.ndarray
    loss: float

    @property
    def error(self) -> float:
        return math.sqrt(self.loss)

    @property
    def complexity(self) -> int:
        return complexity(self.form)


@dataclass
class Problem:
    """The points of a search: r sorted, ``b`` = y w, ``w`` each point's weight over its
    scale, ``s`` the median distance (the unit of the starts)."""

    r: np.ndarray
    b: np.ndarray
    w: np.ndarray
    s: float


def relative_weights(r: np.ndarray, y: np.ndarray, weight: np.ndarray | None) -> np.ndarray:
    """Each point's weight over its scale, the rule of ``bgn.laws.terms.fit_formula``:
    ``sqrt(weight / mean weight) / scale``, scale ``bgn.laws.terms.floored_scale``."""
    share = np.ones_like(r) if weight is None else weight
    return np.sqrt(share / share.mean()) / floored_scale(r, y, share)


def _project(form: Form, inner: np.ndarray, pb: Problem) -> tuple[np.ndarray, np.ndarray]:
    """The amplitudes of ``inner`` by linear least squares and the weighted residual (huge
    where the columns are not finite)."""
    cols = _columns(form, inner, pb.r) * pb.w[:, None]
    gram = cols.T @ cols
    if not np.isfinite(gram).all():
        return np.zeros(cols.shape[1]), np.full_like(pb.b, 1e6)
    # the normal equations (a few columns), scaled to a unit diagonal: far quicker than an SVD
    d = np.sqrt(np.diag(gram)) + 1e-300
    try:
        amps = np.linalg.solve(gram / np.outer(d, d) + 1e-12 * np.eye(len(d)),
                               (cols.T @ pb.b) / d) / d
    except np.linalg.LinAlgError:
        return np.zeros(cols.shape[1]), np.full_like(pb.b, 1e6)
    res = cols @ amps - pb.b
    return amps, np.where(np.isfinite(res), res, 1e6)


def fit_form(form: Form, pb: Problem, starts: list[np.ndarray],
             options: SearchOptions = SEARCH_DEFAULTS) -> Fit | None:
    """The best fit of ``form`` from each start (all inner constants, fixed ones included),
    or None where no start gives a finite fit."""
    with np.errstate(all="ignore"):  # a start may overflow: its residual is then huge
        return _fit_form(form, pb, starts, options)


def _fit_form(form: Form, pb: Problem, starts: list[np.ndarray],
              options: SearchOptions) -> Fit | None:
    fixed = dict(form.fixed)
    free = [i for i in range(form.n_inner) if i not in fixed]
    powers = form.exponent_slots
    best: Fit | None = None
    for start in starts:
        inner = np.array(start, np.float64)
        for i, v in fixed.items():
            inner[i] = v

        def residual(x: np.ndarray, inner: np.ndarray = inner) -> np.ndarray:
            trial = inner.copy()
            trial[free] = x
            if np.any(np.abs(trial[powers]) > options.max_exponent):
                return np.full_like(pb.b, 1e6)  # no power of the data's distances is that steep
            return _project(form, trial, pb)[1]

        if free:
            try:
                sol = least_squares(residual, inner[free], method="lm",
                                    max_nfev=options.evaluations * (len(free) + 1))
            except (ValueError, np.linalg.LinAlgError):
                continue
            inner[free] = sol.x
        if np.any(np.abs(inner[powers]) > options.max_exponent):
            continue
        amps, res = _project(form, inner, pb)
        loss = float(np.mean(res * res))
        if np.isfinite(loss) and loss < 1e11 and (best is None or loss < best.loss):
            best = Fit(form, inner, amps, loss)
    return best


def _fixed_starts(form: Form, s: float, warm: list[tuple[int, np.ndarray]],
                  limit: int) -> list[np.ndarray]:
    """Starts for ``form``: each primitive block from ``warm`` (a parent fit's blocks, matched
    by kind in order) where there is one, else each of the primitive's own starts (all
    combinations, at most ``limit``)."""
    pool = list(warm)
    choices = []
    for p in form.primitives:
        match = next((k for k, (q, _) in enumerate(pool) if q == p), None)
        if match is not None:
            choices.append([pool.pop(match)[1]])
        else:
            prim = PRIMITIVES[p]
            choices.append([np.array([v * s ** _UNIT[kind] for v, kind in zip(st, prim.kinds)])
                            for st in prim.starts])
    return [np.concatenate([np.zeros(0), *c])
            for c in itertools.islice(itertools.product(*choices), limit)]


def _random_starts(form: Form, s: float, rng: np.random.Generator, n: int,
                   options: SearchOptions) -> list[np.ndarray]:
    """``n`` starts drawn at random from the option ranges (exponents uniform, rates and
    shifts log-uniform / uniform, with either sign for rates), in units of ``s``."""
    out = []
    for _ in range(n):
        inner = []
        for p in form.primitives:
            for kind in PRIMITIVES[p].kinds:
                if kind == "exponent":
                    inner.append(rng.uniform(*options.exponent_range))
                elif kind.startswith("rate"):
                    lo, hi = options.rate_range
                    size = math.exp(rng.uniform(math.log(lo), math.log(hi)))
                    sign = -1.0 if kind == "rate2" or rng.random() < 0.75 else 1.0
                    inner.append(sign * size * s ** _UNIT[kind])
                else:
                    inner.append(rng.uniform(*options.shift_range) * s ** _UNIT[kind])
        out.append(np.array(inner))
    return out


def _blocks(fit: Fit) -> list[tuple[int, np.ndarray]]:
    out, i = [], 0
    for p in fit.form.primitives:
        out.append((p, fit.inner[i:i + PRIMITIVES[p].n]))
        i += PRIMITIVES[p].n
    return out


def _children(parent: Form) -> list[Form]:
    """Every form with one more term that holds a product or a common factor (sums of single
    primitives are screened, ``_screen``): any term added to the sum (a product term only,
    where the parent has neither); and where the parent is one product ``P Q``,
    ``P (a Q + b T)`` and ``Q (a P + b T)`` (its factor made common). A potential's forms
    stay potentials (a constant term without a factor exerts no force: never added)."""
    plain = parent.factor is None and all(len(t) < 2 for t in parent.terms)
    pot = parent.potential
    out = [Form(parent.factor, parent.terms + (t,), potential=pot) for t in TERMS
           if t not in parent.terms and not (plain and len(t) < 2)
           and not (pot and parent.factor is None and not t)]
    if parent.factor is None and len(parent.terms) == 1 and len(parent.terms[0]) == 2:
        p, q = parent.terms[0]
        for common, other in ((p, q), (q, p)):
            out += [Form(common, ((other,), t), potential=pot) for t in TERMS
                    if len(t) < 2 and t != (other,)]
    return out


# ----------------------------------------------------------------------------- screening


def _grid(p: int, s: float, options: SearchOptions) -> list[np.ndarray]:
    """The screening grid of primitive ``p``'s constants, in units of the median distance."""
    prim = PRIMITIVES[p]
    lo, hi = options.exponent_range
    steps = np.arange(math.ceil(lo / options.exponent_step),
                      math.floor(hi / options.exponent_step) + 1) * options.exponent_step
    powers = [float(k) for k in steps if k != 0]
    rates = np.geomspace(*options.rate_range, options.grid_rates)
    shifts = np.asarray(options.grid_shifts)
    axes = {"power": [powers],
            "shifted power": [list(options.grid_exponents_shifted), list(shifts * s)],
            "softened power": [powers, list(shifts[shifts > 0] * s * s)],
            "exponential": [list(np.concatenate([-rates, rates]) / s)],
            "gaussian": [list(-rates / s**2)],
            "log": [[0.0, *(shifts * s)]],
            "sine": [list(rates / s)]}[prim.name]
    return [np.array(c) for c in itertools.product(*axes)]


def _screen(pb: Problem, options: SearchOptions, potential: bool = False
            ) -> list[tuple[float, Form, np.ndarray]]:
    """Sums of two and three single primitives (or the constant) by linear least squares over
    every grid point of their constants (every pair and every triple of grid columns; a
    triple as column i and the best pair of the others with i projected out): the best of each
    combination of kinds as
    (loss, form, start of the inner constants), the best ``refine_per_size`` of each size.
    ``potential``: the sums are potentials, each column a primitive's force ``-dP/dr`` (no
    constant: it exerts none)."""
    cols, kinds, consts = ([], [], []) if potential else ([pb.w.copy()], [-1], [np.zeros(0)])
    with np.errstate(all="ignore"):
        for p in range(len(PRIMITIVES)):
            for k in _grid(p, pb.s, options):
                col = (-PRIMITIVES[p].dfn(pb.r, k) if potential
                       else PRIMITIVES[p].fn(pb.r, k)) * pb.w
                if np.isfinite(col).all() and np.abs(col).max() > 0:
                    cols.append(col)
                    kinds.append(p)
                    consts.append(k)
    u = np.stack(cols, 1)
    u = u / np.linalg.norm(u, axis=0)
    kinds_a = np.array(kinds)
    gram, v, bb = u.T @ u, u.T @ pb.b, float(pb.b @ pb.b)
    n = len(pb.b)
    det = 1 - gram**2
    with np.errstate(all="ignore"):
        explained = (v[:, None] ** 2 + v[None, :] ** 2 - 2 * gram * v[:, None] * v[None, :]) / det
    explained[(det < options.collinear) | ~np.triu(np.ones_like(det, bool), 1)] = -np.inf
    loss2 = (bb - explained) / n

    def term(i: int) -> Term:
        return () if kinds[i] < 0 else (kinds[i],)

    def form_of(idx: tuple[int, ...]) -> tuple[Form, np.ndarray]:
        order = sorted(idx, key=lambda i: kinds[i])
        return (Form(None, tuple(term(i) for i in order), potential=potential),
                np.concatenate([np.zeros(0), *(consts[i] for i in order)]))

    pairs: list[tuple[float, tuple[int, int]]] = []
    for a in sorted(set(kinds)):
        for b in sorted(set(kinds)):
            if b < a:
                continue
            mask = (kinds_a[:, None] == a) & (kinds_a[None, :] == b)
            mask |= (kinds_a[:, None] == b) & (kinds_a[None, :] == a)
            block = np.where(mask, loss2, np.inf)
            k = int(np.argmin(block))
            if np.isfinite(block.flat[k]):
                pairs.append((float(block.flat[k]), divmod(k, len(kinds))))
    pairs.sort()
    out = [(loss, *form_of(idx)) for loss, idx in pairs[:options.refine_per_size]]
    if options.max_terms < 3:
        return out
    # every triple: project each column i out of the others and of b, then screen the pairs
    # of the residuals as above (the best triple's pairs need not be the best pairs)
    first = {a: (int(np.flatnonzero(kinds_a == a)[0]), int(np.flatnonzero(kinds_a == a)[-1]) + 1)
             for a in sorted(set(kinds))}  # the columns are grouped by kind
    triples: dict[tuple[int, ...], tuple[float, tuple[int, ...]]] = {}
    with np.errstate(all="ignore"):
        for i in range(len(kinds)):
            g = gram[i]
            d = 1 - g * g  # each column's squared norm once column i is projected out
            norm = np.sqrt(np.where(d > options.collinear, d, np.inf))
            gp = (gram - np.outer(g, g)) / np.outer(norm, norm)
            vp = (v - g * v[i]) / norm
            det = 1 - gp * gp
            ex = (vp[:, None] ** 2 + vp[None, :] ** 2 - 2 * gp * vp[:, None] * vp[None, :]) / det
            ex[(det < options.collinear) | ~np.isfinite(ex)] = -np.inf
            ex[i, :] = ex[:, i] = -np.inf
            for a, (sa, ea) in first.items():
                for b, (sb, eb) in first.items():
                    if b < a:
                        continue
                    block = ex[sa:ea, sb:eb]
                    if a == b:
                        block = np.where(np.triu(np.ones_like(block, bool), 1), block, -np.inf)
                    k = int(np.argmax(block))
                    if not np.isfinite(block.flat[k]):
                        continue
                    j, m = divmod(k, block.shape[1])
                    key = tuple(sorted((kinds[i], a, b)))
                    loss = (bb - v[i] ** 2 - block.flat[k]) / n
                    if key not in triples or loss < triples[key][0]:
                        triples[key] = (float(loss), (i, sa + j, sb + m))
    best3 = sorted(triples.values())[:options.refine_per_size]
    return out + [(loss, *form_of(idx)) for loss, idx in best3]


def _screen_products(pb: Problem, options: SearchOptions, potential: bool = False
                     ) -> dict[Term, np.ndarray]:
    """Each one-term product ``P Q``'s best point on the grid of both primitives' constants
    (one column's least squares, all grid points at once): a start for its fit. ``potential``:
    the column is the product's force ``-(P' Q + P Q')``."""
    grids, banks, dbanks = {}, {}, {}
    with np.errstate(all="ignore"):
        for p in range(len(PRIMITIVES)):
            ks = _grid(p, pb.s, options)
            cols = np.stack([PRIMITIVES[p].fn(pb.r, k) for k in ks])
            dcols = np.stack([PRIMITIVES[p].dfn(pb.r, k) for k in ks])
            ok = np.isfinite(cols).all(1) & np.isfinite(dcols).all(1)
            grids[p], banks[p], dbanks[p] = ([k for k, good in zip(ks, ok) if good], cols[ok],
                                             dcols[ok])
        out: dict[Term, np.ndarray] = {}
        wb, w2 = pb.w * pb.b, pb.w**2
        for t in TERMS:
            if len(t) != 2 or not len(grids[t[0]]) or not len(grids[t[1]]):
                continue
            a, b = banks[t[0]], banks[t[1]]
            if potential:  # the column -(a' b + a b'): its products, expanded
                da, db = dbanks[t[0]], dbanks[t[1]]
                dot = -((da * wb) @ b.T + (a * wb) @ db.T)
                norm2 = ((da * da) @ (b * b * w2).T + 2 * (da * a) @ (b * db * w2).T
                         + (a * a) @ (db * db * w2).T)
            else:
                dot = (a * wb) @ b.T
                norm2 = (a * a) @ (b * b * w2).T
            score = np.where(norm2 > 0, dot**2 / norm2, -np.inf)
            score[~np.isfinite(score)] = -np.inf
            i, j = divmod(int(np.argmax(score)), score.shape[1])
            out[t] = np.concatenate([grids[t[0]][i], grids[t[1]][j]])
    return out


# ----------------------------------------------------------------------------- expressions


def _rational(v: float, options: SearchOptions) -> sympy.Expr | None:
    """``v`` as the multiple of ``snap_step`` it was rounded to (a fixed exponent)."""
    steps = round(v / options.snap_step)
    return sympy.nsimplify(steps * options.snap_step) if math.isclose(
        v, steps * options.snap_step, abs_tol=1e-12) else None


def form_expression(fit: Fit, named: bool = False, digits: int = 15,
                    options: SearchOptions = SEARCH_DEFAULTS, force: bool = True
                    ) -> tuple[sympy.Expr, dict[str, float]]:
    """The fit as a sympy expression in ``R``: its constants as numbers (``named`` False) or
    as symbols ``a1, ...`` (amplitudes) and ``k1, ...`` (inner constants) with their values;
    a rounded exponent is a number either way. Of a potential's fit: its force ``-dU/dr``
    (the product rule on each primitive's ``dexpr``), or with ``force`` False the potential
    ``U`` itself."""
    fixed = dict(fit.form.fixed)
    values: dict[str, float] = {}
    inner_syms: list[Any] = []
    for i, v in enumerate(fit.inner):
        if i in fixed:
            inner_syms.append(_rational(v, options) or sympy.Float(v, digits))
        elif named:
            name = f"k{len([n for n in values if n.startswith('k')]) + 1}"
            values[name] = float(v)
            inner_syms.append(sympy.Symbol(name, real=True))
        else:
            inner_syms.append(sympy.Float(v, digits))
    blocks, i = [], 0
    for p in fit.form.primitives:
        blocks.append(inner_syms[i:i + PRIMITIVES[p].n])
        i += PRIMITIVES[p].n
    it = iter(blocks)
    derive = fit.form.potential and force
    if fit.form.factor is None:
        common: tuple[sympy.Expr, sympy.Expr] = (sympy.Integer(1), sympy.Integer(0))
    else:
        k = next(it)
        common = (PRIMITIVES[fit.form.factor].expr(R, k), PRIMITIVES[fit.form.factor].dexpr(R, k))
    total, dtotal = sympy.Integer(0), sympy.Integer(0)
    for j, (t, a) in enumerate(zip(fit.form.terms, fit.amplitudes)):
        if named:
            values[f"a{j + 1}"] = float(a)
            amp: sympy.Expr = sympy.Symbol(f"a{j + 1}", real=True)
        else:
            amp = sympy.Float(a, digits)
        val, der = sympy.Integer(1), sympy.Integer(0)
        for p in t:
            k = next(it)
            v, d = PRIMITIVES[p].expr(R, k), PRIMITIVES[p].dexpr(R, k)
            val, der = val * v, der * v + val * d
        total, dtotal = total + amp * val, dtotal + amp * der
    if derive:  # -d/dr (F sum) = -(F' sum + F sum')
        return -(common[1] * total + common[0] * dtotal), values
    return common[0] * total, values


# ----------------------------------------------------------------------------- the search


@dataclass
class Member:
    """A front member: ``complexity`` (nodes), ``error`` (RMS weighted relative residual),
    ``expr`` (sympy, constants as numbers), ``template`` (constants as symbols) and
    ``constants`` (their values), ``cleaned``: what the clean-up changed; ``potential``: of a
    member read as a potential, U(r) (its ``expr`` is the force ``-dU/dr``), else None;
    ``holdout``: its held-out error (``holdout_error``)."""

    complexity: int
    error: float
    expr: sympy.Expr
    template: sympy.Expr
    constants: dict[str, float]
    fit: Fit
    cleaned: list[str] = field(default_factory=list)
    potential: sympy.Expr | None = None
    holdout: float = math.nan

    def __call__(self, r: np.ndarray) -> np.ndarray:
        """The member's force at distances ``r`` (its fit's columns and amplitudes)."""
        r = np.asarray(r, np.float64)
        with np.errstate(all="ignore"):
            return _columns(self.fit.form, self.fit.inner, r) @ self.fit.amplitudes

    @property
    def text(self) -> str:
        """The force; of a potential's member, ``-d/dr[U]`` with U written out."""
        if self.potential is not None:
            return f"-d/dr[{sympy.sstr(sympy.N(self.potential, DEFAULTS.significant))}]"
        return sympy.sstr(sympy.N(self.expr, DEFAULTS.significant))


@dataclass
class SearchResult:
    """The front (simplest first), the member chosen (None: no formula fits within
    ``tolerance``), seconds per phase, forms fitted."""

    front: list[Member]
    chosen: Member | None
    tolerance: float
    timings: dict[str, float]
    n_forms: int

    @property
    def outcome(self) -> str:
        return "formula" if self.chosen is not None else "no formula fits"


def _member(fit: Fit, cleaned: list[str], options: SearchOptions) -> Member:
    expr, _ = form_expression(fit, options=options)
    template, constants = form_expression(fit, named=True, options=options)
    potential = (form_expression(fit, options=options, force=False)[0] if fit.form.potential
                 else None)
    return Member(fit.complexity, fit.error, expr, template, constants, fit, cleaned, potential)


def clean_up(fit: Fit, pb: Problem, options: SearchOptions = SEARCH_DEFAULTS
             ) -> tuple[Fit, list[str]]:
    """Engine-neutral simplification of a fitted form, each step kept only while its refitted
    error stays within ``clean_factor`` times the error before it: drop terms (the one whose
    removal costs least, repeatedly), then round each free exponent within
    ``snap_distance`` of a non-zero multiple of ``snap_step`` (closest first)."""
    done: list[str] = []
    while len(fit.form.terms) > 1:
        trials = []
        for k in range(len(fit.form.terms)):
            form = Form(fit.form.factor, fit.form.terms[:k] + fit.form.terms[k + 1:],
                        potential=fit.form.potential)
            head, per_term = _term_blocks(fit)
            keep = head + [b for j, blk in enumerate(per_term) if j != k for b in blk]
            start = np.concatenate(keep or [np.zeros(0)])
            if (one := fit_form(form, pb, [start], options)) is not None:
                trials.append((one.loss, k, one))
        if not trials or min(trials, key=lambda e: e[0])[0] > (options.clean_factor
                                                                 * fit.error) ** 2:
            break
        _, k, fit = min(trials, key=lambda e: e[0])
        done.append(f"dropped term {k + 1}")
    slots = [j for j in fit.form.exponent_slots if j not in dict(fit.form.fixed)]
    step = options.snap_step
    near = sorted(slots, key=lambda j: abs(fit.inner[j] - step * round(fit.inner[j] / step)))
    for j in near:
        v = fit.inner[j]
        h = step * round(v / step)
        if h == 0 or abs(v - h) > options.snap_distance:
            continue
        form = Form(fit.form.factor, fit.form.terms, fit.form.fixed + ((j, h),),
                    fit.form.potential)
        start = fit.inner.copy()
        start[j] = h
        one = fit_form(form, pb, [start], options)
        if one is not None and one.loss <= (options.clean_factor * fit.error) ** 2:
            fit = one
            done.append(f"exponent {v:.4g} -> {h:g}")
    return fit, done


def holdout_blocks(share: np.ndarray, blocks: int) -> list[np.ndarray]:
    """The points (sorted by r) cut into ``blocks`` contiguous ranges of r, each holding an equal
    share of the points' weight: a mask per range."""
    cut = np.cumsum(share) / share.sum()
    index = np.minimum((cut * blocks).astype(int), blocks - 1)
    return [index == j for j in range(blocks)]


def holdout_error(fit: Fit, pb: Problem, masks: list[np.ndarray],
                  options: SearchOptions = SEARCH_DEFAULTS) -> float:
    """The form's error on distances it was not fitted to: each range of ``masks`` predicted by
    the form refitted (from its own constants) on the others, the RMS weighted relative
    residual over every point; inf where a refit fails. A form that interpolates the
    learned law's wiggles fits each range from the rest badly; the law's own form does not."""
    res = np.zeros_like(pb.b)
    for m in masks:
        if not m.any() or m.all():
            continue
        one = fit_form(fit.form, Problem(pb.r[~m], pb.b[~m], pb.w[~m], pb.s), [fit.inner],
                       options)
        if one is None:
            return math.inf
        with np.errstate(all="ignore"):
            out = (_columns(fit.form, one.inner, pb.r[m]) @ one.amplitudes) * pb.w[m] - pb.b[m]
        res[m] = np.where(np.isfinite(out), out, 1e6)
    return float(np.sqrt(np.mean(res * res)))


def _term_blocks(fit: Fit) -> tuple[list[np.ndarray], list[list[np.ndarray]]]:
    """The inner constants of the common factor (empty list: none) and of each term."""
    blocks = [b for _, b in _blocks(fit)]
    head = blocks[:1] if fit.form.factor is not None else []
    out, i = [], len(head)
    for t in fit.form.terms:
        out.append(blocks[i:i + len(t)])
        i += len(t)
    return head, out


def _pareto(fits: list[Fit], margin: float) -> list[Fit]:
    """The simplest fit of least error, then each more complex one that lowers the error below
    ``margin`` times the last kept."""
    best: dict[int, Fit] = {}
    for f in fits:
        if f.complexity not in best or f.loss < best[f.complexity].loss:
            best[f.complexity] = f
    front: list[Fit] = []
    for c in sorted(best):
        if not front or best[c].error < margin * front[-1].error:
            front.append(best[c])
    return front


def search_law(r: np.ndarray, y: np.ndarray, weight: np.ndarray | None = None,
               tolerance: float = DEFAULTS.tolerance,
               options: SearchOptions = SEARCH_DEFAULTS) -> SearchResult:
    """The law ``y(r)`` by the search of the module doc. ``r`` > 0; ``weight``: how much each
    point counts (``fit_formula``'s weights: the density of the data's distances); the
    chosen member is the simplest on the front whose error (RMS weighted relative residual)
    is within ``tolerance``, as fitted and held out (``holdout_error``), else None."""
    # trial constants overflow on the way (a steep power of the data's distances): every fit
    # is checked for finite residuals, so numpy's warnings would only be noise in a command
    with np.errstate(all="ignore"):
        return _search_law(r, y, weight, tolerance, options)


def _search_law(r: np.ndarray, y: np.ndarray, weight: np.ndarray | None, tolerance: float,
                options: SearchOptions) -> SearchResult:
    t0 = time.perf_counter()
    order = np.argsort(r)
    r, y = np.asarray(r, np.float64)[order], np.asarray(y, np.float64)[order]
    share = None if weight is None else np.asarray(weight, np.float64)[order]
    if share is not None:
        if not (np.isfinite(share).all() and (share >= 0).all() and share.sum() > 0):
            raise ValueError("the weights of a law's points must be finite, >= 0, not all 0")
        r, y, share = r[share > 0], y[share > 0], share[share > 0]
    if len(r) < 8 or not (r > 0).all() or not np.isfinite(y).all():
        raise ValueError(f"a law search needs >= 8 finite points at r > 0 of weight > 0; got "
                         f"{len(r)} points")
    w = relative_weights(r, y, share)
    pb = Problem(r, y * w, w, float(np.median(r)))
    rng = np.random.default_rng(options.seed)
    fitted: dict[tuple[Any, ...], Fit] = {}

    def run(form: Form, starts: list[np.ndarray]) -> None:
        one = fit_form(form, pb, starts, options)
        if one is not None and (form.key not in fitted or one.loss < fitted[form.key].loss):
            fitted[form.key] = one

    def restart(fits: list[Fit]) -> None:
        """More starts, drawn at random, for these fits (each kept if better)."""
        for f in fits:
            if f.form.n_inner:
                run(f.form, [f.inner] + _random_starts(f.form, pb.s, rng,
                                                      options.random_starts, options))

    t_screen = 0.0
    # the force's trees, then (``potentials``) the potential's, each searched alike
    for potential in (False, True) if options.potentials else (False,):
        t = time.perf_counter()
        screened = _screen(pb, options, potential)
        product_starts = _screen_products(pb, options, potential)
        for _, form, start in screened:
            if len(form.terms) <= options.max_terms:
                run(form, [start])
        t_screen += time.perf_counter() - t
        parents: list[Fit] = []
        for size in range(1, min(options.max_terms, options.product_terms) + 1):
            if size > 1:
                seen = set(fitted)
                for parent in parents:
                    for child in _children(parent.form):
                        if child.key in seen:
                            continue
                        seen.add(child.key)
                        run(child, _fixed_starts(child, pb.s, _blocks(parent),
                                                 options.child_starts))
            else:
                for term in TERMS:
                    if potential and not term:
                        continue  # a constant potential exerts no force
                    form = Form(None, (term,), potential=potential)
                    grid = [product_starts[term]] if term in product_starts else []
                    run(form, grid + _fixed_starts(form, pb.s, [], options.fixed_starts))
            this = sorted((f for f in fitted.values()
                           if len(f.form.terms) == size and f.form.potential == potential),
                          key=lambda f: f.loss)
            restart(this[:options.random_forms])
            this = sorted((f for f in fitted.values()
                           if len(f.form.terms) == size and f.form.potential == potential),
                          key=lambda f: f.loss)
            parents = this[:options.beam]
    t_search = time.perf_counter() - t0
    raw = _pareto(list(fitted.values()), options.front_margin)
    restart([f for f in raw if f.form.key in fitted])
    t_restart = time.perf_counter() - t0 - t_search
    # the best fit of each complexity of each search (force, potential) cleaned up, and only
    # cleaned fits compared: a rounded exponent costs a little error, so an unrounded fit of
    # the same size would otherwise always beat its cleaned twin
    best: dict[tuple[int, bool], Fit] = {}
    for f in fitted.values():
        at = (f.complexity, f.form.potential)
        if at not in best or f.loss < best[at].loss:
            best[at] = f
    cleaned: dict[int, tuple[Fit, list[str]]] = {}
    pool = []
    for f in best.values():
        g, done = clean_up(f, pb, options)
        cleaned[id(g)] = (g, done)
        pool.append(g)
    front = _pareto(pool, options.front_margin)
    members = [_member(f, cleaned.get(id(f), (f, []))[1], options) for f in front]
    t = time.perf_counter()
    masks = holdout_blocks(np.ones_like(r) if share is None else share, options.holdout_blocks)
    for m in members:
        m.holdout = holdout_error(m.fit, pb, masks, options)
    chosen = next((m for m in members if m.error <= tolerance and m.holdout <= tolerance), None)
    total = time.perf_counter() - t0
    return SearchResult(members, chosen, tolerance,
                        {"screen_s": t_screen, "search_s": t_search, "restarts_s": t_restart,
                         "clean_up_s": t - t0 - t_search - t_restart,
                         "holdout_s": total - (t - t0), "total_s": total},
                        len(fitted))


# ----------------------------------------------------------------------------- judging


def family(expr: sympy.Expr) -> tuple[sympy.Expr, list[sympy.Symbol], list[float]]:
    """``expr`` with every float replaced by a free symbol: its parametric family, the
    symbols and their values (a rational or integer stays: it is the form's)."""
    floats = sorted(sympy.sympify(expr).atoms(sympy.Float), key=lambda f: (float(f), str(f)))
    syms = list(sympy.symbols(f"q0:{len(floats)}", real=True))
    return sympy.sympify(expr).xreplace(dict(zip(floats, syms))), syms, [float(f) for f in floats]


def _reach(fam: sympy.Expr, syms: list[sympy.Symbol], x0: list[float], r: np.ndarray,
           target: np.ndarray, scale: np.ndarray, options: SearchOptions
           ) -> tuple[float, np.ndarray]:
    """The least RMS of ``(fam - target) / scale`` over the family's constants, from ``x0``
    and perturbed starts, and the constants that reach it."""
    fn = sympy.lambdify([R, *syms], fam, "numpy")

    def resid(p: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            v = np.broadcast_to(np.asarray(fn(r, *p), np.float64), r.shape)
        out = (v - target) / scale
        return np.where(np.isfinite(out), out, 1e6)

    if not syms:
        return float(np.sqrt(np.mean(resid(np.zeros(0)) ** 2))), np.zeros(0)
    rng = np.random.default_rng(1)
    best, at = np.inf, np.array(x0, np.float64)
    for k in range(options.same_form_starts):
        p0 = np.array(x0, np.float64) * (1 if k == 0 else np.exp(rng.normal(0, 0.3, len(x0))))
        try:
            sol = least_squares(resid, p0, method="lm" if len(r) >= len(p0) else "trf",
                                max_nfev=400 * (len(p0) + 1), xtol=1e-15, ftol=1e-15,
                                gtol=1e-15)
        except (ValueError, np.linalg.LinAlgError):
            continue
        rms = float(np.sqrt(np.mean(sol.fun ** 2)))
        if rms < best:
            best, at = rms, sol.x
    return best, at


def same_form(found: sympy.Expr, truth: sympy.Expr, r: np.ndarray,
              truth_constants: dict[sympy.Symbol, float] | None = None,
              options: SearchOptions = SEARCH_DEFAULTS) -> bool:
    """Whether ``found`` (constants as numbers) and ``truth`` are the same form up to
    constants, over the distances ``r``: ``found``'s family (every float free) reaches the
    truth, and the truth's family (its symbols ``truth_constants`` free, else its floats)
    reaches ``found``, each within ``same_form_tolerance`` RMS relative to the truth's
    ``law_scale``. A family fitted to a member of a larger family misses it by more."""
    r = np.sort(np.asarray(r, np.float64))
    found = sympy.sympify(found)
    truth = sympy.sympify(truth)
    if truth_constants:
        t_fam, t_syms = truth, list(truth_constants)
        t_x0 = [float(truth_constants[s]) for s in t_syms]
        truth = truth.subs(truth_constants)
    else:
        t_fam, t_syms, t_x0 = family(truth)
    with np.errstate(all="ignore"):
        f_true = np.broadcast_to(np.asarray(sympy.lambdify(R, truth, "numpy")(r), np.float64),
                                 r.shape)
        f_found = np.broadcast_to(np.asarray(sympy.lambdify(R, found, "numpy")(r), np.float64),
                                  r.shape)
    if not (np.isfinite(f_true).all() and np.isfinite(f_found).all()):
        return False
    scale = law_scale(r, f_true, smooth=False)
    fam, syms, x0 = family(found)
    tol = options.same_form_tolerance
    return bool(_reach(fam, syms, x0, r, f_true, scale, options)[0] < tol
                and _reach(t_fam, t_syms, t_x0, r, f_found, scale, options)[0] < tol)


def constant_difference(found: sympy.Expr, truth: sympy.Expr, r: np.ndarray,
                        options: SearchOptions = SEARCH_DEFAULTS) -> float:
    """How far ``found``'s constants are from the truth's in ``found``'s own family: the
    family (every float of ``found`` free) fitted to ``truth`` (constants as numbers) over
    ``r`` as ``same_form`` fits it, and the largest relative difference ``|found - fitted| /
    |fitted|`` of its constants (inf where a fitted constant is 0 and the found one is not;
    meaningful where ``same_form`` holds). 0 for a family without constants."""
    r = np.sort(np.asarray(r, np.float64))
    with np.errstate(all="ignore"):
        f_true = np.broadcast_to(np.asarray(sympy.lambdify(R, sympy.sympify(truth), "numpy")(r),
                                            np.float64), r.shape)
    fam, syms, x0 = family(sympy.sympify(found))
    if not syms:
        return 0.0
    _, fitted = _reach(fam, syms, x0, r, f_true, law_scale(r, f_true, smooth=False), options)
    found_x = np.asarray(x0, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        diff = np.abs(found_x - fitted) / np.abs(fitted)
    diff = np.where(found_x == fitted, 0.0, diff)
    return float(np.max(diff))


# ----------------------------------------------------------------------------- the spec


def expression_spec(member: Member, types: tuple[int, int] = (0, 0),
                    free_exponents: bool = False) -> dict[str, Any]:
    """A front member as one pair's entry of a ``model.law_formula`` spec
    (``bgn.model.formula_law``): ``{"types", "expr", "constants"}``. ``free_exponents``: the
    exponents the clean-up rounded on the learned law become constants again, at their
    rounded values, for a fit to the frames to move (the formula stage's tuning, which rounds
    what it fits by the same rule)."""
    template, constants = member.template, member.constants
    if free_exponents and member.fit.form.fixed:
        fit = replace(member.fit, form=replace(member.fit.form, fixed=()))
        template, constants = form_expression(fit, named=True)
    return {"types": [int(t) for t in types], "expr": sympy.sstr(template),
            "constants": {k: float(v) for k, v in constants.items()}}
