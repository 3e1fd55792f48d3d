"""Pickles of data read without running anything they name (humimic.datapickle)."""

from __future__ import annotations

import pickle
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from byte_mutants import byte_mutants, read_or_refused
from humimic.datapickle import read_data_pickle
from humimic.errors import InputError

DATA = {
    "poses": np.linspace(0, 1, 12).reshape(3, 4),
    "ints": np.arange(5, dtype=np.int32),
    "flags": np.array([True, False]),
    "gender": np.array("female"),
    "names": ["pelvis", "left_hip"],
    "rate": np.float64(30.0),
    "nested": {"t": (1, 2.5, "x"), "none": None},
}


class _Ch:
    """A stand-in for chumpy's ``Ch`` (pickled as ``chumpy.ch.Ch``: its attributes, values in
    ``x``)."""

    def __init__(self, x: np.ndarray) -> None:
        self.x = x
        self._dirty_vars: set[str] = set()


_Ch.__module__, _Ch.__qualname__, _Ch.__name__ = "chumpy.ch", "Ch", "Ch"


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_plain_data_reads_as_pickle_load_reads_it(tmp_path: Path, protocol: int) -> None:
    path = tmp_path / "d.pkl"
    path.write_bytes(pickle.dumps(DATA, protocol=protocol))
    got = read_data_pickle(path)
    want = pickle.loads(path.read_bytes())
    assert isinstance(got, dict) and got.keys() == want.keys()
    for k in ("poses", "ints", "flags", "gender"):
        np.testing.assert_array_equal(got[k], want[k])
        assert got[k].dtype == want[k].dtype
    assert got["names"] == want["names"] and got["rate"] == 30.0
    assert got["nested"] == {"t": (1, 2.5, "x"), "none": None}


@pytest.mark.parametrize("protocol", [0, 2])
def test_sparse_matrices_become_dense_arrays(tmp_path: Path, protocol: int) -> None:
    rng = np.random.default_rng(0)
    dense = np.where(rng.random((5, 7)) < 0.3, rng.standard_normal((5, 7)), 0.0)
    path = tmp_path / "s.pkl"
    data = {"csc": sp.csc_matrix(dense), "csr": sp.csr_matrix(dense)}
    path.write_bytes(pickle.dumps(data, protocol=protocol))
    got = read_data_pickle(path)
    assert isinstance(got, dict)
    np.testing.assert_array_equal(got["csc"], dense)
    np.testing.assert_array_equal(got["csr"], dense)


@pytest.mark.parametrize("protocol", [0, 2])
def test_chumpy_arrays_become_their_values_without_chumpy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, protocol: int
) -> None:
    """SMPL's ``.pkl`` models hold chumpy ``Ch`` arrays (their values in ``x``). A stand-in
    module writes such a file; it is gone when the file is read."""
    mod = types.ModuleType("chumpy.ch")
    mod.Ch = _Ch  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "chumpy", types.ModuleType("chumpy"))
    monkeypatch.setitem(sys.modules, "chumpy.ch", mod)
    values = np.arange(6.0).reshape(2, 3)
    path = tmp_path / "c.pkl"
    path.write_bytes(pickle.dumps({"v_template": _Ch(values)}, protocol=protocol))
    monkeypatch.delitem(sys.modules, "chumpy.ch")
    monkeypatch.delitem(sys.modules, "chumpy")
    got = read_data_pickle(path)
    assert isinstance(got, dict)
    np.testing.assert_array_equal(got["v_template"], values)


def test_code_in_a_pickle_is_refused_and_never_run(tmp_path: Path) -> None:
    marker = tmp_path / "ran"

    class Touch:
        def __reduce__(self) -> tuple:
            return (Path.touch, (marker,))

    cases = {
        "reduce.pkl": pickle.dumps({"x": Touch()}),
        # os.system('touch ran') by hand, protocol 0: the function is refused before the call.
        "system.pkl": f"cos\nsystem\n(S'touch {marker}'\ntR.".encode(),
        "eval.pkl": b"cbuiltins\neval\n(S'1+1'\ntR.",
    }
    for name, raw in cases.items():
        path = tmp_path / name
        path.write_bytes(raw)
        with pytest.raises(InputError, match=rf"{name}: refused: it names \S+, which is not"):
            read_data_pickle(path)
    assert not marker.exists()


def test_bad_pickles_are_refused_naming_the_file(tmp_path: Path) -> None:
    text = tmp_path / "t.pkl"
    text.write_text("hello\n")
    with pytest.raises(InputError, match=r"t\.pkl: "):
        read_data_pickle(text)
    cut = tmp_path / "cut.pkl"
    cut.write_bytes(pickle.dumps(DATA, protocol=4)[:-30])
    with pytest.raises(InputError, match=r"cut\.pkl: not a readable pickle"):
        read_data_pickle(cut)
    with pytest.raises(InputError, match=r"none\.pkl: no such file"):
        read_data_pickle(tmp_path / "none.pkl")


def test_mutated_pickles_are_read_or_refused(tmp_path: Path) -> None:
    """Bytes flipped, cut out or put in: data, or an InputError; never another exception
    (2,100 mutants found none when the reader was written; a sample here)."""
    data = {**DATA, "J": sp.csc_matrix(np.eye(3))}
    seen = {"read": 0, "refused": 0}
    for protocol in (0, 2, 4):
        mutants = byte_mutants(pickle.dumps(data, protocol=protocol), protocol, 70)
        got = read_or_refused(mutants, tmp_path / "m.pkl", read_data_pickle, InputError)
        seen = {k: seen[k] + got[k] for k in seen}
    assert seen["read"] > 0 and seen["refused"] > 0, seen


def test_a_memo_index_is_not_an_allocation(tmp_path: Path) -> None:
    """``LONG_BINPUT`` with the largest index (protocol 2: push 1, memo it at 2**31 - 1, stop):
    read with a few kilobytes. The C unpickler grows a list to the index (16 GiB here); a
    mutated 2 KB file once took it 24 s."""
    import tracemalloc

    path = tmp_path / "memo.pkl"
    path.write_bytes(b"\x80\x02K\x01r\xff\xff\xff\x7f.")
    tracemalloc.start()
    try:
        assert read_data_pickle(path) == 1
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, peak
