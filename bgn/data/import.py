"""``python -m bgn.data.import <path> name=<name> ...``, the import command under the name the
manual gives it: the command itself is ``bgn.train.import`` (it shares the training's config
schema); this runs it. Never imported: ``import`` is a Python keyword."""

import runpy

if __name__ == "__main__":
    runpy.run_module("bgn.train.import", run_name="__main__", alter_sys=True)
