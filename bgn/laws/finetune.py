"""The formula fitted to the frames as the model's law (``finetune_formula``).

``finetune=true`` (``finetune_formula``): the formula as the model's law (``model.law=formula``,
``model.law_formula``: expression pairs, ``bgn.laws.search.expression_spec``, evaluated by
``bgn.model.formula_law``). The law search's front members (``candidate_specs``: the member
chosen first, then the others simplest first, at most ``LawOptions.finetune_members``) each
have their constants fitted to the frames (``tune_constants``: Nelder-Mead on the head's law
loss under a Cauchy loss, ``law_objective``, through ``model.substeps``: a frame's
finite-difference target averages the force over the frame); the lowest loss wins, the
simplest within ``form_tolerance`` of it, and its constants are polished through finer
substeps (``polish_constants``). The network law and the formula are then scored on the
validation rollouts (``bgn.studies.auto``'s protocol) and the better chosen;
``<run>/laws/formula.ckpt`` (with its ``train_config.yaml``) loads as any checkpoint. Where
no formula fits the learned law (the search chose no member), nothing is tuned: the network
law is kept and the record says so (``outcome``). ``model.law=auto`` runs this after training
(``bgn.laws.stage.law_stage``).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import sympy
import torch
from scipy.optimize import minimize

from bgn.laws.compare import LawReport, against_truth, read_law
from bgn.laws.options import DEFAULTS, SEARCH_DEFAULTS, SearchOptions
from bgn.laws.sample import calibrate_scale, pair_distances, pair_force_head
from bgn.laws.search import expression_spec
from bgn.training.budget import NO_DEADLINE, Deadline, OutOfTime, check, clock_text

log = logging.getLogger("bgn.train")


def formula_spec(report: LawReport, free_exponents: bool = False) -> str:
    """The report's formulas (each pair's ``PairLaw.formula``) as ``model.law_formula``: a JSON
    list of expression pairs (``bgn.laws.search.expression_spec``; ``bgn.model.formula_law``'s
    format), in physical units: the head with ``model.law=formula`` evaluates this law.
    ``free_exponents``: the search's rounded exponents as constants again (the tuning's
    starts)."""
    return json.dumps([expression_spec(pair.formula, pair.types, free_exponents)
                       for pair in report.pairs])


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
        {k: v for k, v in old.items() if ".force_law." not in k and "log_law_gain" not in k},
        strict=False)
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
    ``DEFAULTS.close_share`` of ``size`` frames with the closest pairs (weight: their share of the
    split), and frames drawn at random from the rest (weight: the rest's share). The weighted
    sum is an unbiased estimate of the loss over the whole split, with far less variance at
    small r than a random batch of the same size."""
    from bgn.graph import collate

    n = len(dataset)
    if size >= n:
        return [(1.0, collate([dataset[i] for i in range(n)]))]
    order = closest_frames(dataset)
    k = max(1, int(round(size * DEFAULTS.close_share)))
    rest = np.random.default_rng(seed).choice(order[k:], size - k, replace=False)
    return [(k / n, collate([dataset[int(i)] for i in order[:k]])),
            ((n - k) / n, collate([dataset[int(i)] for i in np.sort(rest)]))]


def checked_rollouts(model: Any, val: Any, sims: list[int], starts: list[int], n_steps: int,
                     deadline: Deadline | None = None) -> Any:
    """Validation rollouts (``bgn.rollout.rollout_many``) in batches of at most
    ``DEFAULTS.rollout_chunk`` particles, the job's ``deadline`` and SIGTERM checked before each
    (``check``: ``OutOfTime`` past it): one batch of a large scene's validation split can
    take minutes. The formula stage's and ``bgn.studies.auto``'s scoring."""
    from bgn.rollout import rollout_many

    with torch.no_grad():
        return rollout_many(model.eval(), val, sims, starts, n_steps, chunk=DEFAULTS.rollout_chunk,
                            between=lambda: check(deadline, "the validation rollouts"))


def validation_errors(model: Any, val: Any, history: int, horizon: int = DEFAULTS.finetune_horizon,
                      val_sims: int | None = None,
                      deadline: Deadline | None = None,
                      val_rollouts: int = DEFAULTS.finetune_val_rollouts) -> dict[str, Any]:
    """bgn.studies.auto's scoring: every validation simulation (or ``val_sims`` of them)
    rolled out from the shared start frames, as many as give ``val_rollouts`` rollouts
    (``bgn.rollout.scoring_starts``); after 10 and ``horizon`` steps the mean capped
    error (a failed rollout at the cap) and its geometric mean over the rollouts
    (``typical``, shown beside), and how many failed (``failed``, ``failed_share``).
    ``deadline``: checked between batches (``checked_rollouts``)."""
    from bgn.data.frames import evenly_spaced
    from bgn.metrics import SHORT_HORIZON, failure_capped_errors
    from bgn.rollout import scoring_starts

    n_steps = min(horizon, val.file.n_frames - history - 2)
    horizons = sorted({min(SHORT_HORIZON, n_steps), n_steps})
    sims = evenly_spaced(val.file.n_sims, val_sims)
    starts = scoring_starts(val, n_steps, len(sims), val_rollouts)
    t = checked_rollouts(model, val, sims, starts, n_steps, deadline)
    capped, failed = failure_capped_errors(t.predicted, t.true, t.first_non_finite,
                                           val.meta.box)
    at = {h: capped[:, h - 1] for h in horizons}
    return {"errors": {h: float(e.mean()) for h, e in at.items()},
            "typical": {h: float(np.exp(np.log(e + DEFAULTS.typical_floor).mean()))
                        for h, e in at.items()},
            "failed": int(np.sum(failed >= 0)),
            "failed_share": float(np.mean(failed >= 0)), "horizon": n_steps,
            "rollouts": len(sims) * len(starts),
            # every rollout's error and its simulation (rollout_many's rows: start by start,
            # the simulations within), for law_choice's paired standard error
            "per_rollout": {h: [float(x) for x in e] for h, e in at.items()},
            "simulations": [int(sims[i % len(sims)]) for i in range(len(capped))]}


