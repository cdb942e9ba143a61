"""Result tables as markdown and CSV, one writer for the study report and the sweep summary.

The markdown is what a person reads (numbers to four significant digits, blanks for missing
values, image columns shown inline); the CSV keeps the raw values for further analysis.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def fmt(value: Any) -> str:
    """A table cell: floats to four significant digits, booleans yes/no, None and NaN
    blank."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def markdown_table(columns: Sequence[str], rows: Sequence[dict[str, Any]],
                   images: Sequence[str] = ()) -> str:
    """A markdown table of ``rows`` (missing keys blank); a column in ``images`` holds image
    paths, shown inline."""
    def cell(column: str, value: Any) -> str:
        return f"![{Path(value).stem}]({value})" if column in images and value else fmt(value)

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(c, r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def write_csv(path: Path, columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> None:
    """``rows`` as CSV with a header; keys outside ``columns`` are left out."""
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def write_table(directory: Path, stem: str, columns: Sequence[str],
                rows: Sequence[dict[str, Any]], title: str | None = None, notes: str = "",
                empty: str = "", csv_too: bool = True, images: Sequence[str] = ()) -> str:
    """Write ``<stem>.md`` (optional title and notes above the table; ``empty`` below it
    when there are no rows) and, with ``csv_too``, ``<stem>.csv``; return the markdown."""
    head = []
    if title:
        head += [f"# {title}", ""]
    if notes:
        head += [notes, ""]
    text = "\n".join(head) + ("\n" if head else "") + markdown_table(columns, rows, images)
    if not rows and empty:
        text += f"\n{empty}\n"
    (directory / f"{stem}.md").write_text(text)
    if csv_too:
        write_csv(directory / f"{stem}.csv", columns, rows)
    return text
