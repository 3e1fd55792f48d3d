"""The one check of a :class:`humimic.motion.Motion`: :func:`validate_motion`, which every
motion reader and writer runs (``.npz`` and MCAP alike), and its limits.

Kept apart from :mod:`humimic.motion` (which re-exports :func:`validate_motion`,
:data:`MAX_ABS_VALUE` and :data:`FPS_RANGE`) so that the motion file's code and its checks each
stay a readable size; this module needs neither MuJoCo nor the file formats.
"""

from __future__ import annotations

import json
import os
from typing import TYPE_CHECKING

import numpy as np

from humimic.errors import MotionDataError

if TYPE_CHECKING:  # humimic.motion imports this module: the class is only named in types.
    from humimic.motion import Motion

MAX_ABS_VALUE = 1e6
"""Largest magnitude of a number in a motion (metres, radians, their rates): larger ones are
corrupt data, and would overflow the float32 arithmetic of training."""
FPS_RANGE = (1e-3, 1e5)
"""Accepted frame rates [1/s]."""
_QUAT_TOLERANCE = 1e-3  # |norm - 1| accepted for a stored unit quaternion.
_DYNAMICS_KEYS = ("initial_state", "ctrl", "qpos", "qvel", "physics_dt")


class _Where:
    """Names the file and a field in messages (the ``.npz`` key, or another format's label)."""

    def __init__(self, where: str, labels: dict[str, str] | None) -> None:
        self.where = where
        self.labels = labels or {}

    def name(self, key: str) -> str:
        if key in self.labels:
            return self.labels[key]
        for prefix in ("extra_", "dynamics_"):
            if key.startswith(prefix) and prefix in self.labels:
                return self.labels[prefix] + key[len(prefix) :]
        return key

    def error(self, message: str) -> MotionDataError:
        return MotionDataError(f"{self.where}: {message}")


def _is_real(x: object) -> bool:
    return isinstance(x, int | float | np.integer | np.floating) and not isinstance(
        x, bool | np.bool_
    )


def _check_numbers(w: _Where, key: str, v: object, kinds: str = "iuf") -> np.ndarray:
    """``v`` is an array of real numbers (``kinds``), finite and of sane magnitude."""
    label = w.name(key)
    if not isinstance(v, np.ndarray):
        raise w.error(f"{label}: expected an array, got {type(v).__name__}")
    if v.dtype.kind not in kinds:
        what = "Python objects (they would be pickled)" if v.dtype.hasobject else f"{v.dtype}"
        expected = "numbers or booleans" if "b" in kinds else "real numbers"
        raise w.error(f"{label}: holds {what}, expected {expected}")
    if v.dtype.kind == "f" and v.size:
        bad = ~np.isfinite(v)
        if bad.any():
            raise w.error(f"{label} contains NaN or inf ({_first(bad)})")
    if v.dtype.kind in "iuf" and v.size:
        big = np.abs(v.astype(np.float64, copy=False)) > MAX_ABS_VALUE
        if big.any():
            raise w.error(
                f"{label} holds a value beyond {MAX_ABS_VALUE:g} ({_first(big)}): corrupt data"
            )
    return v


def _first(mask: np.ndarray) -> str:
    """Where the first true entry of ``mask`` is: its frame (the first axis)."""
    return f"frame {np.argwhere(mask)[0][0]}" if mask.ndim else "the value"


def validate_motion(
    motion: Motion,
    where: str | os.PathLike[str] | None = None,
    labels: dict[str, str] | None = None,
) -> None:
    """Check that a motion is whole and consistent: the one check that every reader
    (:func:`humimic.motion.load_motion`, :func:`humimic.formats.mcap.read_motion_mcap`) and
    :func:`humimic.motion.save_motion` run.

    Checks: a robot name; a finite frame rate in :data:`FPS_RANGE`; unique joint and body
    names; every array of frames real-valued, finite, below :data:`MAX_ABS_VALUE`, with
    ``T >= 1`` frames and the shapes of the class doc (``qpos`` (T, 7 + J), bodies (T, B, 3 or
    4)); unit quaternions (the base's in ``qpos`` and every body's); extras of numbers or
    booleans (never objects, which would be pickled) with T frames; ``info`` JSON-able; a
    dynamic section with all of ``initial_state, ctrl, qpos, qvel, physics_dt``, its steps one
    length ``S = (T - 1) * physics steps per frame``.

    Args:
        motion: The motion.
        where: The file to name in messages (default: ``motion.source``, else "the motion").
        labels: How the file names a field in messages, e.g. ``{"qpos": "/reference/qpos"}``;
            keys ``"extra_"`` and ``"dynamics_"`` prefix the extras and the dynamic section.
            Default: the ``.npz`` keys.

    Raises:
        MotionDataError: The first problem found, naming the file, the field and the frame.
    """
    w = _Where(str(where) if where is not None else (motion.source or "the motion"), labels)
    _check_header(w, motion)
    T = _check_frames(w, motion)
    _check_unit(w, "qpos", motion.qpos[:, 3:7], "the base quaternion qpos[3:7]")
    _check_body_quats(w, motion)
    _check_extras(w, motion.extras, T)
    _check_info(w, motion.info)
    if motion.dynamics:
        _check_dynamics(w, motion.dynamics, float(motion.fps), T, len(motion.joint_names))


