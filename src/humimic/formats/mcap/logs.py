"""Arrays from rollout and robot logs: generalized positions over time, zero-order hold."""

from __future__ import annotations

import numpy as np

from humimic.formats.mcap.reader import McapLog
from humimic.formats.mcap.schemas import McapFormatError


def qpos_from_log(log: McapLog, joint_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Generalized positions over time from a rollout or robot log.

    Uses ``/qpos`` when present; otherwise ``/base_pose`` (floating base) and
    ``/joint_states`` matched by joint name, each held at its last value.

    Returns:
        Times [ns] (N,) and qpos (N, 7 + len(joint_names)), on the joint-state times.
    """
    if log.messages.get("/qpos"):
        msgs = log.topic("/qpos")
        times = np.array([t for t, _ in msgs], dtype=np.int64)
        qpos = np.array([m["qpos"] for _, m in msgs], dtype=np.float64)
        if qpos.ndim != 2 or qpos.shape[1] != 7 + len(joint_names):
            raise McapFormatError(
                f"{log.path}: topic /qpos: field qpos has {qpos.shape[-1]} values, the robot "
                f"needs {7 + len(joint_names)}"
            )
        return times, qpos
    states = log.topic("/joint_states")
    base = log.topic("/base_pose")
    times = np.array([t for t, _ in states], dtype=np.int64)
    qpos = np.zeros((len(states), 7 + len(joint_names)))
    first = states[0][1]["name"]
    missing = [j for j in joint_names if j not in first]
    if missing:
        raise McapFormatError(f"{log.path}: topic /joint_states: field name lacks joints {missing}")
    for i, (_, m) in enumerate(states):
        index = {n: k for k, n in enumerate(m["name"])}
        try:
            qpos[i, 7:] = [m["position"][index[j]] for j in joint_names]
        except (KeyError, IndexError):
            raise McapFormatError(
                f"{log.path}: topic /joint_states, message {i}: field position does not match name"
            ) from None
    base_t = np.array([t for t, _ in base], dtype=np.int64)
    k = np.clip(np.searchsorted(base_t, times, side="right") - 1, 0, len(base) - 1)
    for i, j in enumerate(k):
        b = base[j][1]
        p, o = b["position"], b["orientation"]
        qpos[i, :7] = [p["x"], p["y"], p["z"], o["w"], o["x"], o["y"], o["z"]]
    return times, qpos


def sample_at(times_ns: np.ndarray, values: np.ndarray, query_ns: np.ndarray) -> np.ndarray:
    """Zero-order hold: the last value at or before each query time (the first before it)."""
    k = np.clip(np.searchsorted(times_ns, query_ns, side="right") - 1, 0, len(times_ns) - 1)
    return values[k]
