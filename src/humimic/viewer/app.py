"""The browser viewer: a robot motion, the human it came from, scene objects and a rollout.

Built on viser: one server, one robot drawn with its real meshes, optional human skeleton
(beside or overlaid), optional second robot (a rollout, translucent), a timeline with play,
pause, speed, loop and stepping, a panel with the current frame's metrics and a plot of the
key-point error over time.
"""

from __future__ import annotations

import errno
import ipaddress
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from humimic.datasets.clip import HumanClip
from humimic.datasets.scene import load_scene
from humimic.errors import InputError
from humimic.motion import Motion
from humimic.transforms import axis_angle_matrix
from humimic.viewer.scene import PoseTrack, pose_track, skeleton_segments, visual_meshes

HUMAN_BESIDE_OFFSET = np.array([0.0, 1.0, 0.0])
"""Where the human skeleton stands, relative to the robot, in "beside" mode [m]."""

RESOLVE_TIMEOUT_S = 10.0
"""How long looking up ``--host`` may take before the viewer gives up [s]."""

PORT_SEARCH = 100
"""How many ports after a taken ``--port`` the viewer tries before it gives up."""

SockAddr = tuple[int, tuple[Any, ...]]
"""An address family and a socket address (host, port, ...) to listen on."""


@dataclass(frozen=True, kw_only=True)
class SceneMesh:
    """A scene object (box, terrain) in the human clip's frame, before alignment."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    local_vertices: np.ndarray | None = None
    """The vertices in the object's own frame, for objects that move: the motion's
    ``scene_poses`` (interaction-mesh retargeting) place them frame by frame."""


def load_scene_meshes(path: str | Path) -> list[SceneMesh]:
    """Scene objects from what ``humimic retarget --scene`` reads: a scene file (.yaml), a
    mesh file (.obj, .stl) or a clip folder in holosoma's layout (``box_models/*.obj``), with
    the same checks and limits (:func:`humimic.datasets.scene.load_scene`).

    Raises:
        InputError: As :func:`~humimic.datasets.scene.load_scene` (names the file).
    """
    return [
        SceneMesh(
            name=o.name, vertices=o.world_vertices(0), faces=o.faces, local_vertices=o.vertices
        )
        for o in load_scene(path).objects
    ]


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


def resolve_host(host: str) -> list[SockAddr]:
    """The addresses a server bound to ``host`` listens on (as asyncio resolves them).

    The lookup runs in a thread with a time limit (:data:`RESOLVE_TIMEOUT_S`), so that a
    name whose DNS server does not answer cannot hang the viewer.

    Raises:
        InputError: ``host`` is empty, cannot be resolved, or the lookup timed out.
    """
    if not isinstance(host, str) or not host.strip():
        raise InputError(
            f"--host {host!r}: expected an address of this machine (127.0.0.1, 0.0.0.0, ::) "
            "or a host name"
        )
    box: dict[str, Any] = {}

    def lookup() -> None:
        try:
            box["infos"] = socket.getaddrinfo(
                host, None, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
            )
        except (OSError, ValueError) as e:  # ValueError: a NUL byte, a bad IDNA label.
            box["error"] = e

    thread = threading.Thread(target=lookup, name="humimic-resolve-host", daemon=True)
    thread.start()
    thread.join(RESOLVE_TIMEOUT_S)
    if thread.is_alive():
        raise InputError(
            f"--host {host}: looking up this name took over {RESOLVE_TIMEOUT_S:g} s; "
            "expected an address of this machine, e.g. 127.0.0.1"
        )
    if "error" in box:
        e = box["error"]
        reason = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
        shown = host if host.isprintable() else repr(host)
        raise InputError(f"--host {shown}: cannot resolve this name ({reason})")
    addrs: list[SockAddr] = []
    for family, _, _, _, sockaddr in box["infos"]:
        if family in (socket.AF_INET, socket.AF_INET6) and (family, sockaddr) not in addrs:
            addrs.append((family, tuple(sockaddr)))
    if not addrs:
        raise InputError(f"--host {host}: resolves to no IPv4 or IPv6 address")
    return addrs


def try_bind(addrs: list[SockAddr], port: int) -> None:
    """Bind a socket to each address at ``port`` and close it again, as asyncio's
    ``create_server`` (which viser uses) binds them: ``SO_REUSEADDR``, IPv6 only on IPv6.

    Raises:
        OSError: An address cannot be bound (the first such error).
    """
    for family, sockaddr in addrs:
        try:
            sock = socket.socket(family, socket.SOCK_STREAM)
        except OSError:
            continue  # asyncio skips a family this machine lacks, too.
        with sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            sock.bind((sockaddr[0], port, *sockaddr[2:]))


def check_host(host: str) -> list[SockAddr]:
    """Resolve ``host`` and check that this machine can listen on it (a test bind, no traffic).

    Raises:
        InputError: Naming ``--host`` and the operating system's reason.
    """
    addrs = resolve_host(host)
    try:
        try_bind(addrs, 0)
    except OSError as e:
        raise InputError(
            f"--host {host}: cannot listen on this address ({e.strerror or e}); expected an "
            "address of this machine, e.g. 127.0.0.1 (this machine only) or 0.0.0.0 (all)"
        ) from None
    return addrs


def check_port(port: int) -> int:
    """``port`` if it is a TCP port number (0: any free port).

    Raises:
        InputError: Naming ``--port``.
    """
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise InputError(
            f"--port {port}: expected a TCP port from 1 to 65535 (or 0 for any free port)"
        )
    return port


def free_port_from(addrs: list[SockAddr], host: str, port: int) -> int:
    """``port``, or when it is taken on ``host`` the first free one of the next
    :data:`PORT_SEARCH` (as viser would move on, but never past 65535).

    Raises:
        InputError: ``port`` cannot be used for another reason (e.g. no permission), or it
            and the next ports are all taken.
    """
    if port == 0:
        return 0  # The system picks a free one; viser reports which.
    last = min(port + PORT_SEARCH, 65535)
    for p in range(port, last + 1):
        try:
            try_bind(addrs, p)
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                continue
            raise InputError(
                f"--port {port}: cannot listen on {host} port {p} ({e.strerror or e})"
            ) from None
        return p
    raise InputError(
        f"--port {port}: ports {port} to {last} are all taken on {host}; expected a free "
        "port (or 0 for any free port)"
    )


def exposure_warning(host: str, addrs: list[SockAddr]) -> str | None:
    """A one-line warning when ``host`` is not loopback only (others can open the viewer)."""
    ips = [ipaddress.ip_address(sockaddr[0].split("%")[0]) for _, sockaddr in addrs]
    if all(ip.is_loopback for ip in ips):
        return None
    where = (
        "on every network interface"
        if any(ip.is_unspecified for ip in ips)
        else "on a network address"
    )
    return (
        f"--host {host} serves the viewer {where}: anyone who can reach this machine can "
        "open it (--host 127.0.0.1 keeps it on this machine)"
    )


class Viewer:
    """Serve a motion in the browser. :meth:`start` returns at once; :meth:`serve_forever`
    plays until interrupted.

    ``host`` and ``port`` are checked when the viewer is made (:class:`InputError` naming
    ``--host`` or ``--port``). A taken port is replaced by the next free one: :attr:`url`
    is the address actually served, and :attr:`warnings` (also printed on stderr by
    :meth:`start`) says so, as it says when the viewer can be reached from the network.
    """

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
        # Bad addresses fail here, before anything is computed or served.
        self._port_requested = check_port(port)
        self._addrs = check_host(host)
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
        self.warnings: list[str] = []
        """One-line warnings about how the viewer is served (printed on stderr by start)."""
        self.frame = 0
        self._lock = threading.Lock()
        self._server: Any = None
        self._serving = False

    @property
    def url(self) -> str:
        """The address to open: the port actually served; loopback for a wildcard host."""
        host = self.host
        try:
            ip = ipaddress.ip_address(host.split("%")[0])
        except ValueError:
            ip = None  # A host name.
        if ip is not None and ip.is_unspecified:
            host = "127.0.0.1" if ip.version == 4 else "::1"
            ip = ipaddress.ip_address(host)
        if ip is not None and ip.version == 6:
            host = f"[{host}]"
        return f"http://{host}:{self.port}"

    def start(self, frame: int = 0) -> None:
        """Start the server and build the scene and the panel, showing ``frame``.

        Prints :attr:`warnings` on stderr. On any error the server is stopped again.

        Raises:
            InputError: ``frame`` is not a frame of the motion (naming ``--frame``), or the
                port cannot be used (naming ``--port``).
        """
        import viser

        n = self.motion.num_frames
        if not 0 <= frame < n:
            raise InputError(f"--frame {frame}: the motion has {n} frames (0 to {n - 1})")
        port = free_port_from(self._addrs, self.host, self._port_requested)
        self.warnings = []
        server = viser.ViserServer(host=self.host, port=port, label="humimic", verbose=False)
        self._server, self._serving = server, True
        try:
            # viser moves on by itself when a port is taken after the check: ask it.
            self.port = int(server.get_port())
            if self._port_requested and self.port != self._port_requested:
                self.warnings.append(
                    f"--port {self._port_requested} is taken on {self.host}; serving on port "
                    f"{self.port} instead"
                )
            exposed = exposure_warning(self.host, self._addrs)
            if exposed is not None:
                self.warnings.append(exposed)
            for w in self.warnings:
                print(f"humimic: warning: {w}", file=sys.stderr, flush=True)
            self._build_scene(server, frame)
        except BaseException:
            self.stop()
            raise

    def _build_scene(self, server: Any, frame: int) -> None:
        """Everything the page shows, at ``frame``: camera, ground, the robot, the rollout and
        key-point targets where given, the human and the scene, then the panel."""
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
        self._add_human(server)
        self._add_scene(server)
        self._build_gui(server)
        self.set_frame(frame)

    def _add_human(self, server: Any) -> None:
        """The human skeleton (bones and joints) at frame 0, if there is one: its handles join
        ``_human_handles``, which "beside" mode moves aside."""
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

    def _add_scene(self, server: Any) -> None:
        """Each scene object twice: with the human (at its scale, moved aside with it) and at
        the robot's scale where the retargeted motion uses it (posed per frame from the
        motion's ``scene_poses`` when it has them, else static)."""
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
        """Stop the server (if started); safe to call more than once."""
        if self._server is not None and self._serving:
            self._serving = False
            self._server.stop()
