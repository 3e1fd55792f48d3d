"""Hostile robot motion files (.npz, MCAP), scenes and robot models: every bad input is refused
with a message naming the file (and field), exit code 2, and nothing written."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
from mcap.writer import Writer

from humimic.cli.main import main
from humimic.errors import InputError, MotionDataError
from humimic.formats.mcap import SCHEMAS, McapFormatError, read_motion_mcap, write_motion_mcap
from humimic.motion import (
    Motion,
    load_motion,
    motion_from_qpos,
    save_motion,
    validate_motion,
)
from humimic.robots import get_robot, nominal_model

FPS = 50.0
FRAMES = 5
PHYSICS_DT = 0.005  # The G1 training model's step: 4 physics steps per frame at 50 fps.


@pytest.fixture(scope="module")
def g1() -> mujoco.MjModel:
    return nominal_model(get_robot("g1"))


@pytest.fixture(scope="module")
def motion(g1: mujoco.MjModel) -> Motion:
    """A few frames of the G1 near its nominal pose, with extras and a dynamic section of the
    right sizes (its states are not a replay of its controls)."""
    qpos = np.tile(g1.qpos0, (FRAMES, 1))
    qpos[:, 0] = np.linspace(0.0, 0.1, FRAMES)
    qpos[:, 2] = 0.79
    qpos[:, 7:] += 0.01 * np.sin(np.arange(FRAMES))[:, None]
    extras = {
        "human_contacts": np.zeros((FRAMES, 2), dtype=bool),
        "keypoint_targets": np.ones((FRAMES, 3, 3)),
    }
    m = motion_from_qpos(g1, qpos, FPS, "g1", extras=extras, info={"source": "test"})
    steps = (FRAMES - 1) * 4
    state = np.concatenate([[0.0], qpos[0], np.zeros(g1.nv)])
    dynamics = {
        "initial_state": state,
        "ctrl": np.repeat(qpos[1:, 7:], 4, axis=0),
        "qpos": np.repeat(qpos[1:], 4, axis=0),
        "qvel": np.zeros((steps, g1.nv)),
        "physics_dt": np.array(PHYSICS_DT),
    }
    return replace(m, dynamics=dynamics)


def _arrays(motion: Motion, tmp_path: Path) -> dict[str, np.ndarray]:
    """The arrays save_motion writes, to change and write back with np.savez."""
    path = save_motion(motion, tmp_path / "_good.npz")
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    path.unlink()
    return arrays


def _refused(capsys: pytest.CaptureFixture[str], argv: list[str], *names: str) -> str:
    """Run the CLI; assert exit code 2 and that the one-line message names ``names``."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("humimic: error: ") and err.count("\n") == 1, err
    for n in names:
        assert n in err, (n, err)
    assert "Traceback" not in err
    return err


def _only(folder: Path, *names: str) -> None:
    assert sorted(p.name for p in folder.iterdir()) == sorted(names)


# --- One validator -----------------------------------------------------------------------------


def _raw_mcap(path: Path, metadata: dict[str, dict[str, str]], messages: list[tuple]) -> Path:
    """An MCAP file written with the mcap package directly (no validation, NaN allowed), as a
    foreign tool might write one. ``messages``: (topic, schema name, log time, message)."""
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="test", library="test")
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}
        for topic, schema, t, msg in messages:
            if schema not in schemas:
                schemas[schema] = w.register_schema(
                    name=schema, encoding="jsonschema", data=json.dumps(SCHEMAS[schema]).encode()
                )
            if topic not in channels:
                channels[topic] = w.register_channel(
                    topic=topic, message_encoding="json", schema_id=schemas[schema]
                )
            w.add_message(channel_id=channels[topic], log_time=t, publish_time=t,
                          data=json.dumps(msg).encode())  # fmt: skip
        for name, record in metadata.items():
            w.add_metadata(name, record)
        w.finish()
    return path


def _records(motion: Motion, tmp_path: Path) -> tuple[dict[str, dict[str, str]], list[tuple]]:
    """The metadata and messages humimic writes for ``motion`` (to change and rewrite)."""
    from humimic.formats.mcap import TOPICS, read_mcap

    src = write_motion_mcap(motion, tmp_path / "_good.mcap")
    log = read_mcap(src)
    src.unlink()
    messages = [
        (topic, TOPICS[topic], t, msg) for topic, msgs in log.messages.items() for t, msg in msgs
    ]
    return log.metadata, messages


