"""Every benchmark command runs: each module of ``bgn.benchmarks`` on tiny sizes, in-process,
writing its report files with finite numbers; a new benchmark without a smoke test here fails.
Each takes ``key=value`` (``bgn.training.validate.cli``, ``conf/benchmarks/<name>.yaml``): bad
input is refused in one line with exit code 2 and nothing written."""

from __future__ import annotations

import csv
import importlib
import math
import pkgutil
import re
import subprocess
from pathlib import Path

import pytest
import torch

import bgn.benchmarks

# command -> (tiny key=value arguments, the report files it writes under report_dir)
SMOKE = {
    "neighbours": (["sizes=[300,600]", "neighbours=8"],
                   ["neighbours.md", "neighbours.csv", "neighbours.png"]),
    "scaling": (["sizes=[40,80]", "margin=0.5", "threads=1", "repeats=1", "in_process=true"],
                ["scaling.md", "scaling.csv", "scaling.png"]),
    "flow": (["particles=40", "per_frame=20", "hidden=8", "steps=3", "pool=2", "repeat=1",
              "threads=1"],
             ["flow.md", "flow.csv", "flow.png"]),
    "shooting": (["overrides=['dataset.n_sims=2','dataset.n_frames=40']", "frames=8",
                  "iterations=[1,2]", "substeps=[4]", "paths.data_dir={tmp}/data"],
                 ["shooting.md", "shooting.csv"]),
}

NUMBER = re.compile(r"^-?[\d,]*\.?\d+(e[-+]?\d+)?( M)?$")


def commands() -> set[str]:
    """The benchmark commands: every module of bgn/benchmarks except helpers (``_name``)."""
    return {m.name for m in pkgutil.iter_modules(bgn.benchmarks.__path__)
            if not m.name.startswith("_")}


@pytest.fixture
def keep_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_every_benchmark_has_a_smoke_test() -> None:
    missing = commands() - set(SMOKE)
    assert not missing, f"benchmarks without a smoke test in {__file__}: {sorted(missing)}"
    assert not set(SMOKE) - commands(), "smoke tests of benchmarks that no longer exist"


def numbers_of_csv(path: Path) -> list[list[float]]:
    """Each data row's numeric cells (the header and text cells left out)."""
    with path.open(newline="") as f:
        rows = list(csv.reader(f))[1:]
    out = []
    for row in rows:
        values = []
        for cell in row:
            try:
                values.append(float(cell))
            except ValueError:
                continue  # a label (a flow's name)
        out.append(values)
    return out


def numbers_of_markdown_tables(text: str) -> list[str]:
    """The cells of the markdown tables' body rows that should be numbers."""
    cells = []
    for line in text.splitlines():
        if line.startswith("|") and not set(line) <= set("|-: "):
            cells += [c.strip() for c in line.strip("|").split("|")]
    return cells


@pytest.mark.parametrize("name", sorted(SMOKE))
def test_benchmark_writes_reports_with_finite_numbers(name, tmp_path, keep_threads) -> None:
    argv, files = SMOKE[name]
    main = importlib.import_module(f"bgn.benchmarks.{name}").main
    assert main([*(a.format(tmp=tmp_path) for a in argv), f"report_dir={tmp_path}"]) == 0
    for file in files:
        assert (tmp_path / file).stat().st_size > 0, file

    rows = numbers_of_csv(tmp_path / f"{name}.csv")
    assert rows and all(rows), "a CSV row without numbers"
    for values in rows:
        assert all(math.isfinite(v) for v in values), values

    cells = numbers_of_markdown_tables((tmp_path / f"{name}.md").read_text())
    numeric = [c for c in cells if NUMBER.match(c.removeprefix("best of "))]
    assert numeric, "the markdown report has no table of numbers"
    for cell in cells:
        assert cell.lower() not in ("nan", "inf", "-inf"), cells


def test_neighbours_report_has_the_scaling_ratio(tmp_path) -> None:
    from bgn.benchmarks.neighbours import main

    assert main(["sizes=[300,600]", "neighbours=8", f"report_dir={tmp_path}"]) == 0
    lines = (tmp_path / "neighbours.csv").read_text().splitlines()
    assert len(lines) == 3 and lines[1].startswith("300,")
    assert "Linear-scaling ratio" in (tmp_path / "neighbours.md").read_text()


