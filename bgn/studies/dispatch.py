"""The studies' one command: ``python -m bgn.experiments preset=<name>``
(``conf/experiments.yaml``).

A grid preset (tiny | first_look | standard | full | reproduce | recheck) runs
``bgn.studies.grid``; a Pareto preset (pareto_tiny | pareto_first_look | pareto_full: checkpoints
on a time schedule) runs ``bgn.studies.pareto``. Every cell's train config is checked before
the first cell trains.
"""

from __future__ import annotations

import sys

from omegaconf import DictConfig

from bgn.studies import grid, pareto
from bgn.studies.cells import cell_overrides, compose_train, plan_cells
from bgn.studies.headline import validate_stages
from bgn.training.validate import ConfigError, cli, validate_train


def is_pareto(cfg: DictConfig) -> bool:
    """A Pareto-study preset (``conf/preset/pareto_*.yaml``: checkpoints on a time schedule)
    is run by ``bgn.studies.pareto``."""
    return "schedule_s" in cfg.preset


def validate_cells(cfg: DictConfig) -> None:
    """The train config of every cell, checked before the first cell trains
    (``bgn.training.validate.validate_train``): a bad preset fails at once, naming the cell."""
    if not is_pareto(cfg):  # the grid's eval.split and variants, its stability and Pareto
        grid.validate_grid(cfg.preset)  # stages (bgn.studies.headline)
        grid.check_variant_cells(cfg)
        validate_stages(cfg.preset)
    for cell in pareto.plan_cells(cfg) if is_pareto(cfg) else plan_cells(cfg.preset):
        try:
            validate_train(compose_train(cell_overrides(cell, cfg)))
        except ConfigError as err:
            raise ConfigError(err.key, message=f"cell {cell.name}: {err}") from err


@cli("experiments", validate_cells)  # Hydra app; bad input: one line, exit 2
def main(cfg: DictConfig) -> None:
    """``python -m bgn.experiments preset=...``: see the module docstring."""
    if is_pareto(cfg):
        pareto.run(cfg)
        return
    try:
        grid.run(cfg)
    except grid.CellsFailed as err:  # the report of the others is written; the command fails
        raise SystemExit(f"bgn.experiments: {err}") from None


def command() -> None:
    """The console entry: the command line as typed goes into the report's provenance."""
    grid._ARGV[:] = sys.argv
    main()
