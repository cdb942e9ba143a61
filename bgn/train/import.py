"""``python -m bgn.train.import <path> name=<name> [format=...] [split_seed=0] [overwrite=false]
[paths.data_dir=...]``: trajectories from another engine -> bgn's dataset files (``--help``
lists the keys and the formats).

``import`` is a Python keyword: this module is run, or imported with
``importlib.import_module("bgn.train.import")`` for ``command``; the work is
``bgn.data.importing``'s, the config's schema ``bgn.training.config``'s.
"""

from bgn.data.importing import main
from bgn.training.validate import cli

# the path is the first positional argument; bad input: one line, non-zero exit
command = cli("import", positional="path", prog="bgn.data.import")(main)

if __name__ == "__main__":
    command()
