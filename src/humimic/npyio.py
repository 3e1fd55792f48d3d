"""The one careful reader of NumPy ``.npy`` files and ``.npz`` archives: never a pickle, every
header checked before anything is allocated, memory that grows only with the bytes really there,
and every failure one :class:`~humimic.errors.InputError` line naming the file and the array.
"""

from __future__ import annotations

import ast
import lzma
import math
import os
import struct
import tokenize
import zipfile
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

from humimic.errors import InputError, MotionDataError
from humimic.io import check_input_file

MAX_HEADER_BYTES = 10_000
"""Longest ``.npy`` header read (numpy's own limit for untrusted files)."""
MAX_DIMS = 16
"""Most dimensions an array may have."""
READ_CHUNK = 64 << 20
"""Bytes read at a time, so that memory follows the data really there, not a claimed size."""

READ_ERRORS: tuple[type[BaseException], ...] = (
    zipfile.BadZipFile,  # Not a zip, a bad CRC, a local header that differs from the directory.
    zipfile.LargeZipFile,
    zlib.error,  # Corrupt deflate data.
    lzma.LZMAError,
    NotImplementedError,  # An unsupported compression method.
    RuntimeError,  # An encrypted member (a password is required).
    EOFError,  # A member that ends before the size its directory claims.
    OSError,  # bz2's corrupt data, a failing disk.
    struct.error,  # Truncated zip records.
    OverflowError,
    MemoryError,
    tokenize.TokenError,
    RecursionError,
    ValueError,  # Bad offsets, member names that are not UTF-8.
)
"""What reading an archive or its members may raise for a corrupt or hostile file; each is
turned into the caller's error class."""

_VERSIONS = {(1, 0): "<H", (2, 0): "<I", (3, 0): "<I"}  # Format version: header-length field.
_HEADER_KEYS = {"descr", "fortran_order", "shape"}
_MAGIC = b"\x93NUMPY"


@dataclass(frozen=True)
class _Header:
    shape: tuple[int, ...]
    fortran: bool
    dtype: np.dtype
    length: int  # Bytes of the magic, version, length field and header text.


def read_array(
    f: IO[bytes],
    size: int,
    where: str,
    *,
    max_bytes: int,
    kinds: str,
    error: type[InputError] = MotionDataError,
) -> np.ndarray:
    """Read one ``.npy`` array from ``f``, checking its header before allocating anything.

    The header must be format version 1.0, 2.0 or 3.0, at most :data:`MAX_HEADER_BYTES` long,
    a literal dict of exactly ``descr``, ``fortran_order`` and ``shape``, with at most
    :data:`MAX_DIMS` dimensions of sizes >= 0, and a dtype of one of ``kinds`` (never Python
    objects, records, subarrays or empty items). Its data must take at most ``max_bytes`` and
    exactly the ``size`` bytes that follow the header; they are then read in chunks of
    :data:`READ_CHUNK`, so a ``size`` that lies (a zip directory's claim) costs only the bytes
    really there.

    Args:
        f: A binary stream at the start of the ``.npy`` data (a file or a zip member).
        size: Bytes of ``f`` in all, header included.
        where: What messages name: the file, and the member of an archive.
        max_bytes: Most bytes of data the array may take.
        kinds: The dtype kinds accepted (``np.dtype.kind``), e.g. ``"iuf"`` for real numbers,
            ``"biufU"`` for numbers, booleans and strings.
        error: The class raised.

    Returns:
        The array, in the byte order and memory order stored (big-endian and Fortran-ordered
        arrays read exactly), writable.

    Raises:
        InputError: ``error``, with a one-line message starting with ``where``.
    """
    _check_kinds(kinds)
    try:
        header = _read_header(f, where, kinds, error)
        count = math.prod(header.shape)
        nbytes = count * header.dtype.itemsize
        described = f"shape {header.shape} of {header.dtype}"
        if nbytes > max_bytes:
            raise error(
                f"{where}: header claims {described} ({_amount(nbytes)}), over the "
                f"{_amount(max_bytes)} limit"
            )
        available = size - header.length
        if available < nbytes:
            raise error(
                f"{where}: truncated: header says {described} ({nbytes} bytes), but {available} "
                "bytes of data follow it"
            )
        if available > nbytes:
            raise error(
                f"{where}: longer than its header says: {described} is {nbytes} bytes, but "
                f"{available} bytes of data follow the header"
            )
        buf = bytearray()
        while len(buf) < nbytes:
            chunk = f.read(min(READ_CHUNK, nbytes - len(buf)))
            if not chunk:
                raise error(f"{where}: truncated: {len(buf)} of {nbytes} bytes of data")
            buf += chunk
        if f.read(1):  # Also makes a zip member check its CRC.
            raise error(f"{where}: longer than its header says: more than {nbytes} bytes of data")
    except READ_ERRORS as e:
        raise error(f"{where}: cannot read ({_detail(e)})") from None
    array = np.frombuffer(buf, dtype=header.dtype, count=count)
    return array.reshape(header.shape, order="F" if header.fortran else "C")


