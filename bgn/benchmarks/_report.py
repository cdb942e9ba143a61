"""What every benchmark command shares: the console table (their files use the package's
table writer, ``bgn.tables``; the machine line is ``bgn.provenance.machine``). A helper
module, not a command (its name starts with ``_``, so the smoke tests that run every command
in ``bgn.benchmarks`` skip it)."""

from __future__ import annotations

from collections.abc import Sequence


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
