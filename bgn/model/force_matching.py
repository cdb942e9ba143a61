"""Force matching: the pair-force head's MLP law started from a least-squares fit of the pair
law to the training frames, before any gradient step (``law_init=match``; docs/design.md,
"Force matching").

With equal masses (or the recorded ones), the head's acceleration ``a_i = sum_j f(s_ij) u_ij``
is linear in the law ``f``. Written as a table over distances (piecewise linear in ``log s``,
one table per pair of types), the law's values follow from the frames by linear least squares:
the force matching of classical interatomic potentials (Ercolessi & Adams 1994), with a
tabulated law as in MD codes' tabulated pair styles. The pair terms are weighted as the target
sees them (``numerov``, at the window's past frames, whose accelerations are known), so the
fit matches what the head predicts. The MLP is then fitted to the table (a one-dimensional
regression), and gradient training starts from a law that already moves the particles, where
a time budget otherwise spends most of its steps finding one (docs/notes/2026-11-26-force-
matching.md).

Why a table and not the MLP's own last layer: the last layer's least-squares fit over the
MLP's random features reaches the same error, but only by large coefficients that cancel,
which the first gradient steps on the hidden layers undo. Masses: the recorded ones where
the model trains with them (``known_masses``: its law loss), else all equal (the head's mass
fit corrects the rest). The table's smoothness penalty is chosen on validation windows, and
the MLP is kept only where it then beats its initial law there.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass

import torch

from bgn.graph import Graph
from bgn.law_table import NormalEquations, fit_table, hat_basis, law_size, log_knots
from bgn.model.newton import PairForceHead, numerov, pair_force_head_of, past_positions
from bgn.model.ops import scatter_sum
from bgn.model.target_coder import observed_targets, relative_floor

log = logging.getLogger(__name__)

# ``check``: what a fit calls between its iterations (the training layer hands in its clock
# and signal check, which raises to stop the fit; the models layer imports nothing of it)
Check = Callable[[], None]
PROGRESS_S = 5.0  # a fit still running after this many seconds says how far it is

KNOTS = 48  # table knots per pair of types, evenly spaced in log distance
EDGE_ELEMENTS = 1 << 24  # entries of the per-edge design held at once (64 MiB in float32)
# the matched law's learning rate relative to the optimiser's: Adam's first steps move every
# weight by about the full rate, which undoes a law already fitted
# (docs/notes/2026-11-26-force-matching.md)
MATCHED_LAW_LR = 0.1
DISTIL_STEPS, DISTIL_POINTS, DISTIL_LR = 3000, 256, 1e-2
# the MLP's squared error relative to the table's mean square at which its fit stops, far
# below the table's own error against the frames (a spring's and a gravity law's exact
# tables reach it in about 250 of the 3000 steps); and it stops where the error fell by less
# than DISTIL_STALL over the last DISTIL_WINDOW steps. Each step takes milliseconds on an
# idle core but 0.1 s on a busy one
DISTIL_TOL, DISTIL_STALL, DISTIL_WINDOW = 1e-5, 0.1, 500


@dataclass
class Table:
    """A pair law tabulated at ``KNOTS`` distances evenly spaced in ``log s`` from ``lo`` to
    ``hi`` (normalised units), piecewise linear between them, one row per pair of types."""

    lo: float
    hi: float
    values: torch.Tensor  # (pairs, KNOTS)

    def knots(self) -> torch.Tensor:
        return log_knots(self.lo, self.hi, self.values.shape[1])


@dataclass
class MatchResult:
    """What force matching did: the chosen smoothness, the relative squared error of the
    accelerations of the table on the training and validation windows, of the MLP fitted to
    it and of the initial MLP on validation, and whether the fitted MLP was kept."""

    smoothing: float
    table_train_error: float
    table_val_error: float
    val_error: float
    val_error_before: float
    kept: bool
    rows: int

    def as_dict(self) -> dict[str, float | bool | int]:
        return asdict(self)


def matchable(head: object) -> bool:
    """Whether force matching applies: a pair-force head whose law is an MLP (a formula law is
    fitted by the law stage instead) and whose masses the table can weigh: not couplings of
    either sign (``mass_law=coupling``), which a table of equal particles gets wrong in sign."""
    return isinstance(head, PairForceHead) and isinstance(head.force_law, torch.nn.Sequential) \
        and head.mass_law != "coupling"


def distance_range(head: PairForceHead, graphs: Iterable[Graph]) -> tuple[float, float] | None:
    """The smallest and largest pair distance (normalised units) over the windows of
    ``graphs``; None where they hold no pair."""
    lo, hi = math.inf, 0.0
    for g in graphs:
        if g.edge_index.shape[1]:
            dist = head.separations(g, past_positions(g))[1]
            lo, hi = min(lo, float(dist.min())), max(hi, float(dist.max()))
    return (lo, hi) if hi > lo > 0 else None


def mass_weights(head: PairForceHead, g: Graph, known_masses: bool,
                 ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """How the recorded masses enter the fit where they are known: per edge, the sender's mass
    (source law, ``a_i = sum_j m_j f u``), or per particle, its own mass on its target (the
    other laws, ``m_i a_i = sum_j f u``); (None, None) where all masses count as equal."""
    if not known_masses:
        return None, None
    mass = g.mass.to(g.pos.dtype)
    return (mass[g.edge_index[0]], None) if head.mass_law == "source" else (None, mass)


def without_kinematic(g: Graph, *node_values: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``node_values`` (N, ...) without the particles the source moves (never predicted)."""
    if g.kinematic is None:
        return node_values
    return tuple(v[~g.kinematic] for v in node_values)