def read_npy_file(
    path: str | os.PathLike[str],
    *,
    max_bytes: int,
    kinds: str,
    error: type[InputError] = MotionDataError,
) -> np.ndarray:
    """Read one ``.npy`` file with :func:`read_array` (its size is the file's).

    Args:
        path: The file.
        max_bytes: Most bytes of data the array may take.
        kinds: The dtype kinds accepted, as for :func:`read_array`.
        error: The class raised for bad content.

    Returns:
        The array.

    Raises:
        InputError: No such file, a folder, or a file that cannot be opened.
        InputError: ``error``: a ``.npz`` archive, not an ``.npy`` array, or any problem
            :func:`read_array` finds; the message names the file.
    """
    p = Path(path)
    check_input_file(p, "an .npy file")
    try:
        f = p.open("rb")
    except OSError as e:
        raise InputError(f"{p}: cannot read: {e.strerror or _detail(e)}") from None
    with f:
        try:
            size = os.fstat(f.fileno()).st_size
            head = f.read(4)
            f.seek(0)
        except OSError as e:
            raise error(f"{p}: cannot read ({_detail(e)})") from None
        if head == b"PK\x03\x04":
            raise error(f"{p}: expected one .npy array, found a .npz (zip) archive")
        return read_array(f, size, str(p), max_bytes=max_bytes, kinds=kinds, error=error)


def read_npz_members(
    path: str | os.PathLike[str],
    keys: Iterable[str] | None = None,
    *,
    max_bytes: int,
    kinds: str,
    error: type[InputError] = MotionDataError,
    required: Iterable[str] = (),
) -> dict[str, np.ndarray]:
    """Read arrays of an ``.npz`` archive, each with :func:`read_array`, without pickle.

    A member's key is its name less ``.npy``, as :func:`numpy.load` names it. Before any array
    is read: no key may appear twice; with ``keys=None`` every member must be an ``.npy``
    (members besides the wanted keys are ignored otherwise); every key of ``required`` must be
    there; and the sizes that the zip directory declares for the members to read (headers
    included) must sum to at most ``max_bytes``. Each array's data must then be exactly its
    member's declared size less its header, and is read in chunks, so a directory that claims
    more than the archive holds costs only the bytes really there.

    Args:
        path: The archive.
        keys: The keys to read (those absent are left out of the result); None: every member.
        max_bytes: Most bytes the arrays read may take in all.
        kinds: The dtype kinds accepted, as for :func:`read_array`.
        error: The class raised for bad content.
        required: Keys that must be in the archive.

    Returns:
        The arrays by key, in the order of ``keys`` (or of the archive).

    Raises:
        InputError: No such file, or a folder.
        InputError: ``error``: not a readable zip archive, a repeated key, a member that is not
            an ``.npy``, a missing required key, too many bytes, or any problem
            :func:`read_array` finds; the message names the file and the key.
    """
    _check_kinds(kinds)
    p = Path(path)
    check_input_file(p, "an .npz archive")
    wanted_keys = None if keys is None else list(dict.fromkeys(keys))
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(p) as zf:
            members: dict[str, zipfile.ZipInfo] = {}
            for info in zf.infolist():
                name = info.filename
                key = name[: -len(".npy")] if name.endswith(".npy") else name
                if key in members:
                    raise error(f"{p}: key {key!r} appears twice")
                if wanted_keys is None and not name.endswith(".npy"):
                    raise error(f"{p}: member {name!r} is not an .npy array")
                members[key] = info
            missing = [k for k in required if k not in members]
            if missing:
                raise error(f"{p}: missing key(s) {missing}; found keys: {_listing(members)}")
            wanted = list(members) if wanted_keys is None else wanted_keys
            wanted = [k for k in wanted if k in members]
            declared = sum(members[k].file_size for k in wanted)
            if declared > max_bytes:
                raise error(
                    f"{p}: the archive declares {declared} bytes of arrays, more than the "
                    f"{_amount(max_bytes)} limit"
                )
            for key in wanted:
                info = members[key]
                where = f"{p}: array {key!r}"
                try:
                    with zf.open(info) as f:
                        out[key] = read_array(
                            f, info.file_size, where, max_bytes=max_bytes, kinds=kinds, error=error
                        )
                except READ_ERRORS as e:
                    raise error(f"{where}: cannot read ({_detail(e)})") from None
    except READ_ERRORS as e:
        raise error(f"{p}: not a readable .npz archive ({_detail(e)})") from None
    return out


def npz_keys(path: str | os.PathLike[str]) -> set[str]:
    """The array keys of an ``.npz`` archive (its ``.npy`` members, less the suffix), read from
    its zip directory only; empty for a file no reader here could open. For telling the
    kinds of ``.npz`` apart before reading one."""
    try:
        with zipfile.ZipFile(path) as zf:
            return {n[: -len(".npy")] for n in zf.namelist() if n.endswith(".npy")}
    except READ_ERRORS:
        return set()


