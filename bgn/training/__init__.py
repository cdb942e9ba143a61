"""The training stage: the body of ``python -m bgn.train`` (``run``), the LightningModule
(``module``), the config schemas (``config``) and their checks (``validate``), checkpoints,
signals, sweeps and unrolled training.

The commands that run it live one layer up, in ``bgn.train`` (``python -m bgn.train``,
``bgn.train.generate``, ``bgn.train.import``): the training command also starts studies and the
formula stage, which themselves train, so the command cannot sit inside the stage it drives
(docs/design.md, "Layers"). Nothing is imported here, so that a module loads only what it uses.
"""
