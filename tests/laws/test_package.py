"""bgn.laws sits at the evaluation layer (docs/design.md#layers): the layers below never import
it, and its modules import nothing above it, nor the package's own command."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.laws.conftest import ROOT

BGN = ROOT / "bgn"


def imported(path: Path) -> set[str]:
    """Every module ``path`` imports, at the top or inside a function."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names |= {f"{node.module}.{a.name}" for a in node.names}
    return names


@pytest.mark.parametrize("below", ["model", "training", "data", "sim"])
def test_no_layer_below_imports_the_laws(below):
    for path in sorted((BGN / below).rglob("*.py")):
        found = [m for m in imported(path) if m == "bgn.laws" or m.startswith("bgn.laws.")]
        assert not found, f"{path.relative_to(ROOT)} imports {found}"


def test_the_laws_import_nothing_above_them():
    above = ("bgn.studies", "bgn.train", "bgn.laws.__main__", "bgn.experiments")
    for path in sorted((BGN / "laws").glob("*.py")):
        if path.name == "__main__.py":
            continue
        found = [m for m in imported(path)
                 if any(m == a or m.startswith(a + ".") for a in above)]
        assert not found, f"{path.relative_to(ROOT)} imports {found}"