@pytest.mark.parametrize(
    ("change", "names"),
    [
        ("fps_nan", ["bad.mcap", "metadata motion.fps"]),
        ("fps_negative", ["bad.mcap", "metadata motion.fps"]),
        ("qpos_nan", ["bad.mcap", "/reference/qpos", "NaN", "frame 2"]),
        ("object_extras", ["bad.mcap", "motion.extras.human_contacts"]),
        ("string_extras", ["bad.mcap", "motion.extras.human_contacts"]),
        ("short_dynamics", ["bad.mcap", "/dynamics/step", "arrays.ctrl", "15 steps"]),
        ("names_not_a_list", ["bad.mcap", "motion.joint_names"]),
    ],
)
def test_mcap_reader_checks_what_the_npz_reader_checks(
    tmp_path: Path,
    motion: Motion,
    capsys: pytest.CaptureFixture[str],
    change: str,
    names: list[str],
) -> None:
    meta, messages = _records(motion, tmp_path)
    m = dict(meta["motion"])
    if change == "fps_nan":
        m["fps"] = "nan"
    elif change == "fps_negative":
        m["fps"] = "-50.0"
    elif change == "qpos_nan":
        topic, schema, t, msg = next(x for x in messages if x[0] == "/reference/qpos" and
                                     x[2] == round(2 * 1e9 / FPS))  # fmt: skip
        i = messages.index((topic, schema, t, msg))
        messages[i] = (topic, schema, t, {**msg, "qpos": [math.nan, *msg["qpos"][1:]]})
    elif change in ("object_extras", "string_extras"):
        m["extras"] = json.dumps({"human_contacts": ["object" if change == "object_extras"
                                                     else "<U5", [2]]})  # fmt: skip
    elif change == "short_dynamics":
        last = max(t for topic, _, t, _ in messages if topic == "/dynamics/step")
        messages = [x for x in messages if not (x[0] == "/dynamics/step" and x[2] == last)]
    elif change == "names_not_a_list":
        m["joint_names"] = "7"
    bad = _raw_mcap(tmp_path / "bad.mcap", {**meta, "motion": m}, messages)
    before = bad.read_bytes()
    _refused(capsys, ["convert", str(bad), str(tmp_path / "out.npz")], *names)
    _refused(capsys, ["convert", str(bad), str(tmp_path / "out.mcap")], *names)
    with pytest.raises(InputError):
        read_motion_mcap(bad)
    _only(tmp_path, "bad.mcap")
    assert bad.read_bytes() == before


def test_mcap_object_extras_never_become_pickles(
    tmp_path: Path, motion: Motion, capsys: pytest.CaptureFixture[str]
) -> None:
    """The MCAP reader used to build extras of any dtype the metadata named: 'object' made
    ``humimic convert`` write a pickled array. Now the reader refuses them, and a good file
    converts to an archive that loads without pickle."""
    meta, messages = _records(motion, tmp_path)
    m = {**meta["motion"], "extras": json.dumps({"human_contacts": ["O", [2]],
                                                  "keypoint_targets": ["float64", [3, 3]]})}  # fmt: skip
    bad = _raw_mcap(tmp_path / "obj.mcap", {**meta, "motion": m}, messages)
    with pytest.raises(McapFormatError, match=r"obj\.mcap: metadata motion\.extras"):
        read_motion_mcap(bad)
    good = write_motion_mcap(motion, tmp_path / "good.mcap")
    assert main(["convert", str(good), str(tmp_path / "good.npz")]) == 0
    with np.load(tmp_path / "good.npz", allow_pickle=False) as z:
        assert all(z[k].dtype != object for k in z.files)  # Raises on a pickled member.
    assert load_motion(tmp_path / "good.npz").extras is not None


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("fps", math.nan, "fps must be a positive number"),
        ("fps", -1.0, "fps must be a positive number"),
        ("qpos", "nan", "qpos contains NaN or inf (frame 1)"),
        ("extras", {"bad": np.array([object()] * FRAMES)}, "extra_bad: holds Python objects"),
        ("extras", {"short": np.zeros(FRAMES - 1)}, "extra_short has shape"),
        ("info", {"x": object()}, "info_json: not JSON-able"),
    ],
)
def test_save_and_write_refuse_a_bad_motion_and_write_nothing(
    tmp_path: Path, motion: Motion, field: str, value: object, message: str
) -> None:
    """save_motion and write_motion_mcap run the same validator before writing."""
    if value == "nan":
        q = motion.qpos.copy()
        q[1, 9] = np.nan
        value = q
    bad = replace(motion, **{field: value})
    with pytest.raises(MotionDataError, match=r"x\.npz: not written") as info:
        save_motion(bad, tmp_path / "x.npz")
    assert message in str(info.value)
    with pytest.raises(MotionDataError, match=r"x\.mcap: not written") as info:
        write_motion_mcap(bad, tmp_path / "x.mcap")
    assert message in str(info.value)
    _only(tmp_path)


