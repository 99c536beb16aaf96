"""``python -m vsidgen``: the command line, as the ``vsidgen`` script (:func:`vsidgen.cli.main`)."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