def normal_equations(head: PairForceHead, g: Graph, knots: torch.Tensor, known_masses: bool,
                     ) -> NormalEquations:
    """The least-squares problem of one batch for the table's values (``pairs x KNOTS``)
    against the window's past accelerations, one row per particle, frame and coordinate;
    kinematic particles (moved by the source) left out."""
    rel, dist = head.separations(g, past_positions(g))                       # (E, F, D)
    n_frames = rel.shape[1] - 2  # numerov: frames t .. t-k+1; known accelerations: t-1 ..
    seen = observed_targets(g, "acceleration")[:, :n_frames]                 # (N, F-2, D)
    rcv = g.edge_index[1]
    by_edge, by_node = mass_weights(head, g, known_masses)
    pair = head.pair_index(g)
    n_pairs, k = max(head.types, 1) ** 2, len(knots)
    width = n_pairs * k                                                      # P
    design = rel.new_zeros(g.pos.shape[0], n_frames, rel.shape[2], width)    # (N, F-2, D, P)
    step = max(1, EDGE_ELEMENTS // (rel.shape[1] * rel.shape[2] * width))   # edges per chunk
    for lo in range(0, rel.shape[0], step):
        part = slice(lo, lo + step)
        basis = hat_basis(torch.log(dist[part, :, 0]).double(),
                          knots.to(rel.device)).to(rel.dtype)
        if pair is not None:  # each pair of types has its own table: its block of columns
            cols = (pair[part] * k)[:, None, None] + torch.arange(k, device=rel.device)
            basis = basis.new_zeros(*basis.shape[:2], width).scatter(
                -1, cols.expand_as(basis), basis)
        terms = numerov(basis[:, :, None, :] * (rel[part] / dist[part])[..., None])[:, 1:]
        if by_edge is not None:
            terms = terms * by_edge[part].to(terms.dtype)[:, None, None, None]
        design.index_add_(0, rcv[part], terms)
    if by_node is not None:
        seen = seen * by_node.to(seen.dtype)[:, None, None]
    design, seen = without_kinematic(g, design, seen)
    x = design.reshape(-1, design.shape[-1]).double()
    y = seen.reshape(-1).double()
    # the products on the frames' device; the small system is solved on the CPU (fit_table)
    return NormalEquations((x.T @ x).cpu(), (x.T @ y).cpu(), (y @ y).cpu(), int(y.numel()))


class Progress:
    """Calls ``check`` at each iteration and, once the fit has run ``PROGRESS_S`` seconds,
    logs how far it is every ``PROGRESS_S`` seconds."""

    def __init__(self, check: Check | None = None) -> None:
        self.check = check
        self.start = self.shown = time.monotonic()

    def __call__(self, what: str, done: int, total: int) -> None:
        if self.check is not None:
            self.check()
        now = time.monotonic()
        if now - self.shown >= PROGRESS_S:
            self.shown = now
            log.info("law_init=match: %s %d of %d (%.0f s)", what, done, total,
                     now - self.start)


def accumulate(head: PairForceHead, graphs: Iterable[Graph], knots: torch.Tensor,
               known_masses: bool, progress: Progress | None = None,
               ) -> NormalEquations | None:
    """``normal_equations`` summed over ``graphs`` (None when there are none)."""
    total = None
    graphs = list(graphs)
    for i, g in enumerate(graphs):
        if progress is not None:
            progress("batches of the least-squares fit", i, len(graphs))
        eq = normal_equations(head, g, knots, known_masses)
        total = eq if total is None else total + eq
    return total


def law_error(head: PairForceHead, graphs: Iterable[Graph], known_masses: bool) -> float:
    """Relative squared error of the accelerations that the head's current law gives at the
    windows' past frames (equal or recorded masses, as ``normal_equations``)."""
    num = den = 0.0
    for g in graphs:
        terms = numerov(head.pair_terms(g, past_positions(g)))[:, 1:]
        seen = observed_targets(g, "acceleration")[:, :terms.shape[1]]
        by_edge, by_node = mass_weights(head, g, known_masses)
        if by_edge is not None:
            terms = terms * by_edge.to(terms.dtype)[:, None, None]
        if by_node is not None:
            seen = seen * by_node.to(seen.dtype)[:, None, None]
        pred, seen = without_kinematic(g, scatter_sum(terms, g.edge_index[1], g.pos.shape[0]),
                                       seen)
        num += float(((pred - seen) ** 2).sum())
        den += float((seen**2).sum())
    return num / max(den, 1e-300)


def distil(head: PairForceHead, table: Table, progress: Progress | None = None) -> None:
    """Fit the head's MLP law to ``table`` at ``DISTIL_POINTS`` distances per pair of types,
    evenly spaced in log distance (Adam on each point's squared error relative to the
    table's size there, ``law_size``, floored as the relative loss floors a target, at most
    ``DISTIL_STEPS`` steps, until it is below ``DISTIL_TOL`` or stalls). Relative, so that
    every distance weighs alike: against the table's mean square, a law that spans decades
    (softened gravity's) is fitted at its close end only, and its far end starts off by its
    own size (docs/design.md, "Force matching")."""
    t = max(head.types, 1)
    # the unordered pairs of types pair_index gives (lo * t + hi, lo <= hi): the table's
    # other rows are never filled
    pairs = torch.tensor([a * t + b for a in range(t) for b in range(a, t)])
    u = log_knots(table.lo, table.hi, DISTIL_POINTS)
    target = (hat_basis(u, table.knots()) @ table.values[pairs].T).T.reshape(-1, 1)
    dist = torch.exp(u).repeat(len(pairs))[:, None, None]
    pair = None if head.types <= 1 else pairs.repeat_interleave(DISTIL_POINTS)
    param = next(head.force_law.parameters())
    inputs = head.law_input(dist.to(param), None if pair is None else pair.to(param.device))
    target = target.to(param)
    # each pair of types' row of the table, its size at each point (``law_size``), floored
    # as the relative loss floors a target (``target_coder.relative_floor``)
    size = law_size(target.reshape(len(pairs), -1).double().cpu().numpy(), u.numpy())
    size = torch.as_tensor(size, dtype=param.dtype, device=param.device).reshape(-1) ** 2
    scale = (size + relative_floor(size)).clamp_min(torch.finfo(param.dtype).tiny)
    optimizer = torch.optim.Adam(head.force_law.parameters(), lr=DISTIL_LR)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, DISTIL_STEPS)
    with torch.enable_grad():
        seen: list[float] = []  # the error every 50 steps
        for i in range(DISTIL_STEPS):
            optimizer.zero_grad()
            loss = (((head.force_law(inputs).reshape(-1) - target[:, 0]) ** 2) / scale).mean()
            if i % 50 == 0:
                seen.append(float(loss.detach()))
                if progress is not None:
                    progress(f"steps fitting the MLP to the table (relative error "
                             f"{seen[-1]:.2g})", i, DISTIL_STEPS)
                back = DISTIL_WINDOW // 50
                if seen[-1] < DISTIL_TOL or (len(seen) > back and
                                             seen[-1] > (1 - DISTIL_STALL) * seen[-1 - back]):
                    break
            loss.backward()
            optimizer.step()
            schedule.step()


