"""``python -m bgn.evaluate <run folder or checkpoint> [key=value ...]``: the full evaluation
report of one trained model (``bgn.eval.evaluate``); ``--help`` lists the keys."""

from bgn.eval.evaluate import main

if __name__ == "__main__":
    main()
