"""The browser viewer (viser): robot, human, scene and rollout side by side."""

from humimic.viewer.app import Viewer, align_human, load_scene_meshes
from humimic.viewer.scene import pose_track, skeleton_segments, visual_meshes

__all__ = [
    "Viewer",
    "align_human",
    "load_scene_meshes",
    "pose_track",
    "skeleton_segments",
    "visual_meshes",
]
