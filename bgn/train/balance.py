"""``python -m bgn.data.balance <dataset.h5> [more.h5 ...] [results_md=FILE]
[paths.data_dir=...]``: what each dataset file's motion conserves (``bgn.data.balance``), as a
markdown table; ``--help`` lists the keys (``conf/balance.yaml``).

The command of the data stage's module, here with the other commands of this folder: the data
layer reads no config (docs/design.md, "Layers"); ``python -m bgn.data.balance`` runs this.
Several positional paths become one ``files=[...]`` (``cli`` turns only the first positional
argument into its key).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from bgn.data.balance import table
from bgn.training.validate import ARGV, ConfigError, cli


def dataset_files(cfg: Any) -> list[Path]:
    """The files of ``files=`` (one path or a list), relative ones under ``paths.data_dir``
    where it is set."""
    from omegaconf import ListConfig

    given = cfg.get("files")
    if not given:
        raise ConfigError("files", given, "give dataset files: python -m bgn.data.balance "
                          "data/imported/<name>/train.h5 [more.h5 ...]")
    names = list(given) if isinstance(given, (list, tuple, ListConfig)) else [given]
    root = cfg.paths.data_dir
    paths = []
    for name in names:
        path = Path(str(name)).expanduser()
        if root and not path.is_absolute():
            path = Path(str(root)).expanduser() / path
        if not path.is_file():
            where = f" under paths.data_dir={root}" if root else ""
            raise ConfigError("files", str(name), f"no such file{where}: a dataset file "
                              "(<name>.h5) of python -m bgn.train or bgn.data.import")
        paths.append(path)
    return paths


def check(cfg: Any) -> None:
    """Everything the command is given, before any file is read."""
    dataset_files(cfg)
    if cfg.results_md is not None:
        results = Path(str(cfg.results_md)).expanduser()
        if results.suffix != ".md" or results.is_dir():
            raise ConfigError("results_md", cfg.results_md, "a markdown file (.md) whose "
                              "generated block 'balance' is rewritten (null: not written)")


def run(cfg: Any) -> str:
    """Print the table (and write it into ``results_md``'s block); returns it."""
    text = table(dataset_files(cfg), cfg.results_md, " ".join(ARGV))
    print(text)
    return text


_command = cli("balance", check, positional="files", prog="bgn.data.balance")(run)


def one_list(argv: list[str]) -> list[str]:
    """``argv`` with two or more positional paths (no ``=``, not an option nor its value)
    turned into one ``files=[...]`` override, each path quoted for Hydra's grammar."""
    positional = [i for i, a in enumerate(argv) if "=" not in a and not a.startswith("-")
                  and not (i and argv[i - 1].startswith("-"))]
    if len(positional) < 2:
        return list(argv)
    quoted = ",".join("'" + argv[i].replace("\\", "\\\\").replace("'", "\\'") + "'"
                      for i in positional)
    rest = [a for i, a in enumerate(argv) if i not in positional]
    return [f"files=[{quoted}]", *rest]


def command(argv: list[str] | None = None) -> Any:
    """The console's command (``argv`` None: ``sys.argv``) or the same in this process."""
    if argv is None:
        sys.argv[1:] = one_list(sys.argv[1:])
        return _command()
    return _command(one_list(list(argv)))


if __name__ == "__main__":
    command()