# --- Zero quaternions ----------------------------------------------------------------------------


def test_refine_refuses_a_zero_base_quaternion(
    tmp_path: Path, motion: Motion, capsys: pytest.CaptureFixture[str]
) -> None:
    """``humimic refine`` used to exit 0 on it (and ``train`` to blame the environment)."""
    arrays = _arrays(motion, tmp_path)
    arrays["qpos"][2, 3:7] = 0.0
    bad = tmp_path / "zero.npz"
    np.savez(bad, **arrays)  # type: ignore[arg-type]
    _refused(capsys, ["refine", str(bad), "--out", str(tmp_path / "out.npz")],
             "zero.npz", "qpos frame 2", "norm 0")  # fmt: skip
    _only(tmp_path, "zero.npz")


def test_load_refuses_a_zero_body_quaternion(tmp_path: Path, motion: Motion) -> None:
    arrays = _arrays(motion, tmp_path)
    arrays["body_quat_w"][3, 5] = 0.0
    bad = tmp_path / "zero_body.npz"
    np.savez(bad, **arrays)  # type: ignore[arg-type]
    with pytest.raises(MotionDataError) as info:
        load_motion(bad)
    msg = str(info.value)
    assert "zero_body.npz: body_quat_w frame 3" in msg and repr(motion.body_names[5]) in msg


def test_train_refuses_a_zero_quaternion_before_any_work(
    tmp_path: Path, motion: Motion, capsys: pytest.CaptureFixture[str]
) -> None:
    arrays = _arrays(motion, tmp_path)
    arrays["qpos"][0, 3:7] = 0.0
    bad = tmp_path / "zero.npz"
    np.savez(bad, **arrays)  # type: ignore[arg-type]
    _refused(capsys, ["train", "--motion", str(bad), "--out", str(tmp_path / "run")],
             "zero.npz", "qpos frame 0")  # fmt: skip
    _only(tmp_path, "zero.npz")


@pytest.mark.parametrize("cmd", ["convert", "train"])
def test_a_root_copy_that_is_not_body_0s_pose_is_refused(
    cmd: str, tmp_path: Path, motion: Motion, capsys: pytest.CaptureFixture[str]
) -> None:
    """root_quat_w all zeros (what mjlab's tracker reads as the root) passed convert and
    train: humimic read body_quat_w and never looked at the copy."""
    arrays = _arrays(motion, tmp_path)
    arrays["root_quat_w"] = np.zeros_like(arrays["root_quat_w"])
    bad = tmp_path / "root.npz"
    np.savez(bad, **arrays)  # type: ignore[arg-type]
    argv = (["convert", str(bad), str(tmp_path / "out.mcap")] if cmd == "convert"
            else ["train", "--motion", str(bad), "--out", str(tmp_path / "run")])  # fmt: skip
    _refused(capsys, argv, "root.npz", "root_quat_w frame 0", "body_quat_w[:, 0]")
    _only(tmp_path, "root.npz")


@pytest.mark.parametrize(
    ("label", "why"), [("../../etc", "unknown robot"), ("t1", "not that robot's")]
)
def test_convert_refuses_a_motion_labelled_with_another_robot(
    label: str, why: str, tmp_path: Path, motion: Motion, capsys: pytest.CaptureFixture[str]
) -> None:
    """convert wrote a G1 clip labelled ``t1`` (or a path) as it came; train and refine
    refused it."""
    arrays = _arrays(motion, tmp_path)
    arrays["robot"] = np.array(label)
    bad = tmp_path / "labelled.npz"
    np.savez(bad, **arrays)  # type: ignore[arg-type]
    _refused(capsys, ["convert", str(bad), str(tmp_path / "out.mcap")], "labelled.npz", why)
    _only(tmp_path, "labelled.npz")


