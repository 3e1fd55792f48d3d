"""The one .npy/.npz reader: headers checked before allocation, exact sizes, chunked reads, and
every archive or decompressor failure one line of the caller's error class."""

from __future__ import annotations

import io
import lzma
import pickle
import struct
import tokenize
import tracemalloc
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from numpy.lib import format as npformat

from archives import zip_bytes
from humimic.errors import InputError, MotionDataError
from humimic.npyio import (
    MAX_HEADER_BYTES,
    READ_CHUNK,
    READ_ERRORS,
    read_array,
    read_npy_file,
    read_npz_members,
)

GIB = 1 << 30


class CallerError(InputError):
    """A caller's own error class, to check that it is the one raised."""


def _header(shape: tuple[int, ...], descr: str = "<f8", fortran: bool = False) -> bytes:
    buf = io.BytesIO()
    npformat.write_array_header_1_0(buf, {"descr": descr, "fortran_order": fortran, "shape": shape})
    return buf.getvalue()


def _raw(text: bytes, version: int = 1) -> bytes:
    """A ``.npy`` header holding ``text`` as is."""
    size = len(text).to_bytes(2 if version == 1 else 4, "little")
    return b"\x93NUMPY" + bytes([version, 0]) + size + text


def _npy(array: np.ndarray, version: tuple[int, int] | None = None) -> bytes:
    buf = io.BytesIO()
    npformat.write_array(buf, array, version=version, allow_pickle=False)
    return buf.getvalue()


def _read(data: bytes, kinds: str = "biufU", max_bytes: int = GIB) -> np.ndarray:
    return read_array(
        io.BytesIO(data), len(data), "x.npy", max_bytes=max_bytes, kinds=kinds, error=CallerError
    )


def _refused(data: bytes, *needles: str, kinds: str = "biufU", max_bytes: int = GIB) -> str:
    with pytest.raises(CallerError) as e:
        _read(data, kinds, max_bytes)
    message = str(e.value)
    assert message.startswith("x.npy: ") and "\n" not in message, message
    for needle in needles:
        assert needle in message, (needle, message)
    return message


def _peak(fn: Callable[[], object]) -> int:
    """The peak of traced allocations while ``fn`` runs (it must raise an InputError)."""
    tracemalloc.start()
    try:
        with pytest.raises(InputError):
            fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


# ------------------------------------------------------------------ sizes before allocation


def test_a_header_claiming_more_than_the_file_holds_is_refused_without_allocating(
    tmp_path: Path,
) -> None:
    path = tmp_path / "liar.npy"
    path.write_bytes(_header((10**6, 53, 3)) + b"\0" * 8)  # Claims 1.2 GiB, under the cap.
    read = lambda: read_npy_file(path, max_bytes=2 * GIB, kinds="f")  # noqa: E731
    assert _peak(read) < 2**20
    with pytest.raises(
        MotionDataError,
        match=r"liar\.npy: truncated: header says shape \(1000000"
        r", 53, 3\) of float64 \(1272000000 bytes\)",
    ):
        read()


def test_a_header_over_the_callers_cap_is_refused_before_reading(tmp_path: Path) -> None:
    path = tmp_path / "big.npy"
    path.write_bytes(_header((10**11, 53, 3)))  # No data: the header alone decides.
    read = lambda: read_npy_file(path, max_bytes=GIB, kinds="f", error=CallerError)  # noqa: E731
    assert _peak(read) < 2**20
    with pytest.raises(
        CallerError,
        match=r"big\.npy: header claims shape \(100000000000, 53, "
        r"3\) of float64 \(1.18e\+05 GiB\), over the 1 GiB",
    ):
        read()
    small = _npy(np.zeros(100))
    _refused(
        small,
        "header claims shape (100,) of float64 (800 bytes), over the 799 bytes limit",
        max_bytes=799,
    )
    assert _read(small, max_bytes=800).shape == (100,)


