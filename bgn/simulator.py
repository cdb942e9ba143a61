"""The learned simulator: a model + the step rule + the scene's graph rule = the next frame.

The role ``LearnedSimulator`` plays in DeepMind's learning_to_simulate: any model that predicts
the forward target (``PhysicsModel.predict``) becomes a simulator that advances B simulations
at once, in torch, on the model's device. Each step rebuilds the graph with the scene's own
rule (the complete graph, or the radius graph found with a KD-tree, ``bgn.data.edges``, on
the torus where the scene has periodic boundaries) and
integrates the predicted target with the rule that inverts the training targets
(``bgn.data.targets.step``), so a model fed the true targets reproduces the recorded frames.

Positions are kept in float64: the finite differences that make the model's inputs, and the
integration, are exact to round-off whatever the model's precision.
Nothing here knows files, Lightning or Hydra.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Protocol

import torch
from torch import nn

from bgn.data.edges import batch_edges, full_graph, scene_edges
from bgn.data.targets import step
from bgn.graph import Graph, collate, window_graph
from bgn.sim.scene import SceneMeta


class Predictor(Protocol):
    """What the simulator needs of a model: every ``bgn.model.PhysicsModel`` has it, and so
    do the no-learning references (``bgn.model.references``). A model may also have
    ``held_mass_fit(g)``: what a rollout fits once, to its first window, and holds
    (``PhysicsModel.held_mass_fit``), and ``held_fit_windows``: how many windows of the frames
    before the start that fit reads where a rollout is given them (its ``context``)."""

    meta: SceneMeta
    history: int

    def predict(self, g: Graph) -> torch.Tensor: ...

    def parameters(self) -> Iterator[nn.Parameter]: ...


@dataclass
class Particles:
    """What does not change along a simulation: (B, N) masses, radii and types, and the
    index of each simulation (carried into the graphs, e.g. for references and oracles)."""

    masses: torch.Tensor
    radii: torch.Tensor
    types: torch.Tensor
    sims: torch.Tensor
    kinematic: torch.Tensor | None = None  # (B, N) bool: moved by the source (imported data)

    def select(self, rows: torch.Tensor) -> Particles:
        return Particles(self.masses[rows], self.radii[rows], self.types[rows], self.sims[rows],
                         None if self.kinematic is None else self.kinematic[rows])

    def to(self, device: torch.device | str) -> Particles:
        return Particles(self.masses.to(device), self.radii.to(device), self.types.to(device),
                         self.sims.to(device),
                         None if self.kinematic is None else self.kinematic.to(device))


@dataclass
class Rollout:
    """B rollouts of ``n_steps``. ``positions`` (B, n_steps + 1, N, D), float64: the last true
    frame, then the predicted ones. ``first_non_finite`` (B,): the first step whose frame had
    a non-finite value, -1 if none; that frame and every later one are NaN (a failed rollout
    is counted, never dropped). ``seconds_per_step``: wall time of one step of all B."""

    positions: torch.Tensor
    first_non_finite: torch.Tensor
    seconds_per_step: float

    @property
    def failed(self) -> torch.Tensor:
        return self.first_non_finite >= 0


class LearnedSimulator(nn.Module):
    """``next_frame`` and ``rollout`` for any model of a scene (see the module doc).

    ``dt`` is the frame spacing; ``margin`` the radius graph's margin (``r_i + r_j + margin``,
    the dataset's ``margin`` attribute); ``dtype`` what the model's inputs are cast to.
    """

    def __init__(self, model: Predictor, dt: float, margin: float = 0.0,
                 dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        if not dt > 0:
            raise ValueError(f"dt={dt} must be > 0")
        self.model, self.dt, self.margin, self.dtype = model, float(dt), float(margin), dtype
        self.meta = model.meta
        self._full: dict[tuple[int, int], torch.Tensor] = {}  # complete graphs by (B, N)

    @property
    def window_length(self) -> int:
        """Frames a window holds: k+2 positions give k+1 velocities."""
        return self.model.history + 2

    @property
    def device(self) -> torch.device:
        first = next(self.model.parameters(), None)
        return torch.device("cpu") if first is None else first.device

    # ------------------------------------------------------------------ graphs
    def edges(self, pos: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
        """(2, E) edges of B frames (B, N, D), simulation b's nodes offset by b*N."""
        b, n, _ = pos.shape
        if self.meta.graph == "full":
            if (b, n) not in self._full:
                self._full[(b, n)] = torch.as_tensor(batch_edges([full_graph(n)] * b, [n] * b))
            return self._full[(b, n)].to(pos.device)
        # the radius rule runs on the CPU (KD-tree, linear in N)
        x, r = pos.detach().cpu().double().numpy(), radii.detach().cpu().double().numpy()
        lists = [scene_edges(self.meta.graph, x[i], r[i], self.margin, self.meta.period)
                 for i in range(b)]
        return torch.as_tensor(batch_edges(lists, [n] * b)).to(pos.device)

    def graph(self, window: torch.Tensor, particles: Particles, frame: int | torch.Tensor = 0,
              ) -> Graph:
        """The model's graph of B windows (B, k+2, N, D) of positions, newest last."""
        self._check_window(window, particles)
        frames = torch.as_tensor(frame, device=window.device).expand(window.shape[0])
        return window_graph(window, self.dt, self.edges(window[:, -1], particles.radii),
                            particles.masses, particles.radii, particles.types, self.meta.box,
                            particles.sims, frames, self.dtype, particles.kinematic,
                            self.meta.period)

    def _check_window(self, window: torch.Tensor, particles: Particles) -> None:
        if window.ndim != 4 or window.shape[1] != self.window_length \
                or window.shape[3] != self.meta.dim:
            raise ValueError(f"a window must be (B, history + 2, N, dim) = (B, "
                             f"{self.window_length}, N, {self.meta.dim}) positions; got "
                             f"{tuple(window.shape)}")
        if particles.masses.shape != window.shape[:1] + window.shape[2:3]:
            raise ValueError(f"particles are {tuple(particles.masses.shape)}, the window's "
                             f"(B, N) is {tuple(window.shape[:1] + window.shape[2:3])}")

    # ------------------------------------------------------------------ stepping
    def next_frame(self, window: torch.Tensor, particles: Particles,
                   frame: int | torch.Tensor = 0, mass_fit: torch.Tensor | None = None,
                   ) -> torch.Tensor:
        """x[t+1] (B, N, D) from the windows ending at frame t (differentiable). ``mass_fit``
        (B * N,): a mass fit held from an earlier window (``held_mass_fit``), or None."""
        g = self.graph(window, particles, frame)
        if mass_fit is not None:
            g = replace(g, mass_fit=mass_fit)
        target = self.model.predict(g)
        target = target.to(window.dtype).reshape(window.shape[0], -1, self.meta.dim)
        velocity = (window[:, -1] - window[:, -2]) / self.dt
        position, _ = step(window[:, -1], velocity, target, self.dt, self.meta.target)
        return position

    def context_graph(self, context: torch.Tensor, particles: Particles, frame: int,
                      windows: int) -> Graph:
        """The graphs of up to ``windows`` windows of ``context`` (B, C, N, D), the recorded
        frames up to the start ``frame`` (its last), evenly spaced and the start's window last,
        in one batch: window w's graph of simulation b is graph ``w * B + b``."""
        k2 = self.window_length
        ends = torch.linspace(k2 - 1, context.shape[1] - 1, min(windows, context.shape[1] - k2 + 1))
        ends = sorted({int(round(float(e))) for e in ends} | {context.shape[1] - 1})
        return collate([self.graph(context[:, e - k2 + 1:e + 1], particles,
                                   frame - (context.shape[1] - 1 - e)) for e in ends])

    def held(self, window: torch.Tensor, particles: Particles, frame: int,
             context: torch.Tensor | None) -> torch.Tensor | None:
        """(B, N, ...) what the model holds along a rollout from ``window``: its
        ``held_mass_fit`` of the first window, or of ``held_fit_windows`` windows of
        ``context`` (the frames before the start, the window's last) where given; None where
        the model holds nothing."""
        hold = getattr(self.model, "held_mass_fit", None)
        if hold is None:
            return None
        b, n = window.shape[0], window.shape[2]
        windows = int(getattr(self.model, "held_fit_windows", 1))
        if context is None or windows <= 1 or context.shape[1] <= self.window_length:
            fit = hold(self.graph(window, particles, frame))
            return None if fit is None else fit.reshape(b, n, *fit.shape[1:])
        context = context.to(window.device, torch.float64)
        if not torch.equal(context[:, -self.window_length:], window):
            raise ValueError("a rollout's context must end with its first window")
        fit = hold(self.context_graph(context, particles, frame, windows))
        return None if fit is None else fit.reshape(-1, b, n, *fit.shape[1:])[-1]

    @torch.no_grad()
    def rollout(self, window: torch.Tensor, particles: Particles, n_steps: int,
                frame: int = 0, driven: torch.Tensor | None = None,
                context: torch.Tensor | None = None) -> Rollout:
        """Feed the model its own frames for ``n_steps`` from windows ending at ``frame``.

        A simulation whose frame becomes non-finite stops there (NaN from then on); the others
        go on in the same batch. ``driven`` (B, n_steps, N, D): the recorded positions of the
        steps, which ``particles.kinematic`` particles take (the source moves them). A model
        with ``held_mass_fit`` fits its masses once, to these first windows (or to windows of
        ``context`` (B, C, N, D), the recorded frames up to the start, the window's last, where
        the model reads several: ``held``), and keeps them.
        """
        if n_steps < 1:
            raise ValueError(f"n_steps={n_steps} must be at least 1")
        device = self.device
        window = window.to(device, torch.float64)
        particles = particles.to(device)
        kinematic = particles.kinematic if driven is not None else None
        if kinematic is not None:
            driven = driven.to(device, torch.float64)
        b = window.shape[0]
        out = torch.full((b, n_steps + 1, *window.shape[2:]), float("nan"),
                         dtype=torch.float64, device=device)
        out[:, 0] = window[:, -1]
        first_bad = torch.full((b,), -1, dtype=torch.long)
        alive = torch.arange(b, device=device)
        held = self.held(window, particles, frame, context)  # (B, N, ...): a row per simulation
        start = time.perf_counter()
        for i in range(n_steps):
            nxt = self.next_frame(window, particles.select(alive), frame + i,
                                  None if held is None else held[alive].flatten(0, 1))
            if kinematic is not None:
                nxt = torch.where(kinematic[alive, :, None], driven[alive, i], nxt)
            finite = torch.isfinite(nxt).flatten(1).all(1)
            out[alive[finite], i + 1] = nxt[finite]
            first_bad[alive[~finite].cpu()] = i + 1
            window = torch.cat([window[:, 1:], nxt[:, None]], dim=1)[finite]
            alive = alive[finite]
            if len(alive) == 0:
                break
        seconds = (time.perf_counter() - start) / n_steps
        return Rollout(out, first_bad, seconds)