def law_objective(model: Any, head: Any, g: Any) -> torch.Tensor:
    """The loss a pair law's constants are tuned on. Where the model trains its law with the
    recorded masses (BGN's ``law`` head): each particle's relative error (``newton.law_loss``)
    under a Cauchy loss, ``log(1 + rel / DEFAULTS.robust_scale^2)``. A frame whose encounter the
    substeps do not resolve misses its target whatever the law; squared, those few frames
    would decide the constants (they favour a law softer than the truth), where the robust loss
    lets the many resolved frames decide (docs/notes/2026-11-26-results-history.md,
    "The formula stage"). Else the
    model's dynamics loss (the law through the window's mass fit). The other tasks' losses are
    left out: the inverse model reads the head's mass fit (``mass_context=fit``), and its
    likelihood would pull the law towards masses that are easy to predict."""
    from bgn.model.newton import law_loss

    # a coupling head trains no law on recorded masses (law_loss None): its dynamics loss
    rel = law_loss(head, g, reduce=False) if "law" in getattr(model, "heads", ()) else None
    if rel is not None:
        return torch.log1p(rel / DEFAULTS.robust_scale ** 2).mean()
    # the dynamics term of model.loss_terms through the head alone (forward_target): the
    # encoders and the flow, whose losses are left out, need not run for every evaluation
    return model.target_coder.loss(model.forward_target(g), g)


class _Budget(Exception):
    """The fine-tuning's evaluations or seconds are spent."""


def n_constants(spec: str | list[dict[str, Any]]) -> int:
    """Amplitudes and constants c of a ``model.law_formula`` spec, and the constants of its
    expression pairs."""
    pairs = json.loads(spec) if isinstance(spec, str) else spec
    return sum(len(p.get("constants", {})) if "expr" in p
               else sum(1 + (t.get("c") is not None) for t in p["terms"]) for p in pairs)


def candidate_specs(report: LawReport, limit: int = DEFAULTS.finetune_members,
                    ) -> list[tuple[str, int]]:
    """The forms the fine-tuning starts from, each with its complexity (the search's node
    count): the formula read back (the member each pair of types' search chose), then (one
    pair of types only) the other members of its front, simplest first, at most ``limit`` in
    all. The network's law can be off where the frames pin the form (gravity's close
    encounters), so a member the search passed over may fit the frames best. Where no
    formula fits the learned law (the search chose none) and there is one pair of types: the
    front's members simplest first, which ``finetune_formula`` tunes only to check whether the
    frames prefer one to the network law; with several pairs, empty."""
    if report.outcome != "formula":  # the frames may still prefer a member (frames_check)
        if len(report.pairs) != 1:
            return []
        pair = report.pairs[0]
        return [(json.dumps([expression_spec(m, pair.types, free_exponents=True)]),
                 m.complexity) for m in pair.search.front][:max(1, limit)]
    starts = [(formula_spec(report, free_exponents=True),
               sum(p.formula.complexity for p in report.pairs))]
    if len(report.pairs) == 1:
        pair = report.pairs[0]
        starts += [(json.dumps([expression_spec(m, pair.types, free_exponents=True)]),
                    m.complexity) for m in pair.search.front if m is not pair.formula]
    return starts[:max(1, limit)]


def negligible_term(spec: str, reach: np.ndarray | None) -> int | None:
    """The smallest term of a one-pair ``spec`` whose size stays below ``DEFAULTS.negligible`` times
    the law's RMS size at every distance of ``reach`` (where the data reach: the training
    distances at ``DEFAULTS.distance_quantiles``, ``PairLaw.reach``), or None. Such a term
    changes no
    prediction the frames can check; the loss may still prefer it a little, where it absorbs
    what the substeps miss at the closest encounters. Dropping it whatever the loss is
    sequential thresholding, as sparse regression does."""
    from bgn.model.formula_law import FormulaLaw

    pairs = json.loads(spec)
    if reach is None or len(reach) == 0 or not _term_pair(pairs):
        return None
    r = torch.as_tensor(reach, dtype=torch.float64)
    with torch.no_grad():
        values = FormulaLaw(spec).values(r).numpy()                      # (R, K)
    return smallest_negligible(values)


def smallest_negligible(values: np.ndarray) -> int | None:
    """The column of ``values`` (distances x the law's parts, which sum to the law) whose
    largest size stays below ``DEFAULTS.negligible`` times the law's RMS size, the smallest
    such; None where there is none."""
    size = np.sqrt(np.mean(values.sum(-1) ** 2))
    peak = np.abs(values).max(0) / max(size, 1e-300)
    k = int(np.argmin(peak))
    return k if peak[k] < DEFAULTS.negligible else None


