"""The ``vsidgen`` console script: the command line of :func:`vsidgen.cli.main`, imported
inside the handler of Ctrl-C, so that an interrupt while sympy and numpy load (the first
half second) ends like one later: "interrupted", exit status 130, no traceback."""

from __future__ import annotations

import os
import sys


def main(argv=None) -> int:
    try:
        from .cli import main as cli_main

        return cli_main(argv)   # handles an interrupt during the command itself
    except KeyboardInterrupt:   # ... this one, while modules load and arguments are parsed
        print("interrupted", file=sys.stderr)
        # the interrupt may have stopped an extension module (jaxlib, scipy) half-way through
        # its initialisation; the interpreter's own shutdown then tears that module down and
        # can die by a signal instead of exiting 130 (seen once under load: SIGSEGV, session
        # 47). Nothing has been written yet, so the process ends here without that shutdown.
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(130)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
