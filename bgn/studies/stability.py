"""Hard-case stability suite: ``python -m bgn.stability preset=all_cases`` (presets: tiny |
all_cases).

Configs live in their own Hydra root, ``conf/stability/``: ``stability.yaml``, one file per
case (``case/<case>.yaml``: scene, parameters, fps, frames, an initial state or parts of one,
a symmetry transform) and presets (``preset/<preset>.yaml``) that list the cases. For every case:

- the simulator's own checks on the case's exact trajectory: finite values, relative energy
  drift, momentum drift where momentum is conserved (n-body; discs that never touch a wall),
  overlaps and escapes from the box (discs), the closest approach, largest acceleration and
  fastest pair rotation per frame (n-body; ``aliased_frames``: the share of frames where it
  is beyond what frames carry), the most impacts of one disc within one frame, and for an
  offset or scaled case the distance to the untransformed twin mapped back;
- for a model of the case's scene (``checkpoints.<scene>=path``; the preset's
  ``untrained_model`` stands in where none is given, to exercise the pipeline; else skipped):
  through ``bgn.simulator.LearnedSimulator`` from the first full window of the true
  trajectory: finite or not, one-step error of the target (relative, over several starts),
  mean position error after 1, 100 and 1000 steps (those the case has frames for), energy
  error at the end of the rollout, wall time per step; float32 or float64 model arithmetic;
- beside a model of a force scene, two references on the same protocol: the frame oracle
  (``bgn.model.references.FrameOracle``: the true law and masses fed the same frames, what
  frames allow at this frame rate) and the predictability limit (the exact simulator with
  every position moved by 1e-6: what chaos alone does).

The report (``report.md``, ``simulator.csv``, ``model.csv``, ``stability.png``) goes to
``report_dir`` (default ``outputs/stability/<preset>/``).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from bgn.sim import Scene, State, Trajectory, make_scene
from bgn.sim.collisions import CollisionScene
from bgn.sim.nbody import NYQUIST_TURN, pair_turns
from bgn.sim.transform import offset, scaled
from bgn.tables import markdown_table, write_csv
from bgn.training.validate import cli

CONF_DIR = Path(__file__).resolve().parents[2] / "conf" / "stability"
# default limits of the simulator checks; a case's ``limits`` overrides them
LIMITS = {"energy_contact": 1e-9, "energy_pairwise": 1e-6, "momentum": 1e-9, "overlap": 1e-9,
          "transform": 1e-6}
SIM_COLUMNS = ["case", "scene", "n", "fps", "frames", "sim_s", "finite", "energy_drift",
               "momentum_drift", "min_gap", "inside_box", "max_impacts_per_frame",
               "min_distance", "max_accel", "max_turns_per_frame", "aliased_frames",
               "transform_error", "passed", "failed_checks"]
MODEL_COLUMNS = ["case", "scene", "model", "dtype", "steps", "finite", "first_non_finite",
                 "left_scale", "aliased_frames", "one_step_rel_error", "error_1", "error_100",
                 "error_1000", "position_scale", "energy_error", "s_per_step"]


# ----------------------------------------------------------------------------- cases
@dataclasses.dataclass
class Case:
    """One hard case, as read from ``conf/stability/case/<name>.yaml``."""

    name: str
    scene: str
    description: str = ""
    params: dict = dataclasses.field(default_factory=dict)
    fps: float = 50.0
    n_frames: int = 200
    seed: int = 0
    state: dict = dataclasses.field(default_factory=dict)   # overrides of the drawn state
    transform: dict = dataclasses.field(default_factory=dict)  # {offset: x} or {scale: f}
    compare_frames: int = 50                                 # horizon of the twin comparison
    model_dtypes: list = dataclasses.field(default_factory=lambda: ["float32"])
    limits: dict = dataclasses.field(default_factory=dict)

    @property
    def dt(self) -> float:
        return 1.0 / self.fps


def load_case(name: str, conf_dir: Path = CONF_DIR) -> Case:
    path = conf_dir / "case" / f"{name}.yaml"
    if not path.exists():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ValueError(f"no stability case {name!r} ({path}); known: {known}")
    raw = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    assert isinstance(raw, dict)
    known_keys = {f.name for f in dataclasses.fields(Case)}
    unknown = sorted(set(raw) - known_keys)
    if unknown:
        raise ValueError(f"{path}: unknown keys {unknown}; known: {sorted(known_keys)}")
    return Case(**{"name": name, **raw})


def build(case: Case) -> tuple[Scene, State, Scene, State]:
    """(scene, state) of the case and of its untransformed twin (the same when no transform)."""
    scene = make_scene(case.scene, **case.params)
    drawn = scene.draw_state(np.random.default_rng(case.seed))
    n = len(case.state["positions"]) if "positions" in case.state else drawn.positions.shape[0]
    if n != drawn.positions.shape[0]:  # an explicit state sets the number of bodies
        scene = make_scene(case.scene, **{**case.params, "n_particles": n})
        drawn = scene.draw_state(np.random.default_rng(case.seed))
    base = dataclasses.replace(drawn, **{k: np.asarray(v) for k, v in case.state.items()})
    unknown = set(case.transform) - {"offset", "scale"}
    if unknown:
        raise ValueError(f"case {case.name}: unknown transform {sorted(unknown)}; use offset "
                         "or scale")
    twin_scene, twin = scene, base
    if "scale" in case.transform:
        twin_scene, twin = scaled(scene, base, float(case.transform["scale"]))
    if "offset" in case.transform:
        twin = offset(twin, float(case.transform["offset"]))
    return twin_scene, twin, scene, base


def untransform(case: Case, x: np.ndarray) -> np.ndarray:
    """Positions of the transformed case mapped back to the base scene's frame."""
    x = x - float(case.transform.get("offset", 0.0))
    return x / float(case.transform.get("scale", 1.0))