def negligible_addend(spec: str, reach: np.ndarray | None) -> str | None:
    """A one-pair expression ``spec`` without its smallest top-level addend where that addend
    stays below ``DEFAULTS.negligible`` times the law's RMS size at every distance of ``reach``
    (as ``negligible_term`` for a spec of terms), its constants that no longer appear dropped;
    else None. A front member one term larger than the law can be tuned on the frames to
    such an addend (the frames cannot tell it from none: docs/results.md, "Learned laws as
    formulas"); whatever the grammar made it of, it changes no prediction the data reach."""
    from bgn.model.formula_law import parse_expression

    pairs = json.loads(spec)
    if reach is None or len(reach) == 0 or len(pairs) != 1 or "expr" not in pairs[0]:
        return None
    pair = pairs[0]
    constants = pair.get("constants", {})
    addends = sympy.Add.make_args(parse_expression(pair["expr"], constants))
    if len(addends) < 2:
        return None
    r = sympy.Symbol("r", positive=True)
    numbers = {sympy.Symbol(k, real=True): v for k, v in constants.items()}
    x = np.asarray(reach, dtype=np.float64)
    with np.errstate(all="ignore"):
        values = np.stack([np.broadcast_to(np.asarray(
            sympy.lambdify(r, a.subs(numbers), "numpy")(x), dtype=np.float64), x.shape)
            for a in addends], axis=-1)                                   # (R, addends)
    k = smallest_negligible(values) if np.isfinite(values).all() else None
    if k is None:
        return None
    rest = sympy.Add(*(a for j, a in enumerate(addends) if j != k))
    kept = {str(sym) for sym in rest.free_symbols}
    return json.dumps([{**pair, "expr": sympy.sstr(rest),
                        "constants": {n: v for n, v in constants.items() if n in kept}}])


def turning_term(spec: str, floor: float | None) -> int | None:
    """The term of a one-pair ``spec`` that turns the law's sign below ``floor`` (the closest
    ``DEFAULTS.turn_quantile`` of the training distances), or None: the term pulling
    against the law's
    sign at the floor that is largest at the closest distance where the law has turned. No
    frame pins the law down there, so a turn there is the fit's extrapolation, not the data's
    (REBOUND's softened attraction read back with a small 1/r^2 repulsion that takes over in
    a close encounter; docs/design.md, "The formula stage"). A core the data reach (Morse,
    Lennard-Jones) turns the law above the floor and is kept."""
    from bgn.model.formula_law import FormulaLaw

    pairs = json.loads(spec)
    if floor is None or not floor > 0 or not _term_pair(pairs):
        return None
    r = torch.as_tensor(floor * DEFAULTS.below_floor, dtype=torch.float64)
    with torch.no_grad():
        values = FormulaLaw(spec).values(r).numpy()                      # (R, K), r ascending
    law = values.sum(-1)
    sign = np.sign(law[-1])
    turned = np.flatnonzero(np.sign(law) == -sign) if sign != 0 else []
    if len(turned) == 0:
        return None
    against = values[turned[0]] * sign < 0
    return int(np.argmax(np.where(against, np.abs(values[turned[0]]), -np.inf)))


def _term_pair(pairs: list[dict[str, Any]]) -> bool:
    """Whether a spec is one pair of types given as two or more terms (the term kinds of
    ``bgn.model.formula_law``): the only spec whose terms can be pruned (``prune_terms``)."""
    return len(pairs) == 1 and "terms" in pairs[0] and len(pairs[0]["terms"]) >= 2


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
    else a term is dropped while the loss rises by at most ``DEFAULTS.form_tolerance``: a term the
    network's law needed in its tails (where the frames barely pin it) goes.

    An expression pair (a member of the law search's front) loses only negligible top-level
    addends (``negligible_addend``), each followed by a tuning: the search's clean-up already
    dropped each of its terms whose removal kept the error within its ``clean_factor``, and a
    tree's top-level sum is not its terms (a common factor, or a potential's derivative by the
    product rule, mixes them), so dropping an addend the data see would make forms the grammar
    does not hold."""
    while True:
        pairs = json.loads(spec)
        if not _term_pair(pairs):
            smaller = negligible_addend(spec, reach)
            if smaller is None:
                return loss, module, hp, spec
            loss, module, hp, spec = tune(smaller)
            continue
        drop = negligible_term(spec, reach)
        if drop is None:
            drop = turning_term(spec, floor)
        if drop is not None:
            loss, module, hp, spec = tune(drop_term(spec, drop))
            continue
        for k in range(len(pairs[0]["terms"])):
            result = tune(drop_term(spec, k))
            if not result[0] > loss * (1 + DEFAULTS.form_tolerance):
                loss, module, hp, spec = min(result[0], loss), *result[1:]
                break
        else:
            return loss, module, hp, spec


def exponent_constants(pair: dict[str, Any]) -> list[str]:
    """The constants of an expression pair that are exponents: the only symbol of some power's
    exponent, entering it linearly (``r**k1``, ``(r + k2)**(-k1 - 1)``: a potential's
    derivative), as the search's exponent slots are (``bgn.laws.search.Form.exponent_slots``)."""
    from bgn.model.formula_law import parse_expression

    expr = parse_expression(pair["expr"], pair["constants"])
    names: set[str] = set()
    for node in sympy.preorder_traversal(expr):
        if isinstance(node, sympy.Pow) and len(node.exp.free_symbols) == 1:
            (sym,) = node.exp.free_symbols
            if str(sym) in pair["constants"] and sympy.degree(node.exp, sym) == 1:
                names.add(str(sym))
    return sorted(names)


