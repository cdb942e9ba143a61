"""``python -m bgn.data.import <path> name=<name> [format=...] [split_seed=0] [overwrite=false]
[paths.data_dir=...]``: trajectories from another engine -> bgn's dataset files.

``import`` is a Python keyword, so this module is only run, never imported by name; the work
is ``bgn.data.importing``'s.
"""

from bgn.data.importing import run_cli

if __name__ == "__main__":
    run_cli()
