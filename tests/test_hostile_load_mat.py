"""Hostile specs and MATLAB files that cost vsidgen time, stack or memory.

* a spec with tens of thousands of entries is read in time linear in its size (every
  node once showed its source line by splitting the whole file again);
* a long ``extends`` chain is refused at the ``extends`` line that makes it too long
  (it ran out of Python stack and was reported as "YAML nesting is too deep");
* MATLAB files: a v7.3 cell that references itself, datasets declared far larger than
  the file (never written, a compressed fill value), deep or cyclic struct groups, and
  large variables of a compressed v7 file that the data map does not name -- each is
  refused with a DataError naming the variable, or not read at all.

The huge arrays are declared (HDF5 shapes, a zlib stream fed with zeros piecewise),
never allocated.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import struct
import subprocess
import sys
import tracemalloc
import zlib

import numpy as np
import pytest

from vsidgen.data import formats
from vsidgen.data.formats import DataFormat, read_mat_columns
from vsidgen.errors import DataError, SpecError
from vsidgen.spec.load import MAX_EXTENDS_DEPTH, load_spec
from vsidgen.spec.typed import read_spec

h5py = pytest.importorskip("h5py")
scipy_io = pytest.importorskip("scipy.io")

ROOT = pathlib.Path(__file__).resolve().parents[1]
SPEC = ROOT / "specs" / "attas_sp.yaml"
REFS = ["t_s", "de_rad", "alpha_rad", "q_radps"]


# --------------------------------------------------------------------------- D1: big specs

def _many_parameters(path: pathlib.Path, n: int) -> pathlib.Path:
    lines = ["name: big", "states:", "  x1: {unit: '1'}", "inputs:", "  u1: {unit: '1'}",
             "outputs:", "  y0: {unit: '1'}", "parameters:"]
    lines += [f"  p{i}: {{}}" for i in range(n)]
    lines += ["drift: {x1: p0*x1 + u1}", "observations: {y0: x1}",
              "data:", "  time: t", "  inputs: {u1: u}", "  outputs: {y0: y}"]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _characters_split(fn) -> int:
    """Characters of the texts that ``str.splitlines`` was called on while ``fn`` ran."""
    total = 0

    def hook(frame, event, arg):
        nonlocal total
        if event == "c_call" and getattr(arg, "__name__", "") == "splitlines":
            owner = getattr(arg, "__self__", None)
            if isinstance(owner, str):
                total += len(owner)

    sys.setprofile(hook)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return total


def test_reading_a_spec_splits_its_text_into_lines_once(tmp_path):
    """Reading a spec with 2000 parameters (the most a spec may have since session 47) splits
    its text a bounded number of times, not once or more per entry (that made a 250 KB spec
    take 1.5 min, a 750 KB one > 5)."""
    spec = _many_parameters(tmp_path / "big.yaml", 2000)
    size = spec.stat().st_size
    split = _characters_split(lambda: read_spec(spec, generator_version="test"))
    assert split <= 3 * size, f"split {split} characters of a {size}-character spec"


def test_big_spec_reads(tmp_path):
    spec = read_spec(_many_parameters(tmp_path / "big.yaml", 2000), generator_version="test")
    assert len(spec.parameters) == 2000
    assert spec.parameters[-1].name.key_line == 2008
    assert spec.parameters[-1].name.key_text == "p1999: {}"
    with pytest.raises(SpecError, match="more than 2000 parameters"):
        read_spec(_many_parameters(tmp_path / "bigger.yaml", 2001), generator_version="test")


# --------------------------------------------------------------------------- D3: extends chains

def _chain(folder: pathlib.Path, n: int) -> pathlib.Path:
    """c0.yaml (the ATTAS short-period spec) and c{i}.yaml extending c{i-1}.yaml; the top."""
    shutil.copy(SPEC, folder / "c0.yaml")
    for i in range(1, n):
        (folder / f"c{i}.yaml").write_text(f"extends: c{i - 1}.yaml\nname: attas_sp\n",
                                           encoding="utf-8")
    return folder / f"c{n - 1}.yaml"


def test_extends_chain_of_ten_specs_is_read(tmp_path):
    top = _chain(tmp_path, 10)
    spec = read_spec(top, generator_version="test")
    assert len(spec.files) == 10
    assert [p.name for p in spec.files][:2] == ["c0.yaml", "c1.yaml"]


def test_extends_chain_at_the_limit_is_read(tmp_path):
    top = _chain(tmp_path, MAX_EXTENDS_DEPTH)
    assert len(load_spec(top).files) == MAX_EXTENDS_DEPTH


@pytest.mark.parametrize("n", [MAX_EXTENDS_DEPTH + 1, 40, 1500])
def test_extends_chain_too_long_is_a_located_error(tmp_path, n):
    top = _chain(tmp_path, n)
    with pytest.raises(SpecError) as info:
        load_spec(top)
    err = info.value
    # the spec at the limit: its `extends` line would add one spec too many
    culprit = n - MAX_EXTENDS_DEPTH
    assert pathlib.Path(err.path).name == f"c{culprit}.yaml"
    assert (err.line, err.column) == (1, 10)
    assert err.text == f"extends: c{culprit - 1}.yaml"
    assert "`extends` chain is longer than" in err.message and str(MAX_EXTENDS_DEPTH) in err.message
    assert "nesting" not in err.message
    assert err.hint


def test_extends_cycle_still_located(tmp_path):
    (tmp_path / "a.yaml").write_text("extends: b.yaml\nname: a\n", encoding="utf-8")
    (tmp_path / "b.yaml").write_text("extends: a.yaml\nname: b\n", encoding="utf-8")
    with pytest.raises(SpecError) as info:
        load_spec(tmp_path / "a.yaml")
    err = info.value
    assert pathlib.Path(err.path).name == "b.yaml" and err.line == 1
    assert "cycle: a.yaml -> b.yaml -> a.yaml" in err.message


# --------------------------------------------------------------------------- D4: MAT files

def _record(n: int = 50) -> dict[str, np.ndarray]:
    t = np.arange(n) * 0.04
    return {"t_s": t, "de_rad": 0.01 * np.sin(t), "alpha_rad": 0.02 * np.cos(t),
            "q_radps": 0.001 * t}


def _v73(path: pathlib.Path, skip=()):
    """A MATLAB v7.3 file (HDF5 after a 512-byte user block) with the record's vectors."""
    f = h5py.File(path, "w", userblock_size=512)
    for name, v in _record().items():
        if name in skip:
            continue
        d = f.create_dataset(name, data=v[None, :])
        d.attrs["MATLAB_class"] = np.bytes_("double")
    return f