def _check_header(w: _Where, motion: Motion) -> None:
    """The scalars and names: a robot name, a frame rate in :data:`FPS_RANGE`, unique joint
    and body names and at least one body (the floating base)."""
    if not isinstance(motion.robot, str) or not motion.robot.strip():
        raise w.error(f"{w.name('robot')}: expected a robot name, got {motion.robot!r}")
    fps = motion.fps
    if not _is_real(fps) or not FPS_RANGE[0] <= float(fps) <= FPS_RANGE[1]:
        raise w.error(
            f"{w.name('fps')} must be a positive number ({FPS_RANGE[0]:g} to "
            f"{FPS_RANGE[1]:g}), got {fps!r}"
        )
    for key in ("joint_names", "body_names"):
        names = getattr(motion, key)
        if not isinstance(names, tuple) or not all(isinstance(n, str) for n in names):
            raise w.error(f"{w.name(key)}: expected a list of names")
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            raise w.error(f"{w.name(key)}: names repeat: {twice}")
    if not motion.body_names:
        raise w.error(f"{w.name('body_names')}: no bodies (body 0 is the floating base)")


def _check_frames(w: _Where, motion: Motion) -> int:
    """Every array of frames: ``T >= 1`` frames (``qpos`` sets T), the shapes of the class
    doc for the names given, real numbers of sane magnitude (:func:`_check_numbers`).

    Returns:
        The number of frames T.
    """
    J, B = len(motion.joint_names), len(motion.body_names)
    if not isinstance(motion.qpos, np.ndarray) or motion.qpos.ndim < 1:
        raise w.error(f"{w.name('qpos')} must be an array with a frame axis")
    T = int(motion.qpos.shape[0])
    if T < 1:
        raise w.error(f"{w.name('qpos')}: zero frames")
    expected = {
        "qpos": (T, 7 + J),
        "joint_pos": (T, J),
        "joint_vel": (T, J),
        "body_pos_w": (T, B, 3),
        "body_quat_w": (T, B, 4),
        "body_lin_vel_w": (T, B, 3),
        "body_ang_vel_w": (T, B, 3),
    }
    for key, shape in expected.items():
        v = getattr(motion, key)
        label = w.name(key)
        if not isinstance(v, np.ndarray) or v.ndim < 2:
            got = v.shape if isinstance(v, np.ndarray) else type(v).__name__
            raise w.error(f"{label} must be an array with a frame axis, got shape {got}")
        if v.shape[0] != T:
            raise w.error(f"{label} has {v.shape[0]} frames, {w.name('qpos')} has {T}")
        if v.shape != shape:
            raise w.error(
                f"{label} has shape {v.shape}, expected {shape} (frames, then {J} joints / "
                f"{B} bodies as named)"
            )
        _check_numbers(w, key, v)
    return T


def _check_body_quats(w: _Where, motion: Motion) -> None:
    """Every body's quaternion is a unit one: the message names the frame and the body."""
    norms = np.linalg.norm(motion.body_quat_w, axis=-1)
    bad = np.abs(norms - 1.0) > _QUAT_TOLERANCE
    if bad.any():
        t, b = np.argwhere(bad)[0]
        raise w.error(
            f"{w.name('body_quat_w')} frame {t}, body {motion.body_names[b]!r}: quaternion norm "
            f"{norms[t, b]:.3g}, expected a unit quaternion (w, x, y, z)"
        )