def snapped_exponent(spec: str, tried: set[tuple[int, str]],
                     options: SearchOptions = SEARCH_DEFAULTS
                     ) -> tuple[str, tuple[int, str], str] | None:
    """The spec with its free exponent closest to a multiple of ``snap_step`` (within
    ``snap_distance``, not in ``tried``) rounded to it and written into the expression (no
    longer a constant): (spec, (pair, name), what changed); None where no exponent is that
    close. The search's clean-up rule (``bgn.laws.search.clean_up``), on the tuned values,
    and zero too: the search keeps an exponent off 0 because a power of 0 there is the
    constant term its grammar already has, while on the frames a factor ``r^k`` tuned to
    ``k`` near 0 is a factor of 1, and the constants it leaves in no part of the expression
    are dropped. A rounding that leaves no law (an expression of 0) is not offered."""
    from bgn.model.formula_law import parse_expression

    pairs = json.loads(spec)
    near = []
    for i, pair in enumerate(pairs):
        if "expr" not in pair:
            continue
        for name in exponent_constants(pair):
            v = float(pair["constants"][name])
            h = options.snap_step * round(v / options.snap_step)
            if (i, name) not in tried and abs(v - h) <= options.snap_distance:
                near.append((abs(v - h), i, name, v, h))
    for _, i, name, v, h in sorted(near):
        pair = pairs[i]
        expr = parse_expression(pair["expr"], pair["constants"])
        fixed = expr.subs(sympy.Symbol(name, real=True), sympy.nsimplify(h))
        if fixed == 0:
            continue
        left = {str(s) for s in fixed.free_symbols}
        out = [*pairs[:i], {**pair, "expr": sympy.sstr(fixed), "constants": {
            k: c for k, c in pair["constants"].items() if k != name and k in left}},
            *pairs[i + 1:]]
        return json.dumps(out), (i, name), f"exponent {name} {v:.4g} -> {h:g}"
    return None


def snap_exponents(tune: Callable[[str], tuple[float, Any, Any, str]], form: dict[str, Any]
                   ) -> dict[str, Any]:
    """The chosen form's free exponents rounded on the frames, as the search's clean-up rounds
    them on the learned law (``snapped_exponent``: closest first), each rounding kept while
    the tuned loss stays within ``DEFAULTS.form_tolerance`` of the loss before it: the search
    reads the network's law, whose error can hold an exponent off a round value that the
    frames, fitted directly, put on it (spring's ``r^0.93`` tuned to ``r^1.001``). The
    form's ``snapped`` lists the roundings kept."""
    if not math.isfinite(form["loss"]):
        return form
    tried: set[tuple[int, str]] = set()
    form = {**form, "snapped": []}
    while (trial := snapped_exponent(json.dumps(form["tuned"]), tried)) is not None:
        spec, at, change = trial
        tried.add(at)
        try:
            loss, module, hp, tuned = tune(spec)
        except _Budget:
            break
        if not loss > form["loss"] * (1 + DEFAULTS.form_tolerance):
            form = {**form, "tuned": json.loads(tuned), "loss": loss, "module": module,
                    "hp": hp, "constants": n_constants(tuned),
                    "snapped": form["snapped"] + [change]}
    return form


def tune_constants(model: Any, head: Any, batches: list[tuple[float, Any]], steps: int,
                   deadline: Deadline | None) -> tuple[float, int]:
    """The constants of ``head``'s formula law (the terms' amplitudes and c's, the expression
    pairs' constants) fitted in place to ``law_objective`` on the weighted ``batches``,
    derivative-free (Nelder-Mead, at most ``steps`` evaluations): the
    law's loss through the substeps of the closest encounters is smooth at the scale of the
    constants' errors but rough at a quasi-Newton step's (its gradient jumps), where L-BFGS
    stalls. Then ``DEFAULTS.finetune_restarts`` times again from a fresh simplex about the
    best point, ``steps`` evaluations each: a Nelder-Mead simplex that has shrunk along a
    valley stalls short of its minimum, and a restart at the claimed minimum is the standard
    remedy (Press et al., Numerical Recipes, section 10.5); a form whose start lies far from
    its minimum (a softening read off a network law that is wrong at close range) needs it
    (docs/results.md, "The choice rule and the integrator"). A trial point where the loss is
    not finite counts as infinitely worse (a form with no finite point returns inf and
    loses). Returns (the lowest loss, evaluations); ``_Budget`` past ``deadline`` (the
    job's, ``bgn.training.budget``) before any; a SIGTERM ends it between evaluations
    (``check``).

    Couplings (``mass_law=coupling``): their fit per simulation (``bgn.model.coupling``, a
    multi-start Levenberg-Marquardt) costs far more than the law's evaluation, so they are
    fitted once, through the form's starting constants, and held while the constants are
    tuned (``held_couplings``); the loss returned is the tuned constants' with the couplings
    fitted again through them, as every other form's, so forms compare on the same loss."""
    from bgn.model.formula_law import NONLINEAR

    law = head.force_law
    nonlinear = torch.tensor([k in NONLINEAR for k in law.kinds], dtype=torch.bool)
    n_a, n_c = len(law.kinds), int(nonlinear.sum())
    # x: the terms' amplitudes and log c's, then the expression pairs' constants (each
    # relative to its spec value, as the amplitudes are: a relative step)
    expressions = law.constant if law.expressions else None
    best: list[Any] = [math.inf, None]
    count, limit, out_of_time = [0], [steps], [False]

    def place(x: np.ndarray) -> None:
        with torch.no_grad():
            law.amplitude.copy_(torch.as_tensor(x[:n_a]))
            law.log_c[nonlinear] = torch.as_tensor(x[n_a:n_a + n_c], dtype=law.log_c.dtype)
            if expressions is not None:
                expressions.copy_(torch.as_tensor(x[n_a + n_c:], dtype=expressions.dtype))

    def objective(x: np.ndarray) -> float:
        if count[0] >= limit[0]:  # this pass's evaluations spent
            raise _Budget
        try:
            check(deadline, "the formula stage")  # and SIGTERM, between evaluations
        except OutOfTime:
            out_of_time[0] = True
            raise _Budget from None
        place(x)
        with torch.no_grad():
            loss = float(sum(w * law_objective(model, head, g) for w, g in tuned_on))
        count[0] += 1
        if not math.isfinite(loss):  # constants the law cannot take: a worse point, not a stop
            return math.inf
        if loss < best[0]:
            best[:] = [loss, x.copy()]
        return loss

    coupling = getattr(head, "mass_law", None) == "coupling"
    tuned_on = held_couplings(head, batches) if coupling else batches
    x0 = np.concatenate([law.amplitude.detach().numpy(), law.log_c.detach()[nonlinear].numpy(),
                         np.zeros(0) if expressions is None
                         else expressions.detach().numpy()]).astype(np.float64)
    step = np.full(len(x0), DEFAULTS.amplitude_step)
    step[n_a:n_a + n_c] = math.log(DEFAULTS.c_step)
    for attempt in range(1 + DEFAULTS.finetune_restarts):
        if attempt and (best[1] is None or out_of_time[0]):
            break  # no finite point to restart from, or no time
        start = x0 if best[1] is None else best[1].copy()
        limit[0] = count[0] + steps
        try:
            minimize(objective, start, method="Nelder-Mead",
                     options={"initial_simplex": np.vstack([start, start + np.diag(step)]),
                              "maxfev": steps, "xatol": 1e-3, "fatol": 1e-6})
        except _Budget:
            if best[1] is None and count[0] == 0:
                raise
    place(x0 if best[1] is None else best[1])  # no finite point: the form loses (loss inf)
    if coupling and best[1] is not None:  # the couplings fitted again through the tuned law
        with torch.no_grad():
            loss = float(sum(w * law_objective(model, head, g) for w, g in batches))
        return (loss if math.isfinite(loss) else math.inf), count[0] + 1
    return best[0], count[0]