def test_truncated_and_overlong_arrays(tmp_path: Path) -> None:
    good = _npy(np.arange(12.0).reshape(3, 4))
    _refused(good[:-1], "truncated: header says shape (3, 4) of float64 (96 bytes), but 95 bytes")
    _refused(good + b"\0", "longer than its header says", "97 bytes of data")
    for cut in (0, 5, 9, 40):  # Inside the magic, the length field, the header text.
        _refused(good[:cut], ".npy")
    _refused(b"PK\x03\x04 not an array", "not an .npy array")
    # A stream that ends before the size it was said to have (a zip member's claim).
    with pytest.raises(CallerError, match=r"x\.npy: truncated: 48 of 96 bytes of data"):
        read_array(
            io.BytesIO(good[:-48]), len(good), "x.npy", max_bytes=GIB, kinds="f", error=CallerError
        )


# ----------------------------------------------------------------------- headers and dtypes


def test_object_arrays_are_refused_and_never_unpickled(tmp_path: Path) -> None:
    marker = tmp_path / "unpickled"

    class Payload:
        def __reduce__(self) -> tuple[Callable[..., object], tuple[str]]:
            return (Path.mkdir, (str(marker),))  # type: ignore[return-value]

    buf = io.BytesIO()
    np.save(buf, np.array([Payload()], dtype=object), allow_pickle=True)
    assert pickle.loads(pickle.dumps(Payload())) is None and marker.is_dir()  # It would act.
    marker.rmdir()
    message = _refused(buf.getvalue(), "holds Python objects (a pickle)", "expected numbers")
    assert not marker.exists(), message
    npz = tmp_path / "o.npz"
    npz.write_bytes(zip_bytes({"a.npy": buf.getvalue()}))
    with pytest.raises(CallerError, match=r"o\.npz: array 'a': holds Python objects"):
        read_npz_members(npz, max_bytes=GIB, kinds="f", error=CallerError)
    assert not marker.exists()


@pytest.mark.parametrize(
    ("header", "needle"),
    [
        (_raw(b"{'descr': [('a', '<f8')], 'fortran_order': False, 'shape': (2,), }"), "records"),
        (_raw(b"{'descr': '(3,)<f8', 'fortran_order': False, 'shape': (2,), }"), "subarrays"),
        (_raw(b"{'descr': '<U0', 'fortran_order': False, 'shape': (2,), }"), "empty items"),
        (_raw(b"{'descr': '<q99', 'fortran_order': False, 'shape': (2,), }"), "unknown dtype"),
        (_raw(b"{'descr': '<f8', 'fortran_order': 'yes', 'shape': (2,), }"), "fortran_order"),
        (_raw(b"{'descr': '<f8', 'fortran_order': False, 'shape': (-2,), }"), "not a tuple"),
        (_raw(b"{'descr': '<f8', 'fortran_order': False, 'shape': (2.0,), }"), "not a tuple"),
        (_raw(b"{'descr': '<f8', 'fortran_order': False, 'shape': (True,), }"), "not a tuple"),
        (
            _raw(b"{'descr': '<f8', 'fortran_order': False, 'shape': (" + b"1, " * 17 + b"), }"),
            "17 dimensions, at most 16",
        ),
        (_raw(b"{'descr': '<f8', 'shape': (2,), }"), "must be a dict of descr"),
        (_raw(b"[1, 2, 3]"), "must be a dict of descr"),
        (_raw(b"(" * 5000 + b")" * 5000), "not a valid .npy header"),
        (_raw(b"- " * 4000 + b"1"), "not a valid .npy header"),
        (_raw(b"__import__('os')"), "not a valid .npy header"),
        (_raw(b"\xff\xfe{", version=3), "not a valid .npy header (UnicodeDecodeError"),
        (_raw(b" " * (MAX_HEADER_BYTES + 1), version=2), f"at most {MAX_HEADER_BYTES} are read"),
        (b"\x93NUMPY\x09\x00\x10\x00" + b" " * 16, "unsupported .npy format version 9.0"),
        (b"\x93NUMPY\x01\x01\x10\x00" + b" " * 16, "unsupported .npy format version 1.1"),
    ],
)
def test_bad_headers_are_refused(header: bytes, needle: str) -> None:
    _refused(header + b"\0" * 64, needle)


