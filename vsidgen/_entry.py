"""The ``vsidgen`` console script: the command line of :func:`vsidgen.cli.main`.

Ctrl-C while the modules load (sympy, numpy, JAX: the first seconds) is *deferred*: a
handler that only records it is installed until the command line is loaded, and for the
commands that compute, until JAX is imported and its garbage-collector callback guarded
(:mod:`vsidgen.interrupts`); a recorded interrupt then ends the process with "interrupted",
exit status 130. Raised inside JAX's import, the ``KeyboardInterrupt`` was swallowed by that
callback before the guard was in place — "Exception ignored in _xla_gc_callback", and the
fit ran to the end with exit status 0 (red team, session 48)."""

from __future__ import annotations

import os
import sys

#: commands that import JAX: it is loaded (and its gc callback guarded) before Ctrl-C is live
_COMPUTING = frozenset({"fit", "simulate", "diagnose", "fleet"})


def _exit_interrupted() -> None:
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


_deferred: list[int] = []


def _defer():
    """Install the recording handler; the handler it replaced (None: not possible here)."""
    import signal

    try:
        return signal.signal(signal.SIGINT, lambda signum, frame: _deferred.append(signum))
    except ValueError:      # not the main thread: nothing to defer
        return None


# installed when the console script imports this module (its first line), so that the
# deferral covers everything from there on
_previous = _defer()


def main(argv=None) -> int:
    import signal

    global _previous
    previous = _previous if _previous is not None else _defer()
    _previous = None
    deferred = _deferred
    try:
        from .cli import main as cli_main

        args = sys.argv[1:] if argv is None else list(argv)
        if args and args[0] in _COMPUTING:
            from . import precision  # noqa: F401  (JAX, its gc callback guarded)
    except KeyboardInterrupt:   # a handler other than ours raised it (not the main thread)
        _exit_interrupted()
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
            if "vsidgen.interrupts" in sys.modules:   # JAX loaded: Ctrl-C in its gc callback
                sys.modules["vsidgen.interrupts"].install_sigint()
    if deferred:
        _exit_interrupted()
    try:
        return cli_main(argv)   # handles an interrupt during the command itself ...
    except KeyboardInterrupt:   # ... this one came while its arguments were parsed
        _exit_interrupted()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