def held_couplings(head: Any, batches: list[tuple[float, Any]]) -> list[tuple[float, Any]]:
    """``batches`` with each graph's couplings fitted per simulation through ``head``'s law as
    it stands (``PairForceHead.fit``) and held as its ``mass_fit``: the law's loss then needs
    no fit of its own (``tune_constants``)."""
    from dataclasses import replace

    with torch.no_grad():
        return [(w, replace(g, mass_fit=head.fit(g, head.window(g)[1]))) for w, g in batches]


def polish_constants(model: Any, head: Any, batches: list[tuple[float, Any]], steps: int,
                     deadline: Deadline | None) -> dict[str, Any] | None:
    """The chosen form's constants tuned once more (``steps`` evaluations, as every form)
    through ``DEFAULTS.polish_factor`` times finer substeps: through the coarser substeps the forms
    are compared with, the loss is rough at the scale of a softening constant, and its minimum
    spans a band around the truth (docs/notes/2026-11-26-results-history.md,
    "The formula stage"). The substeps are put back after. None where no time is left."""
    coarse = head.substeps
    head.substeps = fine = DEFAULTS.polish_factor * coarse
    try:
        loss, n = tune_constants(model, head, batches, steps, deadline)
    except _Budget:
        return None
    finally:
        head.substeps = coarse
    return {"substeps": fine, "loss": loss, "evaluations": n}


def snap_polished(checkpoint: Path, form: dict[str, Any], polish: dict[str, Any],
                  batches: list[tuple[float, Any]], steps: int, substeps: int,
                  deadline: Deadline | None, evaluations: list[int],
                  ) -> tuple[dict[str, Any], dict[str, Any], Any, Any]:
    """``snap_exponents`` once more after the polish, on the polished constants and through
    the polish's substeps (each rounding re-polished, kept while the polished loss stays
    within ``DEFAULTS.form_tolerance``): through the coarser substeps the fit can hold an
    exponent just off the round value the finer ones put it on (docs/results.md, "The
    default jobs"). ``evaluations`` counts the re-polishes. Returns (form, polish, model,
    head), the form's ``snapped`` marking these roundings "(after the polish)"; unchanged
    where no rounding is kept or no time is left."""
    def polished(spec: str) -> tuple[float, Any, Any, str]:
        module, hp = formula_module(checkpoint, spec, substeps)
        model, head = pair_force_head(module)
        model.requires_grad_(False)
        model.eval()
        again = polish_constants(model, head, batches, steps, deadline)
        if again is None:  # no time left: the polished form stands
            raise _Budget
        evaluations[0] += again["evaluations"]
        evaluations[1] += 1
        return again["loss"], module, hp, head.force_law.spec()

    spec = pair_force_head(form["module"])[1].force_law.spec()
    out = snap_exponents(polished, {"tuned": json.loads(spec), "loss": polish["loss"],
                                    "module": form["module"], "hp": form["hp"]})
    if out["snapped"]:
        log.info("formula stage: after the polish, %s (loss %.4g against %.4g)",
                 "; ".join(out["snapped"]), out["loss"], polish["loss"])
        form = {**form, "module": out["module"], "hp": out["hp"], "tuned": out["tuned"],
                "constants": out["constants"], "snapped": form.get("snapped", [])
                + [f"{change} (after the polish)" for change in out["snapped"]]}
        polish = {**polish, "loss": out["loss"]}
    return (form, polish, *pair_force_head(form["module"]))


def failed_rollouts(score: dict[str, Any]) -> int:
    """How many of a ``validation_errors`` score's rollouts failed (from its share where an
    older record lacks the count)."""
    if "failed" in score:
        return int(score["failed"])
    return int(round(score.get("failed_share", 0.0) * score.get("rollouts", 0)))


def _at(values: dict[Any, Any], horizon: int) -> Any:
    """``values[horizon]``, its key a string in a record read back from JSON; None if absent."""
    return values.get(horizon, values.get(str(horizon)))


def mean_error(score: dict[str, Any], horizon: int) -> float:
    """A ``validation_errors`` score's mean capped error after ``horizon`` steps (inf if
    absent)."""
    value = _at(score.get("errors", {}), horizon)
    return math.inf if value is None else float(value)


