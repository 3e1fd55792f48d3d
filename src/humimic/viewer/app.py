"""The browser viewer: a robot motion, the human it came from, scene objects and a rollout.

Built on viser: one server, one robot drawn with its real meshes, optional human skeleton
(beside or overlaid), optional second robot (a rollout, translucent), a timeline with play,
pause, speed, loop and stepping, a panel with the current frame's metrics and a plot of the
key-point error over time.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from humimic.datasets.clip import HumanClip
from humimic.errors import InputError
from humimic.motion import Motion
from humimic.transforms import axis_angle_matrix
from humimic.viewer.scene import PoseTrack, pose_track, skeleton_segments, visual_meshes

HUMAN_BESIDE_OFFSET = np.array([0.0, 1.0, 0.0])
"""Where the human skeleton stands, relative to the robot, in "beside" mode [m]."""


@dataclass(frozen=True, kw_only=True)
class SceneMesh:
    """A static scene object (box, terrain) in the human clip's frame, before alignment."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    local_vertices: np.ndarray | None = None
    """The vertices in the object's own frame (scene files), for objects that move: the
    motion's ``scene_poses`` (interaction-mesh retargeting) place them frame by frame."""


def load_scene_meshes(path: str | Path) -> list[SceneMesh]:
    """Scene objects from a scene file (.yaml, :func:`humimic.retarget.scene.load_scene`), a
    mesh file (.obj, .stl, .ply) or a folder of them (trimesh)."""
    import trimesh

    p = Path(path)
    if p.suffix.lower() in (".yaml", ".yml"):
        from humimic.retarget.scene import load_scene

        return [
            SceneMesh(
                name=o.name, vertices=o.world_vertices(0), faces=o.faces, local_vertices=o.vertices
            )
            for o in load_scene(p).objects
        ]
    if p.is_dir():
        files = sorted(f for f in p.rglob("*") if f.suffix.lower() in (".obj", ".stl", ".ply"))
        if not files:
            raise InputError(f"{p}: folder holds no .obj, .stl or .ply meshes")
    elif p.is_file():
        files = [p]
    else:
        raise InputError(f"{p}: no such file or folder")
    out = []
    for f in files:
        try:
            mesh = trimesh.load(f, force="mesh")
        except Exception as e:  # trimesh raises many types for bad files.
            raise InputError(f"{f}: cannot read mesh ({e})") from None
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise InputError(f"{f}: no triangles in this mesh file")
        out.append(SceneMesh(name=f.stem, vertices=np.asarray(mesh.vertices), faces=mesh.faces))
    return out


def align_human(motion: Motion, clip: HumanClip) -> np.ndarray:
    """The human clip in the motion's world frame (heading-aligned, not scaled), per frame.

    Uses the alignment the retargeter stored in ``motion.info``; the clip is cut at the same
    start frame and resampled to the motion's rate.

    Returns:
        Joint positions. Shape: (T, J, 3).
    """
    info = motion.info or {}
    if "human_yaw" not in info:
        raise InputError("the motion file has no human alignment (it was not made by humimic)")
    start = int(info.get("start_frame", 0))
    if start >= clip.num_frames:
        raise InputError(f"{clip.source}: start frame {start} beyond the clip's frames")
    c = clip.slice(start).resample(motion.fps)
    rot = axis_angle_matrix("z", np.asarray(float(info["human_yaw"])))
    origin = np.asarray(info["human_origin"], dtype=np.float64)
    origin[2] = float(info.get("human_ground", 0.0))  # The human's measured floor onto ours.
    pos = (c.positions_w - origin) @ rot.T
    n = motion.num_frames
    if pos.shape[0] < n:
        pos = np.concatenate([pos, np.repeat(pos[-1:], n - pos.shape[0], axis=0)])
    return pos[:n]


def align_scene(motion: Motion, meshes: list[SceneMesh]) -> list[SceneMesh]:
    """Scene meshes in the motion's world frame at the human's scale."""
    info = motion.info or {}
    rot = axis_angle_matrix("z", np.asarray(float(info.get("human_yaw", 0.0))))
    origin = np.asarray(info.get("human_origin", [0.0, 0.0, 0.0]), dtype=np.float64)
    origin[2] = float(info.get("human_ground", 0.0))
    return [
        SceneMesh(
            name=m.name,
            vertices=(m.vertices - origin) @ rot.T,
            faces=m.faces,
            local_vertices=m.local_vertices,
        )
        for m in meshes
    ]