# ----------------------------------------------------------------------------- simulator checks
def simulate(scene: Scene, state: State, times: np.ndarray) -> tuple[Trajectory, Any]:
    if isinstance(scene, CollisionScene):
        return scene.simulate_events_from(state, times)
    return scene.simulate_from(state, times), None


def simulator_checks(case: Case, scene: Scene, traj: Trajectory, log: Any,
                     seconds: float) -> dict[str, Any]:
    """The simulator's own checks on one trajectory (see the module doc)."""
    x, v, m = traj.positions, traj.velocities, traj.masses
    finite = bool(np.isfinite(x).all() and np.isfinite(v).all())
    e = scene.energy(x, v, m)
    scale_e = max(abs(float(e[0])), float(np.abs(0.5 * np.einsum("n,tnd,tnd->t", m, v, v)).max()))
    row: dict[str, Any] = {
        "case": case.name, "scene": case.scene, "n": int(x.shape[1]), "fps": case.fps,
        "frames": int(x.shape[0]), "sim_s": seconds, "finite": finite,
        "energy_drift": float(np.abs(e - e[0]).max() / scale_e)}
    momentum = np.einsum("n,tnd->td", m, v)
    p_scale = float(np.abs(m[:, None] * v[0]).sum())
    walls = log is not None and bool((log.j < 0).any())
    if not walls:
        row["momentum_drift"] = float(np.abs(momentum - momentum[0]).max() / p_scale)
    if isinstance(scene, CollisionScene):
        row.update(contact_checks(traj, scene.box, log))
    else:
        i, j = np.triu_indices(x.shape[1], 1)
        row["min_distance"] = float(np.linalg.norm(x[:, i] - x[:, j], axis=-1).min())
        row["max_accel"] = float(np.abs(traj.accelerations).max())
        turns = pair_turns(x, v, 1.0 / case.fps)
        row["max_turns_per_frame"] = float(turns.max())
        row["aliased_frames"] = float((turns > NYQUIST_TURN).mean())
    return row


