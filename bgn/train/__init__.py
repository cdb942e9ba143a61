"""The training stage: ``python -m bgn.train`` (``__main__.py``), its body (``run``), the
LightningModule (``module``), the config schemas (``config``) and their checks (``validate``),
checkpoints, signals, sweeps and unrolled training; and the data commands that share the
training's config (``python -m bgn.train.generate``, ``python -m bgn.train.import``).

Nothing is imported here, so that ``python -m bgn.train.<command>`` loads only what it uses.
"""
