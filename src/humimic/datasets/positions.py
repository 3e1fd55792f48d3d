"""Arrays of global joint positions (``.npy`` / ``.npz``) to :class:`HumanClip`.

A ``.npy`` file holds one float array of global joint positions, shape (T, J, 3). A ``.npz``
file holds ``positions`` (T, J, 3), ``joint_names`` (J,) and optionally ``fps`` (a scalar) and
``parents`` (J,). Arrays are never unpickled, and each header's shape is checked against the
bytes really there (and :data:`MAX_ARRAY_BYTES`) before anything is allocated.
"""

from __future__ import annotations

import lzma
import math
import os
import zipfile
import zlib
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from tokenize import TokenError
from typing import IO

import numpy as np
from numpy.lib import format as npformat

from humimic.datasets.bvh import metres_per_unit
from humimic.datasets.clip import HumanClip
from humimic.errors import InputError, MotionDataError
from humimic.transforms import Y_UP_TO_Z_UP

_FINGERS = ("Thumb", "Index", "Middle", "Ring", "Pinky")

HOLOSOMA_JOINTS: tuple[str, ...] = (
    "Hips",
    "Spine",
    "Spine1",
    "Neck",
    "Head",
    "LeftShoulder",
    "LeftArm",
    "LeftForeArm",
    "LeftHand",
    *(f"LeftHand{f}{k}" for f in _FINGERS for k in (1, 2, 3)),
    "RightShoulder",
    "RightArm",
    "RightForeArm",
    "RightHand",
    *(f"RightHand{f}{k}" for f in _FINGERS for k in (1, 2, 3)),
    "LeftUpLeg",
    "LeftLeg",
    "LeftFoot",
    "LeftToeBase",
    "RightUpLeg",
    "RightLeg",
    "RightFoot",
    "RightToeBase",
    "LeftFootMod",
    "RightFootMod",
)
"""The 53 joints of the holosoma climbing mocap (``demo_data/climb``), in file order."""

_HOLOSOMA_PARENT_NAMES: dict[str, str | None] = {
    "Hips": None,
    "Spine": "Hips",
    "Spine1": "Spine",
    "Neck": "Spine1",
    "Head": "Neck",
    **{
        name: parent
        for side in ("Left", "Right")
        for name, parent in (
            (f"{side}Shoulder", "Spine1"),
            (f"{side}Arm", f"{side}Shoulder"),
            (f"{side}ForeArm", f"{side}Arm"),
            (f"{side}Hand", f"{side}ForeArm"),
            *(
                (f"{side}Hand{f}{k}", f"{side}Hand{f}{k - 1}" if k > 1 else f"{side}Hand")
                for f in _FINGERS
                for k in (1, 2, 3)
            ),
            (f"{side}UpLeg", "Hips"),
            (f"{side}Leg", f"{side}UpLeg"),
            (f"{side}Foot", f"{side}Leg"),
            (f"{side}ToeBase", f"{side}Foot"),
            (f"{side}FootMod", f"{side}Foot"),
        )
    },
}

HOLOSOMA_PARENTS: tuple[int, ...] = tuple(
    -1 if (p := _HOLOSOMA_PARENT_NAMES[n]) is None else HOLOSOMA_JOINTS.index(p)
    for n in HOLOSOMA_JOINTS
)
"""Parent index of each of :data:`HOLOSOMA_JOINTS` (-1 for ``Hips``). Every bone of this tree
keeps a constant length over the three shared climbing clips."""

_SUFFIXES = (".npy", ".npz")

MAX_ARRAY_BYTES = 2 * 2**30
"""Largest array data read from a file (2 GiB: an hour of 53 joints at 120 fps in float64 is
0.55 GiB). Bigger headers are refused before anything is allocated."""

_READ_CHUNK = 64 * 2**20


