"""``python -m app.import_bag``: the command line of ``app.cli.import_bag``, kept under its documented name."""

import sys

from app.cli.import_bag import main

if __name__ == "__main__":
    sys.exit(main())
