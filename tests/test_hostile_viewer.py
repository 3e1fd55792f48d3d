"""Hostile addresses for ``humimic view``: taken, out-of-range and foreign ports and hosts.

Every server binds 127.0.0.1 (or, once, the wildcard address) and every connection goes to
127.0.0.1 only; the foreign addresses are only test-bound, never sent to.
"""

from __future__ import annotations

import socket
import time
import urllib.parse
import urllib.request
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

import humimic.viewer.app as app
from humimic.cli.main import main
from humimic.errors import InputError
from humimic.motion import Motion, motion_from_qpos, save_motion
from humimic.robots import get_robot, nominal_model
from humimic.viewer import Viewer

FOREIGN_CANDIDATES = ("192.0.2.1", "198.51.100.1", "203.0.113.1")
"""Documentation addresses (RFC 5737), never assigned on the public network."""


@cache
def _g1() -> mujoco.MjModel:
    return nominal_model(get_robot("g1"))


@cache
def _still() -> Motion:
    """Three frames of the G1 standing at its reference pose."""
    model = _g1()
    return motion_from_qpos(model, np.repeat(model.qpos0[None], 3, axis=0), 30.0, "g1")


@pytest.fixture
def motion_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The still motion on disk; the CLI reuses the compiled G1 (compiling takes seconds)."""
    monkeypatch.setattr("humimic.robots.nominal_model", lambda cfg, **_: _g1())
    return save_motion(_still(), tmp_path / "still.npz")


@pytest.fixture
def no_server(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if a viser server is made at all."""
    import viser

    def refuse(*_: Any, **__: Any) -> None:
        raise AssertionError("a viser server was started")

    monkeypatch.setattr(viser, "ViserServer", refuse)