def _read(path, refs=REFS, fmt=DataFormat.MAT73):
    return read_mat_columns(path, refs, fmt)


def test_v73_record_reads(tmp_path):
    _v73(tmp_path / "ok.mat").close()
    cols = _read(tmp_path / "ok.mat")
    assert np.allclose(cols["alpha_rad"], _record()["alpha_rad"])


def test_v73_self_referencing_cell(tmp_path):
    path = tmp_path / "selfref.mat"
    with _v73(path) as f:
        d = f.create_dataset("alpha_rad_names", (1, 1), dtype=h5py.ref_dtype)
        d[0, 0] = d.ref
        d.attrs["MATLAB_class"] = np.bytes_("cell")
    with pytest.raises(DataError) as info:
        _read(path)
    assert "alpha_rad_names" in info.value.message
    assert "contains it" in info.value.message


def test_v73_mutually_referencing_cells(tmp_path):
    path = tmp_path / "mutual.mat"
    with _v73(path) as f:
        a = f.create_dataset("a", (1, 1), dtype=h5py.ref_dtype)
        b = f.create_dataset("b", (1, 2), dtype=h5py.ref_dtype)
        a[0, 0] = b.ref
        b[0, 0] = a.ref
        b[0, 1] = f["t_s"].ref
        a.attrs["MATLAB_class"] = b.attrs["MATLAB_class"] = np.bytes_("cell")
    with pytest.raises(DataError) as info:
        _read(path, ["b"])
    assert "reference cycle in variable 'b'" in info.value.message


