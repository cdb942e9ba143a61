"""``python -m bgn.stability preset=<name> [checkpoints.<scene>=<run folder or checkpoint>]``:
the hard-case suite (``bgn.studies.stability``); ``--help`` lists the keys."""

from bgn.studies.stability import main

if __name__ == "__main__":
    main()
