"""docs/design.md, "Layers": every import in bgn (at the top of a module or inside a
function) points down the table of layers, and the data and model layers know nothing of each
other. One exception, stated there: ``bgn/__init__`` imports the Python API (``bgn.load``) on
first use."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "bgn"
BOTTOM = {"graph", "coerce", "metrics", "figures", "paraview", "tables", "law_table",
          "provenance", "__version__"}
# (layer, rank): an import may go to a rank below its own, or to its own layer
ORDER = {"bottom": 0, "scenes": 1, "data": 2, "models": 2, "simulator": 3, "training": 4,
         "evaluation": 5, "studies": 6, "commands": 7}
ALLOWED = {("bgn", "bgn.api")}  # bgn.__getattr__: bgn.load, imported on first use


def layer(module: str) -> str:
    """The layer of a module of bgn (docs/design.md's table)."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] in BOTTOM:
        return "bottom"
    top = parts[1]
    named = {"sim": "scenes", "data": "data", "model": "models", "simulator": "simulator",
             "rollout": "simulator", "training": "training", "eval": "evaluation",
             "api": "evaluation", "studies": "studies"}
    if top == "laws":
        return "commands" if parts[2:3] == ["__main__"] else "evaluation"
    return named.get(top, "commands")  # train/, benchmarks/, the commands under their names


def imports() -> list[tuple[str, str, int]]:
    """(importer, imported module of bgn, line) for every import in the package."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        module = module.removesuffix(".__init__")
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module] if node.module != "bgn" else [
                    f"bgn.{a.name}" for a in node.names]
            else:
                continue
            found += [(module, n, node.lineno) for n in names if n.split(".")[0] == "bgn"]
    return found


def test_every_import_points_down_the_layers() -> None:
    found = imports()
    assert len(found) > 300  # the walk saw the package
    wrong = []
    for importer, imported, line in found:
        mine, theirs = layer(importer), layer(imported)
        up = ORDER[theirs] > ORDER[mine]
        across = ORDER[theirs] == ORDER[mine] and theirs != mine
        if (up or across) and (importer, imported) not in ALLOWED:
            wrong.append(f"{importer}:{line} ({mine}) imports {imported} ({theirs})")
    assert not wrong, "\n".join(wrong)


def test_the_layer_map_knows_every_module() -> None:
    assert layer("bgn.laws.__main__") == "commands" and layer("bgn.laws.search") == "evaluation"
    assert layer("bgn.train.import") == "commands" and layer("bgn.api") == "evaluation"
    assert layer("bgn.paraview") == "bottom" and layer("bgn.data.files") == "data"
