"""``python -m bgn.laws``, kept under its old name: ``bgn.eval.laws``."""

from bgn.eval.laws import main

if __name__ == "__main__":
    main()
