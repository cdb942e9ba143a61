"""The law search (bgn.laws.search) against the fixed term list (bgn.laws.terms.fit_formula with
default_library) on the TUNE half of the held-out law set: each law's exact force from
laws.yaml, sampled at the training split's own pair distances with 1 % relative noise.

    python examples/heldout_laws/search_trial.py [LAW ...] [--seeds 3] [--first-seed 0]
        [--json out.json]

Per law and seed: the distances of the train split (every 10th frame, the pairs within the
layout's radius, as make.py's statistics), a log-spaced grid over them with the density of
their log as each point's weight (as the formula stage samples a learned law); the law on that
grid times (1 + 0.01 N(0, 1)); both searches at the samples' own uncertainty as the tolerance:
the noise's RMS with a quarter's margin (``--margin``; 1.25 % for 1 % noise; the formula stage
passes the learned law's, ``LawOptions.tolerance``). Printed per law and seed: the form
chosen, whether it is the manifest's form (``bgn.laws.search.same_form``: same form up to
constants), the median relative error against the exact law over the 1-99 % distance
quantiles, the front's size and the wall time, the chosen member's held-out error against
the tolerance (``bgn.laws.search.holdout_error``); a law the search read as a potential's
force is printed ``-d/dr[U]``.

The report half (laws.yaml ``half: report``) is refused unless ``--report-half`` is given: it is
run once, after the search is frozen (examples/heldout_laws/README.md, "The rule").
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import sympy as sp

from bgn.laws.compare import log_density
from bgn.laws.options import DEFAULTS
from bgn.laws.search import R, same_form, search_law
from bgn.laws.terms import fit_formula, law_scale

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from make import load_manifest, pair_distances  # noqa: E402

DATA = Path("data/external/heldout_laws")


def truth_family(law: dict[str, Any], lo: float, hi: float
                 ) -> tuple[sp.Expr, dict[sp.Symbol, float]]:
    """The manifest's force with its constants as symbols (the law's family) and their
    values; a Piecewise reduced to the branch that holds over [lo, hi] where one does."""
    consts = {k: sp.Symbol(k, real=True) for k in law["constants"]}
    values = {consts[k]: float(v) for k, v in law["constants"].items()}
    names: dict[str, Any] = {"r": R, **consts}
    for key, text in (law.get("define") or {}).items():
        names[key] = sp.sympify(text, locals=names)
    expr = sp.sympify(law["force"], locals=names)
    pieces = expr.atoms(sp.Piecewise)
    if pieces:
        grid = np.geomspace(lo, hi, 50)
        for pw in pieces:
            held = {i for x in grid for i, (_, cond) in enumerate(pw.args)
                    if cond.subs(values).subs(R, x) == sp.true
                    and all(c2.subs(values).subs(R, x) != sp.true
                            for _, c2 in pw.args[:i])}
            if len(held) == 1:
                expr = expr.xreplace({pw: pw.args[held.pop()][0]})
    used = expr.free_symbols - {R}
    return expr, {s: v for s, v in values.items() if s in used}


def train_distances(law: dict[str, Any], root: Path) -> np.ndarray:
    """The train split's pair distances (make.py's rule: every 10th frame, within the radius)."""
    folder = root / law["name"]
    if law["layout"] == "arrays-npz":
        data = np.load(folder / "trajectories.npz")
        runs = data["positions"][data["split"] == "train"]
    else:
        with h5py.File(folder / "train.h5") as f:
            runs = [np.asarray(f[k]["position"], np.float64) for k in sorted(f)]
    return np.concatenate([pair_distances(law, np.asarray(p, np.float64)) for p in runs])


def median_error(expr: sp.Expr | None, exact: sp.Expr, lo: float, hi: float) -> float:
    """Median |found - exact| / law_scale(exact) over 500 log-spaced r in [lo, hi]."""
    if expr is None:
        return float("nan")
    r = np.geomspace(lo, hi, 500)
    f = np.asarray(sp.lambdify(R, exact, "numpy")(r), np.float64) * np.ones_like(r)
    with np.errstate(all="ignore"):
        g = np.asarray(sp.lambdify(R, expr, "numpy")(r), np.float64) * np.ones_like(r)
    return float(np.median(np.abs(g - f) / law_scale(r, f, smooth=False)))


def prepare(law: dict[str, Any], root: Path) -> dict[str, Any]:
    """The law's grid, weights, exact values and family over its train distances."""
    d = train_distances(law, root)
    d = d[d > 0]
    lo, hi = (float(q) for q in np.quantile(d, [0.01, 0.99]))
    family, constants = truth_family(law, float(d.min()), float(d.max()))
    exact = family.subs(constants)
    r = np.geomspace(d.min(), d.max(), DEFAULTS.grid_points)
    f = np.asarray(sp.lambdify(R, exact, "numpy")(r), np.float64) * np.ones_like(r)
    return {"n": int(len(d)), "lo": lo, "hi": hi, "family": family, "constants": constants,
            "exact": exact, "r": r, "weight": log_density(d, r), "f": f,
            "judge_r": np.geomspace(lo, hi, 400)}