@pytest.mark.parametrize(
    "array",
    [
        np.asfortranarray(np.arange(24.0).reshape(2, 3, 4)),
        np.arange(24.0).reshape(2, 3, 4).astype(">f8"),
        np.asfortranarray(np.arange(24, dtype=">i4").reshape(4, 6)),
        np.array(["a", "bé", "ccc"]),
        np.array(["x", "y"]).astype(">U2"),
        np.array([[True, False], [False, True]]),
        np.zeros((0, 53, 3), np.float32),
        np.array(3.5),
        np.arange(6, dtype=np.uint16),
    ],
    ids=[
        "fortran",
        "big-endian",
        "fortran-big-endian-int",
        "str",
        "big-endian-str",
        "bool",
        "zero-frames",
        "scalar",
        "uint16",
    ],
)
@pytest.mark.parametrize("version", [(1, 0), (2, 0), (3, 0)])
def test_arrays_read_exactly(tmp_path: Path, array: np.ndarray, version: tuple[int, int]) -> None:
    data = _npy(array, version)
    got = _read(data)
    assert got.dtype == array.dtype and got.shape == array.shape
    assert got.flags.f_contiguous == np.load(io.BytesIO(data)).flags.f_contiguous
    assert got.flags.writeable
    np.testing.assert_array_equal(got, array)
    path = tmp_path / "a.npy"
    path.write_bytes(data)
    np.testing.assert_array_equal(read_npy_file(path, max_bytes=GIB, kinds="biufU"), array)
    npz = tmp_path / "a.npz"
    np.savez_compressed(npz, a=array, b=np.zeros(2))
    out = read_npz_members(npz, max_bytes=GIB, kinds="biufU")
    assert list(out) == ["a", "b"] and out["a"].dtype == array.dtype
    np.testing.assert_array_equal(out["a"], array)


def test_kinds_filter() -> None:
    flags = _npy(np.array([True, False]))
    names = _npy(np.array(["a", "b"]))
    assert _read(flags, kinds="b").dtype == bool
    _refused(flags, "dtype bool is not supported; expected numbers", kinds="iuf")
    _refused(flags, "dtype bool is not supported; expected numbers or strings", kinds="iufU")
    _refused(names, "dtype <U1 is not supported; expected numbers or byte strings", kinds="iufS")
    assert _read(names, kinds="U").tolist() == ["a", "b"]
    _refused(_npy(np.ones(2, complex)), "expected numbers, booleans or strings")
    _refused(_npy(np.ones(2, "M8[s]")), "dtype datetime64[s] is not supported")
    _refused(_npy(np.zeros(2, "V8")), "dtype |V8 is not supported")
    for kinds in ("", "fO", "V"):  # Objects and records are never a caller's choice.
        with pytest.raises(ValueError, match="kinds"):
            _read(flags, kinds=kinds)


# ----------------------------------------------------------------------------------- archives


def _patch_sizes(archive: bytes, claimed: int) -> bytes:
    """The archive (one member) with both size fields of its local header and central
    directory entry set to ``claimed``."""
    raw = bytearray(archive)
    central = raw.index(b"PK\x01\x02")
    for offset in (18, 22):
        raw[offset : offset + 4] = claimed.to_bytes(4, "little")
    for offset in (20, 24):
        raw[central + offset : central + offset + 4] = claimed.to_bytes(4, "little")
    return bytes(raw)


def test_a_zip_member_whose_directory_lies_about_its_size(tmp_path: Path) -> None:
    frames = 10**6  # 1.2 GiB claimed, under the cap; the archive holds a few bytes.
    header = _header((frames, 53, 3))
    claimed = len(header) + frames * 53 * 3 * 8
    path = tmp_path / "liar.npz"
    path.write_bytes(_patch_sizes(zip_bytes({"positions.npy": header + b"\0" * 8}), claimed))
    read = lambda: read_npz_members(path, max_bytes=2 * GIB, kinds="f", error=CallerError)  # noqa: E731
    # Memory follows the bytes really there (one chunk at most), not the claim.
    assert _peak(read) < READ_CHUNK + 16 * 2**20
    with pytest.raises(CallerError, match=r"liar\.npz: array 'positions': cannot read \(EOFError"):
        read()
    # The archive's declared total is checked before any member is read.
    with pytest.raises(CallerError, match=r"liar\.npz: the archive declares \d+ bytes of arrays"):
        read_npz_members(path, max_bytes=GIB, kinds="f", error=CallerError)


