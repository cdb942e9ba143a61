"""The structure chosen by evidence: ``python -m bgn.train model.dynamics=auto ...``.

Model only what a scene needs (docs/design.md#the-scene-record), found from the data where
nobody wrote the answer down (docs/design.md#choosing-a-structure). Every structure BGN has that the
data admit is trained for an even part of ``auto.share`` of the job's optimiser steps
(``trainer.max_steps``; ``split_budget``), with no time limit of its own (``trainer.max_time``
is one deadline over the whole job, ``candidate_deadline``), each in
``<run>/auto/<candidate>/``:

- the paper's decoder (Eq. 5): always; it writes no physics in, so it can express any;
- the pair-force head (``bgn.model.newton``) with each way masses can enter (``mass_law``
  inertial, source, type and coupling, the last for at most ``coupling.MAX_PARTICLES``
  particles), where the scene has pairwise (or unknown) forces on a complete or radius graph
  (short-range data: a pair beyond the radius has no edge and no force), an acceleration
  target and a window of at least 3 velocities (``newton.check_scene``), and whose training
  data conserve momentum and angular momentum (``bgn.data.balance``: what central pair forces
  cannot break, so a field, walls, drag or friction rule them out) and
  whose forces do not depend on velocity (``velocity_dependence``: a law of the distance and
  the relative speed along the pair explains the frames no better than one of the distance);
- the contact-impulse head (``bgn.model.impulse``) on contact scenes whose discs have radii;
- the baselines (``auto.references``: GNS, Cranmer et al.'s GN) as references: trained and
  reported on the same protocol, never chosen.

Each is composed from the real configs (``bgn.studies.cells.compose_train``: a scene's
``conf/dataset_model/`` defaults apply) with the run's own overrides, then scored on the
VALIDATION split (never the test split): every validation simulation (or ``auto.val_sims``
of them, evenly spread) rolled out from the same start frames, as many as give
``auto.val_rollouts`` rollouts (``bgn.rollout.scoring_starts``),
the mean position error after ``auto.horizon`` steps over all rollouts, a failed rollout
counted at the cap from its failure on (``bgn.metrics.capped_step_errors``). The eligible
candidate with the lowest error wins (ties: the error after 10 steps, then the order above,
which puts the decoder first); it resumes from its ``last.ckpt`` for the rest of the budget and
is tested as ``bgn.train`` tests. ``<run>/auto/report.md`` (with ``auto.csv``, ``auto.json``
and figures) shows the evidence: the candidates' validation errors, the learned pair laws
against distance and the fitted masses against the recorded ones.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf, open_dict

from bgn.coerce import seconds
from bgn.data.balance import (
    IMBALANCE_MAX,
    Balance,
    VelocityDependence,
    momentum_balance,
    velocity_dependence,
)
from bgn.data.contacts import (
    FREE_RESIDUAL_MAX,
    FreeFlight,
    closest_approach,
    contact_cutoff,
    free_flight,
)
from bgn.metrics import SHORT_HORIZON, rollout_scores
from bgn.sim.scene import SceneMeta
from bgn.training.budget import Deadline, clock_text, received
from bgn.training.checkpoints import save_atomic, write_atomic

log = logging.getLogger("bgn.studies.auto")

MASS_FRAMES = 64         # validation frames the fitted masses are read from
LAW_POINTS = 200         # distances the learned pair law is sampled at
# the share of the job's time left that the candidates leave to the winner's continuation
# and the test, where trainer.max_time caps the job (candidate_deadline)
WINNER_RESERVE = 0.4
MIN_FIT_S = 10.0  # below this a fit's part of trainer.max_time is warned about (run_auto)
# overrides of the run that each candidate sets itself
OWN_KEYS = ("model", "model.dynamics", "model.mass_law", "paths.output_dir", "ckpt_path", "test")


# ----------------------------------------------------------------------------- candidates
@dataclass
class Candidate:
    """One structure: its overrides of the run's train config, whether the data admit it
    (``reason`` if not) and whether it may win (references may not). What it is (label,
    given, physics written in) is its model's ``describe()`` (``Result.model``), the record
    Table 1 reads, so the two never disagree."""

    name: str
    overrides: list[str]
    admitted: bool = True
    reason: str = ""
    eligible: bool = True
    pair_force: bool = False          # carries the pair-force head (law and mass figures)


def candidates(meta: SceneMeta, history: int, radii_given: bool,
               references: Sequence[str] = ("gns", "cranmer_gn"),
               balance: Balance | None = None,
               velocity: VelocityDependence | None = None,
               contacts: FreeFlight | None = None) -> list[Candidate]:
    """Every structure BGN has, each admitted or not (with the reason) by the scene's
    metadata, the window (``history`` past velocities), whether the discs' radii are given
    and what the data conserve (``balance``: a pair-force head cannot make data whose
    momentum or angular momentum changes) and whether their forces depend on velocity
    (``velocity``: a law of the distance cannot express them); then the references."""
    from bgn.model.coupling import MAX_PARTICLES as COUPLING_MAX_PARTICLES
    from bgn.model.newton import check_scene

    out = [Candidate("decoder", ["model.dynamics=decoder"])]
    for law in ("inertial", "source", "type", "coupling"):
        cand = Candidate(f"newton_{law}", ["model.dynamics=newton", f"model.mass_law={law}"],
                         pair_force=True)
        if meta.interaction == "contact":
            cand.admitted, cand.reason = False, "a contact scene: impulses, not forces"
        else:
            try:
                check_scene(meta, history, "the pair-force head")
            except ValueError as err:
                cand.admitted, cand.reason = False, str(err).split(": use model=")[0]
            for evidence in (balance, velocity):
                if cand.admitted and evidence is not None and evidence.breaks():
                    cand.admitted, cand.reason = False, evidence.breaks()
            if cand.admitted and law == "coupling" and meta.n_particles > COUPLING_MAX_PARTICLES:
                cand.admitted, cand.reason = False, (
                    f"{meta.n_particles} particles: couplings are fitted densely per "
                    f"simulation, for at most {COUPLING_MAX_PARTICLES}")
        out.append(cand)
    impulse = Candidate("impulse", ["model.dynamics=newton"])
    if meta.interaction != "contact":
        impulse.admitted, impulse.reason = False, (f"{meta.interaction} interactions, not "
                                                   "contacts")
    elif meta.target != "velocity":
        impulse.admitted, impulse.reason = False, "needs a next-velocity target"
    elif not radii_given:
        impulse.admitted, impulse.reason = False, "the discs' radii are not given"
    elif meta.box is None:
        impulse.admitted, impulse.reason = False, "needs the walls of a box"
    out.append(impulse)
    soft = Candidate("soft_contact", ["model.dynamics=soft_contact"])
    if meta.target != "acceleration":
        soft.admitted, soft.reason = False, "needs an acceleration target"
    elif contacts is None:
        soft.admitted, soft.reason = False, "the contact evidence was not read"
    elif contacts.breaks():
        soft.admitted, soft.reason = False, contacts.breaks()
    out.append(soft)
    for name in references:
        out.append(Candidate(name, [f"model={name}"], eligible=False))
    return out


def radii_given(dataset: Any) -> bool:
    """Whether every particle of the training file has a positive finite radius (imported
    data without radii carry zeros)."""
    radii = np.asarray(dataset.file.read("radii", ...), dtype=float)
    return bool(radii.size and np.all(np.isfinite(radii)) and np.all(radii > 0))


def masses_known(dataset: Any) -> bool:
    """Whether the file's masses are recorded ones (imported data may have none: ones)."""
    return bool(dataset.file.handle.attrs.get("masses_known", True))


