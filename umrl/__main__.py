"""``python -m umrl <command> ...``: the ``umrl`` command line (:mod:`umrl.cli`)."""
from umrl.cli import main

if __name__ == "__main__":
    main()
