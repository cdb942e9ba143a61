"""``python -m bgn.experiments preset=<name>``: the studies' command, kept under its old name
(``bgn.studies.dispatch``)."""

from bgn.studies.dispatch import command

if __name__ == "__main__":
    command()