# ----------------------------------------------------------------------------- budget
def split_budget(trainer: Mapping[str, Any], share: float, n: int,
                 ) -> tuple[dict[str, Any], dict[str, Any]]:
    """The trainer limits of each of ``n`` candidates and the winner's after it resumes:
    bounded by optimiser steps, so the same command and seed train the same candidates on any
    machine. ``share`` of the job's steps (``trainer.max_steps``: each scene's default is
    conf/budget/<scene>.yaml) split evenly; the winner gets its own share plus what the
    candidates left (Lightning counts steps from the start). No epoch limit, and no time
    limit of their own: the job's ``trainer.max_time`` is one deadline over all of it
    (``run_auto``)."""
    steps = trainer.get("max_steps")
    total = int(steps) if steps is not None else -1
    if total <= 0:
        raise ValueError("model.dynamics=auto splits a step budget: set trainer.max_steps to "
                         "a number of optimiser steps")
    part = max(1, math.floor(share * total / n))
    each = {"max_steps": part, "max_epochs": -1}
    winner = {"max_steps": part + max(0, total - n * part), "max_epochs": -1}
    return each, winner


def check_shares(each: Mapping[str, Any], min_steps: int, n: int, total: Any) -> None:
    """Refuse, in one line, a step budget whose share leaves a candidate fewer than
    ``auto.min_steps``: none could be trained, so none could be compared."""
    from bgn.coerce import ConfigError

    if int(each["max_steps"]) < min_steps:
        raise ConfigError("auto.min_steps", min_steps, message=(
            f"model.dynamics=auto gives each of its {n} candidates {each['max_steps']} "
            f"optimiser steps (auto.share of {total} steps), fewer than auto.min_steps="
            f"{min_steps}: raise trainer.max_steps or lower auto.min_steps"))


def candidate_deadline(deadline: Deadline, remaining: int,
                       reserve: float = WINNER_RESERVE) -> Deadline:
    """The deadline of the next of ``remaining`` fits before the choice: an even part of the
    job's time left, less ``reserve`` of it kept for the winner's continuation and the test.
    A cap only: a candidate ends on its steps first where the machine is fast enough."""
    left = deadline.left()
    if left is None:
        return deadline
    return deadline.sooner(left * (1 - reserve) / max(1, remaining))


# ----------------------------------------------------------------------------- scores
# what result.json keeps of a Result besides its overrides and errors
STATE_KEYS = ("failed_share", "curve", "steps", "wall_s", "train_s", "train_steps", "error",
              "law", "masses", "law_match", "untrained", "model")


@dataclass
class Result:
    """A candidate's validation evidence: the capped error after each horizon, the share of
    failed rollouts, the mean capped error per step (``curve``), its steps, its own wall
    time (``wall_s``: training and scoring, this attempt's) and its training time alone
    (``train_s``: its ``train()`` runs over the run's attempts, ``train_steps`` the optimiser
    steps they trained: its steps per second, which the engines' baselines are given;
    the formula candidate's: its fine-tuning); ``error``: why it could not be trained or scored;
    ``model``: its model's ``describe()`` (the trained one's, or, where training failed,
    the one its config builds; None where none could be built)."""

    candidate: Candidate
    errors: dict[int, float] = field(default_factory=dict)
    failed_share: float = float("nan")
    curve: list[float] = field(default_factory=list)
    steps: int = 0
    wall_s: float = float("nan")
    train_s: float = float("nan")
    train_steps: int = 0
    error: str = ""
    law: dict[str, Any] | None = None
    masses: dict[str, Any] | None = None
    law_match: dict[str, Any] | None = None  # force matching's record (law_init=match)
    untrained: str = ""  # why it counts as not trained (fewer than auto.min_steps steps)
    model: dict[str, Any] | None = None
    kept: bool = False  # restored from an earlier attempt of the run (result.json)

    @property
    def label(self) -> str:
        """How the report names it: its model's label (``describe()``), else its name."""
        return (self.model or {}).get("label") or self.candidate.name

    @property
    def compared(self) -> bool:
        """Trained (at least auto.min_steps steps) and scored: it may enter the choice."""
        return self.candidate.admitted and not self.error and not self.untrained \
            and bool(self.errors)

    def status(self) -> str:
        """What became of it, for the report: "trained", "not trained (...)", "failed: ..."."""
        if not self.candidate.admitted:
            return "-"
        if self.error:
            return f"failed: {self.error}"
        return self.untrained or "trained"

    def state(self) -> dict[str, Any]:
        """What ``auto/<candidate>/result.json`` keeps: a resumed run reuses it."""
        return {"overrides": self.candidate.overrides,
                "errors": {str(k): v for k, v in self.errors.items()},
                **{k: getattr(self, k) for k in STATE_KEYS}}

    @classmethod
    def restored(cls, candidate: Candidate, state: Mapping[str, Any]) -> Result:
        candidate.overrides = list(state.get("overrides", candidate.overrides))
        out = cls(candidate, errors={int(k): float(v) for k, v in state["errors"].items()},
                  kept=True)
        for key in STATE_KEYS:
            if key in state:
                setattr(out, key, state[key])
        return out

    def score(self, horizon: int) -> float:
        value = self.errors.get(horizon, float("nan"))
        return value if math.isfinite(value) else float("inf")


def choose(results: Sequence[Result], horizon: int) -> tuple[Result, float]:
    """The eligible, admitted candidate with the lowest error after ``horizon`` steps (ties:
    the lower error after ``SHORT_HORIZON`` steps, then the order of ``results``), and the
    margin: the runner-up's error over the winner's (nan without a runner-up)."""
    pool = [(r.score(horizon), r.score(SHORT_HORIZON), i, r) for i, r in enumerate(results)
            if r.candidate.eligible and r.compared]
    if not pool:
        raise ValueError("no candidate could be trained and scored; see the errors in the log")
    pool.sort(key=lambda item: item[:3])
    best = pool[0]
    if len(pool) == 1:
        return best[3], float("nan")
    runner = pool[1][0]
    margin = runner / best[0] if best[0] > 0 else (1.0 if runner == 0 else float("inf"))
    return best[3], margin


# ----------------------------------------------------------------------------- evidence
def distance_range(dataset: Any, sims: int = 10, frames: int = 50) -> tuple[float, float]:
    """The smallest and largest pair distance in ``frames`` evenly spaced frames of ``sims``
    evenly spaced simulations of ``dataset`` (the training split)."""
    from bgn.data.frames import evenly_spaced

    lo, hi = math.inf, 0.0
    for s in evenly_spaced(dataset.file.n_sims, sims):
        for t in evenly_spaced(dataset.file.n_frames, frames):
            x = dataset.file.read("positions", (s, t))
            d = np.linalg.norm(x[:, None] - x[None], axis=-1)[~np.eye(len(x), dtype=bool)]
            if d.size:
                lo, hi = min(lo, float(d.min())), max(hi, float(d.max()))
    return lo, hi


