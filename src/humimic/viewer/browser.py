"""Screenshots of the viewer in a real browser: headless Chromium over the DevTools protocol.

Used by the tests and to make the README's picture. Needs the system's ``chromium`` (Debian
package ``chromium``); Playwright's own browser download is not used.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

from humimic.errors import MissingDependencyError
from humimic.io import atomic_write

CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)


def find_chromium() -> str:
    """Path of the system Chromium; :class:`MissingDependencyError` with the install hint."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    raise MissingDependencyError(
        "no Chromium found: install it with `apt-get install chromium` (Debian/Ubuntu)"
    )


def free_port() -> int:
    """A free TCP port on the loopback interface."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def screenshot(
    url: str,
    out: str | Path,
    *,
    wait: float = 6.0,
    size: tuple[int, int] = (1200, 800),
    ready: Callable[[bytes], bool] | None = None,
    timeout: float = 60.0,
) -> Path:
    """Open ``url`` in headless Chromium, wait ``wait`` seconds, save a PNG to ``out``.

    With ``ready``, keep capturing every 2 s until ``ready(png)`` holds or ``timeout`` seconds
    have passed (software WebGL on a loaded machine can take a while to draw), and save the
    last capture.
    """
    from websockets.sync.client import connect

    port = free_port()
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as profile:
        proc = subprocess.Popen(
            [
                find_chromium(),
                *CHROMIUM_FLAGS,
                f"--user-data-dir={profile}",
                f"--remote-debugging-port={port}",
                f"--window-size={size[0]},{size[1]}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,  # Its own process group: every helper process ends with it.
        )
        try:
            tabs = _wait_for_tabs(port, timeout=30.0)
            page = next(t for t in tabs if t.get("type") == "page")
            with connect(page["webSocketDebuggerUrl"], max_size=None) as ws:
                counter = iter(range(1, 1_000_000))

                def call(method: str, **params: object) -> dict:
                    n = next(counter)
                    ws.send(json.dumps({"id": n, "method": method, "params": params}))
                    while True:
                        msg = json.loads(ws.recv(timeout=60))
                        if msg.get("id") == n:
                            return msg.get("result", {})

                call("Page.enable")
                call("Page.navigate", url=url)
                time.sleep(wait)
                end = time.monotonic() + timeout
                while True:
                    data = call("Page.captureScreenshot", format="png")["data"]
                    if ready is None or ready(base64.b64decode(data)) or time.monotonic() > end:
                        break
                    time.sleep(2.0)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    path = Path(out)
    with atomic_write(path) as f:  # Never a half-written PNG.
        f.write(base64.b64decode(data))
    return path


def _wait_for_tabs(port: int, timeout: float) -> list[dict]:
    end = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=1) as r:
                return json.load(r)
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.1)
