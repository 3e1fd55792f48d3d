"""Fetch public human-motion data at run time (never shipped in the repository).

The holosoma climbing clips (real mocap of a person climbing onto boxes, Apache-2.0, Amazon FAR)
live in the ``demo_data/climb`` folder of the PyPI wheel ``holosoma-retargeting==0.1.0``. They are
fetched with ``pip download --no-deps`` and only that folder is kept.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path, PurePosixPath

from humimic.errors import FetchError

HOLOSOMA_REQUIREMENT = "holosoma-retargeting==0.1.0"
"""The pinned wheel that carries the climbing clips."""

CLIMB_PREFIX = "holosoma_retargeting/demo_data/climb/"
"""Folder inside the wheel that is extracted."""

CLIMB_FOLDER = "holosoma_climb"
"""Name of the extracted folder in the cache (and under ``$HUMIMIC_DATA``)."""

COMPLETE_MARKER = ".complete"
"""File written inside a fully extracted folder."""

PIP_TIMEOUT_S = 900.0


def default_cache_dir() -> Path:
    """``$HUMIMIC_CACHE`` when set, else ``~/.cache/humimic``."""
    env = os.environ.get("HUMIMIC_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "humimic"


def fetch_holosoma_climb(
    cache_dir: str | os.PathLike[str] | None = None, *, quiet: bool = False
) -> Path:
    """Download (once) the holosoma climbing clips and return their folder.

    The folder holds ``mocap_climb_seq_<k>/`` sub-folders, each with a
    ``*_joint_positions_f<a>-<b>.npy`` array (T, 53, 3) and the box meshes. A folder with the
    marker file ``.complete`` is reused without any download.

    Args:
        cache_dir: Cache root. Default: :func:`default_cache_dir`.
        quiet: Print nothing.

    Returns:
        ``<cache_dir>/holosoma_climb``.

    Raises:
        FetchError: pip failed (the message carries pip's last output lines) or the wheel lacks
            the climbing folder, or the cache cannot be written.
    """
    cache = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    target = cache / CLIMB_FOLDER
    if (target / COMPLETE_MARKER).is_file():
        return target
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FetchError(f"cannot create the cache folder {cache}: {e.strerror}") from e
    if not quiet:
        print(
            f"humimic: downloading {HOLOSOMA_REQUIREMENT} (about 100 MB) from PyPI for its climbing "
            f"clips into {target}",
            file=sys.stderr,
            flush=True,
        )
    with tempfile.TemporaryDirectory(prefix=".download.", dir=cache) as tmp:
        wheel = _pip_download(Path(tmp))
        staging = Path(tempfile.mkdtemp(prefix=f".{CLIMB_FOLDER}.", dir=cache))
        try:
            extract_climb_from_wheel(wheel, staging)
            (staging / COMPLETE_MARKER).write_text(f"{HOLOSOMA_REQUIREMENT}\n")
            if target.exists():  # An incomplete earlier attempt.
                shutil.rmtree(target)
            os.replace(staging, target)
        except OSError as e:
            if (target / COMPLETE_MARKER).is_file():  # Another process finished first.
                return target
            raise FetchError(f"cannot write {target}: {e}") from e
        finally:
            with contextlib.suppress(OSError):
                shutil.rmtree(staging)
    if not quiet:
        print(f"humimic: climbing clips ready in {target}", file=sys.stderr, flush=True)
    return target


def _pip_download(dest: Path) -> Path:
    """Download the pinned wheel into ``dest`` and return its path."""
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--no-deps",
        "--only-binary=:all:",
        HOLOSOMA_REQUIREMENT,
        "-d",
        str(dest),
    ]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=PIP_TIMEOUT_S)
    except subprocess.TimeoutExpired as e:
        raise FetchError(
            f"pip download of {HOLOSOMA_REQUIREMENT} took longer than {PIP_TIMEOUT_S:.0f} s"
        ) from e
    except OSError as e:
        raise FetchError(f"cannot run pip ({sys.executable} -m pip): {e}") from e
    if proc.returncode != 0:
        tail = "\n".join((proc.stderr or proc.stdout or "").strip().splitlines()[-15:])
        raise FetchError(
            f"pip download of {HOLOSOMA_REQUIREMENT} failed (exit {proc.returncode}); is PyPI "
            f"reachable? pip said:\n{tail}"
        )
    wheels = sorted(dest.glob("*.whl"))
    if not wheels:
        raise FetchError(f"pip download of {HOLOSOMA_REQUIREMENT} produced no wheel in {dest}")
    return wheels[0]


def extract_climb_from_wheel(
    wheel_path: str | os.PathLike[str], dest: str | os.PathLike[str]
) -> Path:
    """Extract the wheel's ``holosoma_retargeting/demo_data/climb/`` folder into ``dest``.

    Members keep their paths below that folder: ``.../climb/mocap_climb_seq_0/x.npy`` becomes
    ``dest/mocap_climb_seq_0/x.npy``.

    Args:
        wheel_path: The ``.whl`` (a zip file).
        dest: Destination folder, created if missing.

    Returns:
        ``dest``.

    Raises:
        FetchError: Not a zip file, no climbing folder in it, or a member path that would leave
            ``dest``.
    """
    wheel = Path(wheel_path)
    out = Path(dest)
    try:
        archive = zipfile.ZipFile(wheel)
    except (zipfile.BadZipFile, OSError) as e:
        raise FetchError(f"{wheel}: cannot open as a wheel (zip): {e}") from e
    with archive:
        members = [
            m for m in archive.infolist() if m.filename.startswith(CLIMB_PREFIX) and not m.is_dir()
        ]
        if not members:
            raise FetchError(f"{wheel}: no files under {CLIMB_PREFIX!r} in this wheel")
        out.mkdir(parents=True, exist_ok=True)
        for m in members:
            rel = PurePosixPath(m.filename[len(CLIMB_PREFIX) :])
            if rel.is_absolute() or ".." in rel.parts or not rel.parts:
                raise FetchError(f"{wheel}: refusing unsafe member path {m.filename!r}")
            target = out.joinpath(*rel.parts)
            target.parent.mkdir(parents=True, exist_ok=True)
            with archive.open(m) as src, open(target, "wb") as dst:
                shutil.copyfileobj(src, dst)
    return out


def climb_clip_paths(root: str | os.PathLike[str]) -> list[Path]:
    """The climbing clips' position arrays under ``root``, sorted. Shape of each: (T, 53, 3)."""
    return sorted(Path(root).rglob("*.npy"))


CMU_COMMIT = "62ac0fb0ec43cff2bf66426928f4fa6682d4bbdc"
"""The commit of the public BVH conversion of the CMU database (una-dinosauria/cmu-mocap)
that clips are fetched from."""

CMU_CLIPS: dict[str, str] = {
    "35_01": "9b71307b7592bc7c16013dffa8d9f326e2947af749b56977029a0257534fc053",
}
"""CMU clips humimic fetches (the demo's walk) -> the SHA-256 of the file with its line ends
made ``\\n`` (the conversion writes CRLF; a copy whose line ends were changed is the same clip)."""


def _cmu_digest(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data.replace(b"\r\n", b"\n")).hexdigest()


def fetch_cmu_clip(
    name: str = "35_01",
    cache_dir: str | os.PathLike[str] | None = None,
    *,
    quiet: bool = False,
    timeout_s: float = 120.0,
) -> Path:
    """A CMU motion-capture clip as BVH: ``$HUMIMIC_DATA/cmu/<name>.bvh`` when it is there and
    its content checks, else the cache's copy, else downloaded (once, about 270 kB) from the
    pinned commit :data:`CMU_COMMIT` and checked against :data:`CMU_CLIPS`.

    The CMU database's terms: free for all uses; cite "The data used in this project was
    obtained from mocap.cs.cmu.edu. The database was created with funding from NSF
    EIA-0196217."

    Raises:
        FetchError: An unknown clip, no network, or a download whose content differs.
    """
    import urllib.error
    import urllib.request

    if name not in CMU_CLIPS:
        raise FetchError(f"CMU clip {name!r}: humimic fetches {', '.join(CMU_CLIPS)}")
    want = CMU_CLIPS[name]
    env = os.environ.get("HUMIMIC_DATA")
    if env:
        local = Path(env).expanduser() / "cmu" / f"{name}.bvh"
        if local.is_file() and _cmu_digest(local.read_bytes()) == want:
            return local
    cache = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    target = cache / "cmu" / f"{name}.bvh"
    if target.is_file() and _cmu_digest(target.read_bytes()) == want:
        return target
    subject = name.split("_")[0].zfill(3)
    base = "https://raw.githubusercontent.com/una-dinosauria/cmu-mocap"
    url = f"{base}/{CMU_COMMIT}/{subject}/{name}.bvh"
    if not quiet:
        print(f"humimic: downloading the CMU clip {name} from {url}", file=sys.stderr, flush=True)
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as r:
            data = r.read()
    except (urllib.error.URLError, OSError) as e:
        raise FetchError(f"cannot download {url}: {getattr(e, 'reason', e)}") from None
    if _cmu_digest(data) != want:
        raise FetchError(f"{url}: the download is not the clip humimic pinned (SHA-256 differs)")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, target)
    except OSError as e:
        raise FetchError(f"cannot write {target}: {e.strerror or e}") from None
    return target


def find_climb_data(*, quiet: bool = False) -> Path:
    """The climbing clips' folder: ``$HUMIMIC_DATA/holosoma_climb`` when it exists, else fetched.

    ``$HUMIMIC_DATA`` may also point at the ``holosoma_climb`` folder itself.

    Returns:
        A folder holding ``mocap_climb_seq_<k>/`` sub-folders.
    """
    env = os.environ.get("HUMIMIC_DATA")
    if env:
        base = Path(env).expanduser()
        for candidate in (base / CLIMB_FOLDER, base):
            if (candidate / "mocap_climb_seq_0").is_dir():
                return candidate
    return fetch_holosoma_climb(quiet=quiet)
