"""Arrays of global joint positions (``.npy`` / ``.npz``) to :class:`HumanClip`.

A ``.npy`` file holds one float array of global joint positions, shape (T, J, 3). A ``.npz``
file holds ``positions`` (T, J, 3), ``joint_names`` (J,) and optionally ``fps`` (a scalar) and
``parents`` (J,). Arrays are read by :mod:`humimic.npyio`: never unpickled, each header's shape
checked against the bytes really there (and :data:`MAX_ARRAY_BYTES`) before anything is allocated.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from humimic.datasets.clip import HumanClip
from humimic.datasets.units import metres_per_unit
from humimic.errors import InputError, MotionDataError
from humimic.npyio import read_npy_file, read_npz_members
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
"""Most bytes of array data read from a file, all its arrays together (2 GiB: an hour of 53
joints at 120 fps in float64 is 0.55 GiB). Bigger headers are refused before anything is
allocated."""


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
    _check_request(p, up)
    factor = metres_per_unit(units, p)

    file_names: Sequence[str] | None = None
    file_parents: Sequence[int] | None = None
    file_fps: float | None = None
    if p.suffix.lower() == ".npz":
        positions, file_names, file_fps, file_parents = _clip_arrays(p)
    else:
        positions = read_npy_file(p, max_bytes=MAX_ARRAY_BYTES, kinds="iuf", error=MotionDataError)
    positions = _check_array(p, positions)
    num_joints = positions.shape[1]
    names = _joint_names(p, joint_names if joint_names is not None else file_names, num_joints)
    _check_finite(p, positions, names)

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


def _check_request(p: Path, up: str) -> None:
    """The path is an existing ``.npy`` or ``.npz`` file and ``up`` a known axis: refused
    before anything is read."""
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if p.is_dir():
        raise InputError(f"{p}: is a folder, expected a .npy or .npz file")
    if p.suffix.lower() not in _SUFFIXES:
        raise InputError(f"{p}: unknown file type {p.suffix!r}; expected one of {_SUFFIXES}")
    if up not in ("y", "z"):
        raise InputError(f"{p}: unknown up axis {up!r}; expected 'y' or 'z'")


def _joint_names(p: Path, names: Sequence[str] | None, num_joints: int) -> tuple[str, ...]:
    """The joints' names: those given (by the caller or the file), else
    :data:`HOLOSOMA_JOINTS` for a 53-joint array; one per joint, none repeated."""
    if names is None:
        if num_joints != len(HOLOSOMA_JOINTS):
            raise InputError(
                f"{p}: {num_joints} joints; pass joint_names (only {len(HOLOSOMA_JOINTS)}-joint "
                "holosoma arrays are named automatically)"
            )
        names = HOLOSOMA_JOINTS
    out = tuple(str(n) for n in names)
    if len(out) != num_joints:
        raise MotionDataError(f"{p}: {len(out)} joint names for {num_joints} joints in the array")
    duplicates = sorted(n for n, count in Counter(out).items() if count > 1)
    if duplicates:
        raise MotionDataError(f"{p}: duplicate joint names: {', '.join(duplicates)}")
    return out


def _check_finite(p: Path, positions: np.ndarray, names: tuple[str, ...]) -> None:
    """No NaN or inf: the message names the first bad frame and joint, and counts the bad
    frames (one glitch or a broken recording)."""
    bad = ~np.isfinite(positions)
    if bad.any():
        t, j, _ = np.argwhere(bad)[0]
        count = int(bad.any(axis=(1, 2)).sum())
        raise MotionDataError(
            f"{p}: NaN or inf at frame {t}, joint {j} ({names[j]}); {count} bad frames in all"
        )


def _clip_arrays(p: Path) -> tuple[np.ndarray, list[str] | None, float | None, list[int] | None]:
    """A ``.npz`` clip's positions, and its joint names, fps and parents where it has them."""
    arrays = read_npz_members(
        p,
        ("positions", "joint_names", "fps", "parents"),
        max_bytes=MAX_ARRAY_BYTES,
        kinds="iufU",  # Numbers, and the joint names' strings.
        error=MotionDataError,
        required=("positions",),
    )
    positions = arrays["positions"]
    raw_names, raw_fps = arrays.get("joint_names"), arrays.get("fps")
    raw_parents = arrays.get("parents")
    names = None
    if raw_names is not None:
        if raw_names.dtype.kind != "U" or raw_names.ndim != 1:
            raise MotionDataError(f"{p}: 'joint_names' must be a 1-D array of strings")
        names = raw_names.tolist()
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