# --- The dynamic section -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("key", "cut", "message"),
    [
        ("ctrl", 3, "dynamics_ctrl has 13 steps, expected 16"),
        ("qpos", 1, "dynamics_qpos has shape (15, 36), expected (16, 36)"),
        ("qvel", 2, "dynamics_qvel has shape (14, 35), expected (16, 35)"),
    ],
)
def test_replay_refuses_a_short_dynamic_section(
    tmp_path: Path,
    motion: Motion,
    capsys: pytest.CaptureFixture[str],
    key: str,
    cut: int,
    message: str,
) -> None:
    """``humimic replay`` used to end in a traceback (a broadcasting error)."""
    arrays = _arrays(motion, tmp_path)
    arrays[f"dynamics_{key}"] = arrays[f"dynamics_{key}"][:-cut]
    bad = tmp_path / "short.npz"
    np.savez(bad, **arrays)  # type: ignore[arg-type]
    _refused(capsys, ["replay", str(bad)], "short.npz", message)
    _refused(capsys, ["convert", str(bad), str(tmp_path / "short.mcap")], "short.npz", message)
    _only(tmp_path, "short.npz")


def test_replay_names_the_file_when_the_section_does_not_fit_the_model(
    tmp_path: Path, motion: Motion, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sizes the validator cannot know (the training model's) are checked by check_replay,
    which names the motion's file."""
    from humimic.retarget.dynamics import check_replay

    assert motion.dynamics is not None
    dyn = {**motion.dynamics, "initial_state": np.zeros(80)}  # The G1's state has 72.
    path = save_motion(replace(motion, dynamics=dyn), tmp_path / "big_state.npz")
    _refused(capsys, ["replay", str(path)], "big_state.npz", "dynamics_initial_state", "(72,)")
    good = save_motion(motion, tmp_path / "good.npz")
    r = check_replay(load_motion(good))  # The fixture's section replays (with differences).
    assert r["steps"] == (FRAMES - 1) * 4
    ctrl = np.zeros((16, 5))
    with pytest.raises(InputError, match=r"mine\.npz: dynamics_ctrl has shape \(16, 5\)"):
        check_replay(replace(motion, dynamics={**dyn, "initial_state": motion.dynamics[
            "initial_state"], "ctrl": ctrl}, source="mine.npz"))  # fmt: skip


# --- Files that are not .npz motions ------------------------------------------------------------


def test_random_bytes_and_mcap_given_as_npz_say_what_they_are(
    tmp_path: Path, motion: Motion, capsys: pytest.CaptureFixture[str]
) -> None:
    """They were reported as 'pickled data'."""
    noise = tmp_path / "x.bin"
    noise.write_bytes(np.random.default_rng(0).bytes(3000))
    mcap = write_motion_mcap(motion, tmp_path / "m.mcap")
    out = tmp_path / "out.npz"
    err = _refused(capsys, ["refine", str(noise), "--out", str(out)], "x.bin", "not an .npz")
    assert "pickle" not in err
    err = _refused(capsys, ["refine", str(mcap), "--out", str(out)], "m.mcap", "is an MCAP file",
                   "humimic convert")  # fmt: skip
    assert "pickle" not in err
    # An MCAP file named .npz: rename it; an .npz archive named .mcap: likewise.
    disguised = tmp_path / "disguised.npz"
    disguised.write_bytes(mcap.read_bytes())
    _refused(capsys, ["convert", str(disguised), str(tmp_path / "o.mcap")], "disguised.npz",
             "is an MCAP file", "disguised.mcap")  # fmt: skip
    npz = save_motion(motion, tmp_path / "real.npz")
    fake = tmp_path / "fake.mcap"
    fake.write_bytes(npz.read_bytes())
    _refused(capsys, ["convert", str(fake), str(tmp_path / "o.npz")], "fake.mcap",
             "zip archive", "fake.npz")  # fmt: skip
    # A good archive with the wrong suffix.
    wrong = tmp_path / "motion.bin"
    wrong.write_bytes(npz.read_bytes())
    with pytest.raises(MotionDataError, match=r"motion\.bin: motion files end in \.npz"):
        load_motion(wrong)
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    with pytest.raises(MotionDataError, match=r"empty\.npz: an empty file"):
        load_motion(empty)
    _only(tmp_path, "x.bin", "m.mcap", "disguised.npz", "real.npz", "fake.mcap", "motion.bin",
          "empty.npz")  # fmt: skip


def test_train_given_an_mcap_motion_says_convert_it(
    tmp_path: Path, motion: Motion, capsys: pytest.CaptureFixture[str]
) -> None:
    mcap = write_motion_mcap(motion, tmp_path / "m.mcap")
    err = _refused(capsys, ["train", "--motion", str(mcap), "--out", str(tmp_path / "run")],
                   "m.mcap", "is an MCAP file", "humimic convert")  # fmt: skip
    assert "pickle" not in err
    _only(tmp_path, "m.mcap")


@pytest.mark.parametrize(
    ("mutation", "message"),
    [
        ("object_member", "holds Python objects (a pickle)"),
        ("huge_shape", "claims shape (1000000000000, 36)"),
        ("huge_header", ".npy header of"),
        ("not_npy_member", "is not an .npy array"),
        ("string_fps", "fps: expected one number"),
        ("array_schema", "schema_version: expected one integer"),
    ],
)
def test_archive_members_are_checked_before_they_are_read(
    tmp_path: Path, motion: Motion, mutation: str, message: str
) -> None:
    """The .npz reader parses every member's header itself: no pickle, no allocation of a
    declared size the archive does not hold."""
    import zipfile

    arrays = _arrays(motion, tmp_path)
    path = tmp_path / "bad.npz"
    if mutation == "object_member":
        arrays["extra_x"] = np.array([{"a": 1}] * FRAMES, dtype=object)
        np.savez(path, **arrays, allow_pickle=True)  # type: ignore[arg-type]
    elif mutation in ("huge_shape", "huge_header", "not_npy_member"):
        np.savez(path, **arrays)  # type: ignore[arg-type]
        with zipfile.ZipFile(path, "a") as z:
            if mutation == "huge_shape":
                header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000000, 36), }"
                z.writestr("qpos_big.npy", b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little")
                           + header.encode() + b"\x00" * 64)  # fmt: skip
            elif mutation == "huge_header":
                z.writestr("z.npy", b"\x93NUMPY\x02\x00" + (1 << 31).to_bytes(4, "little"))
            else:
                z.writestr("readme.txt", "hello")
    elif mutation == "string_fps":
        arrays["fps"] = np.array("fifty")
        np.savez(path, **arrays)  # type: ignore[arg-type]
    else:
        arrays["schema_version"] = np.array([1, 1])
        np.savez(path, **arrays)  # type: ignore[arg-type]
    with pytest.raises(MotionDataError) as info:
        load_motion(path)
    assert str(info.value).startswith(f"{path}:") and message in str(info.value)


