"""The MCAP layout humimic reads and writes: known topics, their JSON schemas, message parts.

Quaternions in humimic's own schemas are ``wxyz`` (fields named ``w, x, y, z``); the
``foxglove.FrameTransforms`` messages for Foxglove's 3D panel use Foxglove's field names. Log
times are nanoseconds; message headers carry ``stamp: {sec, nanosec}``.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from humimic.errors import InputError

_NUM = {"type": "number"}
_NUMS = {"type": "array", "items": _NUM}
_NAMES = {"type": "array", "items": {"type": "string"}}
_VEC3 = {
    "type": "object",
    "properties": {"x": _NUM, "y": _NUM, "z": _NUM},
    "required": ["x", "y", "z"],
}
_QUAT = {
    "type": "object",
    "properties": {"w": _NUM, "x": _NUM, "y": _NUM, "z": _NUM},
    "required": ["w", "x", "y", "z"],
}
_HEADER = {
    "type": "object",
    "properties": {
        "stamp": {
            "type": "object",
            "properties": {"sec": {"type": "integer"}, "nanosec": {"type": "integer"}},
            "required": ["sec", "nanosec"],
        },
        "frame_id": {"type": "string"},
    },
    "required": ["stamp"],
}


def _object(properties: dict[str, Any], required: list[str], title: str) -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "type": "object",
        "properties": properties,
        "required": required,
    }


SCHEMAS: dict[str, dict[str, Any]] = {
    "humimic.JointState": _object(
        {"header": _HEADER, "name": _NAMES, "position": _NUMS, "velocity": _NUMS, "effort": _NUMS},
        ["header", "name", "position"],
        "Joint positions [rad], velocities [rad/s], efforts [N m]",
    ),
    "humimic.JointCommand": _object(
        {
            "header": _HEADER,
            "name": _NAMES,
            "position": _NUMS,
            "velocity": _NUMS,
            "effort": _NUMS,
            "kp": _NUMS,
            "kd": _NUMS,
        },
        ["header", "name", "position"],
        "PD targets, feed-forward torques and the gains the drives were told to use",
    ),
    "humimic.Pose": _object(
        {"header": _HEADER, "position": _VEC3, "orientation": _QUAT},
        ["header", "position", "orientation"],
        "A pose in the world frame (orientation w, x, y, z)",
    ),
    "humimic.Imu": _object(
        {
            "header": _HEADER,
            "orientation": _QUAT,
            "angular_velocity": _VEC3,
            "linear_acceleration": _VEC3,
        },
        ["header"],
        "IMU: orientation (w, x, y, z), angular velocity [rad/s], linear acceleration [m/s^2]",
    ),
    "humimic.Qpos": _object(
        {"header": _HEADER, "qpos": _NUMS},
        ["header", "qpos"],
        "MuJoCo generalized positions (free joint: x y z qw qx qy qz, then joints)",
    ),
    "humimic.BodyStates": _object(
        {
            "header": _HEADER,
            "name": _NAMES,
            "position": {"type": "array", "items": _NUMS},
            "orientation": {"type": "array", "items": _NUMS},
            "linear_velocity": {"type": "array", "items": _NUMS},
            "angular_velocity": {"type": "array", "items": _NUMS},
        },
        ["header", "name", "position", "orientation"],
        "World-frame body states; orientation rows are w, x, y, z",
    ),
    "humimic.NamedArrays": _object(
        {"header": _HEADER, "arrays": {"type": "object"}},
        ["header", "arrays"],
        "Named arrays (nested lists) for one time step",
    ),
    "humimic.RewardTerms": _object(
        {"header": _HEADER, "terms": {"type": "object", "additionalProperties": _NUM}},
        ["header", "terms"],
        "Per-step reward terms of one environment",
    ),
    "foxglove.FrameTransforms": {
        "title": "foxglove.FrameTransforms",
        "type": "object",
        "properties": {
            "transforms": {
                "type": "array",
                "items": {
                    "type": "object",
                    "properties": {
                        "timestamp": {
                            "type": "object",
                            "properties": {
                                "sec": {"type": "integer"},
                                "nsec": {"type": "integer"},
                            },
                        },
                        "parent_frame_id": {"type": "string"},
                        "child_frame_id": {"type": "string"},
                        "translation": _VEC3,
                        "rotation": _QUAT,
                    },
                },
            }
        },
        "required": ["transforms"],
    },
}

TOPICS: dict[str, str] = {
    "/joint_states": "humimic.JointState",
    "/joint_commands": "humimic.JointCommand",
    "/base_pose": "humimic.Pose",
    "/imu": "humimic.Imu",
    "/qpos": "humimic.Qpos",
    "/body_states": "humimic.BodyStates",
    "/reward_terms": "humimic.RewardTerms",
    "/reference/qpos": "humimic.Qpos",
    "/reference/joint_states": "humimic.JointState",
    "/reference/body_states": "humimic.BodyStates",
    "/reference/extras": "humimic.NamedArrays",
    "/dynamics/step": "humimic.NamedArrays",
    "/tf": "foxglove.FrameTransforms",
}
"""Known topics -> schema name. Other topics may be written with an explicit schema."""


class McapFormatError(InputError):
    """An MCAP file is truncated, corrupt, or its messages do not match their schemas."""


def stamp(t_ns: int) -> dict[str, int]:
    """A header stamp from nanoseconds."""
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


def _vec(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _quat(q: np.ndarray) -> dict[str, float]:
    return {"w": float(q[0]), "x": float(q[1]), "y": float(q[2]), "z": float(q[3])}


def tf_message(t_ns: int, names: Iterable[str], pos: np.ndarray, quat: np.ndarray) -> dict:
    """Foxglove FrameTransforms of bodies in the world frame (Foxglove's field names)."""
    ts = {"sec": int(t_ns // 1_000_000_000), "nsec": int(t_ns % 1_000_000_000)}
    return {
        "transforms": [
            {
                "timestamp": ts,
                "parent_frame_id": "world",
                "child_frame_id": n,
                "translation": _vec(p),
                "rotation": _quat(q),
            }
            for n, p, q in zip(names, pos, quat, strict=True)
        ]
    }
