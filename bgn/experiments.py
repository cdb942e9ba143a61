"""``python -m bgn.experiments preset=<name> [key=value ...]``: the studies' command
(``bgn.studies.dispatch``); ``--help`` lists the keys and presets."""

from bgn.studies.dispatch import command

if __name__ == "__main__":
    command()