# --- Scenes ---------------------------------------------------------------------------------------


def _scene(tmp_path: Path, text: str, name: str = "scene.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_1000_m_box_is_refused_before_sampling(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The 3-line scene that exhausted the machine's memory (22 GB) in the interaction-mesh
    retargeter."""
    scene = _scene(
        tmp_path, "schema_version: 1\nobjects:\n  - {name: slab, box: [1000, 1000, 1]}\n"
    )
    out = tmp_path / "out.npz"
    _refused(capsys, ["retarget", str(shared_data / "cmu" / "35_01.bvh"), "--method",
                      "interaction-mesh", "--scene", str(scene), "--out", str(out)],
             "scene.yaml", "objects[0] (slab)", "box")  # fmt: skip
    _only(tmp_path, "scene.yaml")


@pytest.mark.parametrize(
    ("obj", "message"),
    [
        ("{name: a, box: [.nan, 1, 1]}", "objects[0] (a).box: expected 3 numbers"),
        ("{name: a, box: [-1, 1, 1]}", "objects[0] (a).box: extents must be positive"),
        ("{name: a, box: [1, 1, 1], pos: [.inf, 0, 0]}", "objects[0] (a).pos: expected 3"),
        ("{name: a, box: [1, 1, 1], pos: [5000, 0, 0]}", "from the origin"),
        ("{name: a, box: [1, 1, 1], quat: [0, 0, 0, 0]}", "a quaternion is zero"),
        ("{name: a, box: [1, 1, 1], scale: .inf}", "objects[0] (a).scale"),
        ("{name: a, box: [1, 1, 1], scale: 1000}", "more than the 100 m"),
        ("{name: a, box: [1.0e-5, 1.0e-5, 1.0e-5]}", "too small"),
        ("{name: [1], box: [1, 1, 1]}", "objects[0].name: expected a non-empty string"),
        ("{name: a, mesh: empty.obj}", "objects[0] (a).mesh"),
        ("{name: a, mesh: flat.obj}", "every triangle has zero area"),
        ("{name: a, mesh: dense.obj}", "triangles, more than the 20000"),
        ("{name: a, mesh: [x]}", "objects[0] (a).mesh: expected a file name"),
        ("{name: a, box: [1, 1, 1], trajectory: huge.npy}", "objects[0] (a).trajectory"),
        ("{name: a, box: [1, 1, 1], trajectory: objects.npy}", "Python objects"),
    ],
)
def test_scenes_it_cannot_handle_are_refused_naming_file_and_object(
    tmp_path: Path, obj: str, message: str
) -> None:
    from humimic.datasets.scene import load_scene

    (tmp_path / "empty.obj").write_text("# nothing\n")
    (tmp_path / "flat.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\nf 1 3 4\nf 1 2 4\n"
    )
    if "dense" in obj:  # A 101 x 101 grid: 20000 triangles, and one more.
        n = 101
        lines = [f"v {i % n} {i // n} {(i % 3) * 0.01}" for i in range(n * n)]
        for r in range(n - 1):
            for c in range(n - 1):
                a = r * n + c + 1
                lines += [f"f {a} {a + 1} {a + n}", f"f {a + 1} {a + n + 1} {a + n}"]
        lines.append("f 1 2 3")
        (tmp_path / "dense.obj").write_text("\n".join(lines) + "\n")
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (100000000000, 7), }"
    (tmp_path / "huge.npy").write_bytes(
        b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode()
    )
    np.save(tmp_path / "objects.npy", np.array([None] * 7, dtype=object), allow_pickle=True)
    scene = _scene(tmp_path, f"schema_version: 1\nfps: 30\nobjects:\n  - {obj}\n")
    with pytest.raises(InputError) as info:
        load_scene(scene)
    msg = str(info.value)
    assert msg.startswith(f"{scene}: objects[0]"), msg
    assert message in msg, msg


def test_scene_sampling_is_bounded_analytically(tmp_path: Path) -> None:
    """The largest box a scene may hold, at the default spacing, would have millions of
    points: the count is computed first and the spacing widened; only then are points made."""
    from humimic.datasets.scene import (
        MAX_POINTS_PER_OBJECT,
        MAX_SCENE_POINTS,
        _sample_count,
        load_scene,
    )

    scene = load_scene(_scene(tmp_path, "schema_version: 1\nobjects:\n"
                                        "  - {name: big, box: [100, 100, 2]}\n"
                                        "  - {name: step, box: [1, 0.8, 0.2]}\n"
                                        + "".join(f"  - {{name: b{i}, box: [90, 90, 1]}}\n"
                                                  for i in range(8))))  # fmt: skip
    big, step = scene.objects[0], scene.objects[1]
    assert _sample_count(big.vertices, big.faces, 0.05) > 5e6  # What it used to sample.
    spacings = scene.sampling_spacings(0.05)
    counts = [_sample_count(o.vertices, o.faces, s) for o, s in zip(scene.objects, spacings,
                                                                     strict=True)]  # fmt: skip
    assert max(counts) <= MAX_POINTS_PER_OBJECT and sum(counts) <= MAX_SCENE_POINTS
    assert spacings[0] > 0.05
    # Asserted bounded before sampling; now sample.
    points = scene.surface_points(0.05)
    assert sum(len(p) for p in points) <= MAX_SCENE_POINTS
    # A small scene keeps the requested spacing exactly.
    small = load_scene(_scene(tmp_path, "schema_version: 1\nobjects:\n"
                                        "  - {name: step, box: [1, 0.8, 0.2]}\n", "small.yaml"))  # fmt: skip
    assert small.sampling_spacings(0.05) == [0.05]
    del step


def test_interaction_mesh_size_is_checked_before_qhull() -> None:
    from humimic.errors import RetargetError
    from humimic.retarget.interaction_mesh import MAX_MESH_POINTS, tetra_neighbors

    with pytest.raises(InputError, match=r"--mesh\.max_scene_points"):
        tetra_neighbors(np.zeros((MAX_MESH_POINTS + 1, 3)))
    pts = np.random.default_rng(0).random((10, 3))
    pts[3, 1] = np.nan
    with pytest.raises(RetargetError, match="NaN"):
        tetra_neighbors(pts)


# --- Robot models ---------------------------------------------------------------------------------

_BODY = "<body name='{name}' pos='0 0 0.1'><joint name='{joint}' type='hinge'/><geom size='.05'/>"
_G1_FEET = ("left_ankle_roll_link", "right_ankle_roll_link")


def _robot_xml(*, joints: tuple[str, ...] = ("left_knee_joint",), feet: bool = True,
               actuated: tuple[str, ...] | None = None, extra: str = "") -> str:  # fmt: skip
    bodies = "".join(_BODY.format(name=f"b{i}", joint=j) + "</body>" for i, j in enumerate(joints))
    if feet:
        bodies += "".join(f"<body name='{f}'><geom size='.05'/></body>" for f in _G1_FEET)
    acts = "".join(f"<motor joint='{j}'/>" for j in (joints if actuated is None else actuated))
    return (f"<mujoco>{extra}<worldbody><body name='pelvis'><freejoint/><geom size='.1'/>"
            f"{bodies}</body></worldbody><actuator>{acts}</actuator></mujoco>")  # fmt: skip


@pytest.mark.parametrize(
    ("xml", "message"),
    [
        ("<mujoco><worldbody>", "MuJoCo cannot load this model"),
        (_robot_xml(feet=False), "no body 'left_ankle_roll_link'"),
        (_robot_xml(joints=("mystery_joint",)), "'mystery_joint' matches no motor pattern"),
        (_robot_xml(actuated=("ghost_joint",)), "'ghost_joint', which is not a joint"),
        (_robot_xml(extra="<asset><mesh name='m' file='missing.stl'/></asset>"), "missing.stl"),
    ],
)
def test_bad_menagerie_root_models_are_input_errors_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], xml: str, message: str
) -> None:
    root = tmp_path / "menagerie"
    (root / "unitree_g1").mkdir(parents=True)
    model = root / "unitree_g1" / "scene.xml"
    model.write_text(xml)
    out = tmp_path / "out" / "g1.xml"
    _refused(capsys, ["robots", "export", "g1", "--out", str(out), "--menagerie-root", str(root)],
             str(model), message)  # fmt: skip
    with pytest.raises(InputError, match=r"scene\.xml"):
        nominal_model(get_robot("g1"), menagerie_root=root)
    _only(tmp_path, "menagerie")


def test_export_refuses_to_overwrite_its_input_model(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "menagerie"
    (root / "unitree_g1").mkdir(parents=True)
    model = root / "unitree_g1" / "scene.xml"
    model.write_text(_robot_xml(joints=("left_knee_joint", "right_knee_joint")))
    before = model.read_text()
    _refused(capsys, ["robots", "export", "g1", "--out", str(model), "--menagerie-root",
                      str(root)], "--out", "would overwrite the robot model")  # fmt: skip
    assert model.read_text() == before
    _only(root / "unitree_g1", "scene.xml")


def test_validate_motion_accepts_the_good_motion(tmp_path: Path, motion: Motion) -> None:
    """The fixture is valid, so every refusal above comes from the change each test makes;
    and both formats round-trip it."""
    validate_motion(motion)
    back = load_motion(save_motion(motion, tmp_path / "g.npz"))
    assert back.source == str(tmp_path / "g.npz")
    via = read_motion_mcap(write_motion_mcap(motion, tmp_path / "g.mcap"))
    assert via.dynamics is not None and back.dynamics is not None
    for k, v in back.dynamics.items():
        np.testing.assert_array_equal(via.dynamics[k], v)
