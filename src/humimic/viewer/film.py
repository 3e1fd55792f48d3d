"""Pictures of a rollout beside its reference, rendered by MuJoCo's own renderer: a filmstrip
(PNG: the rollout above the reference at a few key frames) and a video of the whole episode
(GIF: the two side by side, each frame's tracking error written on it).

Rendering needs an OpenGL context without a display: EGL (Mesa's software renderer works
without a GPU) with ``EGL_PLATFORM=surfaceless``, else OSMesa. MuJoCo reads ``MUJOCO_GL``
when it is first imported, so :func:`render_eval_film` runs the rendering in a child process
(``python -m humimic.viewer.film``) with those variables set, and says why when it fails.

Usage: ``python -m humimic.viewer.film EVAL.mcap --png film.png --gif film.gif``
(an MCAP of ``humimic eval``: its reference and the policy's ``/qpos``).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from humimic.errors import InputError

WIDTH, HEIGHT = 360, 300
"""One view's size in pixels."""


def render_eval_film(mcap: Path, png: Path, gif: Path | None, timeout_s: float = 600.0) -> None:
    """Render an evaluation MCAP's first episode (:func:`film`) in a child process.

    Raises:
        InputError: The renderer failed (no OpenGL context here, say): the child's last
            line of error.
    """
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    if env["MUJOCO_GL"] == "egl":
        env.setdefault("EGL_PLATFORM", "surfaceless")
    cmd = [sys.executable, "-m", "humimic.viewer.film", str(mcap), "--png", str(png)]
    if gif is not None:
        cmd += ["--gif", str(gif)]
    try:
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise InputError(f"rendering {mcap} took more than {timeout_s:.0f} s") from None
    if done.returncode != 0:
        lines = [x for x in done.stderr.splitlines() if x.strip()]
        raise InputError(f"rendering {mcap} failed: {lines[-1] if lines else 'no message'}")


def film(
    robot: str,
    reference: np.ndarray,
    rollout: np.ndarray,
    fps: float,
    png: Path,
    gif: Path | None = None,
    *,
    key_frames: int = 6,
    gif_fps: float = 10.0,
) -> None:
    """Render ``rollout`` (Shape: (K, nq)) beside ``reference`` (Shape: (T, nq), K <= T, at
    ``fps``) on the robot's nominal model: a filmstrip of ``key_frames`` frames spread over
    the rollout (``png``) and, if ``gif``, a video at ``gif_fps``. Each view follows the
    robot's root, so a drift of the whole robot shows only in the error written on the frame:
    the mean distance between the rollout's and the reference's bodies in the world [mm] (red
    above 100 mm)."""
    import mujoco
    from PIL import Image, ImageDraw

    from humimic.io import atomic_write
    from humimic.robots import get_robot, nominal_model

    model = nominal_model(get_robot(robot))
    if rollout.shape[1] != model.nq or reference.shape[1] != model.nq:
        raise InputError(f"the rollout or reference is not a {robot} motion (nq {model.nq})")
    k = min(len(rollout), len(reference))
    if k < 1:
        raise InputError("the rollout has no frame to render")
    data = mujoco.MjData(model)
    renderer = mujoco.Renderer(model, HEIGHT, WIDTH)
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    cam.trackbodyid = 1  # The floating base.
    cam.distance, cam.azimuth, cam.elevation = 2.3, 135.0, -10.0
    body_err = np.zeros(k)

    def view(qpos: np.ndarray) -> tuple[Image.Image, np.ndarray]:
        data.qpos[:] = qpos
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera=cam)
        return Image.fromarray(renderer.render()), data.xpos[1:].copy()

    def pair(i: int) -> Image.Image:
        a, pa = view(rollout[i])
        b, pb = view(reference[i])
        body_err[i] = 1e3 * float(np.linalg.norm(pa - pb, axis=-1).mean())
        img = Image.new("RGB", (2 * WIDTH, HEIGHT + 22), "white")
        img.paste(a, (0, 22))
        img.paste(b, (WIDTH, 22))
        d = ImageDraw.Draw(img)
        d.text((6, 5), f"rollout, t = {i / fps:.2f} s, global error {body_err[i]:.0f} mm",
               fill=(160, 0, 0) if body_err[i] > 100.0 else "black")  # fmt: skip
        d.text((WIDTH + 6, 5), f"reference, t = {i / fps:.2f} s", fill="black")
        return img

    try:
        picks = np.unique(np.linspace(0, k - 1, min(key_frames, k)).round().astype(int))
        strip = Image.new("RGB", (len(picks) * WIDTH, 2 * HEIGHT + 44), "white")
        for c, i in enumerate(picks):
            p = pair(int(i))
            strip.paste(p.crop((0, 0, WIDTH, HEIGHT + 22)), (c * WIDTH, 0))
            strip.paste(p.crop((WIDTH, 0, 2 * WIDTH, HEIGHT + 22)), (c * WIDTH, HEIGHT + 22))
        with atomic_write(png) as f:
            strip.save(f, format="PNG")
        if gif is not None:
            step = max(1, round(fps / gif_fps))
            frames = [pair(i) for i in range(0, k, step)]
            with atomic_write(gif) as f:
                frames[0].save(f, format="GIF", save_all=True, append_images=frames[1:],
                               duration=round(1000 * step / fps), loop=0)  # fmt: skip
    finally:
        renderer.close()


def _main(argv: list[str] | None = None) -> int:
    from humimic.formats.mcap import qpos_from_log, read_mcap, read_motion_mcap

    ap = argparse.ArgumentParser(prog="python -m humimic.viewer.film",
                                 description="Render an evaluation MCAP's first episode.")  # fmt: skip
    ap.add_argument("mcap", type=Path)
    ap.add_argument("--png", type=Path, required=True)
    ap.add_argument("--gif", type=Path)
    a = ap.parse_args(argv)
    try:
        reference = read_motion_mcap(a.mcap)
        _, qpos = qpos_from_log(read_mcap(a.mcap, topics=["/qpos"]), reference.joint_names)
        film(reference.robot, reference.qpos, qpos, reference.fps, a.png, a.gif)
    except InputError as e:
        print(f"humimic: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(_main())


__all__ = ["film", "render_eval_film"]