class Viewer:
    """Serve a motion in the browser. :meth:`start` returns at once; :meth:`serve_forever`
    plays until interrupted."""

    def __init__(
        self,
        motion: Motion,
        model: Any,
        *,
        human: HumanClip | None = None,
        scene: list[SceneMesh] | None = None,
        rollout_qpos: np.ndarray | None = None,
        host: str = "127.0.0.1",
        port: int = 8080,
    ) -> None:
        self.motion = motion
        self.model = model
        self.meshes = visual_meshes(model)
        geoms = [m.geom for m in self.meshes]
        self.track: PoseTrack = pose_track(model, motion.qpos, geoms)
        self.rollout: PoseTrack | None = None
        if rollout_qpos is not None:
            self.rollout = pose_track(model, rollout_qpos, geoms)
        self.human = align_human(motion, human) if human is not None else None
        self.human_parents = human.parents if human is not None else ()
        self.scene = align_scene(motion, scene) if scene else []
        extras = motion.extras or {}
        self.targets = extras.get("keypoint_targets")
        self.kp_error = extras.get("metric_keypoint_error")
        self.penetration = extras.get("metric_ground_penetration")
        self.contacts = extras.get("human_contacts")
        self.scene_penetration = extras.get("metric_scene_penetration")
        poses = extras.get("scene_poses")  # (T, objects, 7), the robot's frame.
        moving = poses is not None and poses.shape[1] == len(self.scene)
        self.scene_poses = poses if moving and all(
            m.local_vertices is not None for m in self.scene
        ) else None  # fmt: skip
        self._scene_handles: list[Any] = []
        self.host, self.port = host, port
        self.frame = 0
        self._lock = threading.Lock()
        self._server: Any = None

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def start(self, frame: int = 0) -> None:
        """Start the server and build the scene and the panel, showing ``frame``."""
        import viser

        server = viser.ViserServer(host=self.host, port=self.port, label="humimic", verbose=False)
        self._server = server
        server.scene.set_up_direction("+z")
        pelvis = self.track.body_pos[frame, 0]
        server.initial_camera.look_at = pelvis
        server.initial_camera.position = pelvis + np.array([1.8, -2.6, 0.9])
        server.scene.add_grid("/ground", width=10.0, height=10.0, cell_size=0.5, position=(0, 0, 0))
        self._robot = [
            server.scene.add_mesh_simple(
                f"/robot/{i}_{m.body}",
                m.vertices,
                m.faces,
                color=(m.rgba[:3] * 255).astype(np.uint8),
            )
            for i, m in enumerate(self.meshes)
        ]
        self._rollout = []
        if self.rollout is not None:
            self._rollout = [
                server.scene.add_mesh_simple(
                    f"/rollout/{i}_{m.body}",
                    m.vertices,
                    m.faces,
                    color=(255, 140, 40),
                    opacity=0.45,
                )
                for i, m in enumerate(self.meshes)
            ]
        self._targets = None
        if self.targets is not None:
            self._targets = server.scene.add_point_cloud(
                "/robot_targets",
                self.targets[0],
                colors=(230, 40, 40),
                point_size=0.025,
                point_shape="circle",
            )
        # The human and its scene move aside together in "beside" mode.
        self._human_handles: list[Any] = []
        self._human_bones = self._human_joints = None
        if self.human is not None:
            segs = skeleton_segments(self.human[:1], self.human_parents)[0]
            self._human_bones = server.scene.add_line_segments(
                "/human/bones", segs, colors=(40, 110, 230), thickness=0.015
            )
            self._human_joints = server.scene.add_point_cloud(
                "/human/joints",
                self.human[0],
                colors=(20, 60, 160),
                point_size=0.03,
                point_shape="circle",
            )
            self._human_handles += [self._human_bones, self._human_joints]
        info = self.motion.info or {}
        scale = float(info.get("human_scale", 1.0))
        lift = np.array([0.0, 0.0, float(info.get("human_z_offset", 0.0))])
        for i, m in enumerate(self.scene):
            # With the human, at its scale...
            self._human_handles.append(
                server.scene.add_mesh_simple(
                    f"/human_scene/{i}_{m.name}",
                    m.vertices,
                    m.faces,
                    color=(90, 120, 220),
                    opacity=0.5,
                )
            )
            # ...and at the robot's scale, where the retargeted motion uses it: posed per
            # frame from the motion's scene_poses when it has them.
            if self.scene_poses is not None and m.local_vertices is not None:
                self._scene_handles.append(
                    server.scene.add_mesh_simple(
                        f"/scene/{i}_{m.name}", m.local_vertices * scale, m.faces,
                        color=(170, 150, 120), opacity=0.8,
                    )
                )  # fmt: skip
            else:
                server.scene.add_mesh_simple(
                    f"/scene/{i}_{m.name}", m.vertices * scale + lift, m.faces,
                    color=(170, 150, 120), opacity=0.8,
                )  # fmt: skip
        self._build_gui(server)
        self.set_frame(frame)

    def _build_gui(self, server: Any) -> None:
        import viser.uplot as uplot

        T = self.motion.num_frames
        gui = server.gui
        with gui.add_folder("Playback"):
            self._slider = gui.add_slider(
                "Frame", min=0, max=max(T - 1, 1), step=1, initial_value=0
            )
            self._playing = gui.add_checkbox("Play", initial_value=False)
            self._speed = gui.add_slider("Speed", min=0.1, max=4.0, step=0.1, initial_value=1.0)
            self._loop = gui.add_checkbox("Loop", initial_value=True)
            prev_btn = gui.add_button("Previous frame")
            next_btn = gui.add_button("Next frame")
            self._follow = gui.add_checkbox("Camera follows pelvis", initial_value=False)
        with gui.add_folder("Show"):
            self._beside = gui.add_checkbox("Human beside (off: overlaid)", initial_value=True)
            self._show_targets = gui.add_checkbox("Key-point targets", initial_value=True)
        with gui.add_folder("Frame metrics"):
            self._metrics = gui.add_markdown("")
            if self.kp_error is not None:
                t = np.arange(T) / self.motion.fps
                gui.add_uplot(
                    data=(t, self.kp_error * 1e3),
                    series=(uplot.Series(label="time [s]"), uplot.Series(label="key-point error [mm]", stroke="red")),
                    title="Key-point error",
                    aspect=1.6,
                )  # fmt: skip

        @self._slider.on_update
        def _(_: Any) -> None:
            self._render(int(self._slider.value))

        @prev_btn.on_click
        def _(_: Any) -> None:
            self._slider.value = max(int(self._slider.value) - 1, 0)

        @next_btn.on_click
        def _(_: Any) -> None:
            self._slider.value = min(int(self._slider.value) + 1, T - 1)

        @self._beside.on_update
        def _(_: Any) -> None:
            self._render(self.frame)

        @self._show_targets.on_update
        def _(_: Any) -> None:
            if self._targets is not None:
                self._targets.visible = bool(self._show_targets.value)

    def set_frame(self, t: int) -> None:
        """Move everything, and the timeline, to frame ``t`` (clamped to the motion)."""
        t = int(np.clip(t, 0, self.motion.num_frames - 1))
        self._render(t)
        if int(self._slider.value) != t:
            self._slider.value = t

    def _render(self, t: int) -> None:
        with self._lock:
            self.frame = t = int(np.clip(t, 0, self.motion.num_frames - 1))
            server = self._server
            with server.atomic():
                for h, p, q in zip(
                    self._robot, self.track.geom_pos[t], self.track.geom_quat[t], strict=True
                ):
                    h.position, h.wxyz = p, q
                if self.rollout is not None:
                    r = min(t, self.rollout.geom_pos.shape[0] - 1)
                    for h, p, q in zip(
                        self._rollout,
                        self.rollout.geom_pos[r],
                        self.rollout.geom_quat[r],
                        strict=True,
                    ):
                        h.position, h.wxyz = p, q
                if self._targets is not None and self.targets is not None:
                    self._targets.points = self.targets[t]
                if self.scene_poses is not None:
                    for h, pose in zip(self._scene_handles, self.scene_poses[t], strict=True):
                        h.position, h.wxyz = pose[:3], pose[3:]
                if self.human is not None and self._human_bones is not None:
                    offset = HUMAN_BESIDE_OFFSET if self._beside.value else np.zeros(3)
                    joints = self.human[t] + offset
                    self._human_bones.points = skeleton_segments(joints[None], self.human_parents)[
                        0
                    ]
                    if self._human_joints is not None:
                        self._human_joints.points = joints
                if self._follow.value:
                    pelvis = self.track.body_pos[t, 0]
                    for client in server.get_clients().values():
                        client.camera.look_at = pelvis
                        client.camera.position = pelvis + np.array([-2.5, -2.5, 1.2])
            self._metrics.content = self.metrics_text(t)

    def metrics_text(self, t: int) -> str:
        """The panel's text for frame ``t``."""
        fps = self.motion.fps
        lines = [f"**Frame {t} / {self.motion.num_frames - 1}** ({t / fps:.2f} s)"]
        if self.kp_error is not None:
            lines.append(f"Key-point error: {self.kp_error[t] * 1e3:.1f} mm")
        if self.contacts is not None:
            c = self.contacts[t]
            feet = [side for side, flags in zip(("left", "right"), c, strict=False) if flags.any()]
            lines.append(f"Human foot contact: {', '.join(feet) or 'none'}")
        if self.penetration is not None:
            lines.append(f"Ground penetration: {self.penetration[t] * 1e3:.1f} mm")
        if self.scene_penetration is not None:
            lines.append(f"Scene penetration: {self.scene_penetration[t] * 1e3:.1f} mm")
        return "  \n".join(lines)

    def step(self, dt: float) -> None:
        """Advance playback by ``dt`` seconds of wall time (when playing)."""
        if not self._playing.value:
            return
        n = self.motion.num_frames
        advance = max(1, round(dt * self.motion.fps * float(self._speed.value)))
        t = self.frame + advance
        if t >= n:
            if not self._loop.value:
                self._playing.value = False
                return
            t %= n
        self.set_frame(t)

    def serve_forever(self, duration: float | None = None) -> None:
        """Play until interrupted (or for ``duration`` seconds)."""
        period = 1.0 / min(self.motion.fps, 30.0)
        t_end = None if duration is None else time.monotonic() + duration
        while t_end is None or time.monotonic() < t_end:
            time.sleep(period)
            self.step(period)

    def stop(self) -> None:
        if self._server is not None:
            self._server.stop()
