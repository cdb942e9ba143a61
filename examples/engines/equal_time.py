"""The engines' baselines get BGN's wall time, expressed in optimiser steps so that it repeats.

    python examples/engines/equal_time.py time <bgn run> -- python -m bgn.train ...
    python examples/engines/equal_time.py steps <bgn run> <model> [--json FILE]

``time`` runs the BGN default job (``model.dynamics=auto``) and, where it succeeds, writes the
whole job's wall time (every candidate, force matching, the formula stage, the test) into
``<bgn run>/job_time.json``, measured around the command itself; its exit status is the
command's. ``steps`` prints the steps a baseline trains in that time: the baseline's steps per
second as ``auto`` measured them in the same run (its candidate of that name in
``<bgn run>/auto/auto.json``: ``train_steps`` over ``train_s``, the steps its training runs
trained over their wall time, start-up and validation included, under the same load as the
job; not ``wall_s``, which also counts auto's scoring of it) times the job's wall time. It
writes one line of its
reasoning to stderr (``regenerate.sh`` sends it to the baseline's log) and, with ``--json``,
the record ``summary.py`` states each baseline's budget from. A missing or unusable record is
refused in one line on stderr, exit status 1.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

JOB_FILE = "job_time.json"  # <bgn run>/job_time.json: the whole job's wall time (``time``)
BUDGET_FILE = "equal_time.json"  # <baseline run>/equal_time.json: how its steps were found


def _fail(message: str) -> SystemExit:
    return SystemExit(f"equal_time.py: {message}")


def job_seconds(run: Path) -> float | None:
    """The whole BGN job's wall time recorded by ``time`` in ``run``, or None where absent."""
    path = Path(run) / JOB_FILE
    if not path.is_file():
        return None
    try:
        return float(json.loads(path.read_text())["wall_s"])
    except (ValueError, KeyError, TypeError) as err:
        raise _fail(f"{path}: unreadable ({type(err).__name__}: {err}): delete the BGN run's "
                    "folder and rerun it through regenerate.sh") from None


def timed(run: Path, command: list[str]) -> int:
    """Run ``command``; where it succeeds, record its wall time in ``run``/job_time.json.
    Returns its exit status (a failed job records nothing: it gives no budget)."""
    if not command:
        raise _fail("time: no command after --: give the BGN job, e.g. -- python -m "
                    "bgn.train dataset=imported dataset.name=<name> hydra.run.dir=<run>")
    started = time.time()
    start = time.perf_counter()
    proc = subprocess.Popen(command)
    # a SIGTERM to this wrapper stops the job as it would alone (bgn saves and says how to
    # resume); Ctrl-C reaches the job through the terminal's process group already
    signal.signal(signal.SIGTERM, lambda signum, frame: proc.send_signal(signum))
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    code = proc.wait()
    wall = time.perf_counter() - start
    if code == 0:
        if not Path(run).is_dir():
            raise _fail(f"time: {run} does not exist after the command: pass the folder the "
                        "command writes its run into (its hydra.run.dir)")
        record = {"wall_s": round(wall, 2), "command": shlex.join(command),
                  "started_unix": round(started, 1)}
        (Path(run) / JOB_FILE).write_text(json.dumps(record, indent=2) + "\n")
    return code


def equal_steps(run: Path, model: str) -> dict[str, Any]:
    """The steps ``model`` trains in the wall time of the BGN job in ``run``, with the
    figures they come from (the record ``--json`` writes)."""
    run = Path(run)
    job_s = job_seconds(run)
    if job_s is None:
        raise _fail(f"{run}: no {JOB_FILE} (the BGN job's wall time, written by "
                    "equal_time.py time around python -m bgn.train): rerun the BGN job "
                    "through regenerate.sh (delete the folder first)")
    auto = run / "auto" / "auto.json"
    if not auto.is_file():
        raise _fail(f"{run}: no auto/auto.json: the budget comes from a model.dynamics=auto "
                    "run, which trains the baselines as candidates")
    try:
        found = [c for c in json.loads(auto.read_text()).get("candidates", [])
                 if c.get("candidate") == model]
    except (ValueError, AttributeError) as err:
        raise _fail(f"{auto}: unreadable ({type(err).__name__}: {err}): rerun the BGN "
                    "job") from None
    if not found:
        raise _fail(f"{auto}: no candidate {model}: run the BGN job with {model} among "
                    "auto.references")
    # its training alone: wall_s also counts auto's validation rollouts of it
    steps, train = found[0].get("train_steps"), found[0].get("train_s")
    if "train_s" not in found[0]:
        raise _fail(f"{auto}: candidate {model} records no training time (train_s: the run "
                    "predates it, and its wall_s counts its scoring too): rerun the BGN job")
    if not steps or train is None or not math.isfinite(float(train)) or float(train) <= 0:
        raise _fail(f"{auto}: candidate {model} records {steps} steps in {train} s of "
                    f"training, no rate (status: {found[0].get('status', '?')}): its steps "
                    "per second cannot be measured; rerun the BGN job")
    rate = int(steps) / float(train)
    budget = max(1, round(rate * job_s))
    reason = (f"{model}: {budget} steps = its {int(steps)} steps in {float(train):.1f} s of "
              f"training as auto's candidate ({rate:.3g} steps/s) x the BGN job's "
              f"{job_s:.1f} s ({run})")
    return {"model": model, "steps": budget, "bgn_run": str(run), "bgn_job_s": job_s,
            "candidate_steps": int(steps), "candidate_train_s": float(train),
            "steps_per_s": rate, "reason": reason}


def budget_record(run: Path) -> dict[str, Any] | None:
    """The record ``steps --json`` wrote into a baseline's run folder, or None."""
    path = Path(run) / BUDGET_FILE
    return json.loads(path.read_text()) if path.is_file() else None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command: list[str] = []
    if "--" in argv:  # the job's own arguments are not this script's
        command, argv = argv[argv.index("--") + 1:], argv[:argv.index("--")]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    t = sub.add_parser("time", help="run the BGN job (after --) and record its wall time")
    t.add_argument("run", type=Path, help="the BGN run folder (the job's hydra.run.dir)")
    s = sub.add_parser("steps", help="print the steps a baseline trains in BGN's wall time")
    s.add_argument("run", type=Path, help="the BGN run folder (model.dynamics=auto)")
    s.add_argument("model", help="the baseline, as auto's candidate: gns or cranmer_gn")
    s.add_argument("--json", type=Path, metavar="FILE", help="also write the record here")
    args = ap.parse_args(argv)
    if args.what == "time":
        return timed(args.run, command)
    if command:
        raise _fail("steps takes no command after --")
    record = equal_steps(args.run, args.model)
    print(record["reason"], file=sys.stderr)
    if args.json:
        args.json.write_text(json.dumps(record, indent=2) + "\n")
    print(record["steps"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