def fitted_masses(head: Any, dataset: Any, frames: int = MASS_FRAMES, batch_size: int = 16,
                  ) -> dict[str, Any]:
    """The pair-force head's least-squares masses on ``frames`` evenly spaced windows of
    ``dataset`` (the validation split) against the recorded ones: per particle and window the
    fitted and true log-masses, and the R^2 of the relative log-masses ``log m_i - log m_j`` on
    the windows' edges (the fit's scale is free). Also the median fit, whose sign orients the
    law (a law and fit of the opposite sign make the same accelerations)."""
    import torch

    from bgn.data.frames import evenly_spaced
    from bgn.eval.evaluate import batches
    from bgn.metrics import r2_score

    fitted, true, rel_fit, rel_true, fits = [], [], [], [], []
    with torch.no_grad():
        for g in batches(dataset, evenly_spaced(len(dataset), frames), batch_size):
            fit, _ = head.least_squares(g, head.window(g)[1])
            log_fit = head.fitted_log_mass(g, fit).double()
            log_true = torch.log(g.mass.double())
            snd, rcv = g.edge_index
            fitted.append(log_fit.numpy())
            true.append(log_true.numpy())
            rel_fit.append((log_fit[rcv] - log_fit[snd]).numpy())
            rel_true.append((log_true[rcv] - log_true[snd]).numpy())
            # coupling: k_i c_i = q_i^2 / m_i > 0 where the law has the truth's sign
            fits.append((fit.prod(-1) if fit.ndim > 1 else fit).double().numpy())
    fitted_a, true_a = np.concatenate(fitted), np.concatenate(true)
    return {"fitted_log": fitted_a, "true_log": true_a,
            "relative_r2": r2_score(np.concatenate(rel_fit), np.concatenate(rel_true)),
            "median_fit": float(np.median(np.concatenate(fits)))}


# ----------------------------------------------------------------------------- figures
def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _log_axes(ax: Any, x: bool = True, y: bool = False) -> None:
    """Log scales without minor tick labels (they overlap over a short range)."""
    from matplotlib.ticker import NullFormatter

    for on, axis, scale in ((x, ax.xaxis, ax.set_xscale), (y, ax.yaxis, ax.set_yscale)):
        if on:
            scale("log")
            axis.set_minor_formatter(NullFormatter())


def error_figure(results: Sequence[Result], path: Path) -> Path:
    """The candidates' mean capped validation error against rollout steps."""
    from bgn.figures import save

    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for r in results:
        if r.curve:
            ax.plot(np.arange(1, len(r.curve) + 1), r.curve, label=r.candidate.name,
                    ls="-" if r.candidate.eligible else "--")
    ax.set_yscale("log")
    ax.set_xlabel("rollout step")
    ax.set_ylabel("mean position error (validation, capped)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save(fig, path)


def candidate_laws_figure(results: Sequence[Result], path: Path) -> Path:
    """The pair-force candidates' learned laws against distance, each scaled to a largest
    magnitude of 1 and oriented by its fitted masses (scale and sign are the fit's)."""
    from bgn.figures import save

    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for r in results:
        if not r.law:
            continue
        for pair, values in r.law["f"].items():
            f = np.asarray(values)
            f = f / max(np.abs(f).max(), 1e-30) * r.law["sign"]
            label = r.candidate.name + ("" if len(r.law["f"]) == 1 else f" types {pair}")
            ax.plot(r.law["s"], f, label=label)
    ax.axhline(0, color="0.6", lw=0.8)
    _log_axes(ax)
    ax.set_xlabel("distance s (training split's range)")
    ax.set_ylabel("learned f(s) / max |f|   (> 0 repulsive)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save(fig, path)


def mass_figure(result: Result, path: Path) -> Path:
    """Fitted against recorded masses (log-log), the fit shifted by its mean log offset."""
    from bgn.figures import save

    plt = _plt()
    m = result.masses or {}
    true, fitted = np.asarray(m["true_log"]), np.asarray(m["fitted_log"])
    fitted = fitted + np.mean(true - fitted)          # the fit's free scale
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    ax.scatter(np.exp(true), np.exp(fitted), s=6, alpha=0.4)
    lo, hi = np.exp(min(true.min(), fitted.min())), np.exp(max(true.max(), fitted.max()))
    ax.plot([lo, hi], [lo, hi], color="0.4", lw=0.8)
    _log_axes(ax, y=True)
    ax.set_xlabel("recorded mass")
    ax.set_ylabel("fitted mass (scaled)")
    ax.set_title(f"{result.candidate.name}: relative log-mass R^2 = {m['relative_r2']:.3f}",
                 fontsize=9)
    fig.tight_layout()
    return save(fig, path)


# ----------------------------------------------------------------------------- report
def _fmt(value: float) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) \
        else f"{value:.3g}"


def _ranges(values: Sequence[int]) -> str:
    """[0, 1, 2, 5, 7, 8] -> "0-2, 5, 7-8": long lists of simulations, short."""
    parts: list[list[int]] = []
    for v in sorted(values):
        if parts and v == parts[-1][1] + 1:
            parts[-1][1] = v
        else:
            parts.append([v, v])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in parts)


def balance_lines(balance: Mapping[str, Any] | None) -> list[str]:
    """The report's paragraph on what the training split conserves (``bgn.data.balance``)."""
    if not balance:
        return []
    if balance.get("linear") is None:
        return [f"What the data conserve: not tested ({balance.get('reason')})."]
    b = Balance(**balance)
    angular = ("not defined (periodic or 1-D)" if b.angular is None
               else f"{b.angular:.2g}")
    verdict = b.breaks() or ("balanced: central pair forces can make these data")
    return [f"What the data conserve (training split, {b.sims} simulations x {b.frames} "
            f"frames, median; 0 = balanced by some positive masses, limit "
            f"{IMBALANCE_MAX:g}): momentum imbalance {b.linear:.2g}, with angular momentum "
            f"{angular}. Verdict: {verdict}."]


def velocity_lines(velocity: Mapping[str, Any] | None) -> list[str]:
    """The report's paragraph on whether the forces depend on velocity
    (``bgn.data.balance.velocity_dependence``)."""
    if not velocity:
        return []
    if velocity.get("distance") is None:
        return [f"Whether the forces depend on velocity: not tested ({velocity.get('reason')})."]
    v = VelocityDependence(**velocity)
    verdict = v.breaks() or "no: a law of the distance explains the frames as well"
    return [f"Whether the forces depend on velocity (a central law in log r fitted to the "
            f"training split's second differences, {v.sims} simulations x {v.frames} frames; "
            f"the share of the validation accelerations it leaves unexplained): a law of the "
            f"distance {v.distance:.2g}, of the distance and the relative speed along the pair "
            f"{v.velocity:.2g}. Verdict: {verdict}."]


def contact_evidence(file: Any, meta: SceneMeta) -> FreeFlight:
    """``bgn.data.contacts.free_flight`` of a training file at its closest approaches, within
    the graph's connectivity radius (every pair on a complete graph)."""
    cutoff = contact_cutoff(file)
    return free_flight(file, meta, closest_approach(file, meta, cutoff), cutoff)


