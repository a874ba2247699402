"""``python -m app.backup``: the command line of ``app.cli.backup``, kept under its documented name."""

import sys

from app.cli.backup import main

if __name__ == "__main__":
    sys.exit(main())