def paired_standard_error(a: dict[str, Any], b: dict[str, Any], horizon: int) -> float | None:
    """The standard error of the difference of two laws' mean capped errors after
    ``horizon`` steps on the same validation rollouts (``validation_errors``' per-rollout
    errors): the differences averaged per simulation first, because the start frames of one
    simulation share one trajectory and one chaotic stretch, then the standard error over
    the simulations (over the rollouts where there is one simulation). None where a score
    lacks the rollouts' errors (a record older than them) or the two were not rolled out
    from the same simulations."""
    ea, eb = _at(a.get("per_rollout", {}), horizon), _at(b.get("per_rollout", {}), horizon)
    if ea is None or eb is None or len(ea) != len(eb) or a.get("simulations") != b.get(
            "simulations"):
        return None
    diff = np.asarray(eb, float) - np.asarray(ea, float)
    sims = np.asarray(a.get("simulations") or range(len(diff)))
    groups = np.array([diff[sims == s].mean() for s in np.unique(sims)])
    if len(groups) < 2:
        groups = diff
    if len(groups) < 2:
        return None
    return float(groups.std(ddof=1) / math.sqrt(len(groups)))


def integrator_choice(by_substeps: dict[int, dict[str, Any]], horizon: int) -> int:
    """The substeps a formula is rolled out with, of ``by_substeps`` (substeps ->
    ``validation_errors``): the fewest failed rollouts, then the lower mean error after
    ``horizon`` steps, the fewer substeps on a tie."""
    return min(by_substeps, key=lambda k: (failed_rollouts(by_substeps[k]),
                                           mean_error(by_substeps[k], horizon), k))


def law_choice(scores: dict[str, dict[str, Any]], horizon: int) -> str:
    """The law a formula stage keeps, of ``scores`` (law -> ``validation_errors``): the fewest
    failed rollouts first, so a law that fails more never wins; then the lower mean error
    after ``horizon`` steps with each failed rollout at the cap (``model.dynamics=auto``'s
    measure, ``bgn.metrics.capped_step_errors``), in which a failure weighs its cap where a
    geometric mean would let it weigh little, the network law on a tie; except that the
    formula, the simpler law (a handful of constants against a network), is kept wherever its
    mean is within one standard error of the network law's (``paired_standard_error``): the
    one-standard-error rule (Breiman et al. 1984; Hastie, Tibshirani and Friedman, The
    Elements of Statistical Learning, section 7.10). On chaotic data a few rollouts that lose
    track set both means, and a difference inside their noise says nothing about the laws
    (docs/design.md, "The formula stage")."""
    fewest = min(failed_rollouts(s) for s in scores.values())
    tied = {k: s for k, s in scores.items() if failed_rollouts(s) == fewest}
    best = min(tied, key=lambda k: (mean_error(tied[k], horizon), k != "network"))
    if best == "network" and "formula" in tied:
        se = paired_standard_error(tied["network"], tied["formula"], horizon)
        margin = mean_error(tied["formula"], horizon) - mean_error(tied["network"], horizon)
        if se is not None and margin <= se:
            return "formula"
    return best