def contact_lines(contacts: Mapping[str, Any] | None) -> list[str]:
    """The report's paragraph on whether velocities change only at contact
    (``bgn.data.contacts.free_flight``)."""
    if not contacts:
        return []
    if contacts.get("residual") is None:
        return [f"Whether velocities change only at contact: not tested "
                f"({contacts.get('reason')})."]
    c = FreeFlight(**{**contacts, "field": tuple(contacts.get("field") or ())})
    verdict = c.breaks() or ("yes: particles that touch nothing fly freely under a uniform "
                             "field and drag; soft contacts can make these data")
    field = ", ".join(f"{g:.3g}" for g in c.field)
    return [f"Whether velocities change only at contact ({c.samples} samples of particles "
            f"touching nothing, at the closest approaches of the training split): a uniform "
            f"field ({field} per frame^2) and a drag ({c.drag:.3g} per frame) leave "
            f"{c.residual:.2g} of the second differences unexplained (limit "
            f"{FREE_RESIDUAL_MAX:g}). Verdict: {verdict}."]


def match_lines(results: Sequence[Result]) -> list[str]:
    """The report's lines on force matching (``bgn.model.force_matching``), one per candidate
    whose law started from it."""
    matched = [r for r in results if r.law_match]
    if not matched:
        return []
    lines = ["Force matching (law_init=match): the pair law fitted to the training frames "
             "before the first step; the relative squared error of the validation windows' "
             "accelerations, equal masses (or the recorded ones where the law trains with "
             "them):", ""]
    for r in matched:
        m = r.law_match or {}
        lines.append(f"- {r.candidate.name}: {_fmt(m.get('val_error'))} (the initial law: "
                     f"{_fmt(m.get('val_error_before'))}; the table it was fitted to: "
                     f"{_fmt(m.get('table_val_error'))}); "
                     + ("kept" if m.get("kept") else "not kept, the initial law trained"))
    return [*lines, ""]


def write_report(auto_dir: Path, results: Sequence[Result], winner: Result, margin: float,
                 protocol: dict[str, Any]) -> Path:
    """``report.md``, ``auto.csv``, ``auto.json`` and the figures in ``auto_dir``. Each
    candidate is named as Table 1 names a model (``bgn.studies.report.describe_columns`` of
    its ``describe()``): its label, what its training loss reads beyond the frames, what it
    is given at inference and the physics written in."""
    from bgn.eval.columns import GIVEN, PHYSICS, TRAINED_WITH
    from bgn.studies.report import describe_columns

    horizons = protocol["horizons"]
    figures = auto_dir / "figures"
    paths = {"errors": error_figure(results, figures / "validation_error.png")}
    if any(r.law for r in results):
        paths["law"] = candidate_laws_figure(results, figures / "pair_law.png")
    for r in results:
        if r.masses and protocol["masses_known"]:
            paths[f"masses_{r.candidate.name}"] = mass_figure(
                r, figures / f"masses_{r.candidate.name}.png")
    rows = []
    for r in results:
        c = r.candidate
        about = describe_columns(r.model) if r.model else dict.fromkeys(
            (TRAINED_WITH, GIVEN, PHYSICS), "-")
        rows.append({"candidate": c.name, "label": r.label, "trained_with": about[TRAINED_WITH],
                     "given": about[GIVEN], "physics": about[PHYSICS],
                     "admitted": c.admitted, "reason": c.reason, "eligible": c.eligible,
                     **{f"val_err@{h}": r.errors.get(h, float("nan")) for h in horizons},
                     "failed_share": r.failed_share, "steps": r.steps, "wall_s": r.wall_s,
                     "train_s": r.train_s, "train_steps": r.train_steps,
                     "mass_relative_r2": (r.masses or {}).get("relative_r2", float("nan")),
                     "chosen": c.name == winner.candidate.name, "error": r.error,
                     "status": r.status(), "kept": r.kept})
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(auto_dir / "auto.csv", buffer.getvalue())
    record = {"choice": winner.candidate.name, "margin": margin, "protocol": protocol,
              "candidates": [{**row, "overrides": r.candidate.overrides,
                              "law": r.law, "curve": r.curve, "model": r.model}
                             for row, r in zip(rows, results)],
              "figures": {k: str(v.relative_to(auto_dir)) for k, v in paths.items()}}
    write_atomic(auto_dir / "auto.json", json.dumps(record, indent=2, default=float))
    h = protocol["horizon"]
    lines = ["# model.dynamics=auto: the structure chosen by evidence", "",
             f"Validation split ({protocol['rollouts']} rollouts: simulations "
             f"{_ranges(protocol['sims'])} from frame(s) {protocol['starts']}), mean "
             f"position error after each horizon, a failed rollout counted at the cap "
             f"(bgn.metrics.capped_step_errors). Each candidate trained for "
             f"{protocol['budget_each']['max_steps']} optimiser steps (at least "
             f"{protocol['min_steps']} to count as trained: fewer, it is neither scored nor "
             f"compared); the winner then resumed to {protocol['budget_winner']['max_steps']}.",
             "`wall s`: the candidate's own time in this attempt, its training and scoring; "
             "`train s`: its training alone, over the run's attempts (the formula "
             "candidate's: its fine-tuning); "
             f"`{TRAINED_WITH}` (beyond the frames), `{GIVEN}` (beyond the position window) "
             f"and `{PHYSICS}`: its model's, as Table 1 says them.",
             "", f"| candidate | model | {TRAINED_WITH} | {GIVEN} | {PHYSICS} | admitted | "
             "may win | trained | " + " | ".join(f"val err @{k}" for k in horizons)
             + " | failed | steps | train s | wall s | rel. mass R^2 |",
             "|---|---|---|---|---|---|---|---|" + "---|" * len(horizons)
             + "---|---|---|---|---|"]
    for row in rows:
        name = f"**{row['candidate']}**" if row["chosen"] else row["candidate"]
        admitted = "yes" if row["admitted"] else f"no: {row['reason']}"
        may_win = ("-" if not row["admitted"] else "yes" if row["eligible"] else "reference")
        status = row["status"].replace("|", "/")
        about = " | ".join(str(row[k]).replace("|", "/")
                           for k in ("label", "trained_with", "given", "physics"))
        lines.append(f"| {name} | {about} | {admitted} | {may_win} | {status} | "
                     + " | ".join(_fmt(row[f"val_err@{k}"]) for k in horizons)
                     + f" | {_fmt(row['failed_share'])} | {row['steps'] or '-'} | "
                     f"{_fmt(row['train_s'])} | {_fmt(row['wall_s'])} | "
                     f"{_fmt(row['mass_relative_r2'])} |")
    if protocol.get("fallback"):
        lines += ["", f"Not chosen by evidence: **{winner.candidate.name}** "
                  f"({winner.label}) is the run's model because "
                  f"{protocol['fallback']}.", ""]
    else:
        lines += ["", f"Chosen: **{winner.candidate.name}** ({winner.label}), error "
                  f"{_fmt(winner.errors.get(h))} after {h} steps; the runner-up's is "
                  f"{_fmt(margin)} times that." if math.isfinite(margin) else
                  f"Chosen: **{winner.candidate.name}**, the one eligible candidate trained "
                  "and scored.", ""]
    for line in protocol.get("cut") or []:
        lines.append(f"- Cut by trainer.max_time: {line}")
    if protocol.get("cut"):
        lines.append("")
    lines += balance_lines(protocol.get("balance")) + [""]
    lines += velocity_lines(protocol.get("velocity")) + [""]
    lines += contact_lines(protocol.get("contacts")) + [""]
    lines += match_lines(results)
    for r in results:
        if r.error:
            lines.append(f"- {r.candidate.name} could not be trained or scored: {r.error}")
        elif r.untrained:
            lines.append(f"- {r.candidate.name}: {r.untrained}; not scored, never compared")
    lines += ["", f"![validation error]({paths['errors'].relative_to(auto_dir)})"]
    if "law" in paths:
        lines += ["", "Learned pair laws f(s) over the training split's distances (scale and "
                  "sign are free: the window's mass fit absorbs them; each curve is scaled to "
                  "a largest magnitude of 1 and oriented by its fitted masses):", "",
                  f"![pair law]({paths['law'].relative_to(auto_dir)})"]
    for key, path in paths.items():
        if key.startswith("masses_"):
            lines += ["", f"![{key}]({path.relative_to(auto_dir)})"]
    if not protocol["masses_known"]:
        lines += ["", "The file records no masses: the fitted masses are not scored."]
    report = auto_dir / "report.md"
    write_atomic(report, "\n".join(lines) + "\n")
    return report