def load_positions(
    path: str | os.PathLike[str],
    *,
    joint_names: Sequence[str] | None = None,
    fps: float | None = None,
    up: str = "z",
    units: str | float = "m",
    skeleton: str | None = None,
    parents: Sequence[int] | None = None,
) -> HumanClip:
    """Load global joint positions from a ``.npy`` or ``.npz`` file.

    Args:
        path: The file.
        joint_names: Joint names, one per joint (J,). Default: the ``.npz`` key ``joint_names``,
            or :data:`HOLOSOMA_JOINTS` for a 53-joint ``.npy``; required otherwise.
        fps: Frames per second. Default: the ``.npz`` key ``fps`` when present, else 120.
        up: The file's up axis, ``"z"`` or ``"y"`` (turned to z up by the proper rotation
            :data:`humimic.transforms.Y_UP_TO_Z_UP`).
        units: ``"m"``, ``"cm"``, ``"mm"``, ``"inch"`` or a number of metres per file unit.
        skeleton: Skeleton convention name. Default: ``"holosoma"`` when the names are
            :data:`HOLOSOMA_JOINTS`, else ``"unknown"``.
        parents: Parent index per joint (J,), -1 for the root. Default: the ``.npz`` key
            ``parents``, :data:`HOLOSOMA_PARENTS` for the holosoma names, else a star rooted at
            joint 0 (``[-1, 0, 0, ...]``), which is enough for per-joint position targets but
            not a real bone tree.

    Returns:
        The clip, positions in metres and z up. Shape: (T, J, 3). No orientations.

    Raises:
        InputError: Missing file, unknown suffix, bad ``up``/``units``, no names for a
            non-holosoma array.
        MotionDataError: Wrong shape or dtype, zero frames, NaN/inf (names the frame and
            joint), names that do not match the joints or repeat.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if p.is_dir():
        raise InputError(f"{p}: is a folder, expected a .npy or .npz file")
    if p.suffix.lower() not in _SUFFIXES:
        raise InputError(f"{p}: unknown file type {p.suffix!r}; expected one of {_SUFFIXES}")
    if up not in ("y", "z"):
        raise InputError(f"{p}: unknown up axis {up!r}; expected 'y' or 'z'")
    factor = metres_per_unit(units, p)

    file_names: Sequence[str] | None = None
    file_parents: Sequence[int] | None = None
    file_fps: float | None = None
    if p.suffix.lower() == ".npz":
        positions, file_names, file_fps, file_parents = _read_npz(p)
    else:
        positions = _read_npy(p)
    positions = _check_array(p, positions)
    num_joints = positions.shape[1]

    names = joint_names if joint_names is not None else file_names
    if names is None:
        if num_joints != len(HOLOSOMA_JOINTS):
            raise InputError(
                f"{p}: {num_joints} joints; pass joint_names (only {len(HOLOSOMA_JOINTS)}-joint "
                "holosoma arrays are named automatically)"
            )
        names = HOLOSOMA_JOINTS
    names = tuple(str(n) for n in names)
    if len(names) != num_joints:
        raise MotionDataError(f"{p}: {len(names)} joint names for {num_joints} joints in the array")
    duplicates = sorted(n for n, count in Counter(names).items() if count > 1)
    if duplicates:
        raise MotionDataError(f"{p}: duplicate joint names: {', '.join(duplicates)}")

    bad = ~np.isfinite(positions)
    if bad.any():
        t, j, _ = np.argwhere(bad)[0]
        count = int(bad.any(axis=(1, 2)).sum())
        raise MotionDataError(
            f"{p}: NaN or inf at frame {t}, joint {j} ({names[j]}); {count} bad frames in all"
        )

    is_holosoma = names == HOLOSOMA_JOINTS
    if parents is None:
        parents = file_parents
    if parents is None:
        parents = HOLOSOMA_PARENTS if is_holosoma else (-1, *([0] * (num_joints - 1)))
    parents = _check_parents(p, parents, num_joints)

    if fps is None:
        fps = file_fps if file_fps is not None else 120.0
    if skeleton is None:
        skeleton = "holosoma" if is_holosoma else "unknown"
    up_matrix = Y_UP_TO_Z_UP if up == "y" else np.eye(3)
    positions_w = np.einsum("ij,tkj->tki", up_matrix * factor, positions.astype(np.float64))
    return HumanClip(
        names=names,
        parents=parents,
        positions_w=positions_w,
        fps=float(fps),
        source=str(p),
        skeleton=skeleton,
        meta={"units": str(units), "metres_per_unit": f"{factor:.6g}", "up": up},
    )


def _read_array(f: IO[bytes], size: int, where: str) -> np.ndarray:
    """Read one ``.npy`` array from ``f`` (``size`` bytes in all), checking its header first.

    The header's shape and dtype must account for exactly the bytes that follow it, so a
    header that claims more data than the file holds (numpy would allocate it all before
    noticing) or a truncated file is refused without allocating anything.

    Args:
        f: A binary file positioned at the start of the ``.npy`` data (a file or a zip member).
        size: Bytes in the file or member.
        where: What to name in errors: the path, and the member of a ``.npz``.

    Returns:
        The array (dtype as stored, never Python objects).

    Raises:
        MotionDataError: Not a ``.npy`` array, an object or zero-size dtype, a size that does
            not match the header, or data over :data:`MAX_ARRAY_BYTES`.
    """
    try:
        version = npformat.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = npformat.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = npformat.read_array_header_2_0(f)
        else:
            raise MotionDataError(
                f"{where}: unsupported .npy format version {version[0]}.{version[1]}"
            )
    except (ValueError, TypeError, SyntaxError, RecursionError, EOFError, TokenError) as e:
        # numpy reads the header's text as a Python literal: these are its parse errors.
        detail = " ".join(str(e).split())[:200]
        raise MotionDataError(f"{where}: not a valid .npy array ({detail})") from None
    if dtype.hasobject:
        raise MotionDataError(
            f"{where}: holds Python objects (dtype {dtype}); only numeric arrays are read"
        )
    if dtype.itemsize == 0 or dtype.subdtype is not None:
        raise MotionDataError(f"{where}: unsupported dtype {dtype}")
    if any(n < 0 for n in shape):
        raise MotionDataError(f"{where}: negative size in the header's shape {shape}")
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes > MAX_ARRAY_BYTES:
        raise MotionDataError(
            f"{where}: header claims shape {shape} of {dtype} ({nbytes / 2**30:.3g} GiB), over "
            f"the {MAX_ARRAY_BYTES / 2**30:g} GiB limit"
        )
    available = size - f.tell()
    if available != nbytes:
        how = "truncated" if available < nbytes else "longer than its header says"
        raise MotionDataError(
            f"{where}: {how}: header says shape {shape} of {dtype} ({nbytes} bytes), the file "
            f"has {available} bytes of data"
        )
    # Read in chunks, so memory grows with the data actually there: a zip member's size is
    # only what its directory claims.
    buf = bytearray()
    while len(buf) < nbytes:
        chunk = f.read(min(_READ_CHUNK, nbytes - len(buf)))
        if not chunk:
            raise MotionDataError(f"{where}: truncated: {len(buf)} of {nbytes} bytes of data")
        buf += chunk
    array = np.frombuffer(buf, dtype=dtype)
    return array.reshape(shape, order="F" if fortran else "C")


def _read_npy(p: Path) -> np.ndarray:
    try:
        with open(p, "rb") as f:
            if f.read(4) == b"PK\x03\x04":
                raise MotionDataError(f"{p}: expected one array, found a .npz (zip) archive")
            f.seek(0)
            return _read_array(f, os.fstat(f.fileno()).st_size, str(p))
    except OSError as e:
        raise InputError(f"{p}: cannot read: {e.strerror or e}") from None


_NPZ_ERRORS = (
    zipfile.BadZipFile,
    zlib.error,
    lzma.LZMAError,
    EOFError,
    OSError,
    NotImplementedError,  # An unsupported compression method.
    RuntimeError,  # An encrypted member.
    ValueError,
)
"""What :mod:`zipfile` raises for a corrupt or unsupported archive or member."""


def _read_npz(
    p: Path,
) -> tuple[np.ndarray, list[str] | None, float | None, list[int] | None]:
    try:
        archive = zipfile.ZipFile(p)
    except _NPZ_ERRORS as e:
        raise MotionDataError(f"{p}: not a readable .npz archive ({e})") from None
    with archive:
        # Keys as np.load names them: the member name less ".npy".
        members = {
            (i.filename[:-4] if i.filename.endswith(".npy") else i.filename): i
            for i in archive.infolist()
        }

        def read(key: str) -> np.ndarray | None:
            info = members.get(key)
            if info is None:
                return None
            where = f"{p}: array {key!r}"
            try:
                with archive.open(info) as f:
                    return _read_array(f, info.file_size, where)
            except _NPZ_ERRORS as e:
                detail = str(e) or "the archive ends early"  # zipfile's EOFError has no text.
                raise MotionDataError(f"{where}: cannot read ({detail})") from None

        if "positions" not in members:
            raise MotionDataError(
                f"{p}: no 'positions' array; found keys: {', '.join(sorted(members)) or 'none'}"
            )
        positions = read("positions")
        raw_names, raw_fps, raw_parents = read("joint_names"), read("fps"), read("parents")
    assert positions is not None
    names = None
    if raw_names is not None:
        names = raw_names.tolist() if raw_names.dtype.kind == "U" and raw_names.ndim == 1 else None
        if names is None:
            raise MotionDataError(f"{p}: 'joint_names' must be a 1-D array of strings")
    fps = None
    if raw_fps is not None:
        if raw_fps.size != 1 or raw_fps.dtype.kind not in "iuf":
            raise MotionDataError(
                f"{p}: 'fps' must be one number, got shape {raw_fps.shape} of {raw_fps.dtype}"
            )
        fps = float(raw_fps.reshape(()))
    parents = None
    if raw_parents is not None:
        parents = _whole_numbers(p, "parents", raw_parents)
    return positions, names, fps, parents


def _whole_numbers(p: Path, key: str, values: np.ndarray) -> list[int]:
    """A 1-D array of integers (or floats with whole values) as a list of ints."""
    if values.ndim != 1 or values.dtype.kind not in "iuf":
        raise MotionDataError(
            f"{p}: '{key}' must be a 1-D array of integers, got shape {values.shape} of "
            f"{values.dtype}"
        )
    if values.dtype.kind == "f" and not (np.isfinite(values) & (values == np.round(values))).all():
        raise MotionDataError(f"{p}: '{key}' must hold whole numbers")
    return [int(x) for x in values]


def _check_array(p: Path, positions: np.ndarray) -> np.ndarray:
    if positions.dtype.kind not in "iuf":  # Not bool, complex, text, dates or records.
        raise MotionDataError(f"{p}: positions have dtype {positions.dtype}, expected floats")
    if positions.ndim != 3 or positions.shape[2] != 3:
        raise MotionDataError(
            f"{p}: positions have shape {positions.shape}, expected (frames, joints, 3)"
        )
    if positions.shape[0] == 0:
        raise MotionDataError(f"{p}: zero frames")
    if positions.shape[1] == 0:
        raise MotionDataError(f"{p}: zero joints")
    return positions


def _check_parents(p: Path, parents: Sequence[int], num_joints: int) -> tuple[int, ...]:
    out = tuple(int(x) for x in parents)
    if len(out) != num_joints:
        raise MotionDataError(f"{p}: {len(out)} parents for {num_joints} joints")
    for j, k in enumerate(out):
        if k < -1 or k >= num_joints or k == j:
            raise MotionDataError(f"{p}: joint {j} has invalid parent index {k}")
    # Walk up from each joint until a root or a joint already known to reach one: linear in
    # the joints, as a file may hold many. Meeting a joint of the current walk is a cycle.
    reaches_root = [False] * num_joints
    for j in range(num_joints):
        walk, on_walk, k = [], set(), j
        while k >= 0 and not reaches_root[k]:
            if k in on_walk:
                raise MotionDataError(f"{p}: parents form a cycle through joint {j}")
            walk.append(k)
            on_walk.add(k)
            k = out[k]
        for q in walk:
            reaches_root[q] = True
    return out
