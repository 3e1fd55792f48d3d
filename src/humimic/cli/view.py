"""``humimic view``: a motion in the browser, beside its human clip, scene and rollout."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from humimic.errors import InputError
from humimic.io import check_not_input, check_writable


@dataclass(frozen=True, kw_only=True)
class ViewCommand:
    """Look at a motion in the browser, beside the human it came from (viser)."""

    motion: Annotated[Path, tyro.conf.Positional]
    """Robot motion (.npz or .mcap)."""
    human: Path | None = None
    """The human clip it was retargeted from (.bvh, .npy, .npz), drawn as a skeleton."""
    scene: Path | None = None
    """Scene objects, in the clip's frame: a scene file (.yaml; moving objects follow the
    motion's scene_poses), a mesh file (.obj, .stl, .ply) or a folder of them."""
    rollout: Path | None = None
    """A rollout or robot log (.mcap with /qpos, or /base_pose and /joint_states). Default: the
    motion file's own /qpos when it is an MCAP that has one (``humimic eval --mcap``)."""
    host: str = "127.0.0.1"
    """Address to bind; 127.0.0.1 keeps the viewer on this machine (0.0.0.0 exposes it)."""
    port: int = 8080
    """TCP port (1-65535; 0: any free port). A taken port moves on to the next free one, and
    the printed URL says which."""
    frame: int = 0
    """Frame to show first."""
    screenshot: Path | None = None
    """Save a PNG of the viewer (headless Chromium, which must be installed) and exit."""
    duration: float | None = None
    """Stop after this many seconds (default: run until Ctrl-C)."""

    def validate(self) -> None:
        """Check the numbers before anything is read; :class:`InputError` names the flag."""
        from humimic.viewer.app import check_port

        check_port(self.port)
        if self.frame < 0:
            raise InputError(f"--frame {self.frame}: must be a frame number >= 0")
        if self.duration is not None and not self.duration >= 0:  # 0: start, then stop.
            raise InputError(f"--duration {self.duration}: must be a number of seconds >= 0")


def run_view(cmd: ViewCommand) -> None:
    """Run ``humimic view``."""
    import time

    from humimic.datasets import load_clip
    from humimic.pipeline.files import load_rollout, read_any_motion
    from humimic.robots.model import motion_model
    from humimic.viewer import Viewer, load_scene_meshes
    from humimic.viewer.app import check_host

    t0 = time.perf_counter()
    cmd.validate()  # Bad addresses fail at once, before the motion loads.
    check_host(cmd.host)
    if cmd.screenshot is not None:
        inputs = {"the motion": cmd.motion, "--human": cmd.human, "--rollout": cmd.rollout}
        check_not_input(cmd.screenshot, inputs, "--screenshot")
        check_writable(cmd.screenshot)
    motion = read_any_motion(cmd.motion)
    model = motion_model(motion, str(cmd.motion))
    human = load_clip(cmd.human) if cmd.human is not None else None
    scene = load_scene_meshes(cmd.scene) if cmd.scene is not None else None
    rollout = load_rollout(cmd.rollout, cmd.motion, motion)
    viewer = Viewer(
        motion, model, human=human, scene=scene, rollout_qpos=rollout, host=cmd.host, port=cmd.port
    )
    if not 0 <= cmd.frame < motion.num_frames:
        raise InputError(f"--frame {cmd.frame}: the motion has {motion.num_frames} frames")
    try:
        viewer.start(frame=cmd.frame)
    except OSError as e:
        raise InputError(
            f"--host {cmd.host} --port {cmd.port}: cannot serve there ({e.strerror})"
        ) from None
    print(
        f"humimic view: {viewer.url} ({motion.num_frames} frames, loaded in "
        f"{time.perf_counter() - t0:.1f} s); Ctrl-C to stop",
        flush=True,
    )
    try:
        if cmd.screenshot is not None:
            from humimic.viewer.browser import screenshot

            screenshot(viewer.url, cmd.screenshot, wait=8.0)
            print(f"wrote {cmd.screenshot}")
        else:
            viewer.serve_forever(cmd.duration)
    finally:
        viewer.stop()