def test_members_must_match_their_declared_size(tmp_path: Path) -> None:
    data = _npy(np.arange(4.0))
    path = tmp_path / "long.npz"
    path.write_bytes(zip_bytes({"a.npy": data + b"\0" * 8}))
    with pytest.raises(CallerError, match=r"long\.npz: array 'a': longer than its header says"):
        read_npz_members(path, max_bytes=GIB, kinds="f", error=CallerError)
    path.write_bytes(zip_bytes({"a.npy": data[:-8]}))
    with pytest.raises(CallerError, match=r"long\.npz: array 'a': truncated: header says"):
        read_npz_members(path, max_bytes=GIB, kinds="f", error=CallerError)


def test_keys_duplicates_and_stray_members(tmp_path: Path) -> None:
    good, bad = _npy(np.arange(3.0)), b"\x93NUMPY garbage"
    path = tmp_path / "a.npz"
    path.write_bytes(zip_bytes({"a.npy": good, "junk.npy": bad, "notes.txt": b"hi"}))
    # Only the wanted keys are read: the broken and stray members are never touched.
    out = read_npz_members(path, ["a", "absent"], max_bytes=GIB, kinds="f")
    assert list(out) == ["a"] and out["a"].tolist() == [0.0, 1.0, 2.0]
    assert read_npz_members(path, [], max_bytes=GIB, kinds="f") == {}
    with pytest.raises(MotionDataError, match=r"a\.npz: member 'notes\.txt' is not an \.npy"):
        read_npz_members(path, max_bytes=GIB, kinds="f")
    with pytest.raises(
        MotionDataError, match=r"a\.npz: array 'junk': unsupported \.npy format version"
    ):
        read_npz_members(path, ["junk"], max_bytes=GIB, kinds="f")
    with pytest.raises(CallerError, match=r"a\.npz: missing key\(s\) \['pos'\]; found keys: 'a'"):
        read_npz_members(path, ["a"], max_bytes=GIB, kinds="f", error=CallerError, required=["pos"])
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z, pytest.warns(UserWarning, match="Duplicate"):
        z.writestr("a.npy", good)
        z.writestr("a.npy", good)
    twice = tmp_path / "twice.npz"
    twice.write_bytes(buf.getvalue())
    with pytest.raises(CallerError, match=r"twice\.npz: key 'a' appears twice"):
        read_npz_members(twice, ["a"], max_bytes=GIB, kinds="f", error=CallerError)
    both = tmp_path / "both.npz"
    both.write_bytes(zip_bytes({"a.npy": good, "a": good}))
    with pytest.raises(CallerError, match=r"both\.npz: key 'a' appears twice"):
        read_npz_members(both, ["a"], max_bytes=GIB, kinds="f", error=CallerError)


