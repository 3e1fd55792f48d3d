"""The viewer in a real browser: headless Chromium loads it and the robot is drawn."""

from __future__ import annotations

import io
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from humimic.configs import retarget_default
from humimic.datasets import load_clip
from humimic.motion import save_motion
from humimic.retarget import Retargeter
from humimic.viewer.browser import free_port, screenshot

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(
        shutil.which("chromium") is None,
        reason="no chromium: scripts/test.sh installs it with apt-get where apt-get works "
        "(Debian package chromium); without apt this test cannot run",
    ),
]


def _start_viewer(motion: Path, port: int) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "humimic.cli.main", "view", str(motion), "--port", str(port),
         "--duration", "90"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )  # fmt: skip
    assert proc.stdout is not None
    end = time.monotonic() + 60
    for line in proc.stdout:
        if f"http://127.0.0.1:{port}" in line and "humimic view" in line:
            return proc
        if time.monotonic() > end:
            break
    proc.kill()
    raise AssertionError("the viewer did not start")


def test_browser_draws_the_robot(tmp_path: Path, shared_data: Path) -> None:
    clip = load_clip(shared_data / "cmu" / "35_01.bvh").slice(1, 61)
    motion = tmp_path / "walk.npz"
    save_motion(Retargeter("g1", "cmu", retarget_default()).run(clip).motion, motion)
    port = free_port()
    proc = _start_viewer(motion, port)
    try:
        png = screenshot(
            f"http://127.0.0.1:{port}/", tmp_path / "shot.png", wait=1.0,
            ready=lambda data: _dark_middle(_pixels(data)) > 200, timeout=60.0,
        )  # fmt: skip
    finally:
        proc.kill()
        proc.wait()
    img = _pixels(png.read_bytes())
    # Not blank: a rendered scene has structure.
    assert img.std() > 10.0
    dark = _dark_middle(img)
    assert dark > 200, f"only {dark} dark pixels where the robot should be"


def _pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(float)


def _dark_middle(img: np.ndarray) -> int:
    """The robot: the camera looks at the pelvis, so the robot fills the middle of the canvas
    (left of the control panel). Its dark parts (black links and joints, RGB ~ 0.2) are the
    only near-black pixels there: the floor grid and the background are light."""
    h, w, _ = img.shape
    middle = img[int(0.25 * h) : int(0.75 * h), int(0.25 * w) : int(0.6 * w)]
    return int((middle.max(axis=2) < 80).sum())


def test_view_screenshot_option(tmp_path: Path, shared_data: Path) -> None:
    """`humimic view --screenshot` writes the picture and exits (as the README's was made)."""
    from humimic.cli.main import main

    clip = load_clip(shared_data / "cmu" / "35_01.bvh").slice(1, 31)
    motion = tmp_path / "walk.npz"
    save_motion(Retargeter("g1", "cmu", retarget_default()).run(clip).motion, motion)
    out = tmp_path / "pic.png"
    argv = ["view", str(motion), "--port", str(free_port()), "--screenshot", str(out)]
    assert main(argv) == 0
    img = np.asarray(Image.open(out).convert("RGB")).astype(float)
    assert img.shape[0] > 500 and img.std() > 10.0
