"""``python -m bgn.laws <run folder or checkpoint> [key=value ...]``: the learned pair law as
a formula (``bgn.eval.laws``); ``--help`` lists the keys."""

from bgn.eval.laws import main

if __name__ == "__main__":
    main()
