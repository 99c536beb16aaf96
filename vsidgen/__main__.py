"""``python -m vsidgen``: the command line, as the ``vsidgen`` script (:func:`vsidgen.cli.main`,
through :mod:`vsidgen._entry`, which turns a Ctrl-C while it loads into exit status 130)."""

import sys

from ._entry import main

if __name__ == "__main__":
    sys.exit(main())