def contact_checks(traj: Trajectory, box: float, log: Any) -> dict[str, Any]:
    """Smallest surface gap (relative to the mean radius; < 0 is an overlap), every disc
    inside the box, and the most impacts of one disc within one frame interval."""
    x, r = traj.positions, traj.radii
    gap = np.inf
    if x.shape[1] > 1:
        from scipy.spatial import cKDTree

        for frame in x:
            pairs = cKDTree(frame).query_pairs(2 * float(r.max()), output_type="ndarray")
            if pairs.size:
                d = np.linalg.norm(frame[pairs[:, 0]] - frame[pairs[:, 1]], axis=-1)
                gap = min(gap, float((d - r[pairs[:, 0]] - r[pairs[:, 1]]).min()))
    tol = 1e-9 * box
    inside = bool((x - r[None, :, None]).min() >= -tol
                  and (box - r[None, :, None] - x).min() >= -tol)
    impacts = 0
    if log is not None and log.times.size:
        frame_of = np.searchsorted(traj.times, log.times, side="left") - 1
        who = np.concatenate([log.i, log.j[log.j >= 0]])
        when = np.concatenate([frame_of, frame_of[log.j >= 0]])
        keep = when >= 0
        if keep.any():
            codes = when[keep] * x.shape[1] + who[keep]
            impacts = int(np.unique(codes, return_counts=True)[1].max())
    return {"min_gap": gap / float(r.mean()) if np.isfinite(gap) else None,
            "inside_box": inside, "max_impacts_per_frame": impacts}


def judge(case: Case, scene: Scene, row: dict[str, Any]) -> None:
    """Add ``passed`` and the list of failed checks to a simulator row."""
    limits = {**LIMITS, **case.limits}
    energy_limit = limits[f"energy_{scene.meta.interaction}"]
    failed = [] if row["finite"] else ["finite"]
    if not row["energy_drift"] <= energy_limit:
        failed.append("energy")
    if row.get("momentum_drift") is not None and not row["momentum_drift"] <= limits["momentum"]:
        failed.append("momentum")
    if row.get("min_gap") is not None and not row["min_gap"] >= -limits["overlap"]:
        failed.append("overlap")
    if row.get("inside_box") is False:
        failed.append("inside_box")
    if row.get("transform_error") is not None and not row["transform_error"] <= limits["transform"]:
        failed.append("transform")
    row["passed"] = not failed
    row["failed_checks"] = " ".join(failed)


# ----------------------------------------------------------------------------- model checks
def model_for(case: Case, scene: Scene, traj: Trajectory, cfg: DictConfig
              ) -> tuple[Any, str] | None:
    """(model, label) for the case's scene: the checkpoint of ``checkpoints.<scene>``, else
    the preset's untrained model with statistics of the default scene, else None."""
    ckpt = (cfg.get("checkpoints") or {}).get(case.scene)
    if ckpt:
        from bgn.training.module import load_model

        model = load_model(ckpt).model
        if model.meta.name != case.scene or model.meta.dim != scene.meta.dim:
            raise ValueError(f"checkpoints.{case.scene}={ckpt} is a {model.meta.name} model in "
                             f"{model.meta.dim}D; the case {case.name} is {case.scene} in "
                             f"{scene.meta.dim}D")
        return model, Path(ckpt).name
    spec = cfg.preset.get("untrained_model")
    if not spec:
        return None
    import torch

    from bgn.data.generate import stack
    from bgn.data.stats import compute_stats
    from bgn.model import build_model

    torch.manual_seed(0)
    # statistics of the default scene (what a model is trained on), 30 frames at the case's fps
    default = make_scene(case.scene)
    train = default.simulate(np.random.default_rng(0), np.arange(30) / case.fps)
    spec = dict(OmegaConf.to_container(spec, resolve=True))  # type: ignore[arg-type]
    history = int(spec.pop("history", 2))
    stats = compute_stats(default, stack([train]), case.dt, graph_margin(default, train, case.dt))
    return build_model(spec, scene.meta, stats, history).eval(), f"untrained {spec['name']}"