@pytest.fixture
def occupied() -> Iterator[int]:
    """A port on 127.0.0.1 held by a plain listening socket (that never answers)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


def _foreign_address() -> str:
    """An IPv4 address that is not on this machine (binding it fails)."""
    for addr in FOREIGN_CANDIDATES:
        with socket.socket() as s:
            try:
                s.bind((addr, 0))
            except OSError:
                return addr
    pytest.skip(f"every one of {FOREIGN_CANDIDATES} is an address of this machine")


def _error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err  # One line, no traceback.
    return lines[0]


def _serves_viser(url: str) -> bool:
    """Whether ``url`` answers with the viser page (a listening socket that never answers:
    no)."""
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return r.status == 200 and b"<html" in r.read().lower()
    except OSError:
        return False


# Item 1: a taken port.


def test_taken_port_serves_on_the_port_really_bound(
    occupied: int, capsys: pytest.CaptureFixture[str]
) -> None:
    viewer = Viewer(_still(), _g1(), port=occupied)
    viewer.start()
    try:
        port = urllib.parse.urlsplit(viewer.url).port
        assert port is not None and port != occupied
        assert port == viewer._server.get_port()
        assert _serves_viser(viewer.url)
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass  # The URL's port is the one actually listening.
        assert len(viewer.warnings) == 1
        assert f"--port {occupied} is taken" in viewer.warnings[0]
        assert f"serving on port {port}" in viewer.warnings[0]
        assert f"humimic: warning: --port {occupied} is taken" in capsys.readouterr().err
    finally:
        viewer.stop()


def test_cli_prints_the_real_url_when_the_port_is_taken(
    motion_file: Path, occupied: int, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(["view", str(motion_file), "--port", str(occupied), "--duration", "0"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    line = next(ln for ln in out.splitlines() if ln.startswith("humimic view: http://"))
    port = urllib.parse.urlsplit(line.split()[2]).port
    assert port is not None and port != occupied
    assert (
        f"humimic: warning: --port {occupied} is taken on 127.0.0.1; serving on port {port}" in err
    )


def test_a_free_port_gives_no_warning(capsys: pytest.CaptureFixture[str]) -> None:
    viewer = Viewer(_still(), _g1(), port=0)  # 0: any free port, read back from viser.
    viewer.start()
    try:
        port = urllib.parse.urlsplit(viewer.url).port
        assert port not in (None, 0)
        assert _serves_viser(viewer.url)
        assert viewer.warnings == []
        assert "warning" not in capsys.readouterr().err
    finally:
        viewer.stop()


def test_every_port_up_to_the_last_taken_is_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    # viser itself would move on to port 65536 and hang; the viewer stops at 65535.
    real = app.try_bind

    def taken_from(addrs: list[app.SockAddr], port: int) -> None:
        if port >= 65530:
            raise OSError(98, "Address already in use")
        real(addrs, port)

    monkeypatch.setattr(app, "try_bind", taken_from)
    viewer = Viewer(_still(), _g1(), port=65530)
    with pytest.raises(InputError, match="--port 65530: ports 65530 to 65535 are all taken"):
        viewer.start()
    assert viewer._server is None


# Item 2: a port out of range.


@pytest.mark.parametrize("port", ["70000", "65536", "-1"])
def test_cli_port_out_of_range_is_an_error_before_anything_starts(
    motion_file: Path,
    tmp_path: Path,
    port: str,
    no_server: None,
    capsys: pytest.CaptureFixture[str],
) -> None:
    shot = tmp_path / "shot.png"
    t0 = time.monotonic()
    rc = main(["view", str(motion_file), "--port", port, "--screenshot", str(shot)])
    assert time.monotonic() - t0 < 10.0  # No hang.
    assert rc == 2
    line = _error_line(capsys)
    assert line.startswith(f"humimic: error: --port {port}: expected a TCP port from 1 to 65535")
    assert not shot.exists()


# Item 3: a host this machine cannot listen on.


def test_cli_foreign_host_is_an_error_naming_host(
    motion_file: Path, no_server: None, capsys: pytest.CaptureFixture[str]
) -> None:
    addr = _foreign_address()
    rc = main(["view", str(motion_file), "--host", addr, "--port", "0"])
    assert rc == 2
    line = _error_line(capsys)
    assert line.startswith(f"humimic: error: --host {addr}: cannot listen on this address (")
    assert "assign requested address" in line  # The operating system's reason.


def test_cli_unknown_host_name_is_an_error_naming_host(
    motion_file: Path, no_server: None, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(["view", str(motion_file), "--host", "no.such.host.invalid"])
    assert rc == 2
    line = _error_line(capsys)
    assert line.startswith("humimic: error: --host no.such.host.invalid: cannot resolve this name")


@pytest.mark.parametrize("host", ["foreign", "no.such.host.invalid", "", "localhost:8080"])
def test_bad_hosts_fail_promptly(host: str, no_server: None) -> None:
    host = _foreign_address() if host == "foreign" else host
    t0 = time.monotonic()
    with pytest.raises(InputError, match=r"^--host "):
        Viewer(_still(), _g1(), host=host, port=8080)
    assert time.monotonic() - t0 < 3.0


def test_a_host_lookup_that_never_answers_times_out(
    monkeypatch: pytest.MonkeyPatch, no_server: None
) -> None:
    import threading

    release = threading.Event()

    def silent_dns(*_: Any, **__: Any) -> list:
        release.wait(10.0)
        raise socket.gaierror(-3, "Temporary failure in name resolution")

    monkeypatch.setattr(app, "RESOLVE_TIMEOUT_S", 0.3)
    monkeypatch.setattr(socket, "getaddrinfo", silent_dns)
    t0 = time.monotonic()
    try:
        with pytest.raises(InputError, match=r"^--host slow\.example: looking up this name took"):
            Viewer(_still(), _g1(), host="slow.example")
        assert time.monotonic() - t0 < 2.0
    finally:
        release.set()  # Let the lookup thread end.


# Item 4: a host reachable from the network.


def test_cli_wildcard_host_warns_that_the_viewer_is_exposed(
    motion_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(["view", str(motion_file), "--host", "0.0.0.0", "--port", "0", "--duration", "0"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    warning = [ln for ln in err.splitlines() if ln.startswith("humimic: warning: --host 0.0.0.0")]
    assert len(warning) == 1 and "every network interface" in warning[0]
    # The URL printed is one to open here (loopback), not the wildcard address.
    assert "humimic view: http://127.0.0.1:" in out


@pytest.mark.parametrize(
    ("host", "exposed"),
    [("127.0.0.1", False), ("localhost", False), ("::1", False), ("0.0.0.0", True),
     ("::", True), ("10.1.2.3", True)],
)  # fmt: skip
def test_exposure_warning_for_non_loopback_hosts(host: str, exposed: bool) -> None:
    addrs = app.resolve_host(host)  # Numeric or /etc/hosts: no network lookup.
    warning = app.exposure_warning(host, addrs)
    if exposed:
        assert warning is not None and warning.startswith(f"--host {host} serves the viewer")
        assert "anyone who can reach this machine" in warning and "\n" not in warning
    else:
        assert warning is None


def test_url_of_wildcard_and_ipv6_hosts() -> None:
    viewer = Viewer(_still(), _g1(), port=0)
    viewer.port = 1234
    assert viewer.url == "http://127.0.0.1:1234"
    viewer.host = "::1"
    assert viewer.url == "http://[::1]:1234"
    viewer.host = "::"
    assert viewer.url == "http://[::1]:1234"
    viewer.host = "0.0.0.0"
    assert viewer.url == "http://127.0.0.1:1234"


# No server is left behind by an error.


def test_start_stops_the_server_when_building_the_scene_fails(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def broken(*_: Any) -> None:
        raise RuntimeError("scene failed")

    monkeypatch.setattr(Viewer, "_build_gui", broken)
    viewer = Viewer(_still(), _g1(), port=0)
    with pytest.raises(RuntimeError, match="scene failed"):
        viewer.start()
    port = viewer.port
    assert port != 0 and not viewer._serving
    end = time.monotonic() + 3.0
    while True:  # The listening socket closes as the server thread ends.
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1):
                pass
        except ConnectionRefusedError:
            break
        assert time.monotonic() < end, "the server still listens after the failed start"
        time.sleep(0.05)
    viewer.stop()  # A second stop does nothing.


def test_start_with_a_frame_past_the_end_starts_nothing(no_server: None) -> None:
    viewer = Viewer(_still(), _g1(), port=0)
    with pytest.raises(InputError, match=r"^--frame 3: the motion has 3 frames"):
        viewer.start(frame=3)


def test_a_port_refused_for_another_reason_is_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    # Ports below 1024 need privileges (the tests may run as root, so the refusal is faked).
    real = app.try_bind

    def privileged(addrs: list[app.SockAddr], port: int) -> None:
        if 0 < port < 1024:
            raise PermissionError(13, "Permission denied")
        real(addrs, port)

    monkeypatch.setattr(app, "try_bind", privileged)
    viewer = Viewer(_still(), _g1(), port=80)
    with pytest.raises(InputError, match=r"^--port 80: cannot listen on 127\.0\.0\.1 port 80 \("):
        viewer.start()
    assert viewer._server is None


# A scene folder means the same to `humimic view --scene` as to `humimic retarget --scene`.


def _write_box_obj(path: Path, size: tuple[float, float, float], pos: tuple[float, ...]) -> None:
    """A box mesh of full extents ``size`` centred at ``pos``, as an OBJ file."""
    from humimic.datasets.scene import box_mesh

    v, f = box_mesh(np.array(size))
    lines = [f"v {x} {y} {z}" for x, y, z in v + np.array(pos)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def _over_limit_scene(tmp_path: Path, kind: str) -> tuple[Path, str]:
    """A holosoma-layout clip folder over one of the scene limits; and what the refusal names."""
    folder = tmp_path / "climb"
    _write_box_obj(folder / "box_models" / "step.obj", (1.0, 0.8, 0.2), (0.6, 0.0, 0.1))
    if kind == "huge":  # More than MAX_EXTENT across.
        _write_box_obj(folder / "box_models" / "slab.obj", (1000.0, 1000.0, 1.0), (0, 0, -0.5))
        return folder, f"{folder / 'box_models' / 'slab.obj'}: 1000 m across, more than the 100 m"
    for k in range(64):  # With step: one more than MAX_OBJECTS.
        _write_box_obj(folder / "box_models" / f"b{k:02d}.obj", (0.1, 0.1, 0.1), (k, 0, 0))
    return folder, f"{folder}: 65 meshes in box_models, at most 64"


@pytest.mark.parametrize("kind", ["huge", "crowded"])
def test_view_refuses_the_over_limit_scene_folder_that_retarget_refuses(
    motion_file: Path,
    tmp_path: Path,
    shared_data: Path,
    kind: str,
    no_server: None,
    capsys: pytest.CaptureFixture[str],
) -> None:
    folder, message = _over_limit_scene(tmp_path, kind)
    out = tmp_path / "out" / "m.npz"
    clip = shared_data / "cmu" / "35_01.bvh"
    rc = main(["retarget", str(clip), "--method", "interaction-mesh", "--scene", str(folder),
               "--out", str(out)])  # fmt: skip
    assert rc == 2
    retarget_line = _error_line(capsys)
    assert message in retarget_line, retarget_line
    assert not out.parent.exists()
    assert main(["view", str(motion_file), "--scene", str(folder)]) == 2
    view_line = _error_line(capsys)
    assert view_line.startswith(f"humimic: error: {message}"), view_line
    assert view_line == retarget_line


def test_view_and_retarget_read_the_same_objects_from_a_scene_folder(
    motion_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Only box_models/*.obj count (holosoma's layout): other meshes in the folder are no part
    of the scene for either command."""
    import humimic.viewer
    from humimic.datasets.scene import load_scene
    from humimic.viewer import load_scene_meshes

    folder = tmp_path / "climb"
    _write_box_obj(folder / "box_models" / "step.obj", (1.0, 0.8, 0.2), (0.6, 0.0, 0.1))
    _write_box_obj(folder / "box_models" / "wall.obj", (0.2, 2.0, 1.5), (2.0, 0.0, 0.75))
    _write_box_obj(folder / "stray.obj", (0.5, 0.5, 0.5), (0.0, 3.0, 0.25))
    _write_box_obj(folder / "box_models" / "extra" / "deep.obj", (0.5, 0.5, 0.5), (0, -3, 0.25))
    scene = load_scene(folder)
    assert [o.name for o in scene.objects] == ["step", "wall"]
    meshes = load_scene_meshes(folder)
    assert [m.name for m in meshes] == ["step", "wall"]
    for o, m in zip(scene.objects, meshes, strict=True):
        np.testing.assert_array_equal(m.vertices, o.world_vertices(0))
        np.testing.assert_array_equal(m.faces, o.faces)
        np.testing.assert_array_equal(m.local_vertices, o.vertices)
    # ...and the command line hands the viewer exactly those.
    seen: list[list[str]] = []

    class Recording(Viewer):
        def __init__(self, *args: Any, scene: Any = None, **kw: Any) -> None:
            seen.append([m.name for m in scene or []])
            super().__init__(*args, scene=scene, **kw)

    monkeypatch.setattr(humimic.viewer, "Viewer", Recording)
    assert main(["view", str(motion_file), "--scene", str(folder), "--port", "0",
                 "--duration", "0"]) == 0  # fmt: skip
    assert seen == [["step", "wall"]]
