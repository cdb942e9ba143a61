"""Hydra callback: at the end of a multirun, one table of every job's final metrics."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from bgn.tables import write_table
from bgn.training.checkpoints import read_record

SUMMARY_METRICS = ("val/nmse", "test/nmse", "test/mse", "test/median_relative_error",
                   "test/type_accuracy", "test/contact_f1", "test/contact_r2",
                   "test/loss_mass_nll", "test/relmass_r2", "wall_time_s")


def collect(sweep_dir: Path) -> list[dict[str, Any]]:
    """One row per job directory that wrote ``metrics.json``."""
    rows = []
    for path in sorted(sweep_dir.rglob("metrics.json"), key=lambda p: p.parent.name):
        record = read_record(path)  # a damaged one is named in a warning and left out
        if record is None:
            continue
        rows.append({"run": str(path.parent.relative_to(sweep_dir)), **record.get("overrides", {}),
                     **{k: record["metrics"].get(k) for k in SUMMARY_METRICS}})
    return rows


def write_summary(sweep_dir: Path, rows: list[dict[str, Any]]) -> str:
    """Write summary.md and summary.csv in the sweep directory (columns that some job filled
    in); return the markdown."""
    if not rows:
        return "no finished runs"
    columns = list(dict.fromkeys(k for row in rows for k in row))
    columns = [c for c in columns if any(row.get(c) is not None for row in rows)]
    return write_table(sweep_dir, "summary", columns, rows)


class SweepSummary(Callback):
    """Writes the summary table when a multirun ends."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        markdown = write_summary(sweep_dir, collect(sweep_dir))
        print(f"\nSweep summary ({sweep_dir / 'summary.md'}):\n{markdown}")