def graph_margin(scene: Scene, traj: Trajectory, dt: float) -> float:
    if scene.meta.graph != "radius":
        return 0.0
    from bgn.data.generate import radius_margin, stack

    return radius_margin(stack([traj]), dt)


def model_checks(case: Case, scene: Scene, traj: Trajectory, model: Any, label: str,
                 horizons: list[int], n_starts: int) -> list[dict[str, Any]]:
    """Rollouts of ``model`` from the first full window of ``traj``, one row per dtype."""
    import torch

    from bgn.data.targets import targets
    from bgn.metrics import rollout_failures
    from bgn.simulator import LearnedSimulator, Particles

    k = model.history
    x = traj.positions
    n_steps = min(max(horizons), len(x) - k - 2)
    if n_steps < 1:
        return []
    meta = dataclasses.replace(model.meta, n_particles=scene.meta.n_particles, box=scene.meta.box)
    margin = graph_margin(scene, traj, case.dt)
    rows = []
    for dtype_name in case.model_dtypes:
        dtype = {"float32": torch.float32, "float64": torch.float64}[dtype_name]
        net = copy.deepcopy(model).to(dtype)
        sim = LearnedSimulator(net, case.dt, margin, dtype=dtype)
        sim.meta = meta  # the case's box and size; the model's own graph rule and target

        def particles(b: int, _sim: Any = sim) -> Particles:
            def rep(a: np.ndarray) -> torch.Tensor:
                return torch.as_tensor(np.repeat(a[None], b, axis=0))
            return Particles(rep(traj.masses), rep(traj.radii), rep(traj.types),
                             torch.zeros(b, dtype=torch.long))

        # one-step error of the target at several start frames (error / dt or dt^2 is exact)
        starts = np.unique(np.linspace(k + 1, len(x) - 2, n_starts).astype(int))
        windows = torch.as_tensor(np.stack([x[s - k - 1:s + 1] for s in starts]))
        with torch.no_grad():
            nxt = sim.next_frame(windows, particles(len(starts)), 0).numpy()
        power = 1 if scene.meta.target == "velocity" else 2
        err = (nxt - x[starts + 1]) / case.dt ** power
        true_t = np.stack([targets(x[s - 1:s + 2], case.dt, scene.meta.target)[0]
                           for s in starts])
        one_step = float(np.sqrt((err ** 2).mean() / max((true_t ** 2).mean(), 1e-300)))

        result = sim.rollout(torch.as_tensor(x[None, :k + 2]), particles(1), n_steps, k + 1)
        pred = result.positions[0].numpy()
        truth = x[k + 1:k + 2 + n_steps]
        err_t = np.linalg.norm(pred - truth, axis=-1).mean(axis=-1)
        # the evaluation's failure rule: a particle more than ESCAPE_FACTOR scene scales astray
        before = x[k:k + 1]
        left = bool(rollout_failures(np.concatenate([before, pred])[None],
                                     np.concatenate([before, truth])[None], scene.meta.box,
                                     np.array([-1]))[0] >= 0)
        row = {"case": case.name, "scene": case.scene, "model": label, "dtype": dtype_name,
               "steps": n_steps, "finite": not bool(result.failed[0]),
               "first_non_finite": int(result.first_non_finite[0]), "left_scale": left,
               "one_step_rel_error": one_step, "position_scale": float(x.std()),
               "s_per_step": result.seconds_per_step}
        for h in horizons:
            if h <= n_steps:
                row[f"error_{h}"] = float(err_t[h])
        good = pred[np.isfinite(pred).all(axis=(1, 2))]
        if len(good) >= 2:
            def energy(pos: np.ndarray) -> float:
                vel = (pos[-1] - pos[-2]) / case.dt
                return float(scene.energy(pos[-1:], vel[None], traj.masses)[0])
            e0 = energy(truth[:2])
            row["energy_error"] = abs(energy(good) - e0) / max(abs(e0), 1e-300)
        rows.append(row)
    return rows