def test_flow_statistics_have_what_the_target_coder_needs() -> None:
    """The synthetic statistics carry every entry real ones have (target_diff1/2 included), so
    BGN builds with its default target prior (``last`` for a velocity target)."""
    from bgn.benchmarks.flow import BOX, HISTORY, synthetic_batch, synthetic_stats
    from bgn.data.stats import summarize
    from bgn.model.registry import build_model
    from bgn.sim.scene import SceneMeta

    g = synthetic_batch(2, 20, torch.Generator().manual_seed(0))
    stats = synthetic_stats(g)
    for name in ("velocity", "velocity_increment", "target", "target_diff1", "target_diff2",
                 "log_mass", "rel_position", "rel_velocity", "rel_log_mass", "contact"):
        assert set(stats[name]) == set(summarize(g.target.numpy())), name
    meta = SceneMeta(name="synthetic_collisions", dim=2, n_particles=20, n_types=2,
                     interaction="contact", target="velocity", graph="radius", box=BOX)
    model = build_model({"name": "bgn", "hidden": 8}, meta, stats, HISTORY)
    assert model.target_coder.prior_name == "last"
    assert torch.isfinite(model.total_loss(model.loss_terms(g, model(g))))


def test_scaling_exponents_and_ratios() -> None:
    """The fitted exponent of a cost that grows like N^1.5 is 1.5; ratios are old / new."""
    from bgn.benchmarks.scaling import exponents, ratios

    rows = [{"impl": impl, "model": "bgn", "n": n, "train_s": k * n**1.5, "infer_s": k * n,
             "train_peak_gb": k * n} for impl, k in (("this", 1.0), ("old", 3.0))
            for n in (100, 1000, 10000)]
    fits = {r["impl"]: r for r in exponents(rows, 1000)}
    assert fits["this"]["train_s_exponent"] == pytest.approx(1.5)
    assert fits["old"]["infer_s_exponent"] == pytest.approx(1.0)
    for r in ratios(rows, "this", "old"):
        assert r["train_s_ratio"] == pytest.approx(3.0)
        assert r["train_peak_gb_ratio"] == pytest.approx(3.0)


def test_the_flop_count_includes_in_place_products() -> None:
    """The cell's counter counts ``addmm_`` (the edge MLPs accumulate weight gradients in
    place) as ``addmm``: 2 m k n each."""
    from torch.utils.flop_counter import FlopCounterMode

    from bgn.benchmarks._scaling_cell import addmm_flop

    a, b, c = torch.randn(64, 32), torch.randn(32, 16), torch.zeros(64, 16)
    counter = FlopCounterMode(display=False, custom_mapping={torch.ops.aten.addmm_: addmm_flop})
    with counter:
        c.addmm_(a, b)
        torch.addmm(c, a, b)
        c.t().addmm_(b.t(), a.t())
    assert counter.get_total_flops() == 3 * 2 * 64 * 32 * 16


def test_a_cell_killed_in_its_flop_count_keeps_its_timings(monkeypatch, tmp_path) -> None:
    """The cell prints its timings before the FLOP count; a process killed after that (out of
    memory) still gives them, with a note, and one killed before gives an error."""
    import argparse

    from bgn.benchmarks import scaling

    args = argparse.Namespace(in_process=False, threads=1, device="cpu", timeout=10)
    timings = '{"edges": 3, "nodes": 2, "infer_s": 0.1, "train_s": 0.2}'
    for stdout, expected in ((timings + "\n", "note"), ("", "error")):
        monkeypatch.setattr(scaling.subprocess, "run", lambda *a, out=stdout, **k:
                            subprocess.CompletedProcess(a, -9, out, "Killed"))
        cell = scaling.run_cell(tmp_path, "payload", "gns", args, [])
        assert expected in cell and "exit -9" in cell[expected]
        assert ("train_s" in cell) == (expected == "note")


def test_scaling_trains_only_up_to_train_max_n(tmp_path, keep_threads) -> None:
    from bgn.benchmarks.scaling import main

    assert main(["sizes=[40,80]", "margin=0.5", "threads=1", "repeats=1", "models=[cranmer_gn]",
                 "train_max_n=40", "in_process=true", f"report_dir={tmp_path}"]) == 0
    with (tmp_path / "scaling.csv").open(newline="") as f:
        rows = {int(r["n"]): r for r in csv.DictReader(f)}
    assert float(rows[40]["train_s"]) > 0 and float(rows[80]["infer_s"]) > 0
    assert rows[80]["train_s"] == "" and "train_max_n=40" in rows[80]["note"]


