"""``python -m bgn.render``, kept under its old name: ``bgn.studies.render``."""

from bgn.studies.render import main

if __name__ == "__main__":
    main()