def test_v73_group_containing_itself(tmp_path):
    path = tmp_path / "loop.mat"
    with _v73(path) as f:
        g = f.create_group("s")
        g["x"] = np.zeros((1, 50))
        g["again"] = g  # a hard link to the group inside itself
    with pytest.raises(DataError) as info:
        _read(path, ["s.x"])
    assert "'s.again'" in info.value.message and "contains it" in info.value.message


def test_v73_deeply_nested_groups(tmp_path):
    path = tmp_path / "deep.mat"
    with _v73(path) as f:
        g = f
        for _ in range(formats.MAX_MAT_NESTING + 8):
            g = g.create_group("s")
    with pytest.raises(DataError) as info:
        _read(path, ["s.s"])
    assert f"more than {formats.MAX_MAT_NESTING} levels deep" in info.value.message
    assert "variable 's'" in info.value.message
    # a missing reference still gets its "not found" message, the deep group is only named
    with pytest.raises(DataError) as info:
        _read(path, ["alpha_radx"])
    assert "not found" in info.value.message and "alpha_rad" in info.value.hint


def test_v73_cell_with_too_many_elements(tmp_path, monkeypatch):
    path = tmp_path / "many.mat"
    with _v73(path) as f:
        d = f.create_dataset("alpha_rad_names", (1, 200), dtype=h5py.ref_dtype)
        d[0, :] = [f["t_s"].ref] * 200
        d.attrs["MATLAB_class"] = np.bytes_("cell")
    monkeypatch.setattr(formats, "MAX_MAT_OBJECTS", 100)
    with pytest.raises(DataError) as info:
        _read(path)
    assert "more than 100 MATLAB arrays" in info.value.message
    assert "alpha_rad_names{" in info.value.message


@pytest.mark.parametrize("cls,dtype,size", [("double", "f8", "14.9 GiB"),
                                            ("char", "u2", "3.7 GiB")])
def test_v73_dataset_declared_huge(tmp_path, monkeypatch, cls, dtype, size):
    """A 2e9-element dataset, gzip-chunked and never written: a file of a few KiB that
    would make h5py allocate gigabytes of fill values."""
    monkeypatch.delenv("VSIDGEN_MAX_DATA_BYTES", raising=False)  # the default, 2 GiB
    path = tmp_path / "bomb.mat"
    with _v73(path, skip=("alpha_rad",)) as f:
        d = f.create_dataset("alpha_rad", shape=(1, 2_000_000_000), dtype=dtype,
                             chunks=(1, 1_000_000), compression="gzip")
        d.attrs["MATLAB_class"] = np.bytes_(cls)
    assert path.stat().st_size < 100_000
    with pytest.raises(DataError) as info:
        _read(path)
    msg = info.value.message
    assert f"variable 'alpha_rad' (2000000000x1 {cls}) is {size} uncompressed" in msg
    assert "more than the limit of 2 GiB" in msg
    assert "VSIDGEN_MAX_DATA_BYTES" in info.value.hint


def test_v73_limit_follows_the_environment(tmp_path, monkeypatch):
    _v73(tmp_path / "ok.mat").close()
    monkeypatch.setenv("VSIDGEN_MAX_DATA_BYTES", "1000")  # 50 doubles each: 400 bytes
    with pytest.raises(DataError) as info:
        _read(tmp_path / "ok.mat")
    assert "'alpha_rad' (50x1 double) is 400 bytes uncompressed, more than the 200 bytes " \
           "left of the limit of 1000 bytes" in info.value.message


# v5/v7 files: elements written by hand, so that a large variable is a zlib stream of
# zeros produced piecewise, never an array in memory

def _tagged(mdtype: int, payload: bytes) -> bytes:
    pad = -len(payload) % 8
    return struct.pack("<II", mdtype, len(payload)) + payload + b"\0" * pad


