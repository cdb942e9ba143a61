"""What every benchmark command shares: the command style (``command``: the one wrapper of
every ``python -m bgn.*`` command, ``bgn.training.validate.cli``, with the config
``conf/benchmarks/<name>.yaml``), checks of list keys, and the console table (their files use
the package's table writer, ``bgn.tables``; the machine line is ``bgn.provenance.machine``). A
helper module, not a command (its name starts with ``_``, so the smoke tests that run every
command in ``bgn.benchmarks`` skip it)."""

from __future__ import annotations

from argparse import Namespace
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from bgn.training.validate import CONF_DIR, ConfigError, cli, need_int

CONF = CONF_DIR / "benchmarks"  # each benchmark's config: conf/benchmarks/<name>.yaml


def command(name: str, validate: Callable[[Any], Any]
              ) -> Callable[[Callable[[Any], Any]], Callable[..., Any]]:
    """``@command("neighbours", check)`` on ``def main(cfg)``: ``python -m
    bgn.benchmarks.<name> [key=value ...]`` (``--help``: the config's help template; bad
    input: one line, exit 2, nothing written)."""
    return cli(name, validate, config_dir=CONF, prog=f"bgn.benchmarks.{name}")


@contextmanager
def outside_app() -> Iterator[None]:
    """Inside: Hydra free to compose ``conf/train.yaml`` (``initialize_config_dir``), which a
    benchmark's own Hydra app (its config folder ``conf/benchmarks``, with no ``train``)
    otherwise holds; the app's Hydra put back after."""
    from hydra.core.global_hydra import GlobalHydra

    app = GlobalHydra.instance().hydra
    GlobalHydra.instance().clear()
    try:
        yield
    finally:
        GlobalHydra.instance().clear()
        if app is not None:
            GlobalHydra.instance().initialize(app)


def compose_train(overrides: list[str]) -> Any:
    """``conf/train.yaml`` composed with ``overrides`` (``bgn.studies.cells.compose_train``),
    in or outside a benchmark's Hydra app."""
    from bgn.studies.cells import compose_train as compose

    with outside_app():
        return compose(overrides)


def options(cfg: Any) -> Namespace:
    """The config's keys as attributes of plain values (lists, numbers), ``report_dir`` a
    ``Path``."""
    from omegaconf import OmegaConf

    values = OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else dict(cfg)
    values["report_dir"] = Path(values["report_dir"])
    return Namespace(**values)


def need_ints(values: Any, key: str, minimum: int, why: str = "") -> list[int]:
    """A non-empty list of integers >= ``minimum`` (``sizes=[300,600]``)."""
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) or not values:
        raise ConfigError(key, values, f"must be a non-empty list of integers >= {minimum}"
                          f"{why}, e.g. {key}=[{minimum},{minimum * 2}]")
    return [int(need_int(v, key, minimum, why=why)) for v in values]  # type: ignore[arg-type]


def need_choices(values: Any, key: str, choices: Sequence[str]) -> list[str]:
    """A non-empty list of names among ``choices``."""
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) or not values \
            or any(v not in choices for v in values):
        raise ConfigError(key, values, f"a non-empty list among {list(choices)}, e.g. "
                          f"{key}=[{choices[0]}]")
    return list(values)


def need_strings(values: Any, key: str) -> list[str]:
    """A list of strings (overrides: ``"key=['dataset.n_sims=2']"``)."""
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) \
            or not all(isinstance(v, str) for v in values):
        raise ConfigError(key, values, f"a list of quoted overrides, e.g. "
                          f"\"{key}=['dataset.n_sims=2']\"")
    return list(values)


def console():
    """A rich console that keeps a wide table on one line in logs and pipes."""
    from rich.console import Console

    out = Console()
    if not out.is_terminal:
        out.width = max(out.width, 110)
    return out


def print_table(out, title: str, header: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
    """``rows`` as a rich table on ``out`` (a console from ``console()``)."""
    from rich.table import Table

    table = Table(title=title)
    for name in header:
        table.add_column(name, justify="right")
    for row in rows:
        table.add_row(*row)
    out.print(table)
