"""``humimic robots add`` on example-robot-data's humanoid URDFs (slow: about a minute, and
needs ``pip install example-robot-data==6.0.0``, about 130 MB, which humimic does not install):
Talos, Romeo, iCub and the G1 are found whole and retarget the CMU walk with the quality bar;
simple_humanoid, which has collision geometry on its trunk only, is refused naming that."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from humimic.configs import retarget_default
from humimic.datasets import load_clip
from humimic.errors import InputError
from humimic.retarget import Retargeter
from humimic.robots.add import add_robot
from humimic.robots.user import ROBOTS_DIR_ENV

pytestmark = pytest.mark.slow


def _erd() -> Path:
    for site in map(Path, sys.path):
        cand = site / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
        if cand.is_dir():
            return cand
    pytest.fail("example-robot-data is not installed: pip install example-robot-data==6.0.0")


@pytest.mark.parametrize(
    ("name", "urdf", "missing"),
    [
        ("talos", "talos_data/robots/talos_reduced.urdf", []),
        ("romeo", "romeo_description/urdf/romeo_small.urdf", []),
        ("icub", "icub_description/robots/icub_reduced.urdf", ["head"]),
        ("g1_urdf", "g1_description/urdf/g1_29dof_rev_1_0.urdf", ["head"]),
    ],
)
def test_example_robot_data_humanoids_retarget_the_walk(
    name: str, urdf: str, missing: list[str], tmp_path: Path, shared_data: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    monkeypatch.setenv(ROBOTS_DIR_ENV, str(tmp_path))
    r = add_robot(_erd() / urdf, name)
    assert r.structure.missing() == missing
    out = Retargeter(name, "cmu", retarget_default()).run(
        load_clip(shared_data / "cmu" / "35_01.bvh").slice(1)
    )
    rep = out.report
    assert rep["joint_limit_violations"] == 0
    assert rep["max_ground_penetration_mm"] <= 5.0
    assert rep["self_collision_frames"] == 0


@pytest.mark.parametrize(
    ("name", "urdf", "clip"),
    [
        ("romeo", "romeo_description/urdf/romeo_small.urdf", "104_53"),
        ("talos", "talos_data/robots/talos_reduced.urdf", "111_37"),
    ],
)
def test_mesh_feet_stay_out_of_the_floor(
    name: str, urdf: str, clip: str, tmp_path: Path, shared_data: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    """The clips where these robots' mesh toes and heels went 27.9 and 16.0 mm into the floor
    while their sole boxes stayed above it (the floor limit saw only the boxes)."""
    monkeypatch.setenv(ROBOTS_DIR_ENV, str(tmp_path))
    add_robot(_erd() / urdf, name)
    out = Retargeter(name, "cmu", retarget_default()).run(
        load_clip(shared_data / "cmu" / f"{clip}.bvh").slice(1)
    )
    assert out.report["max_ground_penetration_mm"] <= 5.0


def test_a_humanoid_without_leg_geometry_is_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"no legs found.*have no collision geometry"):
        add_robot(_erd() / "simple_humanoid_description/urdf/simple_humanoid.urdf", "sh",
                  root=tmp_path)  # fmt: skip
    assert not any(tmp_path.iterdir())