def _compressed_zeros(name: str, n: int) -> bytes:
    """A MAT v5 miCOMPRESSED element holding a 1 x n double row of zeros."""
    data_bytes = 8 * n
    head = (_tagged(6, struct.pack("<II", 6, 0))          # array flags: mxDOUBLE_CLASS
            + _tagged(5, struct.pack("<ii", 1, n))        # dimensions 1 x n
            + _tagged(1, name.encode()))                  # name
    body_len = len(head) + 8 + data_bytes + (-data_bytes % 8)
    c = zlib.compressobj(1)
    parts = [c.compress(struct.pack("<II", 14, body_len) + head
                        + struct.pack("<II", 9, data_bytes))]
    block = bytes(1 << 20)
    left = data_bytes
    while left:
        k = min(left, len(block))
        parts.append(c.compress(block[:k]))
        left -= k
    parts.append(c.flush())
    z = b"".join(parts)
    return struct.pack("<II", 15, len(z)) + z


def _v7_with_junk(path: pathlib.Path, junk_values: int) -> None:
    scipy_io.savemat(path, _record(), do_compression=True)
    with open(path, "ab") as fh:
        fh.write(_compressed_zeros("junk", junk_values))


def test_v7_hand_built_variable_is_readable(tmp_path):
    path = tmp_path / "junk.mat"
    _v7_with_junk(path, 50)
    assert ("junk", (1, 50), "double") in scipy_io.whosmat(path)
    cols = read_mat_columns(path, ["junk", "t_s"], DataFormat.MAT)
    assert cols["junk"].shape == (50,) and not cols["junk"].any()


def test_v7_reads_only_the_variables_of_the_data_map(tmp_path):
    """A 64 MB variable the data map does not name (compressed to ~300 KB) is not read."""
    path = tmp_path / "junk.mat"
    _v7_with_junk(path, 8_000_000)
    assert path.stat().st_size < 1_000_000
    tracemalloc.start()
    try:
        cols = read_mat_columns(path, REFS, DataFormat.MAT)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert np.allclose(cols["q_radps"], _record()["q_radps"])
    assert peak < 16_000_000, f"peak {peak} bytes"


def test_v7_variable_over_the_limit(tmp_path, monkeypatch):
    path = tmp_path / "junk.mat"
    _v7_with_junk(path, 1_000_000)  # 8 MB uncompressed
    monkeypatch.setenv("VSIDGEN_MAX_DATA_BYTES", "4M")
    with pytest.raises(DataError) as info:
        read_mat_columns(path, ["t_s", "junk"], DataFormat.MAT)
    msg = info.value.message
    assert "variable 'junk' (1x1000000 double) is more than" in msg
    assert "uncompressed" in msg and "limit of 4 MiB" in msg
    # not needed: not read, and named among the file's variables when a name is wrong
    assert set(read_mat_columns(path, REFS, DataFormat.MAT)) == set(REFS)
    with pytest.raises(DataError) as info:
        read_mat_columns(path, ["t_s", "alpha_radx"], DataFormat.MAT)
    assert "not found" in info.value.message and "alpha_rad" in info.value.hint


def test_v5_plain_file_still_reads(tmp_path):
    path = tmp_path / "plain.mat"
    rec = _record()
    scipy_io.savemat(path, {**rec, "X": np.column_stack([rec["de_rad"], rec["q_radps"]]),
                            "X_names": np.array(["de", "q"], dtype=object),
                            "s": {"a": rec["alpha_rad"]}})
    cols = read_mat_columns(path, ["t_s", "de", "s.a", "X(:,2)"], DataFormat.MAT)
    assert np.allclose(cols["de"], rec["de_rad"])
    assert np.allclose(cols["s.a"], rec["alpha_rad"])
    assert np.allclose(cols["X(:,2)"], rec["q_radps"])


def test_cli_check_refuses_self_referencing_mat(tmp_path):
    """Through the command line: exit 2 with the file and the variable, no traceback."""
    path = tmp_path / "selfref.mat"
    with _v73(path) as f:
        d = f.create_dataset("alpha_rad_names", (1, 1), dtype=h5py.ref_dtype)
        d[0, 0] = d.ref
        d.attrs["MATLAB_class"] = np.bytes_("cell")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("VSIDGEN_DEBUG", None)
    proc = subprocess.run([sys.executable, "-m", "vsidgen.cli", "check", str(SPEC), "--data",
                           str(path)], capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 2, proc.stderr
    assert "selfref.mat" in proc.stderr and "alpha_rad_names" in proc.stderr
    assert "Traceback" not in proc.stderr and "internal error" not in proc.stderr
