"""Arrays of global joint positions (``.npy`` / ``.npz``) to :class:`HumanClip`.

A ``.npy`` file holds one float array of global joint positions, shape (T, J, 3). A ``.npz``
file holds ``positions`` (T, J, 3), ``joint_names`` (J,) and optionally ``fps`` (a scalar) and
``parents`` (J,). Files are read with ``allow_pickle=False``.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

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
    if p.suffix.lower() not in _SUFFIXES:
        raise InputError(f"{p}: unknown file type {p.suffix!r}; expected one of {_SUFFIXES}")
    if up not in ("y", "z"):
        raise InputError(f"{p}: unknown up axis {up!r}; expected 'y' or 'z'")
    factor = metres_per_unit(units)

    file_names: Sequence[str] | None = None
    file_parents: Sequence[int] | None = None
    file_fps: float | None = None
    if p.suffix.lower() == ".npz":
        positions, file_names, file_fps, file_parents = _read_npz(p)
    else:
        positions = _load(p)
        if not isinstance(positions, np.ndarray):
            raise MotionDataError(f"{p}: expected one array, found an archive")
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
    duplicates = sorted({n for n in names if names.count(n) > 1})
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


def _load(p: Path) -> object:
    try:
        return np.load(p, allow_pickle=False)
    except (zipfile.BadZipFile, EOFError) as e:
        raise MotionDataError(f"{p}: not a readable .npy/.npz file ({e})") from None
    except ValueError as e:
        raise MotionDataError(f"{p}: cannot read as a numpy array file: {e}") from e
    except OSError as e:
        raise InputError(f"{p}: cannot read: {e}") from e


def _read_npz(
    p: Path,
) -> tuple[np.ndarray, list[str] | None, float | None, list[int] | None]:
    archive = _load(p)
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise MotionDataError(f"{p}: expected a .npz archive")
    with archive:
        keys = set(archive.files)
        if "positions" not in keys:
            raise MotionDataError(
                f"{p}: no 'positions' array; found keys: {', '.join(sorted(keys)) or 'none'}"
            )
        try:
            positions = archive["positions"]
            names = archive["joint_names"].tolist() if "joint_names" in keys else None
            fps = float(archive["fps"]) if "fps" in keys else None
            parents = [int(x) for x in archive["parents"]] if "parents" in keys else None
        except (ValueError, TypeError) as e:
            raise MotionDataError(f"{p}: malformed array in archive: {e}") from e
    if names is not None and (
        not isinstance(names, list) or not all(isinstance(n, str) for n in names)
    ):
        raise MotionDataError(f"{p}: 'joint_names' must be a 1-D array of strings")
    return positions, names, fps, parents


def _check_array(p: Path, positions: np.ndarray) -> np.ndarray:
    if not np.issubdtype(positions.dtype, np.number) or np.issubdtype(
        positions.dtype, np.complexfloating
    ):
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
    for j in range(num_joints):
        k, steps = j, 0
        while out[k] >= 0:
            k, steps = out[k], steps + 1
            if steps > num_joints:
                raise MotionDataError(f"{p}: parents form a cycle through joint {j}")
    return out
