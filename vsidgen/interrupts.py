"""Ctrl-C that is never lost inside a garbage-collector callback.

Python runs a signal handler at the next bytecode boundary of the main thread. When that
boundary lies inside a ``gc.callbacks`` function — JAX registers one that frees device
buffers after every collection — the ``KeyboardInterrupt`` raised there is *swallowed*:
Python prints "Exception ignored in gc callback" and the computation goes on (observed
once in seven interrupts of a fit). :func:`guard_gc_callbacks` wraps every registered
callback so that an interrupt caught there is delivered again to the main thread a moment
later, outside the callback, where it propagates as usual.

A wrapped callback compares equal to (and hashes as) the callback it wraps, so a library
that later removes its own callback (``gc.callbacks.remove(cb)``: dask's workers do when
they close) still finds it.
"""

from __future__ import annotations

import _thread
import gc
import threading

#: delay (s) before an interrupt caught in a gc callback is delivered again
REDELIVERY_DELAY_S = 0.02


class _Guarded:
    """``callback`` with a ``KeyboardInterrupt`` raised in it delivered again later; equal to
    ``callback`` (``list.remove`` and ``in`` on ``gc.callbacks`` find it by the original)."""

    __slots__ = ("vsidgen_guarded",)

    def __init__(self, callback):
        self.vsidgen_guarded = callback

    def __call__(self, phase, info):
        try:
            self.vsidgen_guarded(phase, info)
        except KeyboardInterrupt:
            threading.Timer(REDELIVERY_DELAY_S, _thread.interrupt_main).start()

    def __eq__(self, other):
        return other is self or other == self.vsidgen_guarded

    def __hash__(self):
        return hash(self.vsidgen_guarded)

    def __repr__(self):
        return f"guarded({self.vsidgen_guarded!r})"


def _guarded(callback):
    return _Guarded(callback)


def guard_gc_callbacks() -> None:
    """Wrap every callback in ``gc.callbacks`` (idempotent; call after the libraries that
    register callbacks are imported) and install :func:`sigint_handler` where Ctrl-C still
    has Python's default handler."""
    gc.callbacks[:] = [cb if hasattr(cb, "vsidgen_guarded") else _guarded(cb)
                       for cb in gc.callbacks]
    install_sigint()


def _in_gc_callback(frame) -> bool:
    """``frame`` or a frame it was called from runs a ``gc.callbacks`` function."""
    codes = {_Guarded.__call__.__code__}
    for cb in list(gc.callbacks):
        code = getattr(getattr(cb, "vsidgen_guarded", cb), "__code__", None)
        if code is not None:
            codes.add(code)
    while frame is not None:
        if frame.f_code in codes:
            return True
        frame = frame.f_back
    return False


def sigint_handler(signum, frame):
    """Python's ``KeyboardInterrupt`` on Ctrl-C, except inside a garbage-collector callback,
    where it would be swallowed: there it is delivered again a moment later. The wrapper of
    :func:`guard_gc_callbacks` alone leaves a window: a signal that becomes pending while the
    collector runs is raised at the first bytecode of the callback, before the wrapper's
    ``try`` (a fit interrupted 3.5 s after its start ran to the end, status 0; session 48)."""
    if _in_gc_callback(frame):
        threading.Timer(REDELIVERY_DELAY_S, _thread.interrupt_main).start()
        return
    raise KeyboardInterrupt


def install_sigint() -> None:
    """:func:`sigint_handler` for SIGINT when Python's default handler is installed (never
    over an application's own handler; only the main thread can)."""
    import signal

    try:
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            signal.signal(signal.SIGINT, sigint_handler)
    except ValueError:      # not the main thread
        pass


__all__ = ["REDELIVERY_DELAY_S", "guard_gc_callbacks", "install_sigint", "sigint_handler"]
