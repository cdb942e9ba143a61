"""``python -m bgn.train.import <path> name=<name> [format=...] [split_seed=0] [overwrite=false]
[paths.data_dir=...]``: trajectories from another engine -> bgn's dataset files.

``import`` is a Python keyword, so this module is only run, never imported by name; the work
is ``bgn.data.importing``'s, the config's schema ``bgn.training.config``'s.
"""

import sys

from bgn.data.importing import main, path_override
from bgn.training.config import register_configs
from bgn.training.validate import cli

if __name__ == "__main__":
    sys.argv = [sys.argv[0], *path_override(sys.argv[1:])]
    register_configs(models=False)
    cli("import")(main)()  # bad input: one line, non-zero exit (bgn.training.validate)
