"""What the data conserve (bgn.data.balance): central pair forces balance, a field, walls or
tangential pair forces do not, whatever the masses, the units or the particles' order."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bgn.data.balance import (
    IMBALANCE_MAX,
    PAIRS_MAX,
    UNEXPLAINED_MIN,
    Balance,
    VelocityDependence,
    imbalance,
    momentum_balance,
    simulation_columns,
    velocity_dependence,
)


def trajectory(seed: int, field: float = 0.0, tangential: float = 0.0, dim: int = 2,
               n: int = 5, frames: int = 120, substeps: int = 20, dt: float = 0.02,
               ) -> np.ndarray:
    """(T, N, D) positions of ``n`` particles of random masses under spring-like central
    pair forces ``-(s - 1) u_ij``, plus a uniform ``field`` along the first axis and, equal
    and opposite but across the line, ``tangential`` times the pair's force turned by 90
    degrees (2-D); velocity Verlet with ``substeps`` per frame."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(0.5, 2.0, n)
    x = rng.uniform(-1.5, 1.5, (n, dim))
    v = rng.normal(0.0, 0.5, (n, dim))
    v -= (m[:, None] * v).sum(0) / m.sum()

    def accel(x: np.ndarray) -> np.ndarray:
        d = x[:, None] - x[None]                       # x_i - x_j
        s = np.linalg.norm(d, axis=-1) + np.eye(n)
        u = d / s[..., None]
        f = (-(s - 1.0))[..., None] * u * (1 - np.eye(n))[..., None]
        if tangential:
            f = f + tangential * np.stack([-f[..., 1], f[..., 0]], -1)
        a = f.sum(1) / m[:, None]
        a[:, 0] += field
        return a

    h = dt / substeps
    out = [x.copy()]
    a = accel(x)
    for _ in range(frames - 1):
        for _ in range(substeps):
            v += 0.5 * h * a
            x += h * v
            a = accel(x)
            v += 0.5 * h * a
        out.append(x.copy())
    return np.stack(out)


def columns_imbalance(x: np.ndarray, angular: bool) -> float:
    cols = simulation_columns(x, angular)
    return imbalance(cols if angular else cols[: (len(x) - 2) * x.shape[-1]])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_central_pair_forces_balance_with_unknown_masses(seed):
    x = trajectory(seed)
    assert columns_imbalance(x, angular=False) < 1e-12
    assert columns_imbalance(x, angular=True) < IMBALANCE_MAX / 10


@pytest.mark.parametrize("seed", [0, 1])
def test_a_field_breaks_the_momentum_balance(seed):
    assert columns_imbalance(trajectory(seed, field=-1.0), angular=False) > 10 * IMBALANCE_MAX


@pytest.mark.parametrize("seed", [0, 1])
def test_forces_across_the_line_keep_momentum_but_not_angular_momentum(seed):
    x = trajectory(seed, tangential=0.5)
    assert columns_imbalance(x, angular=False) < 1e-12
    assert columns_imbalance(x, angular=True) > 10 * IMBALANCE_MAX


def test_the_imbalance_does_not_depend_on_order_units_or_origin():
    x = trajectory(3, field=-0.3)
    ref = columns_imbalance(x, angular=True)
    perm = np.random.default_rng(0).permutation(x.shape[1])
    assert columns_imbalance(x[:, perm], angular=True) == pytest.approx(ref, rel=1e-6)
    assert columns_imbalance(7.0 * x, angular=True) == pytest.approx(ref, rel=1e-6)
    assert columns_imbalance(x + np.array([3.0, -2.0]), angular=True) == \
        pytest.approx(ref, rel=1e-6)


def test_a_particle_that_never_accelerates_balances_nothing():
    x = trajectory(4, field=-1.0)
    still = np.zeros((len(x), 1, 2)) + 5.0       # a particle at rest far away
    assert columns_imbalance(np.concatenate([x, still], 1), angular=False) > 10 * IMBALANCE_MAX


