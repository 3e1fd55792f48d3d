"""What the retargeter computes from a scene: the human's contacts with it, and the motion
file's per-frame scene arrays. Scenes themselves load in :mod:`humimic.datasets.scene`."""

from __future__ import annotations

import numpy as np

from humimic.datasets.scene import Scene
from humimic.retarget.interaction_mesh import point_triangle_distance


def human_contacts(
    scene: Scene, keypoints: np.ndarray, radius: np.ndarray, distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Which object each key point touches in each frame: the nearest object whose surface is
    closer than the key point's contact ``radius`` plus ``distance`` (-1: none).

    Args:
        scene: Posed per frame, in the key points' frame.
        keypoints: Shape: (T, K, 3).
        radius: How far each key point sits from a surface it rests on (a joint centre is
            inside the limb) [m]. Shape: (K,).
        distance: Touching tolerance [m].

    Returns:
        Object indices, Shape: (T, K); and how firmly each contact holds, 1 at the contact
        radius falling linearly to 0 at ``radius + distance`` (0 where there is none),
        Shape: (T, K).
    """
    T, K = keypoints.shape[:2]
    out = np.full((T, K), -1, dtype=np.int64)
    firm = np.zeros((T, K))
    if not scene.objects:
        return out, firm
    for t in range(T):
        d = np.stack(
            [point_triangle_distance(keypoints[t], o.world_vertices(t)[o.faces]).min(axis=1)
             for o in scene.objects]
        )  # fmt: skip
        near, best = d.min(axis=0), d.argmin(axis=0)
        out[t] = np.where(near < radius + distance, best, -1)
        firm[t] = np.clip((radius + distance - near) / distance, 0.0, 1.0)
    return out, firm


REST_SPEED = 0.1
"""A human toe joint slower than this [m/s] (horizontally) rests where it is."""

REST_REACH = 0.1
"""...on an object whose surface is within this distance of it [m]..."""

REST_ABOVE = 0.05
"""...when it is this much higher than its planted height on the floor [m] (not on the floor)."""

MIN_REST_FRAMES = 10
"""Fewer resting (frame, toe) samples than this measure no clearance."""


def scene_floor(
    scene: Scene, toes: np.ndarray, fps: float, floor_height: float | None
) -> tuple[float, str, float | None]:
    """Where the clip's floor is, in its world frame, for mapping ``scene`` onto the robot: the
    height under the human's planted toe joints by as much as those joints rest above the
    scene's objects.

    A toe joint sits above the surface it rests on (inside the foot: 3.4-4.4 cm over the boxes
    on the climbing clips, wherever the capture put it), so the floor is not at the planted toes' height, and
    a clip's world may not have it at z = 0 either: on the holosoma clips the planted toe
    joints are 1.6-6.5 cm above z = 0 while they rest 3.4-4.4 cm above the boxes
    (``benchmarks/interaction_retarget.py``, its rows' ``scene_floor``). Measured
    here: the median distance to the nearest object surface of toe joints that rest on an
    object (slower than :data:`REST_SPEED`, within :data:`REST_REACH` of a surface, more than
    :data:`REST_ABOVE` above their planted height), subtracted from the planted height (the
    2nd percentile of each toe's height, averaged). Mapping that floor onto the robot's puts a
    box top the human's toes rest on where the robot's soles rest.

    Args:
        scene: At the toes' frame rate, in the clip's world frame.
        toes: The human's toe joints. Shape: (T, N, 3).
        fps: Their frame rate.
        floor_height: Given by the user: used as it is. ``None``: measured, or 0 (z = 0)
            where no toe rests on an object (the source says so).

    Returns:
        The floor height [m], where it comes from (``"given"``, ``"toe rests on objects"``,
        ``"z = 0 (no toe rests on an object)"``), and the measured clearance [m] (``None``
        where not measured).
    """
    if floor_height is not None:
        return float(floor_height), "given", None
    planted = float(np.percentile(toes[:, :, 2], 2.0, axis=0).mean())
    if not scene.objects or toes.shape[0] < 2:
        return 0.0, "z = 0 (no toe rests on an object)", None
    speed = np.zeros(toes.shape[:2])
    speed[1:] = np.linalg.norm(np.diff(toes[:, :, :2], axis=0), axis=-1) * fps
    high = toes[:, :, 2] > planted + REST_ABOVE
    found = []
    for t in np.flatnonzero(((speed < REST_SPEED) & high).any(axis=1)):
        k = (speed[t] < REST_SPEED) & high[t]
        d = np.min(
            [point_triangle_distance(toes[t, k], o.world_vertices(int(t))[o.faces]).min(axis=1)
             for o in scene.objects],
            axis=0,
        )  # fmt: skip
        found.append(d[d < REST_REACH])
    rests = np.concatenate(found) if found else np.zeros(0)
    if rests.size < MIN_REST_FRAMES:
        return 0.0, "z = 0 (no toe rests on an object)", None
    clearance = float(np.median(rests))
    return planted - clearance, "toe rests on objects", clearance


def scene_arrays(scene: Scene, num_frames: int) -> dict[str, np.ndarray]:
    """The motion file's per-frame scene arrays: ``scene_poses``, each object's pose (position,
    wxyz quaternion) in every frame, in scene order. Shape: (T, O, 7)."""
    frames = np.arange(num_frames)
    rows = [o.poses[np.minimum(frames, o.poses.shape[0] - 1)] for o in scene.objects]
    poses = np.stack(rows, axis=1) if rows else np.zeros((num_frames, 0, 7))
    return {"scene_poses": poses}


__all__ = ["human_contacts", "scene_arrays", "scene_floor"]
