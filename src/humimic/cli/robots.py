"""``humimic robots list|export|add``: the robot registry, and robots a user adds."""

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
class RobotsAdd:
    """Add any humanoid from its MJCF or URDF: every command then takes it as --robot NAME.

    The model is read by MuJoCo's compiler; a URDF gets a floating base, meshes MuJoCo cannot
    read are converted or replaced (said in the output), a floor and position actuators are
    added where missing, and a robot map is generated from the tree and geometry (feet, knees,
    hips, hands, elbows, shoulders, torso, head), with a check list of what was not found."""

    model: Annotated[Path, tyro.conf.Positional]
    """The robot's MJCF (.xml) or URDF (.urdf)."""
    name: str
    """Its name in humimic (lower case letters, digits and _)."""
    robots_dir: Path | None = None
    """Where added robots live (default: $HUMIMIC_ROBOTS_DIR, else
    ~/.local/share/humimic/robots). Other commands read $HUMIMIC_ROBOTS_DIR."""
    force: bool = False
    """Replace an added robot of the same name."""


@dataclass(frozen=True, kw_only=True)
class RobotsCommand:
    """Robot registry: list robots, export the nominal model, add a robot."""

    command: tyro.conf.OmitSubcommandPrefixes[
        Annotated[RobotsList, tyro.conf.subcommand("list")]
        | Annotated[RobotsExport, tyro.conf.subcommand("export")]
        | Annotated[RobotsAdd, tyro.conf.subcommand("add")]
    ]
    """list, export or add."""


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


def run_add(cmd: RobotsAdd) -> None:
    """Run ``humimic robots add``."""
    from humimic.robots.add import add_robot

    r = add_robot(cmd.model, cmd.name, root=cmd.robots_dir, force=cmd.force)
    s = r.structure
    print(f"added robot {r.name}: {r.joints} joints, {r.mass:.1f} kg, {s.height:.2f} m tall -> "
          f"{r.folder}")  # fmt: skip
    print(f"  root {s.root}, torso {s.torso}, head {s.head or '-'}")
    for side in ("left", "right"):
        print(f"  {side}: hip {s.hips[side]}, knee {s.knees[side] or '-'}, foot {s.feet[side]}, "
              f"shoulder {s.shoulders.get(side) or '-'}, elbow {s.elbows.get(side) or '-'}, "
              f"hand {s.hands.get(side) or '-'}")  # fmt: skip
    missing = s.missing()
    print(f"  not found: {', '.join(missing)}" if missing else "  everything found")
    for note in r.notes:
        print(f"  note: {note}")
    env = "" if cmd.robots_dir is None else f"HUMIMIC_ROBOTS_DIR={cmd.robots_dir} "
    print(f"  use it: {env}humimic retarget CLIP --robot {r.name} --out OUT.npz; edit its map: "
          f"{r.folder / 'map.yaml'}")  # fmt: skip
