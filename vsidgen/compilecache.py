"""Persistent JAX compilation cache: compiled XLA programs kept on disk across runs, and the
traced programs of the estimator's jitted functions (:class:`StoredJit`).

JAX keys its compilation cache on the *lowered* program, so a process with a warm cache still
traces and lowers every function before it finds the compiled one: 1.7 s of a 6.4-s warm
HFB-320 fit was tracing and lowering the Hessian assembly. :class:`StoredJit` keeps the
lowered program itself (``jax.export``, serialized) under a key of everything the trace
depends on, so a later process deserializes it (≈ 2 ms) instead of tracing it.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pathlib
import sys
import threading


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
    global _EXPORTED_DIR
    try:
        pathlib.Path(cache).mkdir(parents=True, exist_ok=True)
        _EXPORTED_DIR = pathlib.Path(cache) / EXPORTED_SUBDIR
        if "jax" not in sys.modules:  # read by jax when it is imported (not before it is needed)
            os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", cache)
            os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(MIN_COMPILE_SECS))
            return
        import jax

        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECS)
    except (OSError, AttributeError, ValueError):  # read-only home, older jax: run uncached
        pass


#: sub-folder of the cache folder with the serialized traced programs (:class:`StoredJit`)
EXPORTED_SUBDIR = "vsidgen-exported"
#: where :class:`StoredJit` keeps its programs; set by :func:`enable_compilation_cache` (None:
#: not kept, every process traces; the test suite's own cache leaves it None)
_EXPORTED_DIR: pathlib.Path | None = None


def exported_dir() -> pathlib.Path | None:
    """The folder of stored traced programs, or None when they are not kept."""
    return _EXPORTED_DIR


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """Hash of every Python source file of the vsidgen package and of the JAX and jaxlib
    versions: a stored program is valid only for the code that traced it."""
    import jax
    import jaxlib

    h = hashlib.sha256()
    root = pathlib.Path(__file__).resolve().parent
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    h.update(f"jax {jax.__version__} jaxlib {jaxlib.__version__}".encode())
    return h.hexdigest()


def _signature(leaves) -> tuple:
    import jax

    out = []
    for leaf in leaves:
        a = jax.typeof(leaf)
        out.append((tuple(a.shape), str(a.dtype), bool(getattr(a, "weak_type", False))))
    return tuple(out)


class StoredJit:
    """``jax.jit(fn)`` whose traced and lowered program is kept on disk per argument signature.

    ``key``: a string naming everything ``fn``'s trace depends on besides its arguments'
    shapes and dtypes (the caller's responsibility: the model's generated code, the
    estimator's settings; :func:`code_fingerprint`, the backend, the x64 and matmul-precision
    flags and the compiler options are added here). Per signature (the arguments' tree
    structure, shapes, dtypes and weak types) the program is loaded from
    ``exported_dir()/<sha256>.jaxexp`` when there, else exported (``jax.export``: one trace
    and lowering, as ``jax.jit`` would do), written atomically, and run through
    ``jax.jit(exported.call)``, in both cases, so the process that stores it and the ones
    that load it compile the same program (one entry of the compilation cache). Any failure
    to export, write or read falls back to the plain ``jax.jit`` (a corrupt file is
    replaced). Calls with tracers (inside another transformation) use the plain jit.
    """

    def __init__(self, fn, *, key: str, compiler_options=None, directory: pathlib.Path | None = None):
        import jax

        self._jit = jax.jit(fn, compiler_options=compiler_options)
        self._opts = compiler_options
        self._dir = directory if directory is not None else exported_dir()
        self._key = key
        self._calls: dict = {}
        self._lock = threading.Lock()
        self.loaded = 0       # signatures whose program came from the disk (tests, benchmarks)
        self.stored = 0       # signatures exported and written by this process

    def _base_key(self) -> str:
        import jax

        flags = (jax.default_backend(), bool(jax.config.jax_enable_x64),
                 str(jax.config.jax_default_matmul_precision),
                 tuple(sorted((self._opts or {}).items())))
        return f"{code_fingerprint()}|{flags!r}|{self._key}"

    def _path(self, treedef, sig) -> pathlib.Path:
        h = hashlib.sha256(f"{self._base_key()}|{treedef}|{sig!r}".encode()).hexdigest()
        return self._dir / f"{h}.jaxexp"

    def _build(self, args, treedef, sig):
        import jax
        from jax import export

        from .atomic import write_bytes_atomic

        path = self._path(treedef, sig)
        try:
            exp = export.deserialize(bytearray(path.read_bytes()))
            self.loaded += 1
        except Exception:  # noqa: BLE001 - missing, corrupt or foreign: export it (again)
            exp = None
        if exp is None:
            exp = export.export(self._jit)(*args)
            try:
                write_bytes_atomic(path, exp.serialize())
                self.stored += 1
            except Exception:  # noqa: BLE001 - a read-only cache: run it anyway
                pass
        return jax.jit(exp.call, compiler_options=self._opts)

    def __call__(self, *args):
        import jax

        if self._dir is None:
            return self._jit(*args)
        leaves, treedef = jax.tree_util.tree_flatten(args)
        if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
            return self._jit(*args)
        sig = _signature(leaves)
        k = (treedef, sig)
        f = self._calls.get(k)
        if f is None:
            with self._lock:
                f = self._calls.get(k)
                if f is None:
                    try:
                        f = self._build(args, treedef, sig)
                    except Exception:  # noqa: BLE001 - not exportable: the plain jit
                        f = self._jit
                    self._calls[k] = f
        return f(*args)


__all__ = ["StoredJit", "code_fingerprint", "enable_compilation_cache", "exported_dir"]
