"""The training commands: ``python -m bgn.train`` (``__main__.py``) and the data commands that
share the training's config (``python -m bgn.train.generate``, ``python -m bgn.train.import``).

The stage they run is ``bgn.training``; these modules stand above it and above the studies and
evaluation that ``python -m bgn.train`` may start (docs/design.md, "Layers"). Nothing is
imported here, so that ``python -m bgn.train.<command>`` loads only what it uses.
"""
