"""The tables of docs/results.md's "Data from other engines", from the runs themselves.

    python examples/engines/summary.py <run> [<run> ...] [--out outputs/engines/summary]
        [--results-md docs/results.md]

Each ``<run>`` is a ``python -m bgn.train dataset=imported dataset.name=<name> seed=<s>`` run
directory (``model.dynamics=auto``: ``<run>/auto/auto.json``) or a single model's run (a
baseline, trained for the steps it fits in BGN's wall time on the same data: ``equal_time.py``
beside this script, whose record ``<run>/equal_time.json`` the tables state); each evaluated
by ``python -m bgn.evaluate`` (the auto run's winner, ``<run>/eval`` or
``<run>/auto/<choice>/eval``) and, for the auto candidates that were, ``python -m
bgn.evaluate <run>/auto/<candidate>``; the engine's own energy along the winner's rollouts
where ``engine_energy.py ... --json <run>/energy_<key>.json`` wrote it (``regenerate.sh``
beside this script runs all of it). Prints markdown (seeds aggregated: mean ± std (min-max))
and writes it with CSV files under ``--out``; ``--results-md FILE`` also writes it, with this
command and the commits the runs were evaluated at, into FILE's generated block
``<!-- generated:engines:... -->`` (``--block NAME``: another block, e.g. the built-in scenes'
``model.dynamics=auto`` runs).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

from equal_time import budget_record, job_seconds  # beside this script
from omegaconf import OmegaConf

from bgn.eval.columns import VARIANT_COLUMNS
from bgn.provenance import git_commit, write_block
from bgn.studies.report import aggregate_rows, describe_columns, spread
from bgn.tables import write_csv

BLOCK = "engines"  # the generated block --results-md rewrites
HORIZONS = (10, 50, 100)
LB = ("mse@5", "mse@10", "mse@20", "mse@50", "mse@100", "sinkhorn", "e_kin_mse")
INVERSE = ("relmass_r2", "coverage50", "coverage90", "info_gain")


def _metrics(directory: Path) -> dict[str, Any] | None:
    path = directory / "eval" / "test" / "metrics.json"
    return json.loads(path.read_text())["metrics"] if path.exists() else None


def _run_config(run: Path) -> Any:
    for path in (run / ".hydra" / "config.yaml", run / "train_config.yaml"):
        if path.exists():
            return OmegaConf.load(path)
    raise SystemExit(f"{run}: no run config (.hydra/config.yaml or train_config.yaml)")


def _variant(directory: Path) -> dict[str, str]:
    """What the run's model was trained with, is given at inference and has written in (its
    metrics.json's ``variant``: ``PhysicsModel.describe``), as the study's tables show it."""
    path = directory / "metrics.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    return describe_columns(record.get("variant") or {})


def _steps(directory: Path) -> int | None:
    """The optimiser steps the run trained (its last checkpoint's)."""
    from bgn.studies.grid import trained_steps

    return trained_steps(directory)


def _budget(directory: Path) -> float | None:
    path = directory / "metrics.json"
    if not path.exists():
        return None
    record = json.loads(path.read_text())
    return record.get("wall_time_s", record.get("metrics", {}).get("wall_time_s"))


def _cut(directory: Path) -> str:
    """`` (cut by trainer.max_time)`` where the wall-clock cap cut the run short (its
    metrics.json's ``budget.cut_by``, or an auto run's ``auto.cut``): its own row, not
    averaged with whole runs."""
    path = directory / "metrics.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    cut = (record.get("budget") or {}).get("cut_by") or (record.get("auto") or {}).get("cut")
    return " (cut by trainer.max_time)" if cut else ""


def best_reference(metrics: dict[str, Any], h: int) -> float | None:
    """The better no-learning reference's mean error after ``h`` steps (repeat the last
    target, or extrapolate linearly)."""
    refs = [metrics.get(f"rollout_{r}/pos_err_mean@{h}") for r in ("last", "linear")]
    return min((r for r in refs if r is not None), default=None)


def test_row(name: str, seed: int, model: str, metrics: dict[str, Any],
             budget: float | None, directory: Path | None = None,
             job: float | None = None) -> dict[str, Any]:
    """One model's test rollouts (mean over all rollouts, a failed one at the cap), with what
    the model in ``directory`` was trained with and given (``_variant``), its steps and
    training time (``budget``: a run's ``wall_time_s``; an auto candidate's ``train_s``, its
    training alone, not auto's scoring of it), and ``job``: the whole BGN job's wall time (the
    winner's row: its own job's; a baseline's: the seed-0 job whose time it was given,
    ``equal_time.py``)."""
    about = _variant(directory) if directory is not None else {}
    row: dict[str, Any] = {"data": name, "model": model, **about, "seed": seed,
                           "steps": _steps(directory) if directory is not None else None,
                           "budget s": budget, "BGN job s": job}
    for h in HORIZONS:
        row[f"@{h}"] = metrics.get(f"rollout/pos_err_mean@{h}")
    row["median @100"] = metrics.get("rollout/pos_err_median@100")
    row["failed"] = metrics.get("rollout/failed_share")
    row["best no-learning @100"] = best_reference(metrics, 100)
    for h in (100, 50):
        best = best_reference(metrics, h)
        row[f"ratio @{h}"] = row[f"@{h}"] / best if best and row[f"@{h}"] is not None else None
    # the total momentum's change over the rollout against the sum of |m v|, the median over
    # the rollouts (bgn.metrics.rollout_metrics; absent where the scene does not conserve it)
    row["momentum drift @100 (median)"] = metrics.get("rollout/momentum_err@100")
    for key in ("speed_w1_type0", "speed_w1_type1", "collision_rate_ratio"):
        if f"rollout/{key}" in metrics:
            row[key] = metrics[f"rollout/{key}"]
    for key in LB:
        row[f"lb {key}"] = metrics.get(f"lb/{key}")
    for key in INVERSE:
        row[key] = metrics.get(key)
    return row


def rows_of(run: Path) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    """The test rows of a run (the winner and every evaluated candidate, or the one model)
    and, for an auto run, its choice row (validation evidence)."""
    cfg = _run_config(run)
    name, seed = str(cfg.dataset.get("name", cfg.dataset.get("scene"))), int(cfg.seed)
    auto = run / "auto" / "auto.json"
    if not auto.exists():
        metrics = _metrics(run)
        given = budget_record(run)  # equal_time.py's: the steps of BGN's wall time
        model = str(cfg.model.get("name", "model")) + (" (BGN's wall time)" if given
                                                        else " (default budget)")
        return ([test_row(name, seed, model + _cut(run), metrics, _budget(run), run,
                          given["bgn_job_s"] if given else None)]
                if metrics else []), None
    record = json.loads(auto.read_text())
    choice = record["choice"]
    rows = []
    winner = _metrics(run / "auto" / choice) or _metrics(run)
    if winner:
        rows.append(test_row(name, seed, f"chosen ({choice.split('_')[0]})" + _cut(run),
                             winner, _budget(run / "auto" / choice), run / "auto" / choice,
                             job_seconds(run)))
    choice_row: dict[str, Any] = {"data": name, "seed": seed, "chosen": choice,
                                  "margin": record.get("margin")}
    for c in record["candidates"]:
        key = "formula" if c["candidate"].startswith("formula_") else c["candidate"]
        h = record["protocol"]["horizon"]
        choice_row[f"{key} @{h}"] = (c.get(f"val_err@{h}") if c["admitted"] else None)
        metrics = _metrics(run / "auto" / c["candidate"])
        if metrics and c["candidate"] != choice:
            rows.append(test_row(name, seed, f"{c['candidate']} (candidate)", metrics,
                                 c.get("train_s"), run / "auto" / c["candidate"]))
    balance = record["protocol"].get("balance") or {}
    choice_row["momentum imbalance"] = balance.get("linear")
    rows += energy_rows(run, name, seed, f"chosen ({choice.split('_')[0]})")
    return rows, choice_row


def energy_rows(run: Path, name: str, seed: int, model: str) -> list[dict[str, Any]]:
    """The engine's own energy along the winner's test rollouts and along the recorded
    frames of the same trajectories (``engine_energy.py ... --json <run>/energy_<key>.json``,
    key predicted or true): the worst trajectory's relative change after each horizon."""
    rows = []
    for key, label in (("predicted", model), ("true", "recorded frames")):
        path = run / f"energy_{key}.json"
        if not path.exists():
            continue
        record = json.loads(path.read_text())
        row: dict[str, Any] = {"data": name, "model": label, "seed": seed}
        for i, h in enumerate(record["after"]):
            changes = [t[i] for t in record["relative_change"] if len(t) > i]
            row[f"energy @{h} (worst)"] = max(changes) if changes else None
        rows.append(row)
    return rows


def is_energy(row: dict[str, Any]) -> bool:
    """An ``energy_rows`` row (its own table, not a rollout's)."""
    return any(k.startswith("energy @") for k in row)


def table(rows: list[dict[str, Any]], keys: list[str]) -> tuple[str, list[str]]:
    merged = aggregate_rows(rows, keys)
    columns = keys + ["seeds"] + [c for c in dict.fromkeys(k for r in rows for k in r)
                                  if c not in keys and c != "seed"]
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in merged:
        lines.append("| " + " | ".join(str(row.get(c) or "") if c in keys or c == "seeds"
                                        else spread(row, c) for c in columns) + " |")
    return "\n".join(lines) + "\n", columns


def evaluated_at(runs: list[Path]) -> dict[str, int]:
    """The commits the runs' evaluations ran at (each ``eval/test/metrics.json``'s
    provenance, the run's and its candidates'), with how many evaluations each."""
    commits: dict[str, int] = {}
    for run in runs:
        for path in [run / "eval" / "test" / "metrics.json",
                     *sorted((run / "auto").glob("*/eval/test/metrics.json"))]:
            if path.exists():
                commit = json.loads(path.read_text()).get("provenance", {}).get("git_commit")
                commits[str(commit)[:10]] = commits.get(str(commit)[:10], 0) + 1
    return commits


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, default=Path("outputs/engines/summary"))
    ap.add_argument("--results-md", type=Path, metavar="FILE",
                    help="also write the tables into FILE's generated block (--block)")
    ap.add_argument("--block", default=BLOCK,
                    help=f"the generated block's name (default {BLOCK})")
    args = ap.parse_args(argv)
    tests, choices = [], []
    for run in args.runs:
        rows, choice = rows_of(run)
        tests += rows
        if choice:
            choices.append(choice)
    args.out.mkdir(parents=True, exist_ok=True)
    keys = ["data", "model", *VARIANT_COLUMNS]
    lb = [f"lb {k}" for k in LB]
    rollouts = [r for r in tests if not is_energy(r)]
    groups = {"choices": (choices, ["data"], None),
              "rollouts": (rollouts, keys, lambda c: c not in lb and c not in INVERSE),
              "lagrangebench": (rollouts, keys, lambda c: c in lb),
              "masses": ([r for r in rollouts if r.get("relmass_r2") is not None], keys,
                         lambda c: c in INVERSE),
              "energy": ([r for r in tests if is_energy(r)], keys,
                         lambda c: c.startswith("energy @"))}
    text = []
    for stem, (rows, by, keep) in groups.items():
        if not rows:
            continue
        kept = [{k: v for k, v in r.items() if k in by or k == "seed" or keep is None
                 or keep(k)} for r in rows]
        md, columns = table(kept, by)
        write_csv(args.out / f"{stem}_per_seed.csv", ["seed", *columns], kept)
        (args.out / f"{stem}.md").write_text(md)
        text += [f"## {stem}", "", md]
    print("\n".join(text))
    if args.results_md:
        command = " ".join(["python examples/engines/summary.py",
                            *map(shlex.quote, sys.argv[1:] if argv is None else argv)])
        commits = ", ".join(f"{c} ({n})" for c, n in evaluated_at(args.runs).items())
        write_block(args.results_md, args.block, "\n".join([
            "_Written by the command below; do not edit by hand._", "",
            f"Regenerated by `{command}` (this script at commit {git_commit()[:10]}; the "
            f"runs' evaluations at: {commits or 'unknown'}).", "",
            *[f"##{line}" if line.startswith("## ") else line for line in text]]))
    return "\n".join(text)


if __name__ == "__main__":
    main()
