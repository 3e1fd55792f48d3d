"""Robots a user added (``humimic robots add``): one folder each under the user's robots folder,
read back as :class:`~humimic.robots.registry.RobotConfig`.

A robot's folder holds ``robot.yaml`` (what :class:`RobotConfig` needs, and a motor per
actuated joint), ``map.yaml`` (its robot map: canonical key points on its bodies), the model
``<name>.xml`` (robot and floor) with its meshes in ``assets/``, and ``SOURCE.txt`` (where it
came from). Pure data and files: no simulator imports.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

from humimic.errors import InputError
from humimic.io import read_yaml
from humimic.robots.actuators import ActuatorRecipe, MotorSpec

ROBOTS_DIR_ENV = "HUMIMIC_ROBOTS_DIR"
"""Environment variable naming the folder of added robots (every command reads it)."""

ROBOT_FILE = "robot.yaml"
MAP_FILE = "map.yaml"
SCHEMA_VERSION = 1
NAME_PATTERN = re.compile(r"[a-z][a-z0-9_]{0,39}")
"""A robot name: lower case letters, digits and underscores, a letter first (it names a
folder, a map and a ``--robot`` choice)."""


def robots_dir() -> Path:
    """The folder of added robots: ``$HUMIMIC_ROBOTS_DIR``, else
    ``$XDG_DATA_HOME/humimic/robots``, else ``~/.local/share/humimic/robots``."""
    env = os.environ.get(ROBOTS_DIR_ENV)
    if env:
        return Path(env).expanduser()
    data = os.environ.get("XDG_DATA_HOME")
    base = Path(data).expanduser() if data else Path.home() / ".local" / "share"
    return base / "humimic" / "robots"


def user_robot_names(root: Path | None = None) -> list[str]:
    """Names of the added robots in ``root`` (default :func:`robots_dir`): its subfolders that
    hold a ``robot.yaml``, named as robots may be."""
    root = robots_dir() if root is None else root
    try:
        entries = sorted(root.iterdir())
    except OSError:
        return []
    return [
        e.name for e in entries if NAME_PATTERN.fullmatch(e.name) and (e / ROBOT_FILE).is_file()
    ]


def user_robot_folder(name: str, root: Path | None = None) -> Path | None:
    """The folder of added robot ``name``, or None."""
    root = robots_dir() if root is None else root
    folder = root / name
    return folder if (folder / ROBOT_FILE).is_file() else None


def _field(data: dict[str, Any], key: str, kind: type, where: str) -> Any:
    value = data.get(key)
    if not isinstance(value, kind):
        raise InputError(f"{where}: {key}: expected a {kind.__name__}, got {value!r}")
    return value


def load_user_robot(name: str, root: Path | None = None) -> dict[str, Any]:
    """The keyword arguments of :class:`RobotConfig` for added robot ``name``.

    Raises:
        InputError: A missing or malformed ``robot.yaml`` (names the file and field).
    """
    folder = user_robot_folder(name, root)
    if folder is None:
        raise InputError(f"no added robot {name!r} in {robots_dir() if root is None else root}")
    path = folder / ROBOT_FILE
    data = read_yaml(path)
    where = str(path)
    if not isinstance(data, dict) or data.get("schema_version") != SCHEMA_VERSION:
        raise InputError(f"{where}: not a humimic robot file (schema_version {SCHEMA_VERSION})")
    motors_raw = _field(data, "motors", dict, where)
    motors: dict[str, MotorSpec] = {}
    for joint, m in motors_raw.items():
        if not isinstance(m, dict):
            raise InputError(f"{where}: motors.{joint}: expected a mapping")
        try:
            motors[re.escape(str(joint))] = MotorSpec(
                armature=float(m["armature"]),
                effort_limit=float(m["effort_limit"]),
                velocity_limit=float(m["velocity_limit"]),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{where}: motors.{joint}: {e}") from None
    feet = _field(data, "feet", dict, where)
    if set(feet) != {"left", "right"}:
        raise InputError(f"{where}: feet: expected left and right, got {sorted(feet)}")
    model = folder / _field(data, "model", str, where)
    return {
        "name": name,
        "description": str(data.get("description", f"{name} (added)")),
        "menagerie_dir": name,
        "xml": model.name,
        "license": str(data.get("license", "as its source model's")),
        "root_body": _field(data, "root_body", str, where),
        "feet": {str(k): str(v) for k, v in feet.items()},
        "actuators": ActuatorRecipe(
            motors=motors,
            natural_frequency_hz=float(data.get("natural_frequency_hz", 10.0)),
            damping_ratio=float(data.get("damping_ratio", 2.0)),
        ),
        "key_bodies": tuple(str(b) for b in _field(data, "key_bodies", list, where)),
        "torso_body": _field(data, "torso_body", str, where),
        "floor_geom": str(data.get("floor_geom", "floor")),
        "model_file": model,
    }


def user_robot_hands(name: str, root: Path | None = None) -> tuple[str, ...]:
    """The hand bodies ``robots add`` found on added robot ``name`` (empty if none)."""
    folder = user_robot_folder(name, root)
    if folder is None:
        return ()
    data = read_yaml(folder / ROBOT_FILE)
    hands = data.get("hands") if isinstance(data, dict) else None
    return tuple(str(h) for h in hands.values()) if isinstance(hands, dict) else ()
