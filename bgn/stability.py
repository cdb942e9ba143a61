"""``python -m bgn.stability``, kept under its old name: ``bgn.studies.stability``."""

from bgn.studies.stability import main

if __name__ == "__main__":
    main()
