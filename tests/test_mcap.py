"""MCAP: lossless motion round trips, Foxglove-readable files, clear errors on bad files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from humimic.cli.main import main
from humimic.formats.mcap import (
    SCHEMAS,
    McapFormatError,
    McapWriter,
    qpos_from_log,
    read_mcap,
    read_motion_mcap,
    stamp,
    write_motion_mcap,
)
from humimic.motion import Motion, load_motion, motion_from_qpos, save_motion
from humimic.robots import get_robot, nominal_model


@pytest.fixture(scope="module")
def g1_model():
    return nominal_model(get_robot("g1"))


@pytest.fixture(scope="module")
def motion(g1_model) -> Motion:
    rng = np.random.default_rng(0)
    T = 30
    qpos = np.tile(g1_model.qpos0, (T, 1))
    qpos[:, 0] = np.linspace(0.0, 0.6, T)
    lo, hi = g1_model.jnt_range[1:, 0], g1_model.jnt_range[1:, 1]
    qpos[:, 7:] = lo + (hi - lo) * (0.5 + 0.2 * np.sin(np.linspace(0, 3, T))[:, None])
    qpos[:, 7:] += rng.normal(0, 1e-3, qpos[:, 7:].shape)
    extras = {
        "human_contacts": rng.random((T, 2, 2)) > 0.5,
        "keypoint_targets": rng.normal(size=(T, 16, 3)),
    }
    return motion_from_qpos(g1_model, qpos, 50.0, "g1", extras=extras, info={"source": "x.bvh"})


def _assert_same(a: Motion, b: Motion) -> None:
    for k in ("qpos", "joint_pos", "joint_vel", "body_pos_w", "body_quat_w", "body_lin_vel_w",
              "body_ang_vel_w"):  # fmt: skip
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    assert (a.robot, a.fps, a.joint_names, a.body_names, a.info) == (
        b.robot, b.fps, b.joint_names, b.body_names, b.info
    )  # fmt: skip
    assert set(a.extras or {}) == set(b.extras or {})
    for k, v in (a.extras or {}).items():
        assert b.extras is not None
        np.testing.assert_array_equal(v, b.extras[k])
        assert v.dtype == b.extras[k].dtype


def test_motion_round_trip_is_lossless(tmp_path: Path, motion: Motion) -> None:
    path = write_motion_mcap(motion, tmp_path / "m.mcap")
    _assert_same(motion, read_motion_mcap(path))


def test_npz_to_mcap_to_npz_through_the_cli(tmp_path: Path, motion: Motion) -> None:
    save_motion(motion, tmp_path / "a.npz")
    assert main(["convert", str(tmp_path / "a.npz"), str(tmp_path / "b.mcap")]) == 0
    assert main(["convert", str(tmp_path / "b.mcap"), str(tmp_path / "c.npz")]) == 0
    _assert_same(load_motion(tmp_path / "a.npz"), load_motion(tmp_path / "c.npz"))


def test_file_is_foxglove_readable(tmp_path: Path, motion: Motion) -> None:
    """Plain mcap reader: jsonschema schemas, json messages, a /tf topic of FrameTransforms."""
    path = write_motion_mcap(motion, tmp_path / "m.mcap")
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.name: s for s in summary.schemas.values()}
        channels = {c.topic: c for c in summary.channels.values()}
        assert all(s.encoding == "jsonschema" for s in schemas.values())
        assert all(c.message_encoding == "json" for c in channels.values())
        assert schemas[summary.schemas[channels["/tf"].schema_id].name].name == (
            "foxglove.FrameTransforms"
        )
        assert summary.statistics is not None
        assert summary.statistics.channel_message_counts[channels["/tf"].id] == motion.num_frames
        _, _, msg = next(reader.iter_messages(topics=["/tf"]))
    tf = json.loads(msg.data)["transforms"]
    assert tf[0]["child_frame_id"] == "pelvis"
    q = motion.body_quat_w[0, 0]
    assert tf[0]["rotation"] == {"w": q[0], "x": q[1], "y": q[2], "z": q[3]}


def test_truncated_file(tmp_path: Path, motion: Motion) -> None:
    path = write_motion_mcap(motion, tmp_path / "m.mcap")
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    with pytest.raises(McapFormatError, match=r"cut\.mcap.*truncated or corrupt"):
        read_motion_mcap(cut)


def test_missing_topic_is_named(tmp_path: Path) -> None:
    with McapWriter(tmp_path / "only_states.mcap") as w:
        w.write(
            "/joint_states", 0, {"header": {"stamp": stamp(0)}, "name": ["a"], "position": [0.0]}
        )
    with pytest.raises(McapFormatError, match=r"no messages on topic /reference/qpos"):
        read_motion_mcap(tmp_path / "only_states.mcap")
    with pytest.raises(McapFormatError, match="/base_pose"):
        read_mcap(tmp_path / "only_states.mcap", require=["/joint_states", "/base_pose"])


def _raw_file(path: Path, topic: str, schema_name: str, message: dict) -> Path:
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(
            schema_name, "jsonschema", json.dumps(SCHEMAS.get(schema_name, {})).encode()
        )
        cid = w.register_channel(topic, "json", sid)
        w.add_message(cid, 0, json.dumps(message).encode(), 0)
        w.finish()
    return path


def test_schema_mismatch_names_topic_and_field(tmp_path: Path) -> None:
    bad = {"header": {"stamp": stamp(5)}, "name": ["a", "b"], "position": [0.1, "x"]}
    p = _raw_file(tmp_path / "bad.mcap", "/joint_states", "humimic.JointState", bad)
    with pytest.raises(
        McapFormatError, match=r"topic /joint_states .*message 0: field position\.1"
    ):
        read_mcap(p)
    missing = {"header": {"stamp": stamp(5)}, "name": ["a"]}
    p = _raw_file(tmp_path / "missing.mcap", "/joint_states", "humimic.JointState", missing)
    with pytest.raises(McapFormatError, match=r"field position: required field missing"):
        read_mcap(p)
    p = _raw_file(tmp_path / "other.mcap", "/joint_states", "my.Thing", {"x": 1})
    with pytest.raises(McapFormatError, match=r"/joint_states has schema 'my\.Thing'"):
        read_mcap(p)


def test_writer_validates_and_leaves_nothing_on_failure(tmp_path: Path) -> None:
    out = tmp_path / "w.mcap"
    with (
        pytest.raises(McapFormatError, match=r"topic /base_pose .*field orientation"),
        McapWriter(out) as w,
    ):
        w.write(
            "/base_pose",
            0,
            {"header": {"stamp": stamp(0)}, "position": {"x": 0, "y": 0, "z": 0}},
        )
    assert list(tmp_path.iterdir()) == []


def test_qpos_from_robot_log_matches_joints_by_name(tmp_path: Path, g1_model) -> None:
    names = [g1_model.joint(j).name for j in range(1, g1_model.njnt)]
    q = np.linspace(-0.1, 0.1, len(names))
    order = names[::-1]  # The log's joint order differs from the model's.
    with McapWriter(tmp_path / "log.mcap") as w:
        for i, t in enumerate((0, 10_000_000, 20_000_000)):
            h = {"stamp": stamp(t)}
            w.write("/base_pose", t, {"header": h, "position": {"x": i * 0.1, "y": 0, "z": 0.8},
                                      "orientation": {"w": 1, "x": 0, "y": 0, "z": 0}})  # fmt: skip
            w.write("/joint_states", t, {"header": h, "name": order,
                                         "position": [float(q[names.index(n)]) + i for n in order]})  # fmt: skip
    times, qpos = qpos_from_log(read_mcap(tmp_path / "log.mcap"), tuple(names))
    np.testing.assert_array_equal(times, [0, 10_000_000, 20_000_000])
    np.testing.assert_allclose(qpos[2, 7:], q + 2)
    np.testing.assert_allclose(qpos[1, :3], [0.1, 0, 0.8])


def test_cli_convert_bad_input_exits_2_and_writes_nothing(
    tmp_path: Path, motion: Motion, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write_motion_mcap(motion, tmp_path / "m.mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:2000])
    assert main(["convert", str(cut), str(tmp_path / "out.npz")]) == 2
    assert "cut.mcap" in capsys.readouterr().err
    assert not (tmp_path / "out.npz").exists()
