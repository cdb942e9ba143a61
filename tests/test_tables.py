"""The one table writer: cell formatting, markdown and CSV agree, titles, notes, images."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from bgn.tables import fmt, markdown_table, write_table


def test_fmt() -> None:
    assert fmt(None) == "" and fmt(math.nan) == ""
    assert fmt(0.123456789) == "0.1235" and fmt(3) == "3" and fmt("gns") == "gns"


def test_markdown_table_blanks_missing_values_and_shows_images() -> None:
    text = markdown_table(["a", "figure"], [{"a": 1.0, "figure": "figures/x.png"}, {}],
                          images=("figure",))
    assert text.splitlines() == ["| a | figure |", "|---|---|",
                                 "| 1 | ![x](figures/x.png) |", "|  |  |"]


def test_write_table_markdown_and_csv(tmp_path: Path) -> None:
    rows = [{"run": "0", "nmse": 0.5, "extra": "not a column"}, {"run": "1", "nmse": None}]
    text = write_table(tmp_path, "t", ["run", "nmse"], rows, title="T", notes="Some notes.")
    assert text.startswith("# T\n\nSome notes.\n\n| run | nmse |\n")
    assert (tmp_path / "t.md").read_text() == text
    with open(tmp_path / "t.csv", newline="") as fh:
        assert list(csv.DictReader(fh)) == [{"run": "0", "nmse": "0.5"},
                                            {"run": "1", "nmse": ""}]


def test_write_table_without_rows_or_title(tmp_path: Path) -> None:
    text = write_table(tmp_path, "e", ["a"], [], empty="(nothing)", csv_too=False)
    assert text == "| a |\n|---|\n\n(nothing)\n"
    assert not (tmp_path / "e.csv").exists()
