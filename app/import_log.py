"""``python -m app.import_log``: the command line of ``app.cli.import_log``, kept under its documented name."""

import sys

from app.cli.import_log import main

if __name__ == "__main__":
    sys.exit(main())
