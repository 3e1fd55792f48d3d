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


def scene_arrays(scene: Scene, num_frames: int) -> dict[str, np.ndarray]:
    """The motion file's per-frame scene arrays: ``scene_poses``, each object's pose (position,
    wxyz quaternion) in every frame, in scene order. Shape: (T, O, 7)."""
    frames = np.arange(num_frames)
    rows = [o.poses[np.minimum(frames, o.poses.shape[0] - 1)] for o in scene.objects]
    poses = np.stack(rows, axis=1) if rows else np.zeros((num_frames, 0, 7))
    return {"scene_poses": poses}


__all__ = ["human_contacts", "scene_arrays"]
