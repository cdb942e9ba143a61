"""``python -m bgn.render <run folder or checkpoint> [key=value ...]``: a rollout animated
against the truth (``bgn.studies.render``); ``--help`` lists the keys."""

from bgn.studies.render import main

if __name__ == "__main__":
    main()
