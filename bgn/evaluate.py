"""``python -m bgn.evaluate``, kept under its old name: ``bgn.eval.evaluate``."""

from bgn.eval.evaluate import command

if __name__ == "__main__":
    command()