def _corrupt(path: Path, kind: str) -> None:
    """An archive of one member ``a.npy`` broken the way ``kind`` says."""
    data = _npy(np.arange(64.0))
    method = {"lzma": zipfile.ZIP_LZMA, "bz2": zipfile.ZIP_BZIP2, "deflate": zipfile.ZIP_DEFLATED}
    raw = bytearray(zip_bytes({"a.npy": data}, method.get(kind, zipfile.ZIP_STORED)))
    central = raw.index(b"PK\x01\x02")
    if kind == "encrypted":
        raw[central + 8] |= 1  # General purpose flag bit 0.
    elif kind == "method":
        raw[central + 10 : central + 12] = (99).to_bytes(2, "little")
    elif kind == "crc":
        raw[14] ^= 1
        raw[central + 16] ^= 1
    elif kind in method:  # Garble the compressed bytes (after the 30-byte header, the name
        # and, for LZMA, 9 bytes of version and properties).
        start = 30 + len("a.npy") + 9
        raw[start : start + 31] = b"\xff" * 31
    elif kind == "cut":
        raw = raw[: len(raw) // 2]
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize(
    ("kind", "exception"),
    [
        ("encrypted", "RuntimeError"),
        ("method", "NotImplementedError"),
        ("crc", "BadZipFile"),
        ("deflate", "error"),  # zlib.error
        ("lzma", "LZMAError"),
        ("bz2", "OSError"),
        ("cut", "BadZipFile"),
    ],
)
def test_broken_archives_become_the_callers_error(
    tmp_path: Path, kind: str, exception: str
) -> None:
    path = tmp_path / f"{kind}.npz"
    _corrupt(path, kind)
    with pytest.raises(CallerError) as e:
        read_npz_members(path, max_bytes=GIB, kinds="f", error=CallerError)
    message = str(e.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message
    assert f"({exception}:" in message, message
    if kind != "cut":
        assert message.startswith(f"{path}: array 'a': cannot read"), message


_RAISED = [
    zipfile.BadZipFile("bad zip"),
    zipfile.LargeZipFile("too large"),
    zlib.error("invalid block"),
    lzma.LZMAError("corrupt"),
    NotImplementedError("method"),
    RuntimeError("encrypted"),
    EOFError(),
    OSError(5, "Input/output error"),
    struct.error("unpack"),
    OverflowError("big"),
    MemoryError(),
    tokenize.TokenError("EOF in multi-line statement", (1, 0)),
    RecursionError("deep"),
    ValueError("negative seek"),
    UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte"),
]


def test_every_read_error_is_listed() -> None:
    for e in _RAISED:
        assert isinstance(e, READ_ERRORS), type(e)


class _Failing(io.BytesIO):
    """A stream that raises ``error`` once ``after`` bytes have been read."""

    def __init__(self, data: bytes, after: int, error: BaseException) -> None:
        super().__init__(data)
        self.after, self.error = after, error

    def read(self, n: int | None = -1) -> bytes:
        if self.tell() >= self.after:
            raise self.error
        return super().read(n)


@pytest.mark.parametrize("exc", _RAISED, ids=lambda e: type(e).__name__)
def test_every_exception_kind_becomes_the_callers_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, exc: BaseException
) -> None:
    data = _npy(np.arange(4.0))
    data_start = len(data) - 32
    for after in (0, data_start):  # In the header, then in the data.
        with pytest.raises(CallerError) as e:
            read_array(
                _Failing(data, after, exc),
                len(data),
                "f.npz: array 'q'",
                max_bytes=GIB,
                kinds="f",
                error=CallerError,
            )
        message = str(e.value)
        assert message.startswith(f"f.npz: array 'q': cannot read ({type(exc).__name__}")
        assert "\n" not in message
    path = tmp_path / "m.npz"
    path.write_bytes(zip_bytes({"q.npy": data}))

    def fail(*args: object, **kwargs: object) -> None:
        raise exc

    with monkeypatch.context() as m:  # Opening a member.
        m.setattr(zipfile.ZipFile, "open", fail)
        with pytest.raises(
            CallerError, match=rf"m\.npz: array 'q': cannot read \({type(exc).__name__}"
        ):
            read_npz_members(path, max_bytes=GIB, kinds="f", error=CallerError)
    with monkeypatch.context() as m:  # Reading the archive's directory.
        m.setattr(zipfile.ZipFile, "infolist", fail)
        with pytest.raises(
            CallerError, match=rf"m\.npz: not a readable \.npz archive \({type(exc).__name__}"
        ):
            read_npz_members(path, max_bytes=GIB, kinds="f", error=CallerError)
    assert read_npz_members(path, max_bytes=GIB, kinds="f")["q"].tolist() == [0, 1, 2, 3]


def test_files_that_are_not_what_they_should_be(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"nope\.npy: no such file"):
        read_npy_file(tmp_path / "nope.npy", max_bytes=GIB, kinds="f")
    with pytest.raises(InputError, match=r"nope\.npz: no such file"):
        read_npz_members(tmp_path / "nope.npz", max_bytes=GIB, kinds="f")
    with pytest.raises(InputError, match="is a folder"):
        read_npy_file(tmp_path, max_bytes=GIB, kinds="f")
    zipped = tmp_path / "z.npy"
    zipped.write_bytes(zip_bytes({"a.npy": _npy(np.zeros(2))}))
    with pytest.raises(CallerError, match=r"z\.npy: expected one \.npy array, found a \.npz"):
        read_npy_file(zipped, max_bytes=GIB, kinds="f", error=CallerError)
    text = tmp_path / "t.npz"
    text.write_text("not a zip")
    with pytest.raises(CallerError, match=r"t\.npz: not a readable \.npz archive \(BadZipFile"):
        read_npz_members(text, max_bytes=GIB, kinds="f", error=CallerError)