# ----------------------------------------------------------------------------- the run
def run_overrides(overrides: Sequence[str] | None = None) -> list[str]:
    """The run's own train overrides: ``overrides``, else Hydra's command line."""
    if overrides is not None:
        return list(overrides)
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return list(HydraConfig.get().overrides.task)
    raise ValueError("model.dynamics=auto composes its candidates from the run's overrides: "
                     "call run_auto(cfg, overrides) outside python -m bgn.train")


def _key(override: str) -> str:
    return override.lstrip("~+").split("=", 1)[0]


# what a pair-force candidate on data with recorded masses adds where no scene default says
# otherwise: the force scenes' own recipe (conf/dataset_model/gravity_r2_bgn.yaml)
WITH_MASSES = ("model.loss_weights.law=1.0", "model.mass_context=fit",
               "model.mass_fit_error=true")


def compose_candidate(base: Sequence[str], cand: Candidate, out_dir: Path,
                      limits: Mapping[str, Any], test: bool = False,
                      masses: bool = False) -> DictConfig:
    """The train config of one candidate: conf/train.yaml with the run's overrides (less
    those the candidate sets, and less its model options for a reference, which has other
    ones), the candidate's, its directory and budget. A dynamics loss weighted 0 (a scene
    that trains its pair-force head on the law alone) is weighted 1 for a candidate without
    that head: it would otherwise learn nothing; a law stage (``model.law``, gravity_r2's
    default) is left to the candidates with that head. Where the data record masses (``masses``)
    and the law loss and the mass context are left at their defaults (0, ``pairs``), a pair-force
    candidate gets ``WITH_MASSES``: its law also learns with the recorded masses (through
    the window's fit alone its shape is barely pinned, docs/design.md#choosing-a-structure)
    and its mass flow reads the masses the head fits."""
    from bgn.studies.cells import compose_train

    reference = any(_key(o) == "model" for o in cand.overrides)
    kept = [o for o in base if _key(o) not in OWN_KEYS
            and not (reference and _key(o).startswith("model."))]
    own = [*cand.overrides, f"paths.output_dir={out_dir}", f"test={str(test).lower()}"]
    if not test:  # a candidate: auto draws its evidence, TensorBoard's figures cost time
        own += ["figures=false", "animation_every=0"]
    cfg = compose_train([*kept, *own])
    weights = cfg.model.get("loss_weights") or {}
    extra: list[str] = []
    if not cand.pair_force and not reference:
        if weights.get("dynamics", 1.0) == 0:
            extra.append("model.loss_weights.dynamics=1.0")
        if cfg.model.get("law", "mlp") != "mlp":   # a law stage needs the pair-force head
            extra.append("model.law=mlp")
    elif cand.pair_force and masses and not weights.get("law", 0.0) \
            and cfg.model.get("mass_context") == "pairs":
        extra = list(WITH_MASSES)
    if extra:
        cand.overrides.extend(extra)
        cfg = compose_train([*kept, *extra, *own])
    with open_dict(cfg):
        for key, value in limits.items():
            cfg.trainer[key] = value
    return cfg


