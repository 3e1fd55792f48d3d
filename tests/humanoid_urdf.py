"""A small humanoid URDF written by the tests (no third-party model): pelvis, waist, torso,
head, two 6-joint legs and two 4-joint arms with hands, about 1.25 m tall, x forward, y left."""

from __future__ import annotations

from pathlib import Path


def _inertial(mass: float, xyz: str = "0 0 0", i: float = 0.01) -> str:
    return (f'<inertial><origin xyz="{xyz}"/><mass value="{mass}"/>'
            f'<inertia ixx="{i}" iyy="{i}" izz="{i}" ixy="0" ixz="0" iyz="0"/></inertial>')  # fmt: skip


def _link(name: str, mass: float, geom: str, xyz: str = "0 0 0", rpy: str = "0 0 0") -> str:
    col = f'<collision><origin xyz="{xyz}" rpy="{rpy}"/><geometry>{geom}</geometry></collision>'
    vis = f'<visual><origin xyz="{xyz}" rpy="{rpy}"/><geometry>{geom}</geometry></visual>'
    return f'<link name="{name}">{_inertial(mass, xyz)}{vis}{col}</link>'


def _joint(name: str, parent: str, child: str, xyz: str, axis: str, lo: float, hi: float,
           effort: float | None = 80.0) -> str:  # fmt: skip
    eff = "" if effort is None else f' effort="{effort}"'
    return (f'<joint name="{name}" type="revolute"><parent link="{parent}"/>'
            f'<child link="{child}"/><origin xyz="{xyz}"/><axis xyz="{axis}"/>'
            f'<limit lower="{lo}" upper="{hi}"{eff} velocity="20"/></joint>')  # fmt: skip


def _empty(name: str, mass: float = 0.5) -> str:
    return f'<link name="{name}">{_inertial(mass)}</link>'