# ----------------------------------------------------------------------------- the suite
def run_case(case: Case, cfg: DictConfig) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Simulator checks and model rows of one case."""
    case, scene, traj, row = simulate_case(case, cfg.preset)
    picked = model_for(case, scene, traj, cfg)
    rows = [] if picked is None else case_model_rows(case, scene, traj, row, *picked, cfg.preset)
    return row, rows


def simulate_case(case: Case, preset: DictConfig) -> tuple[Case, Scene, Trajectory,
                                                           dict[str, Any]]:
    """The case capped at ``preset.max_frames``, its scene, its exact trajectory and the
    simulator's checks of it (judged)."""
    if preset.get("max_frames"):
        case = dataclasses.replace(case, n_frames=min(case.n_frames, int(preset.max_frames)))
    times = np.arange(case.n_frames) / case.fps
    scene, state, base_scene, base = build(case)
    start = time.perf_counter()
    traj, log = simulate(scene, state, times)
    row = simulator_checks(case, scene, traj, log, time.perf_counter() - start)
    if case.transform:
        n = min(case.compare_frames, case.n_frames)
        ref, _ = simulate(base_scene, base, times[:n])
        diff = np.abs(untransform(case, traj.positions[:n]) - ref.positions).max()
        row["transform_error"] = float(diff / ref.positions.std())
    judge(case, scene, row)
    return case, scene, traj, row


def case_model_rows(case: Case, scene: Scene, traj: Trajectory, row: dict[str, Any],
                    model: Any, label: str, preset: DictConfig, references: bool = True,
                    ) -> list[dict[str, Any]]:
    """The rollout rows of one model on a simulated case and, on a force scene with
    ``references``, the frame oracle's and the predictability limit's (they do not depend on
    the model: several models of one scene need them once)."""
    horizons, starts = list(preset.horizons), int(preset.one_step_starts)
    model_rows = model_checks(case, scene, traj, model, label, horizons, starts)
    if references and not isinstance(scene, CollisionScene):  # a force scene's references
        from bgn.model.references import FrameOracle

        oracle = FrameOracle(scene, model.history)
        model_rows += model_checks(dataclasses.replace(case, model_dtypes=["float64"]),
                                   scene, traj, oracle, oracle.label, horizons, starts)
        model_rows.append(predictability_row(case, scene, traj, model.history, horizons))
    if "aliased_frames" in row:  # beside left_scale: how much the frames alias
        for model_row in model_rows:
            model_row["aliased_frames"] = row["aliased_frames"]
    return model_rows


def predictability_row(case: Case, scene: Scene, traj: Trajectory, history: int,
                       horizons: list[int], eps: float = 1e-6) -> dict[str, Any]:
    """The exact simulator from the rollouts' start state with every position moved by
    ``eps``: the error chaos alone makes of ``eps`` (the scene's predictability limit), on the
    model rows' protocol (start at frame history + 1)."""
    start = history + 1
    n_steps = min(max(horizons), len(traj.positions) - start - 1)
    state = State(traj.positions[start], traj.velocities[start], traj.masses, traj.radii,
                  traj.types)
    kick = np.random.default_rng(case.seed).standard_normal(state.positions.shape)
    kick *= eps / np.linalg.norm(kick, axis=-1, keepdims=True)
    moved = dataclasses.replace(state, positions=state.positions + kick)
    pred, _ = simulate(scene, moved, np.arange(n_steps + 1) / case.fps)
    err_t = np.linalg.norm(pred.positions - traj.positions[start:start + n_steps + 1],
                           axis=-1).mean(axis=-1)
    row = {"case": case.name, "scene": case.scene, "model": f"predictability ({eps:g} off)",
           "dtype": "float64", "steps": n_steps, "finite": bool(np.isfinite(err_t).all()),
           "first_non_finite": -1, "left_scale": False,
           "position_scale": float(traj.positions.std())}
    row.update({f"error_{h}": float(err_t[h]) for h in horizons if h <= n_steps})
    return row


