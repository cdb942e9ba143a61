"""The Python surface of bgn: a trained model asked for frames, masses and its pair law on
plain numpy arrays, with no Lightning or Hydra object in the caller's hands.

``load`` takes what ``python -m bgn.evaluate`` takes: a run folder of ``python -m bgn.train``
(its chosen checkpoint: ``bgn.training.checkpoints.resolve_run``) or a ``.ckpt`` file. The
checkpoint alone rebuilds the model and its step rule (the scene record, the frame spacing
and the radius graph's margin are in it); no data file is read.

Shapes: a window is the last ``history + 2`` frames of positions, ``(k+2, N, D)``, oldest
first; a trajectory ``(T, N, D)``; per-particle arrays ``(N,)``. What a model reads beyond
the positions is ``Model.given`` (radii, types, masses); an array it needs and was not given
is refused in one line, one it does not read is ignored.

Example, with ``run`` a spring run folder (4 particles in 2-D) and ``trajectory`` its
recorded positions (T, 4, 2):

>>> import bgn
>>> model = bgn.load(run)
>>> window = trajectory[:model.window_length]      # the last history + 2 frames
>>> model.rollout(window, n_steps=100).shape       # 100 predicted frames
(100, 4, 2)
>>> posterior = model.infer(trajectory)            # the masses of the 4 particles
>>> posterior.median().shape
(4,)
>>> float(model.law()(1.0)) == float(model.law()([1.0])[0])   # the pair law f(r)
True
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bgn.data.targets import targets
from bgn.graph import Graph
from bgn.simulator import LearnedSimulator, Particles


def load(path: str | Path) -> Model:
    """The trained model of a run folder or checkpoint, on the CPU (``Model.to`` moves it).

    >>> model = bgn.load(run)
    >>> model.dim, model.window_length == model.model.history + 2
    (2, True)
    >>> model                                      # doctest: +ELLIPSIS
    bgn.Model(BGN ... on spring, dim=2, dt=..., window=... frames, from ...)
    """
    from bgn.training.checkpoints import CheckpointError, read, recorded_provenance, resolve_run
    from bgn.training.module import load_model

    ckpt, _, _ = resolve_run(str(path)) if Path(path).is_dir() else (Path(path), None, None)
    record = recorded_provenance(read(ckpt))
    if "fps" not in record:
        raise CheckpointError(f"checkpoint {ckpt} records no frame rate (it predates bgn's "
                              "provenance record): retrain it with this version")
    module = load_model(ckpt)
    return Model(module.model, dt=1.0 / float(record["fps"]),
                 margin=float(record.get("margin", 0.0)), source=str(ckpt),
                 mass_prior=_mass_prior(record, module.hparams.get("stats", {})))


def _mass_prior(record: dict[str, Any], stats: dict[str, Any]) -> Any:
    """The scene's mass law (``bgn.eval.mass_baselines.MassPrior``) from the scene a
    checkpoint's record rebuilds, or from its training split's log-mass statistics (imported
    data); None where neither gives one (data without recorded masses, a checkpoint older than
    the record's ``scene_config``)."""
    from bgn.eval.mass_baselines import MassPrior
    from bgn.sim import make_scene

    scene: Any = object()  # no mass law of its own: the statistics' log-normal
    try:
        scene = make_scene(record["scene"], **record["scene_config"])
    except (KeyError, TypeError, ValueError):
        if record.get("scene") != "imported":  # a built-in scene's law is not its statistics'
            return None
    try:
        return MassPrior.of_scene(scene, stats.get("log_mass"))
    except ValueError:
        return None


@dataclass(frozen=True)
class MassPosterior:
    """Each particle's hidden mass given a trajectory, in two forms side by side.

    ``per_frame``: draws of log-mass (S, N) from the inverse model's posterior (the flow, Eq.
    7-8) at each of ``frames`` windows of the trajectory, pooled (``S = frames x samples``):
    what one frame says, spread over the frames; None where the model has no inverse model
    (baselines, data without recorded masses). ``law``: one least-squares fit of all the
    windows through the model's own learned pair law (``bgn.eval.law_posterior``), log-mass
    (N,) and its standard deviation (N,), NaN where a particle is not identified; None without
    a pair-force head or where its masses are per type. The fit's deviations are the least
    squares' alone, not calibrated: ``python -m bgn.evaluate`` calibrates them on the run's
    validation split. ``law_scale``: "physical" where the law was trained on recorded masses;
    "per-frame" where its one free common factor was set by the per-frame posterior (the
    median over particles of the two log-masses' difference); "relative" where nothing sets
    it: the masses are right up to one common factor. ``impacts``: with a contact head (the
    impulse head), the momentum exchanged at the impacts it sees in all the windows, each
    type's mass law as prior (``bgn.eval.impact_posterior``), log-mass (N,) and its standard
    deviation (N,), the noise the equations' own scatter (``python -m bgn.evaluate`` sets it
    on the validation split); None otherwise. ``median`` and the rest read the law's fit where
    it identifies a particle, else the impacts', else the per-frame draws."""

    per_frame: np.ndarray | None
    frames: int
    law: tuple[np.ndarray, np.ndarray] | None
    law_scale: str | None
    impacts: tuple[np.ndarray, np.ndarray] | None = None

    def _law_identified(self) -> bool:
        return self.law is not None and bool(np.isfinite(self.law[0]).any())

    def _fit(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The per-simulation Gaussian (log-mass mean and std, (N,) each) that ``median``
        and the rest read: the law's where it identifies any particle, else the impacts'."""
        return self.law if self._law_identified() else self.impacts

    def median(self) -> np.ndarray:
        """(N,) the median mass: the law fit's where it identifies any particle, else the
        per-frame draws'."""
        if self._fit() is not None:
            return np.exp(self._fit()[0])
        return np.exp(np.median(self._draws(), axis=0))

    def log_std(self) -> np.ndarray:
        """(N,) the spread of log-mass, from the same source as ``median``."""
        if self._fit() is not None:
            return self._fit()[1]
        return np.std(self._draws(), axis=0)

    def interval(self, level: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
        """(N,), (N,) the central ``level`` interval of mass, from the same source as
        ``median``."""
        if not 0 < level < 1:
            raise ValueError(f"level={level} must lie in (0, 1)")
        fit = self._fit()
        if fit is not None:
            from scipy.stats import norm

            z = norm.ppf(0.5 + level / 2)
            return np.exp(fit[0] - z * fit[1]), np.exp(fit[0] + z * fit[1])
        low, high = np.quantile(self._draws(), [0.5 - level / 2, 0.5 + level / 2], axis=0)
        return np.exp(low), np.exp(high)

    def describe(self) -> str:
        """Where ``median`` comes from, in a few words."""
        if self._law_identified():
            return (f"the learned law's fit of {self.frames} windows (scale {self.law_scale})")
        if self.impacts is not None:
            return (f"the impacts the contact head sees in {self.frames} windows, each type's "
                    "mass law as prior")
        return f"the inverse model's posterior at {self.frames} windows, pooled"

    def _draws(self) -> np.ndarray:
        if self.per_frame is None:
            raise ValueError("the learned law identifies no particle here and the model has "
                             "no inverse model nor contact head: no masses to report")
        return self.per_frame


@dataclass(frozen=True)
class PairLaw:
    """The pair law ``f(r)`` a model's pair-force head learned (the force between a particle
    of type ``types[0]`` and one of ``types[1]`` at distance ``r``, positive repulsive, before
    the masses or couplings multiply it). ``scale``: "physical" where the law was trained on
    recorded masses, or a formula stage put it in physical units with them; else "shape":
    right up to one factor (of either sign) that the fitted masses absorb.
    ``formula``: the law as text where the model's law is a formula (``model.law=auto``
    chose one, or ``model.law_formula``), else None (a network law: ``python -m bgn.laws``
    reads one back)."""

    head: Any
    dim: int
    scale: str
    mass_law: str
    formula: str | None

    def __call__(self, r: Any, types: tuple[int, int] = (0, 0)) -> np.ndarray:
        r = np.asarray(r, dtype=np.float64)
        if r.ndim > 1 or not np.all(np.isfinite(r)) or np.any(r <= 0):
            raise ValueError("r: give distances > 0 as a number or a 1-D array")
        return self.head.labelled_law_at(np.atleast_1d(r), self.dim, types).reshape(r.shape)


class Model:
    """A trained bgn model on numpy arrays (``load`` builds it). ``dt``: the frame spacing it
    was trained at; ``window_length``: frames a window holds (``history + 2``)."""

    def __init__(self, model: Any, dt: float, margin: float = 0.0, source: str = "",
                 mass_prior: Any = None) -> None:
        self.model = model.eval()
        # the scene's mass law (bgn.eval.mass_baselines.MassPrior): the impacts' prior
        self.mass_prior = mass_prior
        self.simulator = LearnedSimulator(model, dt, margin)
        self.dt, self.margin, self.source = float(dt), float(margin), source
        self.meta = model.meta

    def __repr__(self) -> str:
        return (f"bgn.Model({self.model.label} on {self.meta.name}, dim={self.dim}, "
                f"dt={self.dt:g}, window={self.window_length} frames, from {self.source})")

    @property
    def dim(self) -> int:
        return int(self.meta.dim)

    @property
    def window_length(self) -> int:
        return self.simulator.window_length

    @property
    def given(self) -> tuple[str, ...]:
        """What the model reads beyond the positions ("radii", "types", "masses", ...)."""
        return tuple(self.model.given)

    def to(self, device: str | torch.device) -> Model:
        """The model on ``device`` ("cuda", "cpu"); returns itself."""
        self.model.to(device)
        return self

    # ------------------------------------------------------------------ inputs
    def _positions(self, name: str, x: Any, min_frames: int) -> np.ndarray:
        arr = np.asarray(x, dtype=np.float64)
        if arr.ndim != 3 or arr.shape[2] != self.dim or arr.shape[0] < min_frames \
                or arr.shape[1] < 1:
            raise ValueError(f"{name}: give positions (frames, N, {self.dim}) with at least "
                             f"{min_frames} frames; got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name}: positions hold NaN or inf")
        # a periodic scene's frames may come wrapped into the box (LagrangeBench's layout,
        # most engines): each frame joins the previous by the minimum image, as the importer
        # does, so that no velocity spans the box
        period = np.asarray(self.meta.period or (), dtype=np.float64)
        if period.size and bool((period > 0).any()):
            from bgn.data.formats import unwrap_periodic

            bounds = np.column_stack([np.zeros_like(period), period])
            arr = unwrap_periodic(arr[None], bounds, period > 0)[0]
        return arr

    def _particles(self, n: int, masses: Any, radii: Any, types: Any) -> Particles:
        def field(name: str, value: Any, default: float, needed: bool | str) -> torch.Tensor:
            if value is None:
                if needed:
                    why = needed if isinstance(needed, str) else f"reads {name}"
                    raise ValueError(f"{self.model.label} {why}: pass {name}= (N,)")
                return torch.full((1, n), default, dtype=torch.float64)
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape != (n,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"{name}: give {n} finite values, one per particle; got "
                                 f"shape {arr.shape}")
            return torch.as_tensor(arr)[None]

        m = field("masses", masses, 1.0, "masses" in self.given)
        if not bool((m > 0).all()):
            raise ValueError("masses: every mass must be > 0")
        r = field("radii", radii, 0.0, "radii" in self.given or (
            self.meta.graph != "full" and "joins pairs closer than r_i + r_j + margin (zeros "
            "where the training data recorded no radii)"))
        t = field("types", types, 0.0, "types" in self.given)
        if not bool(((t >= 0) & (t < self.meta.n_types) & (t == t.round())).all()):
            raise ValueError(f"types: give integers 0 .. {self.meta.n_types - 1} (the types "
                             "the model was trained on)")
        return Particles(m, r, t.long(), torch.zeros(1, dtype=torch.long))

    def _window_ends(self, n_frames: int, frames: int) -> np.ndarray:
        """The last frame of each of up to ``frames`` windows evenly spaced over a trajectory
        of ``n_frames`` (each followed by one more frame: its observed target)."""
        k2 = self.window_length
        return np.unique(np.linspace(k2 - 1, n_frames - 2, frames).round().astype(int))

    def _graphs(self, trajectory: np.ndarray, particles: Particles, frames: int) -> list[Graph]:
        """The graphs of up to ``frames`` windows evenly spaced over ``trajectory``, each with
        its observed target (the next frame's acceleration or velocity)."""
        k2 = self.window_length
        graphs = []
        for end in self._window_ends(len(trajectory), frames):
            window = torch.as_tensor(trajectory[None, end - k2 + 1:end + 1])
            g = self.simulator.graph(window.to(self.simulator.device), particles.to(
                self.simulator.device), int(end))
            observed = targets(trajectory[end - 1:end + 2], self.dt, self.meta.target)[0]
            g.target = torch.as_tensor(observed.reshape(-1, self.dim), dtype=g.target.dtype,
                                       device=g.target.device)
            graphs.append(g)
        return graphs

    # ------------------------------------------------------------------ forward
    @torch.no_grad()
    def predict_step(self, window: Any, masses: Any = None, radii: Any = None,
                     types: Any = None) -> np.ndarray:
        """(N, D) the next frame after ``window`` (the last ``window_length`` frames).

        >>> model = bgn.load(run)
        >>> model.predict_step(trajectory[:model.window_length]).shape
        (4, 2)
        """
        return self.rollout(window, 1, masses, radii, types)[0]

    @torch.no_grad()
    def rollout(self, window: Any, n_steps: int, masses: Any = None, radii: Any = None,
                types: Any = None, context: Any = None) -> np.ndarray:
        """(n_steps, N, D) frames predicted from ``window`` on (the model fed its own frames).

        A model that fits masses to the frames (a pair-force head) fits them to the window, or
        to ``context`` (the recorded frames before the start, ending with the window) where
        it reads several windows. A rollout whose frame becomes non-finite holds NaN from
        that step on.

        >>> model = bgn.load(run)
        >>> future = model.rollout(trajectory[:model.window_length], 50)
        >>> future.shape, bool(abs(future[0] - trajectory[model.window_length]).max() < 0.1)
        ((50, 4, 2), True)
        """
        if int(n_steps) != n_steps or n_steps < 1:
            raise ValueError(f"n_steps={n_steps} must be an integer >= 1")
        x = self._positions("window", window, self.window_length)[-self.window_length:]
        particles = self._particles(x.shape[1], masses, radii, types)
        recorded = None
        if context is not None:
            recorded = torch.as_tensor(self._positions("context", context, self.window_length))
            if recorded.shape[1:] != x.shape[1:]:
                raise ValueError(f"context: {tuple(recorded.shape)} does not match the "
                                 f"window's {x.shape}")
            recorded = torch.cat([recorded, torch.as_tensor(x)])[None]
            recorded = None if len(recorded[0]) <= self.window_length else recorded
        out = self.simulator.rollout(torch.as_tensor(x)[None], particles, int(n_steps),
                                     frame=0, context=recorded)
        return out.positions[0, 1:].cpu().numpy()

    # ------------------------------------------------------------------ inverse
    @torch.no_grad()
    def infer(self, trajectory: Any, frames: int = 32, samples: int = 64,
              radii: Any = None, types: Any = None, seed: int = 0) -> MassPosterior:
        """Each particle's mass given a trajectory (T, N, D) of at least ``window_length + 1``
        frames: the per-frame posterior of ``frames`` evenly spaced windows (``samples`` draws
        each) and the learned law's fit of them all (``MassPosterior``).

        >>> posterior = bgn.load(run).infer(trajectory, frames=8)
        >>> posterior.per_frame.shape                  # 8 windows x 64 draws, 4 particles
        (512, 4)
        >>> low, high = posterior.interval(0.9)
        >>> bool((low <= posterior.median()).all() and (posterior.median() <= high).all())
        True
        """
        from bgn.eval.law_posterior import fit_simulation, law_scale_pinned
        from bgn.graph import collate
        from bgn.model.newton import pair_force_head_of

        if int(frames) != frames or frames < 1 or int(samples) != samples or samples < 1:
            raise ValueError(f"frames={frames} and samples={samples} must be integers >= 1")
        x = self._positions("trajectory", trajectory, self.window_length + 1)
        particles = self._particles(x.shape[1], None, radii, types)
        graphs = self._graphs(x, particles, int(frames))
        per_frame = None
        if self.model.has_inverse:
            torch.manual_seed(seed)
            draws, _ = self.model.mass_posterior(collate(graphs), int(samples))  # (S, B*N)
            draws = draws.double().cpu().numpy().reshape(int(samples), len(graphs), -1)
            per_frame = draws.reshape(-1, x.shape[1])
        head = pair_force_head_of(self.model)
        fit = None if head is None else fit_simulation(head, graphs)
        impacts = self._impact_fit(x, graphs, int(frames), types) if head is None else None
        if per_frame is None and fit is None and impacts is None:
            raise ValueError(f"{self.model.label} infers no masses: it has neither an inverse "
                             "model, nor a pair-force head whose law fits them, nor a contact "
                             "head whose impacts do")
        scale = None
        if fit is not None:
            scale = "physical" if law_scale_pinned(self.model) else "relative"
            seen = np.isfinite(fit[0])
            if scale == "relative" and per_frame is not None and seen.any():
                shift = float(np.median(np.median(per_frame, axis=0)[seen] - fit[0][seen]))
                fit, scale = (fit[0] + shift, fit[1]), "per-frame"
        return MassPosterior(per_frame, len(graphs), fit, scale, impacts)

    def _impact_fit(self, x: np.ndarray, graphs: list[Graph], frames: int, types: Any,
                    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The impact posterior (``bgn.eval.impact_posterior``) of the trajectory ``x``: the
        momentum exchanged at the impacts the model's contact head sees in the windows of
        ``graphs``, each disc's type's mass law as prior, the noise the equations' own residual
        scatter; log-mass mean and std (N,) (``graphs``: ``_graphs`` of ``x`` and ``frames``).
        None without a contact head or a mass law. The
        types: ``types`` where given, else the model's type classifier's (mean over the
        windows)."""
        from bgn.eval.impact_posterior import (
            SimulationImpacts,
            contact_rows,
            impact_posterior,
            residual_noise,
        )
        from bgn.eval.mass_baselines import impact_equations
        from bgn.graph import collate
        from bgn.model.impulse import ContactImpulseHead

        head = getattr(self.model, "force_head", None)
        if not isinstance(head, ContactImpulseHead) or self.mass_prior is None:
            return None
        g = collate(graphs)
        k2, n = self.window_length, x.shape[1]
        windows = np.stack([x[e - k2 + 1:e + 1] for e in self._window_ends(len(x), frames)])
        pairs, ratios = impact_equations(windows, self.dt, contact_rows(head, g, k2))
        if types is not None:
            kinds = np.asarray(types, dtype=np.int64)
        elif not self.mass_prior.typed:
            kinds = np.zeros(n, dtype=np.int64)
        elif "type" in self.model.heads:
            logits = self.model(g).type_logits.double().cpu().numpy()
            kinds = logits.reshape(len(graphs), n, -1).mean(axis=0).argmax(axis=1)
        else:
            raise ValueError(f"{self.model.label}: pass types= (N,): each disc's type's mass "
                             "law is the prior of the masses its impacts give")
        sim = SimulationImpacts(0, pairs, ratios, kinds, np.full(n, np.nan), len(graphs))
        return impact_posterior(sim, self.mass_prior, residual_noise([sim]))

    def law(self) -> PairLaw:
        """The learned pair law (``PairLaw``); a model without a pair-force head has none.

        >>> law = bgn.load(run).law()
        >>> law([0.5, 1.0, 2.0]).shape, law.scale in ("physical", "shape")
        ((3,), True)
        """
        from bgn.eval.law_posterior import law_scale_pinned
        from bgn.laws.sample import pair_force_head
        from bgn.model.newton import formula_text

        _, head = pair_force_head(self.model)  # refused in one line without one
        physical = law_scale_pinned(self.model) or float(head.law_scale) != 1.0
        return PairLaw(head, self.dim, "physical" if physical else "shape", head.mass_law,
                       formula_text(head))
