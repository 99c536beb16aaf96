"""Shared pytest fixtures."""

from __future__ import annotations

import os
import pathlib

import pytest

_DEFAULT_FLIGHT_DATA = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data" / "flight"


@pytest.fixture(scope="session")
def flight_data_dir() -> pathlib.Path:
    """Directory of the real flight records (third-party data, never copied into the repo).

    ``$VSIDGEN_FLIGHT_DATA`` overrides the default ``<repo>/../shared/data/flight``.
    When the directory is absent the test is skipped, unless
    ``VSIDGEN_REQUIRE_FLIGHT_DATA=1``, in which case it fails.
    """
    env = os.environ.get("VSIDGEN_FLIGHT_DATA")
    path = pathlib.Path(env) if env else _DEFAULT_FLIGHT_DATA
    if not path.is_dir():
        reason = (f"flight data directory {path} not found "
                  "(set VSIDGEN_FLIGHT_DATA to the folder holding hfb320_1_10.csv etc.)")
        if os.environ.get("VSIDGEN_REQUIRE_FLIGHT_DATA") == "1":
            pytest.fail(reason + "; VSIDGEN_REQUIRE_FLIGHT_DATA=1 makes this an error")
        pytest.skip(reason)
    return path


def _hypothesis_without_deadline() -> None:
    """Property tests are judged on their examples, not their speed: a shared 2-core CI
    machine makes per-example wall time meaningless, so hypothesis's deadline is off."""
    try:
        from hypothesis import settings
    except ImportError:  # the test extra is not installed; property tests are skipped
        return
    settings.register_profile("vsidgen", deadline=None)
    settings.load_profile("vsidgen")


_hypothesis_without_deadline()


def pytest_configure(config):
    """Persistent JAX compilation cache for the test session, under pytest's cache directory
    (``.pytest_cache/d/jax-compilation-cache``): a second run of the suite skips most XLA
    compile time. Tracing still happens, so tests that count traces are unaffected.
    ``VSIDGEN_TEST_JAX_CACHE=0`` disables it. Only compilations above 0.2 s are kept, as
    before the CLI started keeping all (:data:`vsidgen.compilecache.MIN_COMPILE_SECS`):
    whether the small ones pay for their writing in a cold CI cache is not measured. Subprocesses (CLI tests, dask workers) get it
    through ``JAX_COMPILATION_CACHE_DIR``."""
    # no stored traced programs (vsidgen.compilecache.StoredJit) in the suite's processes: a
    # program stored by an earlier run would skip a trace that a test counts; the CLI's
    # subprocesses keep JAX's cache below (tests/test_stored_programs.py enables it itself)
    os.environ.setdefault("VSIDGEN_CACHE_DIR", "")
    if os.environ.get("VSIDGEN_TEST_JAX_CACHE", "1") == "0" or getattr(config, "cache", None) is None:
        return
    try:
        cache = config.cache.mkdir("jax-compilation-cache")
        import jax

        jax.config.update("jax_compilation_cache_dir", str(cache))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    except (OSError, AttributeError, ValueError):  # read-only checkout, older jax: uncached
        return
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(cache))
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")