def run_law(law: dict[str, Any], p: dict[str, Any], seed: int, noise: float,
            tolerance: float) -> dict[str, Any]:
    """Both searches on the law's samples with noise drawn from seed [56, seed]."""
    r, weight, lo, hi = p["r"], p["weight"], p["lo"], p["hi"]
    family, constants, exact, judge_r = p["family"], p["constants"], p["exact"], p["judge_r"]
    y = p["f"] * (1 + noise * np.random.default_rng([56, seed]).standard_normal(len(r)))
    t = time.perf_counter()
    found = search_law(r, y, weight, tolerance=tolerance)
    t_search = time.perf_counter() - t
    best = min(found.front, key=lambda m: m.error)
    pick = found.chosen or best
    t = time.perf_counter()
    listed = fit_formula(r, y, weight, tolerance=tolerance, n_boot=0)
    t_list = time.perf_counter() - t
    listed_expr = listed.expr(digits=15)
    row = {
        "law": law["name"], "seed": seed, "n_distances": p["n"], "quantiles_1_99": [lo, hi],
        "tolerance": tolerance,
        "search": {"outcome": found.outcome,
                   "chosen": found.chosen.text if found.chosen else None,
                   "chosen_is_potential": bool(found.chosen is not None
                                               and found.chosen.potential is not None),
                   "chosen_holdout": None if found.chosen is None else found.chosen.holdout,
                   "best_on_front": best.text,
                   "right_form": bool(found.chosen is not None and same_form(
                       found.chosen.expr, family, judge_r, constants)),
                   "right_form_on_front": any(same_form(m.expr, family, judge_r, constants)
                                              for m in found.front),
                   "median_error": median_error(pick.expr, exact, lo, hi),
                   "front": len(found.front), "wall_s": t_search, "forms": found.n_forms,
                   "front_members": [[m.complexity, m.error, m.holdout, m.text]
                                     for m in found.front]},
        "list": {"chosen": sp.sstr(listed.expr()),
                 "right_form": bool(same_form(listed_expr, family, judge_r, constants)),
                 "median_error": median_error(listed_expr, exact, lo, hi),
                 "front": len(listed.front), "wall_s": t_list},
    }
    s, li = row["search"], row["list"]
    print(f"{law['name']:16s} seed {seed}  search: {s['outcome']:15s} "
          f"right={'yes' if s['right_form'] else 'no ':3s} "
          f"(on front {'yes' if s['right_form_on_front'] else 'no'}) "
          f"err={s['median_error']:.2%} front={s['front']} {s['wall_s']:.0f}s "
          f"| list: right={'yes' if li['right_form'] else 'no ':3s} "
          f"err={li['median_error']:.2%} front={li['front']} {li['wall_s']:.0f}s", flush=True)
    chosen = (f"{s['chosen']}  (held out {s['chosen_holdout'] / tolerance:.2f} x tolerance)"
              if s["chosen"] else f"(none; most accurate on the front: {s['best_on_front']})")
    print(f"    search chose: {chosen}")
    print(f"    list chose:   {li['chosen']}", flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("laws", nargs="*", help="laws to run (default: the whole tune half)")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--noise", type=float, default=0.01, help="relative noise")
    parser.add_argument("--margin", type=float, default=1.25,
                        help="tolerance = noise x margin (the samples' own uncertainty)")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--json", type=Path, default=None, help="write every row here")
    parser.add_argument("--report-half", action="store_true",
                        help="allow report-half laws (once, after the search is frozen)")
    args = parser.parse_args()
    manifest = {law["name"]: law for law in load_manifest()}
    unknown = [n for n in args.laws if n not in manifest]
    if unknown:
        sys.exit(f"search_trial: no law {unknown[0]!r} in laws.yaml; choose from "
                 f"{sorted(manifest)}")
    report = [n for n in args.laws if manifest[n]["half"] == "report"]
    if report and not args.report_half:
        sys.exit(f"search_trial: {report[0]} is in the report half: it is run once, after the "
                 "search is frozen (--report-half); tune on the tune half")
    names = args.laws or [n for n, law in manifest.items()
                          if law["half"] == "tune" and "not_made" not in law]
    prepared = {name: prepare(manifest[name], args.data) for name in names}
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):  # every law, then more seeds
        for name in names:
            rows.append(run_law(manifest[name], prepared[name], seed, args.noise,
                                args.noise * args.margin))
            if args.json:  # after each row: a run cut short keeps what it made
                args.json.write_text(json.dumps(rows, indent=1))
    print("\nlaw              | search: right form (seeds), on front, median err, front, wall s"
          " | list: right form, median err, wall s")
    for name in names:
        mine = [r for r in rows if r["law"] == name]
        s = [r["search"] for r in mine]
        li = [r["list"] for r in mine]
        print(f"{name:16s} | {sum(x['right_form'] for x in s)}/{len(s)}, "
              f"{sum(x['right_form_on_front'] for x in s)}/{len(s)}, "
              f"{np.median([x['median_error'] for x in s]):.2%}, "
              f"{np.median([x['front'] for x in s]):.0f}, "
              f"{np.median([x['wall_s'] for x in s]):.0f} | "
              f"{sum(x['right_form'] for x in li)}/{len(li)}, "
              f"{np.median([x['median_error'] for x in li]):.2%}, "
              f"{np.median([x['wall_s'] for x in li]):.0f}")


if __name__ == "__main__":
    main()