def finetune_formula(checkpoint: Path, train_split: Any, val: Any,
                     report: LawReport | None = None, steps: int = DEFAULTS.finetune_steps,
                     substeps: int = DEFAULTS.finetune_substeps,
                     batch_size: int = DEFAULTS.finetune_batch_size,
                     horizon: int = DEFAULTS.finetune_horizon,
                     val_sims: int | None = None, out_dir: Path | None = None,
                     seed: int = 0, start: str | None = None,
                     max_seconds: float | None = None,
                     deadline: Deadline | None = None,
                     members: int = DEFAULTS.finetune_members,
                     val_rollouts: int = DEFAULTS.finetune_val_rollouts) -> dict[str, Any]:
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
    after the horizon, a failed rollout at the cap, the formula wherever its mean is within
    one standard error of the network law's).
    ``out_dir``: writes ``formula.ckpt`` (loadable as any checkpoint) and ``formula.json``.
    The forms tuned: the law search's front members (``candidate_specs``, at most
    ``members``). Where no formula fits the learned law (the search chose no member) the
    network law's own error can be what no member matched (a law trained briefly, off in the
    tails it barely saw): with one pair of types the front's members are tuned on the frames
    all the same, and the best goes on to the validation rollouts only if its loss is at most
    the network law's on the same frames through the same substeps (``network_loss``; the
    record's ``basis`` is then ``frames``, ``frames`` holds both losses); else, and with
    several pairs of types, the network law is kept (``no_formula_record``).
    ``start``: a spec to start from in place of the law read back (tests). The fit is
    bounded by its evaluation count (``steps`` per form); ``deadline`` (the job's wall-clock
    cap, ``bgn.training.budget``) and ``max_seconds`` (from now) stop it earlier, and the
    record's ``budget.cut_by`` says so. The validation rollouts check ``deadline`` alone
    between their batches (``checked_rollouts``); past it the network law is kept (the
    run stays usable), ``validation`` is empty and ``budget.cut`` names them. A line per
    tuned form shows its progress. Returns the record (specs before and after, errors,
    choice)."""
    from bgn.training.module import load_model

    if start is None and report is not None and not _tunable(report):
        return no_formula_record(checkpoint, report)
    network = load_model(checkpoint)
    if start is None and report is None:
        report = read_law(network, train_split)
        if not _tunable(report):
            return no_formula_record(checkpoint, report)
    # no member fits the learned law: the members are tuned on the frames anyway, and one
    # goes on only if it explains them as well as the network law (the frames check)
    on_frames = start is None and report.outcome != "formula"
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

    starts = ([(start, n_constants(start))] if start is not None
              else candidate_specs(report, members))
    forms = _tuned_forms(tune, starts, checkpoint, substeps, reach, floor)
    frames = None
    if on_frames:
        frames = {"network_loss": network_loss(network, batches, substeps),
                  "formula_loss": _chosen_form(forms)["loss"]}
        if not frames["formula_loss"] <= frames["network_loss"]:  # NaN: nothing tuned
            log.info("formula stage: no formula fits the learned law, and none fitted to the "
                     "frames explains them as well as the network law (loss %.4g against "
                     "%.4g): the network law is kept", frames["formula_loss"],
                     frames["network_loss"])
            return {**no_formula_record(checkpoint, report), "frames": frames,
                    "steps": evaluations[0], "tunings": evaluations[1],
                    "forms": [{k: f[k] for k in ("start", "tuned", "loss", "constants",
                                                 "complexity")} for f in forms]}
        log.info("formula stage: no formula fits the learned law, but one fitted to the frames "
                 "explains them better than the network law (loss %.4g against %.4g): it is "
                 "rolled out against it", frames["formula_loss"], frames["network_loss"])
    form = snap_exponents(tune, _chosen_form(forms))
    module, hp = form["module"], form["hp"]
    model, head = pair_force_head(module)
    polish = polish_constants(model, head, batches, steps, deadline) \
        if math.isfinite(form["loss"]) else None
    if polish:
        evaluations[0] += polish["evaluations"]
        evaluations[1] += 1
        form, polish, model, head = snap_polished(checkpoint, form, polish, batches, steps,
                                                  substeps, deadline, evaluations)
        module, hp = form["module"], form["hp"]
    # the fit ended by the cap, not by its evaluation count: another machine fits otherwise
    budget = {"steps_per_form": steps, "restarts": DEFAULTS.finetune_restarts,
              "evaluations": evaluations[0],
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
    head.force_law.scale_(scale)
    spec = head.force_law.spec()
    head.force_law.scale_(model_scale)
    hp["model_config"] = {**hp["model_config"], "law_formula": head.force_law.spec(),
                          "law_scale": 1 / model_scale}  # its labels in physical units
    history = int(hp["history"])
    try:
        # the integrators tried: the tuning's substeps, the polish's (the constants were
        # last fitted through them) and the network's own
        tried = [substeps] + ([polish["substeps"]] if polish else [])
        scores, by_substeps = _validated_laws(network, model, head, val, history, horizon,
                                              val_sims, tried, job, val_rollouts)
        choice = law_choice(scores, scores["network"]["horizon"])
    except OutOfTime:  # nothing compared: the law the checkpoint validated with stays
        scores, by_substeps, choice = {}, {}, "network"
        budget["cut_by"] = "max_time"
        budget["cut"].append("the validation rollouts")
        log.warning("formula stage: the validation rollouts reached the job's wall-clock cap "
                    "(trainer.max_time): the network law is kept; raise trainer.max_time to "
                    "compare the formula")
    hp["model_config"] = {**hp["model_config"], "substeps": head.substeps}
    record = {"checkpoint": str(checkpoint), "outcome": "formula",
              "basis": "frames" if on_frames else "learned law", "frames": frames,
              "tolerance": None if report is None else report.pairs[0].search.tolerance,
              "substeps": substeps,
              "steps": evaluations[0], "tunings": evaluations[1], "batch_size": batch_size,
              "budget": budget,
              "forms": [{k: f[k] for k in ("start", "tuned", "loss", "constants",
                                           "complexity")}
                        for f in forms],
              "rollout_substeps": head.substeps,
              "formula_by_substeps": {str(k): v for k, v in by_substeps.items()},
              "start": form["start"], "tuned": json.loads(spec),
              "snapped": form.get("snapped", []),
              "scale": scale, "model_scale": model_scale,
              "model_tuned": json.loads(hp["model_config"]["law_formula"]),
              "loss": form["loss"], "polish": polish, "floor": floor,
              "validation": scores, "choice": choice,
              "choice_standard_error": (None if "formula" not in scores else
                                        paired_standard_error(scores["network"],
                                                              scores["formula"],
                                                              scores["network"]["horizon"])),
              "against_truth": {} if report is None else against_truth(report,
                                                                        json.loads(spec)),
              "truth": None if report is None else report.truth_text}
    if out_dir is not None:
        record["path"] = str(_write_formula(Path(out_dir), checkpoint, module, hp, record))
    return record


def _tunable(report: LawReport) -> bool:
    """Whether the fine-tuning has forms to tune: a formula read back, or (the frames check)
    one pair of types whose search's front offers members."""
    return report.outcome == "formula" or (len(report.pairs) == 1
                                           and bool(report.pairs[0].search.front))


def _data_reach(report: LawReport | None, train_split: Any) -> tuple[Any, float | None]:
    """(reach, floor) of the training distances: where the data reach (the report's, for one
    pair of types; else the split's distance quantiles), and the floor below which a law may
    not turn (``DEFAULTS.turn_quantile``); None where the split has no pairs."""
    seen = np.concatenate([np.zeros(0), *pair_distances(train_split).values()])
    floor = float(np.quantile(seen, DEFAULTS.turn_quantile)) if seen.size else None
    if report is not None and len(report.pairs) == 1:
        reach = report.pairs[0].reach
    else:
        reach = np.quantile(seen, DEFAULTS.distance_quantiles) if seen.size else None
    return reach, floor