class FakeFile:
    """The slice of ``DatasetFile`` that momentum_balance reads."""

    def __init__(self, positions: np.ndarray, kinematic: np.ndarray | None = None) -> None:
        self.arrays = {"positions": positions}
        if kinematic is not None:
            self.arrays["kinematic"] = kinematic
        self.handle = self.arrays
        self.n_sims, self.n_frames = positions.shape[:2]

    def read(self, name: str, index=()) -> np.ndarray:
        return self.arrays[name][index]


def meta(dim: int = 2, periodic: bool = False) -> SimpleNamespace:
    return SimpleNamespace(dim=dim, periodic=periodic)


def test_momentum_balance_over_simulations_and_its_verdict():
    balanced = FakeFile(np.stack([trajectory(s) for s in range(3)]))
    b = momentum_balance(balanced, meta())
    assert b.sims == 3 and b.linear < 1e-12 and b.angular < IMBALANCE_MAX and b.breaks() == ""
    pulled = FakeFile(np.stack([trajectory(s, field=-1.0) for s in range(3)]))
    assert "total momentum changes" in momentum_balance(pulled, meta()).breaks()
    turned = FakeFile(np.stack([trajectory(s, tangential=0.5) for s in range(3)]))
    assert "angular momentum changes" in momentum_balance(turned, meta()).breaks()
    # periodic: angular momentum is not defined, momentum still is
    b = momentum_balance(turned, meta(periodic=True))
    assert b.angular is None and b.breaks() == ""


def test_sources_that_move_particles_leave_the_balance_untested():
    x = np.stack([trajectory(s, field=-1.0) for s in range(2)])
    kinematic = np.zeros((x.shape[0], x.shape[2]), dtype=bool)
    kinematic[:, 0] = True
    b = momentum_balance(FakeFile(x, kinematic), meta())
    assert b.linear is None and "moved by the source" in b.reason and b.breaks() == ""


def test_auto_refuses_the_pair_force_head_where_the_data_do_not_balance():
    from bgn.sim.scene import SceneMeta
    from bgn.studies.auto import candidates

    gas = SceneMeta("imported", 2, 8, 1, "unknown", "acceleration", "radius")
    broken = Balance(linear=0.2, angular=0.2, sims=4, frames=100)
    pool = {c.name: c for c in candidates(gas, 5, False, (), broken)}
    assert pool["decoder"].admitted
    for law in ("inertial", "source"):
        assert not pool[f"newton_{law}"].admitted
        assert "total momentum changes" in pool[f"newton_{law}"].reason
    fine = Balance(linear=1e-9, angular=None, sims=4, frames=100)
    assert all(c.admitted for c in candidates(gas, 5, False, (), fine)
               if c.name.startswith("newton"))


def springs_within(x: np.ndarray, v: np.ndarray, stiff, rest: float, reach: float,
                   frames: int, substeps: int, h: float) -> np.ndarray:
    """(frames, N, D) positions of springs ``-stiff (r - rest)`` between every pair closer
    than ``reach`` (unit masses), velocity Verlet with ``substeps`` steps of ``h`` a frame."""
    n = len(x)

    def accel(y: np.ndarray) -> np.ndarray:
        d = y[:, None] - y[None]
        r = np.linalg.norm(d, axis=-1) + np.eye(n)
        f = -stiff * (r - rest) * (r <= reach) * (1 - np.eye(n))
        return (f[..., None] * d / r[..., None]).sum(1)

    x, v, out = x.copy(), v.copy(), []
    for _ in range(frames):
        out.append(x.copy())
        for _ in range(substeps):
            v += 0.5 * h * accel(x)
            x += h * v
            v += 0.5 * h * accel(x)
    return np.stack(out)


def split_files(x: np.ndarray, tmp_path, name: str, **arrays) -> tuple:
    from bgn.data import from_arrays
    from bgn.data.files import DatasetFile

    n = len(x)
    paths = from_arrays(x, 0.02, name=name, data_dir=tmp_path, splits={
        "train": list(range(n - 2)), "val": [n - 2], "test": [n - 1]}, **arrays)
    return DatasetFile(paths["train"]), DatasetFile(paths["val"])