def humanoid_urdf(
    *, thigh_mesh: str | None = None, foot_mesh: str | None = None, effort: float | None = 80.0,
    name: str = "testbot", world_link: bool = False, legs: bool = True,
) -> str:  # fmt: skip
    """The URDF text. ``thigh_mesh`` / ``foot_mesh``: a mesh file name for the left thigh's or
    foot's collision geometry (instead of a primitive); ``effort=None``: no effort limits;
    ``world_link``: a massless ``world`` link fixed to the pelvis, as many URDFs have;
    ``legs=False``: the legs left out (a model humimic must refuse)."""
    parts = [_link("pelvis", 8.0, '<box size="0.16 0.24 0.12"/>')]
    if world_link:
        parts.insert(0, '<link name="world"/>')
        parts.append('<joint name="world_fix" type="fixed"><parent link="world"/>'
                     '<child link="pelvis"/></joint>')  # fmt: skip
    parts += [
        _empty("waist", 1.0),
        _joint("waist_yaw", "pelvis", "waist", "0 0 0.08", "0 0 1", -1.0, 1.0, effort),
        _link("torso", 12.0, '<box size="0.18 0.28 0.3"/>', "0 0 0.17"),
        _joint("waist_pitch", "waist", "torso", "0 0 0.02", "0 1 0", -0.5, 1.0, effort),
        _link("head", 2.0, '<sphere radius="0.09"/>', "0 0 0.1"),
        _joint("neck_yaw", "torso", "head", "0 0 0.34", "0 0 1", -1.0, 1.0, effort),
    ]
    sides = (("left", 1), ("right", -1)) if legs else ()
    for side, s in sides:
        p = side[0]
        thigh = (f'<mesh filename="{thigh_mesh}"/>' if thigh_mesh and side == "left"
                 else '<cylinder radius="0.05" length="0.3"/>')  # fmt: skip
        foot = (f'<mesh filename="{foot_mesh}"/>' if foot_mesh and side == "left"
                else '<box size="0.2 0.08 0.03"/>')  # fmt: skip
        parts += [
            _empty(f"{p}_hip_yaw_link"),
            _joint(
                f"{p}_hip_yaw",
                "pelvis",
                f"{p}_hip_yaw_link",
                f"0 {0.09 * s} -0.06",
                "0 0 1",
                -0.8,
                0.8,
                effort,
            ),
            _empty(f"{p}_hip_roll_link"),
            _joint(
                f"{p}_hip_roll",
                f"{p}_hip_yaw_link",
                f"{p}_hip_roll_link",
                "0 0 0",
                "1 0 0",
                -0.5,
                0.5,
                effort,
            ),
            _link(f"{p}_thigh", 3.0, thigh, "0 0 -0.2"),
            _joint(
                f"{p}_hip_pitch",
                f"{p}_hip_roll_link",
                f"{p}_thigh",
                "0 0 0",
                "0 1 0",
                -2.0,
                0.6,
                effort,
            ),
            _link(f"{p}_shin", 2.0, '<cylinder radius="0.04" length="0.3"/>', "0 0 -0.18"),
            _joint(f"{p}_knee", f"{p}_thigh", f"{p}_shin", "0 0 -0.38", "0 1 0", 0.0, 2.4, effort),
            _empty(f"{p}_ankle_pitch_link"),
            _joint(
                f"{p}_ankle_pitch",
                f"{p}_shin",
                f"{p}_ankle_pitch_link",
                "0 0 -0.36",
                "0 1 0",
                -0.8,
                0.6,
                effort,
            ),
            _link(f"{p}_foot", 1.0, foot, "0.04 0 -0.045"),
            _joint(
                f"{p}_ankle_roll",
                f"{p}_ankle_pitch_link",
                f"{p}_foot",
                "0 0 0",
                "1 0 0",
                -0.4,
                0.4,
                effort,
            ),
        ]
    for side, s in (("left", 1), ("right", -1)):
        p = side[0]
        parts += [
            _empty(f"{p}_shoulder_pitch_link"),
            _joint(
                f"{p}_shoulder_pitch",
                "torso",
                f"{p}_shoulder_pitch_link",
                f"0 {0.19 * s} 0.28",
                "0 1 0",
                -3.0,
                1.2,
                effort,
            ),
            _empty(f"{p}_shoulder_roll_link"),
            _joint(
                f"{p}_shoulder_roll",
                f"{p}_shoulder_pitch_link",
                f"{p}_shoulder_roll_link",
                "0 0 0",
                "1 0 0",
                -0.3 if s > 0 else -2.5,
                2.5 if s > 0 else 0.3,
                effort,
            ),
            _link(f"{p}_upper_arm", 1.5, '<cylinder radius="0.035" length="0.2"/>', "0 0 -0.13"),
            _joint(
                f"{p}_shoulder_yaw",
                f"{p}_shoulder_roll_link",
                f"{p}_upper_arm",
                "0 0 0",
                "0 0 1",
                -1.5,
                1.5,
                effort,
            ),
            _link(f"{p}_forearm", 1.0, '<cylinder radius="0.03" length="0.18"/>', "0 0 -0.12"),
            _joint(
                f"{p}_elbow",
                f"{p}_upper_arm",
                f"{p}_forearm",
                "0 0 -0.26",
                "0 1 0",
                -2.4,
                0.0,
                effort,
            ),
            _link(f"{p}_hand", 0.4, '<box size="0.06 0.03 0.08"/>', "0 0 -0.05"),
            _joint(
                f"{p}_wrist", f"{p}_forearm", f"{p}_hand", "0 0 -0.23", "0 0 1", -1.5, 1.5, effort
            ),
        ]
    return f'<?xml version="1.0"?>\n<robot name="{name}">\n' + "\n".join(parts) + "\n</robot>\n"


def write_humanoid(folder: Path, **kw: object) -> Path:
    """Write :func:`humanoid_urdf` as ``folder/testbot.urdf``; returns its path."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "testbot.urdf"
    path.write_text(humanoid_urdf(**kw))  # type: ignore[arg-type]
    return path