def _tuned_forms(tune: Callable[[str], tuple[float, Any, Any, str]],
                 starts: list[tuple[str, int]], checkpoint: Path, substeps: int, reach: Any,
                 floor: float | None) -> list[dict[str, Any]]:
    """Every candidate form (a spec and its complexity), each tuned on the frames (``tune``)
    and, a spec of terms, pruned of the terms the frames do not need (``prune_terms``), until
    the budget runs out; with no time for even one evaluation, the first form, untuned, less
    the terms that turn it below the data (``turning_term`` needs no evaluation)."""
    forms = []
    for spec, size in starts:
        try:
            loss, module, hp, tuned = tune(spec)
            loss, module, hp, tuned = prune_terms(tune, loss, module, hp, tuned, reach, floor)
        except _Budget:
            break
        removed = n_constants(spec) - n_constants(tuned)
        # a pruned spec of terms counts its constants; a pruned expression its member's nodes
        # less the constants gone with its addends (each constant is a node of the search's
        # count, so the true count is no larger)
        expression = "expr" in json.loads(tuned)[0]
        complexity = (size if removed <= 0 else size - removed if expression
                      else n_constants(tuned))
        forms.append({"start": json.loads(spec), "tuned": json.loads(tuned), "loss": loss,
                      "constants": n_constants(tuned),
                      "complexity": complexity,
                      "module": module, "hp": hp})
    if not forms:
        spec = starts[0][0]
        while (drop := turning_term(spec, floor)) is not None:
            spec = drop_term(spec, drop)
        module, hp = formula_module(checkpoint, spec, substeps)
        forms.append({"start": json.loads(starts[0][0]), "tuned": json.loads(spec),
                      "loss": math.nan, "constants": n_constants(spec),
                      "complexity": (starts[0][1] if spec == starts[0][0]
                                     else n_constants(spec)),
                      "module": module, "hp": hp})
    return forms


def _chosen_form(forms: list[dict[str, Any]]) -> dict[str, Any]:
    """The lowest loss wins, the simplest among those within ``DEFAULTS.form_tolerance`` (the
    least complexity: the search's node count of a front member; then the fewest constants)."""
    lowest = min(f["loss"] for f in forms)
    near = [f for f in forms if not f["loss"] > lowest * (1 + DEFAULTS.form_tolerance)] or forms
    return min(near, key=lambda f: (f["complexity"], f["constants"], f["loss"]))


def network_loss(network: Any, batches: list[tuple[float, Any]], substeps: int) -> float:
    """The network law's ``law_objective`` on the tuning ``batches`` through ``substeps`` (the
    forms' own), the yardstick of the frames check: its model is left as it was."""
    model, head = pair_force_head(network)
    coarse, mode = head.substeps, model.training
    head.substeps = substeps
    model.eval()
    try:
        with torch.no_grad():
            return float(sum(w * law_objective(model, head, g) for w, g in batches))
    finally:
        head.substeps = coarse
        model.train(mode)


def no_formula_record(checkpoint: Path, report: LawReport) -> dict[str, Any]:
    """``finetune_formula``'s record where no formula fits the learned law (a pair of types'
    search chose no member within its tolerance): nothing tuned or rolled out, the network
    law kept (``choice``), the ``outcome`` said, with the tolerance and each such pair's most
    accurate member and its error (``best_error``: the worst of them)."""
    missed = [p for p in report.pairs if not p.chosen]
    return {"checkpoint": str(checkpoint), "outcome": "no formula fits", "choice": "network",
            "tolerance": missed[0].search.tolerance,
            "best_error": max(p.formula.error for p in missed),
            "best": [{"types": list(p.types), "formula": p.formula.text,
                      "complexity": p.formula.complexity, "error": p.formula.error}
                     for p in missed],
            "steps": 0, "tunings": 0, "forms": [], "start": None, "tuned": None,
            "validation": {}, "polish": None,
            "budget": {"steps_per_form": 0, "evaluations": 0, "cut_by": None, "cut": []},
            "against_truth": against_truth(report), "truth": report.truth_text}


def _validated_laws(network: Any, model: Any, head: Any, val: Any, history: int, horizon: int,
                    val_sims: int | None, substeps: list[int],
                    deadline: Deadline | None = None,
                    val_rollouts: int = DEFAULTS.finetune_val_rollouts,
                    ) -> tuple[dict[str, Any], dict[int, Any]]:
    """Validation rollouts of the network law and of the formula (``scores``), the formula
    rolled out with each of ``substeps`` (the tuning's, the polish's) and with the network's
    own (``by_substeps``); ``head.substeps`` is left at the one with the fewest failed
    rollouts, then the lower mean error: the shooting's velocity estimate can cost more over
    a rollout than the substeps gain (docs/notes/2026-11-26-results-history.md, "The formula
    stage"), and substeps are there for the rare close encounters, at which a law of the
    truth's form rolled out through too few can fling a body away where the network law,
    softer there, does not; a typical (geometric-mean) error would discount both.
    ``deadline``: the job's, checked between rollout batches (``OutOfTime``, with
    ``head.substeps`` put back to the first of ``substeps``)."""
    scores = {"network": validation_errors(network.model, val, history, horizon, val_sims,
                                           deadline, val_rollouts)}
    n = scores["network"]["horizon"]
    by_substeps = {}
    for k in sorted({*substeps, pair_force_head(network)[1].substeps}):
        head.substeps = k
        try:
            by_substeps[k] = validation_errors(model, val, history, horizon, val_sims,
                                               deadline, val_rollouts)
        except OutOfTime:
            head.substeps = substeps[0]
            raise
    head.substeps = integrator_choice(by_substeps, n)
    scores["formula"] = by_substeps[head.substeps]
    return scores, by_substeps


def _write_formula(out: Path, checkpoint: Path, module: Any, hp: dict[str, Any],
                   record: dict[str, Any]) -> Path:
    """``formula.ckpt`` (the checkpoint with the formula law: loadable as any checkpoint) and
    ``formula.json`` (the record) in ``out``; returns the checkpoint's path."""
    from bgn.training.checkpoints import read, save_atomic, write_atomic

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
    save_atomic(ckpt, out / "formula.ckpt")
    write_atomic(out / "formula.json", json.dumps(record, indent=2, default=float))
    return out / "formula.ckpt"