def _read_header(f: IO[bytes], where: str, kinds: str, error: type[InputError]) -> _Header:
    """The magic, version, length and dict of a ``.npy`` header, every field checked."""
    magic = f.read(8)
    if len(magic) < 8 or magic[:6] != _MAGIC:
        raise error(f"{where}: not an .npy array (it lacks the \\x93NUMPY magic)")
    version = (magic[6], magic[7])
    if version not in _VERSIONS:
        raise error(
            f"{where}: unsupported .npy format version {version[0]}.{version[1]}; 1.0, 2.0 and "
            "3.0 are read"
        )
    fmt = _VERSIONS[version]
    (hlen,) = struct.unpack(fmt, _read_exact(f, struct.calcsize(fmt), where, error))
    if hlen > MAX_HEADER_BYTES:
        raise error(f"{where}: .npy header of {hlen} bytes, at most {MAX_HEADER_BYTES} are read")
    raw = _read_exact(f, hlen, where, error)
    try:
        header = ast.literal_eval(raw.decode("utf8" if version == (3, 0) else "latin1"))
    except (
        SyntaxError,
        ValueError,  # Also a UTF-8 decoding error.
        TypeError,
        MemoryError,
        RecursionError,
        tokenize.TokenError,
    ) as e:
        raise error(f"{where}: not a valid .npy header ({_detail(e)})") from None
    if not isinstance(header, dict) or set(header) != _HEADER_KEYS:
        raise error(
            f"{where}: the .npy header must be a dict of descr, fortran_order and shape, got "
            f"{_short(header)}"
        )
    shape, fortran = header["shape"], header["fortran_order"]
    if not isinstance(shape, tuple) or not all(type(n) is int and n >= 0 for n in shape):
        raise error(f"{where}: the .npy header's shape {_short(shape)} is not a tuple of sizes")
    if len(shape) > MAX_DIMS:
        raise error(f"{where}: {len(shape)} dimensions, at most {MAX_DIMS} are read")
    if not isinstance(fortran, bool):
        raise error(f"{where}: the .npy header's fortran_order {_short(fortran)} is not a bool")
    try:
        dtype = np.lib.format.descr_to_dtype(header["descr"])
    except (
        TypeError,
        ValueError,
        KeyError,
        IndexError,
        SyntaxError,
        OverflowError,
        RecursionError,
        MemoryError,
    ) as e:
        raise error(f"{where}: unknown dtype {_short(header['descr'])} ({_detail(e)})") from None
    expected = _kinds_phrase(kinds)
    if dtype.hasobject:
        raise error(
            f"{where}: holds Python objects (a pickle), which humimic never loads; expected "
            f"{expected}"
        )
    if dtype.fields is not None or dtype.subdtype is not None:
        raise error(
            f"{where}: dtype {dtype} (records or subarrays) is not read; expected {expected}"
        )
    if dtype.kind not in kinds:
        raise error(f"{where}: dtype {dtype} is not supported; expected {expected}")
    if dtype.itemsize == 0:
        raise error(f"{where}: dtype {dtype} has empty items")
    return _Header(shape, fortran, dtype, 8 + struct.calcsize(fmt) + hlen)


def _read_exact(f: IO[bytes], n: int, where: str, error: type[InputError]) -> bytes:
    out = f.read(n)
    if len(out) != n:
        raise error(f"{where}: truncated .npy header: {len(out)} of {n} bytes")
    return out


def _check_kinds(kinds: str) -> None:
    """The caller's ``kinds`` never admit objects or records (a programming error)."""
    if not kinds or set(kinds) & set("OV"):
        raise ValueError(f"kinds {kinds!r}: give dtype kinds other than 'O' and 'V'")


_KIND_WORDS = (("iuf", "numbers"), ("c", "complex numbers"), ("b", "booleans"),
               ("U", "strings"), ("S", "byte strings"), ("mM", "times"))  # fmt: skip


def _kinds_phrase(kinds: str) -> str:
    """``"biufU"`` -> ``"numbers, booleans or strings"``."""
    words = [w for chars, w in _KIND_WORDS if set(chars) & set(kinds)]
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " or " + words[-1]


def _amount(n: int) -> str:
    """A byte count for messages: bytes, MiB or GiB."""
    if n >= 1 << 30:
        return f"{n / (1 << 30):.3g} GiB"
    if n >= 1 << 20:
        return f"{n / (1 << 20):.3g} MiB"
    return f"{n} bytes"


def _listing(members: dict[str, zipfile.ZipInfo]) -> str:
    keys = sorted(members)
    shown = ", ".join(repr(k) for k in keys[:20])
    return (shown + (f" and {len(keys) - 20} more" if len(keys) > 20 else "")) or "none"


def _short(value: object) -> str:
    """A value's repr for a message: one line, at most 100 characters."""
    text = " ".join(repr(value).split())
    return text if len(text) <= 100 else text[:97] + "..."


def _detail(e: BaseException) -> str:
    """An exception as one short line: its type and text."""
    text = " ".join(str(e).split())[:200]
    if not text and isinstance(e, EOFError):
        text = "the data ends early"  # zipfile's EOFError has no text.
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


__all__ = [
    "MAX_DIMS",
    "MAX_HEADER_BYTES",
    "READ_CHUNK",
    "READ_ERRORS",
    "read_array",
    "read_npy_file",
    "read_npz_members",
]