def _check_unit(w: _Where, key: str, quat: np.ndarray, what: str) -> None:
    norms = np.linalg.norm(quat, axis=-1)
    bad = np.abs(norms - 1.0) > _QUAT_TOLERANCE
    if bad.any():
        t = int(np.argmax(bad))
        raise w.error(
            f"{w.name(key)} frame {t}: {what} {np.round(quat[t], 6).tolist()} has norm "
            f"{norms[t]:.3g}, expected a unit quaternion (w, x, y, z)"
        )


def _check_extras(w: _Where, extras: object, T: int) -> None:
    if extras is None:
        return
    if not isinstance(extras, dict):
        raise w.error(f"extras: expected named arrays, got {type(extras).__name__}")
    for k, v in extras.items():
        if not isinstance(k, str) or not k:
            raise w.error(f"extras: names must be non-empty strings, got {k!r}")
        key = f"extra_{k}"
        _check_numbers(w, key, v, kinds="biuf")
        if v.ndim < 1 or v.shape[0] != T:
            raise w.error(
                f"{w.name(key)} has shape {v.shape}: an extra has one row per frame ({T})"
            )


def _check_info(w: _Where, info: object) -> None:
    if info is None:
        return
    if not isinstance(info, dict):
        raise w.error(f"{w.name('info_json')}: expected a JSON object, got {type(info).__name__}")
    try:
        json.dumps(info)
    except (TypeError, ValueError, RecursionError) as e:
        raise w.error(f"{w.name('info_json')}: not JSON-able ({e})") from None


def _check_dynamics(w: _Where, dyn: dict[str, np.ndarray], fps: float, T: int, J: int) -> None:
    """The dynamic section: every key, one step count ``S = (T - 1) * steps per frame``."""
    missing = [k for k in _DYNAMICS_KEYS if k not in dyn]
    unknown = sorted(str(k) for k in dyn if k not in _DYNAMICS_KEYS)
    if missing or unknown:
        problem = f"lacks {missing}" if missing else f"has unknown keys {unknown}"
        raise w.error(
            f"the dynamic section {problem}; expected "
            f"{', '.join(w.name('dynamics_' + k) for k in _DYNAMICS_KEYS)} (humimic refine)"
        )
    for k in _DYNAMICS_KEYS:
        _check_numbers(w, f"dynamics_{k}", dyn[k])
    dt_arr, state = dyn["physics_dt"], dyn["initial_state"]
    ctrl, qpos, qvel = dyn["ctrl"], dyn["qpos"], dyn["qvel"]
    if dt_arr.ndim != 0 or not 1e-6 <= float(dt_arr) <= 1.0:
        raise w.error(
            f"{w.name('dynamics_physics_dt')}: expected one physics step of 1e-6 to 1 s, got "
            f"{dt_arr.tolist()}"
        )
    if state.ndim != 1 or state.size < 1 + (7 + J) + (6 + J):
        raise w.error(
            f"{w.name('dynamics_initial_state')} has shape {state.shape}, expected a full "
            f"physics state of at least {1 + (7 + J) + (6 + J)} numbers"
        )
    if ctrl.ndim != 2 or ctrl.shape[0] < 1 or ctrl.shape[1] < 1:
        raise w.error(
            f"{w.name('dynamics_ctrl')} has shape {ctrl.shape}, expected (steps, actuators)"
        )
    steps = ctrl.shape[0]
    dt = float(dt_arr)
    ratio = 1.0 / (fps * dt)
    per_frame = round(ratio)
    if per_frame < 1 or abs(ratio - per_frame) > 1e-6:
        raise w.error(
            f"{w.name('dynamics_physics_dt')} {dt} s is not a whole fraction of the frame "
            f"period 1/{fps} s"
        )
    if steps != (T - 1) * per_frame:
        raise w.error(
            f"{w.name('dynamics_ctrl')} has {steps} steps, expected {(T - 1) * per_frame} "
            f"({per_frame} physics steps for each of the {T - 1} frame intervals)"
        )
    for key, arr, width in (("qpos", qpos, 7 + J), ("qvel", qvel, 6 + J)):
        if arr.shape != (steps, width):
            raise w.error(
                f"{w.name('dynamics_' + key)} has shape {arr.shape}, expected ({steps}, "
                f"{width}): one row per step of {w.name('dynamics_ctrl')}"
            )
