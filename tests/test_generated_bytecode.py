"""The generated module is executed from the text vsidgen generates for the spec, never from a
bytecode cache or a file changed after the check (red team, session 47: a crafted
``generated/__pycache__/<name>.cpython-*.pyc`` whose header matches the checked ``.py`` ran at
``simulate``; two specs of one model name raced for ``generated/<name>.py``)."""

import importlib.util
import os
import pathlib
import shutil
import sys

import numpy as np

from vsidgen.model import load_model

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _project(tmp_path):
    spec = tmp_path / "attas_sp.yaml"
    shutil.copy(ROOT / "specs" / "attas_sp.yaml", spec)
    return spec, tmp_path / "gen"


def _plant_pyc(module_path: pathlib.Path, canary: pathlib.Path) -> pathlib.Path:
    """A timestamp pyc for ``module_path`` (its mtime and size in the header) whose code
    writes ``canary``: what Python's own loader would run instead of the source."""
    from importlib._bootstrap_external import _code_to_timestamp_pyc

    st = module_path.stat()
    code = compile(f"open({str(canary)!r}, 'w').write('ran')\n", str(module_path), "exec")
    data = _code_to_timestamp_pyc(code, int(st.st_mtime), st.st_size)
    pyc = pathlib.Path(importlib.util.cache_from_source(str(module_path)))
    pyc.parent.mkdir(parents=True, exist_ok=True)
    pyc.write_bytes(bytes(data))
    return pyc


def test_a_matching_pyc_is_never_run(tmp_path):
    spec, gen = _project(tmp_path)
    m = load_model(spec, generated_dir=gen)
    canary = tmp_path / "PWNED"
    pyc = _plant_pyc(m.module_path, canary)
    # Python's own loader does run it: the plant is real
    s = importlib.util.spec_from_file_location("probe_attas", m.module_path)
    s.loader.exec_module(importlib.util.module_from_spec(s))
    assert canary.exists()
    canary.unlink()
    m2 = load_model(spec, generated_dir=gen)
    assert not canary.exists()
    assert m2.drift is not None and pyc.exists()
    x = np.zeros(len(m2.state_names))
    u = np.zeros(len(m2.input_names))
    th = np.zeros(len(m2.parameter_names))
    assert np.all(np.isfinite(np.asarray(m2.drift(x, u, th))))


def test_no_bytecode_written_for_generated_modules(tmp_path):
    spec, gen = _project(tmp_path)
    dont = sys.dont_write_bytecode
    try:
        sys.dont_write_bytecode = False
        load_model(spec, generated_dir=gen)
    finally:
        sys.dont_write_bytecode = dont
    assert not (gen / "__pycache__").exists()


def test_the_executed_text_is_the_spec_s_not_the_file_s(tmp_path, monkeypatch):
    """The file replaced between the check and the import (another spec of the same model
    name, built from the same folder at that moment) does not change what runs."""
    from vsidgen.codegen import jaxmodule

    spec, gen = _project(tmp_path)
    m = load_model(spec, generated_dir=gen)
    real = jaxmodule.build_model

    def build_then_swap(symbolic, **kw):
        res = real(symbolic, **kw)
        res.module_path.write_text("raise SystemExit('the other spec ran')\n")
        return res

    monkeypatch.setattr(jaxmodule, "build_model", build_then_swap)
    import vsidgen.codegen as cg
    monkeypatch.setattr(cg, "build_model", build_then_swap)
    m2 = load_model(spec, generated_dir=gen)
    assert m2.module.__vsidgen_source_sha256__ == m.module.__vsidgen_source_sha256__
    assert os.path.getsize(m2.module_path) < 100     # the file was swapped; the module is right