@pytest.mark.parametrize("damping", [0.0, 0.2, 1.0])
def test_central_damping_is_seen_by_the_law_fit_where_the_balance_cannot(tmp_path, damping):
    """Springs with damping along the line between the particles keep momentum and angular
    momentum; a law of the distance leaves the damping unexplained, one of the distance and
    the relative speed along the pair does not."""
    from tests.model.test_force_matching import damped_springs

    train, val = split_files(damped_springs(damping, sims=5, frames=120), tmp_path, "damped")
    assert momentum_balance(train, train.meta).breaks() == ""
    v = velocity_dependence(train, val, train.meta)
    assert v.velocity < 1e-2 and v.sims == 3 and v.frames == 120
    if damping == 0:
        assert v.distance < 1e-3 and v.breaks() == ""
    else:
        assert v.distance > 100 * v.velocity and "depend on velocity" in v.breaks()


def test_unknown_masses_are_not_taken_for_velocity(tmp_path):
    """Springs between particles of random masses (not recorded): a law with equal masses
    leaves much unexplained, and a law with velocity no less, so nothing is refused."""
    x = np.stack([trajectory(s) for s in range(5)])
    train, val = split_files(x, tmp_path, "masses")
    v = velocity_dependence(train, val, train.meta)
    assert v.distance > UNEXPLAINED_MIN and v.velocity > v.distance / 2 and v.breaks() == ""


def test_velocity_dependence_on_a_radius_graph_with_two_types(tmp_path):
    """One table per pair of types, pairs beyond the graph's reach left out: springs whose
    stiffness depends on the pair's types and that act only within the reach are explained
    by the law of the distance."""
    n, rng = 6, np.random.default_rng(0)
    types = np.array([0, 0, 0, 1, 1, 1])
    stiff = np.array([[1.0, 2.0], [2.0, 3.0]])[types[:, None], types[None]]
    reach = 1.5

    sims = [springs_within(rng.uniform(0, 2.0, (n, 2)), rng.normal(0, 0.3, (n, 2)), stiff,
                           1.0, reach, 100, 20, 0.001) for _ in range(5)]
    train, val = split_files(np.stack(sims), tmp_path, "typed", types=types,
                             connectivity_radius=reach)
    assert train.meta.graph == "radius" and train.meta.n_types == 2
    v = velocity_dependence(train, val, train.meta)
    assert v.distance < 1e-2 and v.velocity > v.distance / 2 and v.breaks() == ""


def test_too_many_pairs_or_frames_leave_the_velocity_test_undone():
    crowd = SimpleNamespace(n_particles=2000, graph="full")
    v = velocity_dependence(SimpleNamespace(meta=crowd), None, crowd)
    assert v.distance is None and "more than the pair-law test reads" in v.reason
    assert v.breaks() == ""
    few = SimpleNamespace(n_particles=5, graph="full")
    short = SimpleNamespace(n_frames=4, meta=few)
    v = velocity_dependence(short, short, few)
    assert v.distance is None and "fewer than 5 frames" in v.reason


def test_a_radius_graph_counts_only_the_pairs_within_reach(tmp_path):
    """600 particles have more pairs than the test reads, but on a radius graph only those
    within its reach enter: sparse springs are tested (and explained by the distance)."""
    n, reach, rng = 600, 0.5, np.random.default_rng(1)
    assert n * (n - 1) // 2 > PAIRS_MAX

    sims = [springs_within(rng.uniform(0, 30.0, (n, 2)), rng.normal(0, 0.05, (n, 2)), 1.0,
                           0.4, reach, 12, 5, 0.01) for _ in range(3)]
    train, val = split_files(np.stack(sims), tmp_path, "sparse", connectivity_radius=reach)
    v = velocity_dependence(train, val, train.meta)
    assert v.reason == "" and v.distance is not None and v.distance < 1e-2