def train_candidate(cand: Candidate, cfg: DictConfig, deadline: Deadline | None = None,
                    run_dir: Path | None = None, overrides: Sequence[str] | None = None,
                    min_steps: int = 0, earlier: Result | None = None) -> Result:
    """Train one candidate (``bgn.training.run.train``) in its own directory until its
    steps or ``deadline``; a signal's resume command names ``run_dir`` with ``overrides``
    (the auto run's, not the candidate's folder). Fewer than ``min_steps`` steps: the result
    says it is not trained. ``train_s`` is the fit's own time (its ``wall_time_s``) and
    ``train_steps`` the steps it added to its checkpoint (``cfg.ckpt_path``: the one it
    continues); ``earlier``: the result an earlier attempt recorded of that checkpoint,
    whose training time and steps are added (an attempt a signal stopped recorded none: its
    steps are then left out with its time)."""
    from bgn.laws.stage import law_stage
    from bgn.training.checkpoints import read
    from bgn.training.run import train

    out_dir = Path(cfg.paths.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(out_dir / "train_config.yaml", OmegaConf.to_yaml(cfg, resolve=False))
    result = Result(cand)
    begun = cfg.get("ckpt_path")
    before = int(read(begun).get("global_step", 0)) if begun and Path(begun).exists() else 0
    start = time.perf_counter()
    metrics = train(cfg, law_stage=law_stage, deadline=deadline, run_dir=run_dir,
                    overrides=None if overrides is None else list(overrides), closing=False)
    result.train_s = float(metrics.get("wall_time_s", time.perf_counter() - start))
    last = out_dir / "checkpoints" / "last.ckpt"
    result.steps = int(read(last).get("global_step", 0)) if last.exists() else 0
    result.train_steps = max(0, result.steps - before)
    if earlier is not None and math.isfinite(earlier.train_s):
        result.train_s += earlier.train_s
        result.train_steps += int(earlier.train_steps)
    record = out_dir / "metrics.json"
    if record.exists():
        result.law_match = json.loads(record.read_text()).get("law_match")
    if result.steps < min_steps:
        result.untrained = (f"not trained ({result.steps} steps of auto.min_steps={min_steps}"
                            " before trainer.max_time)")
    return result


def described(cfg: DictConfig, datamodule: Any) -> dict[str, Any] | None:
    """``describe()`` of the model a candidate's config builds, untrained (cheap: layers
    only), for a candidate that failed before it had a checkpoint; None where it cannot be
    built."""
    from bgn.training.run import build_module, plain_stats

    try:
        return build_module(cfg, dict(vars(datamodule.meta)), plain_stats(datamodule.stats()),
                            datamodule.history).model.describe()
    except Exception as err:  # the report falls back on the candidate's name
        log.debug("auto: no model description for %s: %s", cfg.paths.output_dir, err)
        return None


def score_candidate(result: Result, out_dir: Path, val: Any, train_split: Any,
                    sims: list[int], starts: list[int], n_steps: int,
                    horizons: Sequence[int], deadline: Deadline | None = None) -> None:
    """The validation evidence of a trained candidate (its best checkpoint): rollout errors,
    and for a pair-force head its law over the training split's distances and its fitted
    masses on validation windows. ``deadline``: the job's, checked between rollout chunks
    (``OutOfTime``)."""
    from bgn.laws.finetune import checked_rollouts
    from bgn.laws.sample import sample_law
    from bgn.model.newton import PairForceHead
    from bgn.training.checkpoints import best_checkpoint
    from bgn.training.module import load_model

    module = load_model(best_checkpoint(out_dir))
    result.model = module.model.describe()  # what it is, as Table 1 says it
    t = checked_rollouts(module.model, val, sims, starts, n_steps, deadline)
    errors, failed, curve = rollout_scores(t.predicted, t.true, t.first_non_finite,
                                           val.meta.box, horizons)
    result.errors, result.failed_share, result.curve = errors, failed, curve.tolist()
    head = getattr(module.model, "force_head", None)
    if isinstance(head, PairForceHead):
        masses = fitted_masses(head, val)
        result.masses = {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                         for k, v in masses.items()}
        lo, hi = distance_range(train_split)
        s = np.geomspace(max(lo, hi * 1e-4), hi, LAW_POINTS)
        n = head.types
        pairs = [(a, b) for a in range(n) for b in range(a, n)] if n > 1 else [(0, 0)]
        result.law = {"s": s.tolist(), "sign": 1.0 if masses["median_fit"] >= 0 else -1.0,
                      "f": {f"{a}-{b}": sample_law(head, s, 1, (a, b)).tolist()
                            for a, b in pairs}}


def own_checkpoint(source: Path, target: Path) -> None:
    """``source`` (``finetune_formula``'s formula.ckpt, a copy of another candidate's
    checkpoint with the formula law) moved to ``target`` without the callbacks' state it
    carried over: that candidate's ``ModelCheckpoint`` named its own best.ckpt, which a
    resumed run would otherwise test (its network law does not load into the formula model),
    and its early stopping counted that candidate's validations."""
    import torch

    ckpt = torch.load(source, map_location="cpu", weights_only=True)
    ckpt["callbacks"] = {}
    save_atomic(ckpt, target)
    source.unlink()


def formula_candidate(results: Sequence[Result], auto_dir: Path, val: Any, train_split: Any,
                      sims: list[int], starts: list[int], n_steps: int,
                      horizons: Sequence[int], each: Mapping[str, Any],
                      deadline: Deadline | None = None) -> Result | None:
    """The best pair-force candidate's law read back as a formula (``bgn.laws``), its
    constants fine-tuned through substeps (``bgn.laws.finetune.finetune_formula``: its default
    iterations, at most half the candidates' ``max_steps``) and scored as the others;
    eligible to win, and its checkpoint (``last.ckpt``: its own, carrying no other
    candidate's callback state, ``own_checkpoint``) the one the winner resumes from.
    ``deadline``: the job's; the fit stops at an even part of it (``candidate_deadline``),
    the validation rollouts at it (``OutOfTime``). None without a trained and scored
    pair-force candidate, or where no formula fits its law (the law search's outcome)."""
    from bgn.laws.finetune import finetune_formula
    from bgn.laws.options import DEFAULTS
    from bgn.training.checkpoints import best_checkpoint

    best = best_pair_force(results, n_steps)
    if best is None:
        return None
    steps = DEFAULTS.finetune_steps
    if "max_steps" in each:
        steps = min(steps, max(1, int(each["max_steps"]) // 2))
    out_dir = auto_dir / f"formula_{best.candidate.name}"
    start = time.perf_counter()
    part = None if deadline is None else candidate_deadline(deadline, 1).left()
    record = finetune_formula(best_checkpoint(auto_dir / best.candidate.name), train_split,
                              val, steps=steps, substeps=DEFAULTS.finetune_substeps,
                              out_dir=out_dir, max_seconds=part, deadline=deadline)
    if record.get("outcome") == "no formula fits":  # the law search's honest outcome
        log.info(f"auto: no formula fits {best.candidate.name}'s law within "
                 f"{record.get('tolerance')}: no formula candidate")
        return None
    spec = json.dumps(record["model_tuned"])  # the model's scale (finetune_formula)
    cand = Candidate(out_dir.name, [*best.candidate.overrides, "model.law=formula",
                      f"model.law_formula='{spec}'",
                      f"model.law_scale={1 / record['model_scale']!r}",
                      f"model.substeps={record['rollout_substeps']}"],
                     pair_force=True)
    (out_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    own_checkpoint(out_dir / "formula.ckpt", out_dir / "checkpoints" / "last.ckpt")
    result = Result(cand, steps=best.steps, train_s=time.perf_counter() - start)
    score_candidate(result, out_dir, val, train_split, sims, starts, n_steps, horizons,
                    deadline)
    result.wall_s = time.perf_counter() - start
    return result


def best_pair_force(results: Sequence[Result], n_steps: int) -> Result | None:
    """The trained and scored pair-force candidate with the lowest error after ``n_steps``
    (the first of a tie), whose law the formula candidate is; None where there is none."""
    scored = [r for r in results if r.candidate.pair_force and r.compared]
    return min(scored, key=lambda r: r.score(n_steps)) if scored else None


def one_line(err: BaseException) -> str:
    """An exception as one short line (the report's and the log's reason)."""
    return " ".join(f"{type(err).__name__}: {err}".split())[:300]


def kept_formula(auto_dir: Path, results: Sequence[Result], n_steps: int) -> Result | None:
    """The formula candidate an earlier attempt of this run fitted and scored
    (``formula_<candidate>/result.json``) from the law of the candidate that is still the
    best pair-force one of ``results`` (``best_pair_force``), or None: one fitted from
    another candidate's law (a candidate retrained on this resume may now be the best) is
    not kept, and the log says it is replaced."""
    from bgn.training.run import info

    best = best_pair_force(results, n_steps)
    source = None if best is None else f"formula_{best.candidate.name}"
    others = []
    for path in sorted(auto_dir.glob("formula_*/result.json")):
        kept = stored_result(Candidate(path.parent.name, [], pair_force=True), path.parent)
        if kept is None or kept.untrained or kept.error:
            continue
        if path.parent.name == source:
            return kept
        others.append(path.parent.name)
    if others:
        info(f"auto: {', '.join(others)} (the run's earlier attempt) not kept: the best "
             "pair-force candidate is now "
             + (f"{best.candidate.name}, whose law is fitted in its place" if best is not None
                else "none (none was trained and scored), so no formula is fitted"))
    return None


def not_compared(results: Sequence[Result]) -> str:
    """The candidates the wall-clock cap kept out of the choice, each with what became of
    it ("decoder not trained (40 steps of auto.min_steps=100 ...)", "gns not scored (...)"),
    for the log's warning; "" where there are none."""
    return "; ".join(f"{r.candidate.name} {r.untrained}" for r in results if r.untrained)


def stored_result(cand: Candidate, out_dir: Path) -> Result | None:
    """A candidate's result kept by an earlier attempt of this run (``result.json``), or None."""
    path = out_dir / "result.json"
    try:
        return Result.restored(cand, json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def fallback(results: Sequence[Result]) -> Result | None:
    """Where no candidate was trained and scored: the first eligible one (in the pool's
    order, which puts the decoder, which writes no physics in, first) that has a checkpoint
    to continue from; None where none has."""
    for r in results:
        c = r.candidate
        if c.eligible and c.admitted and not r.error and r.steps > 0:
            return r
    return None


def run_auto(cfg: DictConfig, overrides: Sequence[str] | None = None,
             deadline: Deadline | None = None) -> dict[str, float]:
    """``model.dynamics=auto``: train the candidates, choose on validation rollouts, train the
    winner for the rest of the budget and test it (module doc). ``overrides``: the run's
    train overrides (default: Hydra's command line). ``deadline``: the job's wall-clock cap
    (default ``trainer.max_time`` from now), one over the candidates, their force matching,
    the formula candidate, the winner's continuation and the test: each candidate gets an
    even part of what is left (``candidate_deadline``). A resumed run (``ckpt_path=last``)
    keeps every candidate already trained and scored (``result.json``) and continues one
    stopped half-way from its ``last.ckpt``. Returns the winner's final metrics; the run
    directory gets ``metrics.json`` (the winner's, with the choice; its ``wall_time_s`` the
    whole job's, each candidate's own in ``auto.wall_s``, its training alone in
    ``auto.train_s``) and ``auto/``, and the job ends
    with the closing summary (``bgn.training.run.summary``)."""
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    from bgn.training.signals import interrupted

    began = time.perf_counter()  # the whole job's wall time counts from here
    base = run_overrides(overrides)
    run_dir = Path(cfg.paths.output_dir)
    if deadline is None:
        deadline = Deadline.after(seconds(cfg.trainer.get("max_time")))
    phase = ["choosing the structure"]
    try:
        return _run_auto(cfg, base, run_dir, deadline, phase, began)
    except SIGTERMException:  # outside a fit (scoring, the formula): the run's resume command
        raise interrupted(received() or "SIGTERM", run_dir, base,
                          phase=f"model.dynamics=auto ({phase[0]})",
                          checkpoint_dir=run_dir / "auto") from None


def _run_auto(cfg: DictConfig, base: list[str], run_dir: Path, deadline: Deadline,
              phase: list[str], began: float) -> dict[str, float]:
    from bgn.coerce import ConfigError
    from bgn.data.frames import evenly_spaced
    from bgn.laws.stage import law_stage
    from bgn.rollout import scoring_starts
    from bgn.training.budget import OutOfTime
    from bgn.training.run import data_module, info, summary, train

    auto_dir = run_dir / "auto"
    auto = cfg.get("auto") or {}
    share = float(auto.get("share", 0.5))
    min_steps = int(auto.get("min_steps", 100))
    resume = cfg.get("ckpt_path") == "last"
    datamodule = data_module(cfg)
    datamodule.prepare_data()
    datamodule.setup()
    val, train_split = datamodule.datasets["val"], datamodule.datasets["train"]
    balance = momentum_balance(train_split.file, datamodule.meta)
    # the velocity test only where it could refuse a candidate still admitted
    velocity = (None if balance.breaks() or datamodule.meta.interaction == "contact"
                else velocity_dependence(train_split.file, val.file, datamodule.meta))
    contacts = (None if datamodule.meta.target != "acceleration"
                else contact_evidence(train_split.file, datamodule.meta))
    known = masses_known(val)
    pool = candidates(datamodule.meta, datamodule.history, radii_given(train_split),
                      list(auto.get("references", ["gns", "cranmer_gn"]) or []), balance,
                      velocity, contacts)
    admitted = [c for c in pool if c.admitted]
    each, winner_limits = split_budget(cfg.trainer, share, len(admitted))
    check_shares(each, min_steps, len(admitted), cfg.trainer.get("max_steps"))
    epoch = math.ceil(len(train_split) / int(cfg.dataset.batch_size))
    if each["max_steps"] < epoch:  # validated once, where the candidate's steps end
        each = {**each, "val_check_interval": each["max_steps"]}
    n_steps = min(int(auto.get("horizon", 50)), val.file.n_frames - datamodule.history - 2)
    horizons = sorted({min(SHORT_HORIZON, n_steps), n_steps})
    sims = evenly_spaced(val.file.n_sims, auto.get("val_sims"))
    starts = scoring_starts(val, n_steps, len(sims), int(auto.get("val_rollouts", 100)))
    # the fits before the choice: the candidates and, with a pair-force head, the formula
    fits = len(admitted) + any(c.pair_force for c in admitted)
    left = deadline.left()
    info("model.dynamics=auto: " + ", ".join(
        c.name if c.admitted else f"{c.name} (not admitted: {c.reason})" for c in pool)
        + f"; each trained for {each['max_steps']} optimiser steps (at least {min_steps} to "
        f"be compared), the winner to {winner_limits['max_steps']}"
        + ("" if left is None else f"; trainer.max_time leaves the job {clock_text(left)}"))
    if left is not None and left * (1 - WINNER_RESERVE) / fits < MIN_FIT_S:
        log.warning("trainer.max_time leaves each of auto's %d fits about %s, too little for "
                    "%d optimiser steps and a validation: candidates cut short are reported "
                    "as not trained; raise trainer.max_time", fits,
                    clock_text(left * (1 - WINNER_RESERVE) / fits), min_steps)
    results: list[Result] = []
    cut: list[str] = []
    for cand in pool:
        result = Result(cand)
        if cand.admitted:
            out_dir = auto_dir / cand.name
            # a resumed run keeps what was trained and scored (or failed); one the cap or a
            # signal cut short continues from its last.ckpt
            kept = stored_result(cand, out_dir) if resume else None
            if kept is not None and not kept.untrained:
                info(f"auto: {cand.name} kept from the run's earlier attempt ({kept.status()})")
                results.append(kept)
                continue
            phase[0] = f"candidate {cand.name}"
            remaining = fits - sum(1 for r in results if r.candidate.admitted)
            start = time.perf_counter()
            try:
                if deadline.passed():
                    result.untrained = "not trained (trainer.max_time was reached before it began)"
                else:
                    cfg_c = compose_candidate(base, cand, out_dir, each, masses=known)
                    # what it is before it trains: kept where it fails before a checkpoint
                    result.model = described(cfg_c, datamodule)
                    last = out_dir / "checkpoints" / "last.ckpt"
                    continued = resume and last.exists()
                    if continued:  # stopped half-way: continue it
                        cfg_c.ckpt_path = str(last)
                    model = result.model
                    result = train_candidate(cand, cfg_c, candidate_deadline(deadline, remaining),
                                             run_dir, base, min_steps,
                                             earlier=kept if continued else None)
                    result.model = model
                    if not result.untrained:
                        phase[0] = f"scoring candidate {cand.name}"
                        score_candidate(result, out_dir, val, train_split, sims, starts,
                                        n_steps, horizons, deadline)
            except ConfigError as err:  # the cap reached while it read its data
                if err.key != "trainer.max_time":
                    raise
                result.untrained = "not trained (trainer.max_time was reached before it began)"
            except OutOfTime:  # trained, but the cap came during its validation rollouts
                result.errors, result.untrained = {}, (
                    "not scored (trainer.max_time was reached during its validation rollouts)")
            except Exception as err:  # one candidate's failure is evidence, not the end
                result.error = one_line(err)
                log.error("auto: candidate %s failed: %s", cand.name, result.error)
                log.debug("candidate %s", cand.name, exc_info=True)
            # its own in this attempt: training and scoring (train_s: training alone)
            result.wall_s = time.perf_counter() - start
            write_atomic(out_dir / "result.json", json.dumps(result.state(), default=float))
            info(f"auto: {cand.name} {result.status()}" + "".join(
                f", val error @{h} {v:.4g}" for h, v in result.errors.items()))
        results.append(result)
    formula = kept_formula(auto_dir, results, n_steps) if resume else None
    phase[0] = "the formula candidate"
    if formula is not None:
        info(f"auto: {formula.candidate.name} kept from the run's earlier attempt "
             f"({formula.status()})")
    elif deadline.passed():
        if any(c.pair_force for c in admitted):
            cut.append("the formula candidate: not fitted (trainer.max_time was reached)")
    else:
        try:  # the best pair-force law as a formula, fine-tuned: a candidate of its own
            formula = formula_candidate(results, auto_dir, val, train_split, sims, starts,
                                        n_steps, horizons, each, deadline)
        except OutOfTime:
            formula = Result(Candidate("formula", [], pair_force=True), untrained=(
                "not scored (trainer.max_time was reached during its validation rollouts)"))
            cut.append(f"the formula candidate: {formula.untrained}")
        except Exception as err:
            formula = Result(Candidate("formula", [], pair_force=True), error=one_line(err))
            log.error("auto: the formula candidate failed: %s", formula.error)
            log.debug("the formula candidate", exc_info=True)
        if formula is not None and formula.candidate.name != "formula":  # kept on a resume
            write_atomic(auto_dir / formula.candidate.name / "result.json",
                         json.dumps(formula.state(), default=float))
    if formula is not None:
        if not formula.kept:
            info(f"auto: {formula.candidate.name} {formula.status()}" + "".join(
                f", val error @{h} {v:.4g}" for h, v in formula.errors.items()))
        results.append(formula)
    phase[0] = "the choice"
    why_fallback = ""
    try:
        winner, margin = choose(results, n_steps)
    except ValueError:
        chosen = fallback(results)
        if chosen is None:
            raise ValueError("model.dynamics=auto: no candidate could be trained"
                             + (" before trainer.max_time" if deadline.end is not None else "")
                             + ": " + "; ".join(f"{r.candidate.name} {r.status()}"
                                                for r in results if r.candidate.admitted)
                             ) from None
        winner, margin = chosen, float("nan")
        why_fallback = (f"no candidate trained {min_steps} steps (auto.min_steps) before "
                        "trainer.max_time, so none could be compared: the first that may win "
                        "and has a checkpoint continues")
        log.warning("auto: %s (%s)", why_fallback, winner.candidate.name)
    protocol = {"horizon": n_steps, "horizons": horizons, "sims": sims, "starts": starts,
                "rollouts": len(sims) * len(starts), "share": share, "min_steps": min_steps,
                "budget_each": each, "budget_winner": winner_limits,
                "masses_known": known, "balance": asdict(balance),
                "velocity": asdict(velocity) if velocity is not None else None,
                "contacts": asdict(contacts) if contacts is not None else None,
                "cut": cut, "fallback": why_fallback}
    report = write_report(auto_dir, results, winner, margin, protocol)
    short = not_compared(results)
    if short:
        log.warning("trainer.max_time cut model.dynamics=auto short, so these were not "
                    "compared: %s; see %s", short, report)
    info(f"auto: chose {winner.candidate.name} "
         + (f"(runner-up / winner at {n_steps} steps: {margin:.3g})" if not why_fallback
            else "(not by evidence: see the report)") + f"; report: {report}")
    phase[0] = f"the winner {winner.candidate.name}"
    out_dir = auto_dir / winner.candidate.name
    final = compose_candidate(base, winner.candidate, out_dir, winner_limits,
                              test=bool(cfg.test), masses=known)
    last = out_dir / "checkpoints" / "last.ckpt"
    if last.exists():
        final.ckpt_path = str(last)
    # beside its checkpoints, as a candidate's: bgn.render and bgn.laws read it there
    write_atomic(out_dir / "train_config.yaml", OmegaConf.to_yaml(final, resolve=False))
    metrics: dict[str, float] = {}
    stopped = "" if not deadline.passed() else "trainer.max_time was reached first"
    if not stopped:
        try:
            metrics = train(final, law_stage=law_stage, deadline=deadline, run_dir=run_dir,
                            overrides=base, closing=False)  # the job's summary: below
        except ConfigError as err:  # the cap reached while it read its data
            if err.key != "trainer.max_time":
                raise
            stopped = str(err)
    if stopped:
        cut.append(f"the winner {winner.candidate.name}: neither continued nor tested "
                   f"({stopped}); python -m bgn.evaluate {run_dir} tests it as it is")
        log.warning("trainer.max_time: %s", cut[-1])
        write_report(auto_dir, results, winner, margin, protocol)  # protocol["cut"] is cut
    path = out_dir / "metrics.json"
    record = json.loads(path.read_text()) if path.exists() and not stopped \
        else {"metrics": dict(metrics)}
    winner_s = record["metrics"].get("wall_time_s")
    # the whole job's time: the candidates, their force matching, the formula candidate, the
    # winner's continuation and its test (the winner's own record keeps its continuation's)
    record["metrics"]["wall_time_s"] = time.perf_counter() - began
    record.setdefault("model", winner.candidate.name)
    record.setdefault("variant", winner.model or {})
    record.setdefault("budget", {"steps": winner.steps, "max_steps": None,
                                 "cut_by": "max_time", "cut": ["the winner's continuation"]})
    record["auto"] = {"choice": winner.candidate.name, "label": winner.label,
                      "margin": margin, "report": str(report), "fallback": why_fallback,
                      "cut": cut, "status": {r.candidate.name: r.status() for r in results},
                      "steps": {r.candidate.name: r.steps for r in results},
                      "val_errors": {r.candidate.name: r.errors for r in results},
                      "wall_s": {r.candidate.name: r.wall_s for r in results
                                 if r.candidate.admitted},
                      "train_s": {r.candidate.name: r.train_s for r in results
                                  if r.candidate.admitted},
                      # the parts of the job that ran after the choice (the closing summary)
                      "continued": not stopped,
                      # candidates kept from an earlier attempt: their time is not this one's
                      "kept": [r.candidate.name for r in results if r.kept],
                      "winner_wall_time_s": winner_s}
    record["overrides"] = dict(o.split("=", 1) for o in base if "=" in o)
    write_atomic(run_dir / "metrics.json", json.dumps(record, indent=2, sort_keys=True,
                                                      default=float))
    info(summary(record, run_dir))
    out = metrics or {k: float(v) for k, v in record.get("metrics", {}).items()}
    return {**out, "wall_time_s": record["metrics"]["wall_time_s"]}
