"""``python -m bgn.train.import <path> name=<name> [format=...] [split_seed=0] [overwrite=false]
[paths.data_dir=...]``: trajectories from another engine -> bgn's dataset files (``--help``
lists the keys and the formats).

``import`` is a Python keyword, so this module is only run, never imported by name; the work
is ``bgn.data.importing``'s, the config's schema ``bgn.training.config``'s.
"""

from bgn.data.importing import main
from bgn.training.validate import cli

if __name__ == "__main__":
    # the path is the first positional argument; bad input: one line, non-zero exit
    cli("import", positional="path", prog="bgn.data.import")(main)()