def figure(path: Path, sim_rows: list[dict[str, Any]], model_rows: list[dict[str, Any]]) -> None:
    """Energy drift per case (simulator), and rollout errors per case (model) if any."""
    import matplotlib.pyplot as plt

    from bgn.figures import save

    panels = 2 if model_rows else 1
    fig, axes = plt.subplots(1, panels, figsize=(7 * panels, 0.28 * len(sim_rows) + 1.5),
                             squeeze=False)
    ax = axes[0, 0]
    names = [r["case"] for r in sim_rows]
    drift = [max(r["energy_drift"], 1e-17) if r["energy_drift"] == r["energy_drift"] else 1e-17
             for r in sim_rows]
    ax.barh(names, drift, color=["tab:blue" if r["passed"] else "tab:red" for r in sim_rows])
    ax.set_xscale("log")
    ax.set_xlabel("simulator: max relative energy drift (red: a check failed)")
    ax.invert_yaxis()
    if model_rows:
        ax = axes[0, 1]
        labels = [f"{r['case']} ({r['dtype']})" for r in model_rows]
        for key, color in (("one_step_rel_error", "tab:green"), ("error_100", "tab:orange"),
                           ("error_1000", "tab:red")):
            vals = [r.get(key) if r.get(key) is not None else np.nan for r in model_rows]
            if np.isfinite(vals).any():
                ax.scatter(vals, labels, label=key, color=color)
        ax.set_xscale("log")
        ax.set_xlabel("model: relative one-step error, mean position error")
        ax.legend(fontsize=7)
        ax.invert_yaxis()
    fig.tight_layout()
    save(fig, path, dpi=100)


def write_report(out: Path, preset: str, cases: list[Case], sim_rows: list[dict[str, Any]],
                 model_rows: list[dict[str, Any]], checkpoints: Mapping[str, Any],
                 untrained: bool, seconds: float) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "simulator.csv", SIM_COLUMNS, sim_rows)
    write_csv(out / "model.csv", MODEL_COLUMNS, model_rows)
    figure(out / "stability.png", sim_rows, model_rows)
    (out / "results.json").write_text(json.dumps({"simulator": sim_rows, "model": model_rows},
                                                 indent=1, default=str))
    given = {k: v for k, v in checkpoints.items() if v}
    if given:
        model_note = "Models: " + ", ".join(f"{k}: `{v}`" for k, v in given.items()) + "."
    elif untrained:
        model_note = ("No checkpoints given: the model part ran an *untrained* small model "
                      "(the numbers only show that the pipeline runs).")
    else:
        model_note = ("No checkpoints given (`checkpoints.<scene>=path`): the model part was "
                      "skipped.")
    scenes_without = sorted({c.scene for c in cases} - set(given))
    if given and scenes_without:
        model_note += f" No model for: {', '.join(scenes_without)}."
    n_failed = sum(not r["passed"] for r in sim_rows)
    text = [
        f"# Stability suite, preset `{preset}`", "",
        f"{len(cases)} cases, {n_failed} with a failed simulator check; {seconds:.0f} s.", "",
        "## Simulator checks", "",
        "energy_drift: max |E_t - E_0| / max(|E_0|, max kinetic energy); momentum_drift: max "
        "|P_t - P_0| / sum |m v_0| (blank where walls exchange momentum); min_gap: smallest "
        "surface gap / mean radius (< 0: overlap); max_impacts_per_frame: most events of one "
        "disc within one frame interval; min_distance, max_accel: closest pair and largest "
        "|a| over the frames (n-body); max_turns_per_frame: the fastest rotation of any pair "
        "at the frame times, in revolutions per frame (n-body); aliased_frames: the share of "
        f"frames where some pair turns more than {NYQUIST_TURN:g} revolution per frame, "
        "beyond what frames sampled at this rate carry (Nyquist: they cannot tell such a turn "
        "from a slower one the other way round); transform_error: offset or "
        "scaled case mapped back, "
        "max distance to the untransformed twin over its first `compare_frames` frames / "
        "position std. Limits: " + ", ".join(f"{k} {v:g}" for k, v in LIMITS.items())
        + " (a case may set its own).", "",
        markdown_table(SIM_COLUMNS, sim_rows), "",
        "## Cases", "",
        *[f"- `{c.name}` ({c.scene}): {c.description.strip()}" for c in cases], "",
        "## Model rollouts", "", model_note, "",
    ]
    if model_rows:
        text += ["One rollout from the first full window (frame k+1) of each case's true "
                 "trajectory. one_step_rel_error: RMS target error / RMS target over "
                 "several starts; error_h: mean position error per particle after h steps; "
                 "energy_error: |E_end - E_start| / |E_start| (finite-difference velocities); "
                 "left_scale: a particle more than 10 scene scales astray (the box, or the true "
                 "trajectory's extent; the evaluation's failure rule); aliased_frames: the "
                 "case's, from the simulator checks. Force scenes also "
                 "have two references: the frame oracle (the true law and masses fed the "
                 "same frames, integrated in substeps: what frames allow) and the "
                 "predictability limit (the exact simulator with positions 1e-6 off).", "",
                 markdown_table(MODEL_COLUMNS, model_rows), ""]
    text += ["![stability](stability.png)", ""]
    path = out / "report.md"
    path.write_text("\n".join(text))
    return path