@torch.no_grad()
def match_forces(head: PairForceHead, train: list[Graph], val: list[Graph],
                 known_masses: bool = False, check: Check | None = None) -> MatchResult | None:
    """Fit a tabulated law to the ``train`` windows (its smoothness chosen on ``val``), fit
    the head's MLP law to it, and keep that where it beats the initial law on ``val``. None
    where nothing could be fitted (no windows or no pairs). ``check``: called between
    iterations (it raises to stop the fit: a deadline, a signal); where it stops the fit,
    the law is left as it was before."""
    span = distance_range(head, train)
    if span is None or not val:
        return None
    n_pairs = max(head.types, 1) ** 2
    knots = log_knots(*span, KNOTS)
    progress = Progress(check)
    fit = accumulate(head, train, knots, known_masses, progress)
    held = accumulate(head, val, knots, known_masses, progress)
    assert fit is not None and held is not None
    if not torch.isfinite(fit.gram).all() or not float(fit.gram.diagonal().mean()) > 0:
        return None
    values, smoothing = fit_table(fit, held, n_pairs)
    table = Table(*span, values)
    before = law_error(head, val, known_masses)
    state = {k: v.clone() for k, v in head.force_law.state_dict().items()}
    try:
        distil(head, table, progress)
    except BaseException:  # stopped: the law as it was, not half fitted
        head.force_law.load_state_dict(state)
        raise
    after = law_error(head, val, known_masses)
    kept = after < before
    if not kept:
        head.force_law.load_state_dict(state)
    flat = values.reshape(-1)
    return MatchResult(smoothing, fit.relative_error(flat), held.relative_error(flat), after,
                       before, kept, fit.rows)


def matched_head(model: torch.nn.Module) -> PairForceHead | None:
    """A model's pair-force head where its config asks for force matching (``law_init=match``,
    an MLP law): BGN with ``dynamics=newton`` and ``model=newton``; else None."""
    head = pair_force_head_of(model)
    if getattr(getattr(model, "cfg", None), "law_init", "random") != "match" \
            or not matchable(head):
        return None
    return head


def matched_law_parameters(model: torch.nn.Module) -> list[torch.nn.Parameter]:
    """The parameters of a matched law (``matched_head``), which train at ``MATCHED_LAW_LR``
    times the optimiser's rate; empty where there is none."""
    head = matched_head(model)
    return [] if head is None else list(head.force_law.parameters())


def prepare(model: torch.nn.Module, train: Iterable[Graph], val: Iterable[Graph],
            check: Check | None = None) -> MatchResult | None:
    """Force matching of ``matched_head(model)``, with the recorded masses where the model
    trains with them (its law loss). None where nothing was fitted. ``check``: as
    ``match_forces``'s, also between the batches read."""
    head = matched_head(model)
    if head is None:
        return None
    return match_forces(head, list(train), list(val),
                        known_masses="law" in getattr(model, "heads", ()), check=check)