def test_against_takes_a_folder_holding_an_export_as_it_is(tmp_path) -> None:
    """A machine without the git history (a lent GPU) compares with a checkout exported
    elsewhere; a folder without ``bgn/`` and ``conf/`` is taken as a git ref."""
    from bgn.benchmarks.scaling import export

    checkout = tmp_path / "old"
    (checkout / "bgn").mkdir(parents=True)
    (checkout / "conf").mkdir()
    assert export(str(checkout), tmp_path / "unused") == checkout.resolve()
    assert not (tmp_path / "unused").exists()
    with pytest.raises(subprocess.CalledProcessError):
        export(str(tmp_path / "not-a-checkout"), tmp_path / "unused")


def test_scaling_frames_are_the_collisions_scenes_start() -> None:
    # discs placed without overlap inside the box at the scene's density (a uniform draw
    # overlapped hundreds of pairs, which no simulation has), both types, finite window
    from bgn.benchmarks.scaling import DENSITY, frame

    g = frame(2000, 1.25)
    snd, rcv = g.edge_index
    gap = (g.pos[rcv] - g.pos[snd]).norm(dim=1) - g.radius[rcv] - g.radius[snd]
    assert gap.min() > 0
    box = math.sqrt(2000 / DENSITY)
    assert ((g.pos - g.radius[:, None] >= 0) & (g.pos + g.radius[:, None] <= box)).all()
    assert set(g.types.tolist()) == {0, 1} and torch.isfinite(g.vel).all()


def test_shooting_finds_the_fewest_iterations_within_the_tolerance() -> None:
    """The fewest iterations whose three percentiles are all within the tolerance of the
    most iterations' (per substeps)."""
    from bgn.benchmarks.shooting import fewest

    def row(k: int, it: int, median: float, p90: float, p99: float) -> dict:
        return {"substeps": k, "iterations": it, "median": median, "p90": p90, "p99": p99}

    rows = [row(16, 1, 2.0, 2.0, 2.0), row(16, 2, 1.0, 1.2, 1.0), row(16, 3, 1.0, 1.005, 1.0),
            row(16, 8, 1.0, 1.0, 1.0), row(64, 1, 1.0, 1.0, 1.0), row(64, 4, 1.0, 1.0, 1.0)]
    assert fewest(rows, 0.01) == {16: 3, 64: 1}


# name -> bad key=value arguments, each refused before any work (what the line names)
BAD = [
    ("neighbours", ["sizes=[1,600]"], "sizes=1"),
    ("neighbours", ["sizes=300"], "sizes=300"),
    ("neighbours", ["neighbours=0"], "neighbours=0"),
    ("neighbours", ["neighbors=8"], "did you mean neighbours"),
    ("neighbours", ["--sizes", "300"], "sizes=<value>"),
    ("scaling", ["models=[bgn,nope]"], "models="),
    ("scaling", ["in_process=true", "against=HEAD"], "against needs separate processes"),
    ("scaling", ["device=tpu"], "device='tpu'"),
    ("scaling", ["training_steps=1"], "training_steps=1"),
    ("flow", ["particles=10", "per_frame=20"], "must be >= per_frame"),
    ("flow", ["flows=[nsf,maf]"], "flows="),
    ("flow", ["degree_normalize=1"], "degree_normalize=1"),
    ("shooting", ["scene=nope"], "scene='nope'"),
    ("shooting", ["split=dev"], "split='dev'"),
    ("shooting", ["substeps=[1]"], "one substep does not shoot"),
    ("shooting", ["overrides=['dataset.n_sims=0']"], "dataset.n_sims=0"),
    ("shooting", ["overrides=['dataset.nsims=2']"], "dataset.nsims"),
]


@pytest.mark.parametrize("name, argv, named", BAD)
def test_bad_input_is_one_line_exit_2_and_nothing_written(name, argv, named, tmp_path,
                                                          capsys) -> None:
    main = importlib.import_module(f"bgn.benchmarks.{name}").main
    out = tmp_path / "report"
    with pytest.raises(SystemExit) as done:
        main([*argv, f"report_dir={out}", f"paths.data_dir={tmp_path / 'data'}"]
             if name == "shooting" else [*argv, f"report_dir={out}"])
    assert done.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and named in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_benchmark_on_the_console_writes_its_report(tmp_path) -> None:
    """``python -m bgn.benchmarks.neighbours key=value``: the report under report_dir and
    nothing else in the working folder (no Hydra run folder, no log)."""
    import sys

    done = subprocess.run([sys.executable, "-m", "bgn.benchmarks.neighbours", "sizes=[300,600]",
                           "neighbours=8", f"report_dir={tmp_path / 'r'}"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == [
        "neighbours.csv", "neighbours.md", "neighbours.png"]
    assert [p.name for p in tmp_path.iterdir()] == ["r"]