def test_auto_refuses_the_pair_force_head_where_the_forces_depend_on_velocity():
    from bgn.sim.scene import SceneMeta
    from bgn.studies.auto import candidates

    gas = SceneMeta("imported", 2, 8, 1, "unknown", "acceleration", "radius")
    damped = VelocityDependence(distance=0.3, velocity=1e-5, sims=4, frames=100)
    pool = {c.name: c for c in candidates(gas, 5, False, (), None, damped)}
    assert pool["decoder"].admitted
    for law in ("inertial", "source", "type"):
        assert not pool[f"newton_{law}"].admitted
        assert "depend on velocity" in pool[f"newton_{law}"].reason
    # a law of the distance explaining 99.5 % is kept, however much better velocity does
    close = VelocityDependence(distance=0.005, velocity=1e-7, sims=4, frames=100)
    assert all(c.admitted for c in candidates(gas, 5, False, (), None, close)
               if c.name.startswith("newton"))


def test_the_command_tabulates_each_file(tmp_path, capsys):
    """``python -m bgn.data.balance <files> [results_md=FILE]`` (``bgn.train.balance``): one
    row per file; several paths, or relative ones under ``paths.data_dir``; a missing file
    refused in one line (exit 2) before any is read."""
    import importlib

    from bgn.data import from_arrays
    from bgn.provenance import block_markers

    main = importlib.import_module("bgn.train.balance").command
    x = np.stack([trajectory(s, field=-1.0) for s in range(5)])
    paths = from_arrays(x, 0.02, name="pulled", data_dir=tmp_path)
    table = main([str(paths["train"])])
    assert table.count("\n") == 2 and "total momentum changes" in table
    assert "free flight beside contacts" in table.splitlines()[0]      # soft contacts' evidence
    # the validation split beside it: the velocity test's two errors
    assert " / " in table.splitlines()[-1]
    relative = str(paths["val"].relative_to(tmp_path))
    two = main([str(paths["train"]), relative, f"paths.data_dir={tmp_path}"])
    assert two.count("\n") == 3 and relative in two.splitlines()[-1]
    capsys.readouterr()
    for argv, named in (([], "give dataset files"), ([str(tmp_path / "none.h5")], "none.h5"),
                        ([str(paths["train"]), "results_md=out.txt"], "results_md")):
        with pytest.raises(SystemExit) as done:
            main(argv)
        err = capsys.readouterr().err.strip()
        assert done.value.code == 2 and len(err.splitlines()) == 1 and named in err, err
    # results_md=: the table and the command that wrote it, in the file's block, in place
    results = tmp_path / "results.md"
    results.write_text("before\n<!-- generated:balance:begin -->\nold\n"
                       "<!-- generated:balance:end -->\nafter\n")
    again = main([str(paths["train"]), f"results_md={results}"])
    assert again.splitlines()[-1].rsplit("|", 2)[0] == table.splitlines()[-1].rsplit("|", 2)[0]
    text = results.read_text()
    begin, end = block_markers("balance")
    block = text[text.index(begin):text.index(end)]
    assert text.startswith("before\n") and text.endswith("after\n") and "old" not in block
    assert "total momentum changes" in block
    assert f"python -m bgn.data.balance {paths['train']} results_md=" in block
    assert "commit" in block


def test_several_paths_become_one_files_list():
    from bgn.train.balance import one_list

    assert one_list(["a.h5"]) == ["a.h5"]
    assert one_list(["a.h5", "b c.h5", "results_md=r.md"]) == [
        "files=['a.h5','b c.h5']", "results_md=r.md"]
    assert one_list(["-cn", "balance", "a.h5"]) == ["-cn", "balance", "a.h5"]


def test_frames_too_coarse_to_tell_leave_the_balance_untested():
    x = np.stack([trajectory(s) for s in range(3)])
    far = (x + 1e4).astype(np.float32)            # float32 far from the origin
    b = momentum_balance(FakeFile(far.astype(np.float64)), meta())
    assert b.linear is None and "too coarse" in b.reason and b.breaks() == ""
    near = x.astype(np.float32).astype(np.float64)  # float32 near it: still testable
    assert momentum_balance(FakeFile(near), meta()).linear < IMBALANCE_MAX / 100
