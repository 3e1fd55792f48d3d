"""Pickle files of plain data, read without running anything they name.

Body models (SMPL's ``.pkl`` files) and motion files passed around the SMPL world (GMR's and
PHC's per-sequence ``.pkl``, OMOMO split into sequences) are pickles. ``pickle.load`` runs
whatever functions a file names, so a motion file could run code on the user's machine. This
reader's unpickler resolves only NumPy's array, dtype and scalar constructors, a few builtin
containers (``set``, ``frozenset``, ``complex``, ``object``) and ``_codecs.encode`` (which
Python 2 era pickles use for bytes); objects of the classes these
files are known to hold without their packages installed (chumpy's ``Ch`` arrays in SMPL
models, SciPy's sparse CSC/CSR matrices) are rebuilt as plain arrays from their stored state,
never by importing or calling their code. Any other class or function in the file refuses it,
before anything of it runs.
"""

from __future__ import annotations

import io
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from humimic.errors import InputError

MAX_BYTES = 2 * 1024**3
"""Most bytes read from one file."""

_NUMPY = {
    ("multiarray", "_reconstruct"): np._core.multiarray._reconstruct,  # type: ignore[attr-defined]
    ("multiarray", "scalar"): np._core.multiarray.scalar,  # type: ignore[attr-defined]
    ("numeric", "_frombuffer"): np._core.numeric._frombuffer,  # type: ignore[attr-defined]
}
"""NumPy's array, scalar and (protocol 5) buffer constructors, under ``numpy.core`` (NumPy 1)
or ``numpy._core`` (NumPy 2)."""

_CHUMPY = ("chumpy.ch", "Ch")
_SPARSE = {
    ("scipy.sparse.csc", "csc_matrix"): "csc",
    ("scipy.sparse._csc", "csc_matrix"): "csc",
    ("scipy.sparse.csr", "csr_matrix"): "csr",
    ("scipy.sparse._csr", "csr_matrix"): "csr",
}


_BUILTINS = {"object": object, "set": set, "frozenset": frozenset, "complex": complex}
"""Builtins data pickles name: containers and numbers (``object``: the base the protocol 0
and 1 reconstructor names)."""


class _Stored:
    """An object of a known class, its state kept, its class's code never imported."""

    kind = ""

    def __init__(self, *args: object) -> None:
        self.args = args
        self.state: object = None

    def __setstate__(self, state: object) -> None:
        self.state = state


class _ChumpyArray(_Stored):
    kind = "chumpy.ch.Ch"


class _CscMatrix(_Stored):
    kind = "csc"


class _CsrMatrix(_Stored):
    kind = "csr"


class _NotData(pickle.UnpicklingError):
    """The file names a class or function beyond plain data."""


def _reconstructor(cls: type, base: type, state: object) -> object:
    """``copyreg._reconstructor`` (protocol 0 and 1 objects) for the stored classes only."""
    if not (isinstance(cls, type) and issubclass(cls, _Stored)) or base is not object:
        raise _NotData("copyreg._reconstructor of something that is not data")
    obj = cls()
    if state is not None:
        obj.__setstate__(state)
    return obj


class _Unpickler(pickle._Unpickler):  # type: ignore[name-defined]
    """Python's own unpickler, not the C one: its memo is a dict, so a memo index in the file
    (``LONG_BINPUT``) is an entry, not an allocation (the C unpickler grew a list to a mutated
    index of 825 million: 17-24 s and gigabytes for a 2 KB file)."""

    def find_class(self, module: str, name: str) -> Any:
        head, _, tail = module.rpartition(".")
        if head in ("numpy.core", "numpy._core") and (tail, name) in _NUMPY:
            return _NUMPY[tail, name]
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return np.dtype
        if module in ("builtins", "__builtin__") and name in _BUILTINS:
            return _BUILTINS[name]
        if (module, name) == ("_codecs", "encode"):
            import codecs

            return codecs.encode
        if module in ("copyreg", "copy_reg") and name == "_reconstructor":  # protocols 0, 1
            return _reconstructor
        if (module, name) == _CHUMPY:
            return _ChumpyArray
        if (module, name) in _SPARSE:
            return _CscMatrix if _SPARSE[module, name] == "csc" else _CsrMatrix
        raise _NotData(f"it names {module}.{name}, which is not plain data")


def _dense(obj: _Stored, where: str) -> np.ndarray:
    state = obj.state if isinstance(obj.state, dict) else {}
    if isinstance(obj, _ChumpyArray):
        if "x" not in state:
            raise InputError(f"{where}: a chumpy array without its values ('x')")
        return np.asarray(state["x"])
    try:
        data = np.asarray(state["data"], dtype=float)
        indices = np.asarray(state["indices"], dtype=np.int64)
        indptr = np.asarray(state["indptr"], dtype=np.int64)
        shape = tuple(int(n) for n in state.get("_shape", state.get("shape", ())))
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{where}: a sparse matrix without data, indices, indptr") from None
    if len(shape) != 2 or min(shape) < 0 or shape[0] * shape[1] > 10**9:
        raise InputError(f"{where}: a sparse matrix of shape {shape}")
    out = np.zeros(shape)
    major = shape[1] if isinstance(obj, _CscMatrix) else shape[0]
    if indptr.shape != (major + 1,) or indices.shape != data.shape:
        raise InputError(f"{where}: a sparse matrix whose index arrays do not fit its shape")
    if data.size and (indptr[0] != 0 or np.any(np.diff(indptr) < 0) or indptr[-1] > data.size):
        raise InputError(f"{where}: a sparse matrix with bad index pointers")
    minor = shape[0] if isinstance(obj, _CscMatrix) else shape[1]
    if np.any(indices < 0) or np.any(indices >= minor):
        raise InputError(f"{where}: a sparse matrix with indices outside its shape")
    for k in range(major):
        lo, hi = int(indptr[k]), int(indptr[k + 1])
        if isinstance(obj, _CscMatrix):
            out[indices[lo:hi], k] = data[lo:hi]
        else:
            out[k, indices[lo:hi]] = data[lo:hi]
    return out


def _plain(obj: object, where: str) -> object:
    if isinstance(obj, _Stored):
        return _dense(obj, where)
    if isinstance(obj, dict):
        return {k: _plain(v, f"{where}[{k!r}]") for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_plain(v, where) for v in obj)
    if isinstance(obj, np.ndarray) and obj.dtype == object:
        return np.array([_plain(v, where) for v in obj.ravel()], dtype=object).reshape(obj.shape)
    return obj


def read_data_pickle(path: str | os.PathLike[str]) -> object:
    """The contents of a pickle file of plain data (dicts, lists, numbers, strings, NumPy
    arrays; chumpy arrays and SciPy sparse matrices become NumPy arrays).

    Raises:
        InputError: Naming the file: missing, too large, not a pickle, or naming any class or
            function beyond plain data (nothing of it is run).
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    if p.stat().st_size > MAX_BYTES:
        raise InputError(f"{p}: larger than {MAX_BYTES} bytes")
    raw = p.read_bytes()
    try:
        obj = _Unpickler(io.BytesIO(raw), encoding="latin1").load()
    except _NotData as e:
        raise InputError(f"{p}: refused: {e}") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, KeyError, IndexError, AttributeError,
            OverflowError, MemoryError, UnicodeDecodeError, RecursionError) as e:  # fmt: skip
        detail = " ".join(str(e).split())[:200] or type(e).__name__
        raise InputError(f"{p}: not a readable pickle of data ({detail})") from None
    return _plain(obj, str(p))
