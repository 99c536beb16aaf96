"""Ctrl-C raised inside a gc callback (JAX registers one) is delivered again, not lost."""

import gc
import time

import pytest

from vsidgen import precision  # noqa: F401  (imports jax and guards its callback)
from vsidgen.interrupts import guard_gc_callbacks


def test_jax_gc_callback_is_guarded():
    """JAX's callback is wrapped when vsidgen.precision is imported (callbacks registered
    later, e.g. by hypothesis under pytest, are not vsidgen's concern)."""
    xla = [cb for cb in gc.callbacks
           if "xla" in getattr(getattr(cb, "vsidgen_guarded", cb), "__name__", "")]
    assert xla and all(hasattr(cb, "vsidgen_guarded") for cb in xla), gc.callbacks


def test_an_interrupt_swallowed_by_a_gc_callback_is_delivered_again():
    fired = []

    def interrupted_during_callback(phase, info):
        if phase == "start" and not fired:
            fired.append(1)
            raise KeyboardInterrupt      # what a Ctrl-C arriving here does

    gc.callbacks.append(interrupted_during_callback)
    try:
        guard_gc_callbacks()
        guard_gc_callbacks()             # idempotent
        assert sum(getattr(cb, "vsidgen_guarded", None) is interrupted_during_callback
                   for cb in gc.callbacks) == 1
        with pytest.raises(KeyboardInterrupt):
            gc.collect()                 # unguarded, Python would print and go on
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:
                time.sleep(0.01)
        assert fired
    finally:
        gc.callbacks[:] = [cb for cb in gc.callbacks
                           if getattr(cb, "vsidgen_guarded", cb) is not interrupted_during_callback]
