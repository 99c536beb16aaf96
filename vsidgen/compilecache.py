"""Persistent JAX compilation cache: compiled XLA programs kept on disk across runs."""

from __future__ import annotations

import os
import pathlib
import sys


#: every compilation is kept, the small eager ones too: a warm HFB-320 fit compiled ~110 small
#: host-side programs (< 0.2 s each, ~5 s together) again in every process when only those
#: above 0.2 s were kept (docs/performance.md)
MIN_COMPILE_SECS = 0.0


def enable_compilation_cache() -> None:
    """Persist JAX compilations across runs (``$VSIDGEN_CACHE_DIR``, default ~/.cache/vsidgen/jax).

    A second fit of the same model then skips most of its compile time. Set
    ``VSIDGEN_CACHE_DIR=`` (empty) to disable.
    """
    default = pathlib.Path(os.environ.get("XDG_CACHE_HOME", pathlib.Path.home() / ".cache"))
    cache = os.environ.get("VSIDGEN_CACHE_DIR", str(default / "vsidgen" / "jax"))
    if not cache:
        return
    try:
        pathlib.Path(cache).mkdir(parents=True, exist_ok=True)
        if "jax" not in sys.modules:  # read by jax when it is imported (not before it is needed)
            os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", cache)
            os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(MIN_COMPILE_SECS))
            return
        import jax

        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECS)
    except (OSError, AttributeError, ValueError):  # read-only home, older jax: run uncached
        pass


__all__ = ["enable_compilation_cache"]