def run(cfg: DictConfig) -> Path:
    """Every case of ``cfg.preset``; the report under ``cfg.report_dir``."""
    start = time.perf_counter()
    preset = cfg.preset
    cases = [load_case(str(name)) for name in preset.cases]
    sim_rows, model_rows = [], []
    for i, case in enumerate(cases, 1):
        t0 = time.perf_counter()
        try:
            row, rows = run_case(case, cfg)
        except (ValueError, RuntimeError) as err:  # a broken case is reported, not fatal
            row = {"case": case.name, "scene": case.scene, "passed": False,
                   "failed_checks": f"error: {err}", "energy_drift": float("nan")}
            rows = []
        sim_rows.append(row)
        model_rows += rows
        status = "ok" if row["passed"] else f"FAILED {row['failed_checks']}"
        print(f"[{i}/{len(cases)}] {case.name}: {status} ({time.perf_counter() - t0:.1f} s)",
              flush=True)
    checkpoints = OmegaConf.to_container(cfg.get("checkpoints") or {}, resolve=True)
    report = write_report(Path(cfg.report_dir), str(preset.name), cases, sim_rows,
                          model_rows, checkpoints,  # type: ignore[arg-type]
                          bool(preset.get("untrained_model")), time.perf_counter() - start)
    return report


def resolve_checkpoints(cfg: DictConfig) -> None:
    """Each ``checkpoints.<scene>`` given (a run folder or checkpoint) replaced by the
    checkpoint ``python -m bgn.evaluate`` would score (``bgn.training.checkpoints.resolve_run``); a
    path that is neither: one line, exit 2, before any case runs."""
    from bgn.training.checkpoints import resolve_run
    from bgn.training.validate import ConfigError

    given = cfg.get("checkpoints") or {}
    for scene in list(given):  # the scenes' keys are conf/stability/stability.yaml's
        if given[scene]:
            try:
                ckpt, _, _ = resolve_run(str(given[scene]))
            except ConfigError as err:
                raise ConfigError(f"checkpoints.{scene}", message=str(err).replace(
                    "ckpt=", f"checkpoints.{scene}=", 1)) from None
            given[scene] = str(ckpt)


@cli("stability", resolve_checkpoints, config_dir=CONF_DIR)  # bad input: one line, exit 2
def main(cfg: DictConfig) -> None:
    """``python -m bgn.stability preset=all_cases checkpoints.spring=<run>``: see the module
    doc."""
    start = time.perf_counter()
    print(f"report: {run(cfg)} ({time.perf_counter() - start:.0f} s)")
