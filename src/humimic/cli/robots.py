"""``humimic robots list|export``: the robot registry."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from humimic.configs.choices import RobotName


@dataclass(frozen=True, kw_only=True)
class RobotsList:
    """List the registered robots."""


@dataclass(frozen=True, kw_only=True)
class RobotsExport:
    """Write the exact nominal MJCF humimic simulates with (meshes copied beside it)."""

    name: Annotated[RobotName, tyro.conf.Positional]
    """Robot name."""
    out: Path
    """Output .xml file."""
    menagerie_root: Path | None = None
    """A MuJoCo Menagerie folder (or the robot's own folder) to load the robot from."""


@dataclass(frozen=True, kw_only=True)
class RobotsCommand:
    """Robot registry: list robots, export the nominal model."""

    command: tyro.conf.OmitSubcommandPrefixes[
        Annotated[RobotsList, tyro.conf.subcommand("list")]
        | Annotated[RobotsExport, tyro.conf.subcommand("export")]
    ]
    """list or export."""


def run_list(cmd: RobotsList) -> None:
    """Run ``humimic robots list``."""
    from humimic.robots import get_robot, robot_names

    del cmd
    names = robot_names()
    width = max(map(len, names), default=0)
    for name in names:
        cfg = get_robot(name)
        print(f"{name:{width}s} {cfg.description} [{cfg.license}]")


def run_export(cmd: RobotsExport) -> None:
    """Run ``humimic robots export``."""
    from humimic.robots import export_nominal, get_robot

    path = export_nominal(
        get_robot(cmd.name, "robots export"), cmd.out, menagerie_root=cmd.menagerie_root
    )
    print(f"wrote {path} (meshes in {path.parent / (path.stem + '_assets')})")
