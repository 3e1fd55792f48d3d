"""Fuzz the readers the hostile pass found unfuzzed: ``sysid import``'s Unitree ``.npz`` logs,
checkpoints, and run folders' ``config.yaml``. Seeded mutations of small valid files.

Each case fails on an exception that is not a :class:`HumimicError` (a traceback), on an exit
code other than 0 or 2, on a message that is not one line, on an output left behind by a
refused import, and on a changed input. Failures name the kind, the seed and the change.
"""

from __future__ import annotations

import io
import shutil
import traceback
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml

from archives import flip_bytes, truncate_bytes
from humimic.cli.main import main
from humimic.errors import HumimicError, InputError
from humimic.motion import motion_from_qpos, save_motion
from humimic.real2sim import LogSettings, simulate_log
from humimic.robots import get_robot, nominal_model

CASES = 12
"""Seeds per kind of mutation."""


# --- sysid import: Unitree .npz --------------------------------------------------------------


@pytest.fixture(scope="module")
def unitree_npz(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A 1 s Unitree low-state log of the G1 on the floor (29 motors, IMU), as np.savez
    writes it; made here from a simulated log."""
    log = simulate_log(get_robot("g1"), [], LogSettings(duration=1.0, base="floating", seed=5))
    assert log.imu is not None
    idx = log.command_index(log.t)  # One command row per state row, as a recorder writes.
    arrays = {"time": log.t, "q": log.q, "dq": log.qd, "quaternion": log.imu.quat_w,
              "gyroscope": log.imu.gyro_b, "cmd_q": log.cmd_q[idx], "cmd_dq": log.cmd_qd[idx],
              "cmd_tau": log.cmd_tau[idx], "cmd_kp": log.kp[idx], "cmd_kd": log.kd[idx]}  # fmt: skip
    buf = io.BytesIO()
    np.savez(buf, **arrays)  # type: ignore[arg-type]
    return buf.getvalue()


def _arrays(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _savez(arrays: dict[str, Any]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=True, **arrays)
    return buf.getvalue()


def _npz_mutation(kind: str, rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    if kind == "flip":
        return flip_bytes(rng, data)
    if kind == "truncate":
        return truncate_bytes(rng, data)
    arrays = _arrays(data)
    k = sorted(arrays)[int(rng.integers(len(arrays)))]
    v = arrays[k]
    if kind == "values":
        bad = [np.nan, np.inf, -1e300, 1e300, 0.0][int(rng.integers(5))]
        v = v.copy()
        v.reshape(-1)[int(rng.integers(v.size))] = bad
        return _savez({**arrays, k: v}), f"{k}: one value {bad}"
    if kind == "shape":
        ops = {"drop_row": lambda a: a[:-1], "drop_column": lambda a: a[:, :-1] if a.ndim > 1
               else a[:0], "ravel": lambda a: a.ravel(), "add_axis": lambda a: a[None],
               "empty": lambda a: a[:0]}  # fmt: skip
        op = sorted(ops)[int(rng.integers(len(ops)))]
        return _savez({**arrays, k: ops[op](v)}), f"{k} {op}"
    dtypes: list[Any] = [np.float16, np.int8, bool, np.complex64, "<U3", object]
    dt = dtypes[int(rng.integers(len(dtypes)))]
    with np.errstate(all="ignore"):
        w = v.astype(dt)
    return _savez({**arrays, k: w}), f"{k} as {np.dtype(dt)}"


@pytest.mark.parametrize("kind", ["flip", "truncate", "values", "shape", "dtype"])
def test_sysid_import_of_a_mutated_unitree_npz(
    kind: str, unitree_npz: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for seed in range(CASES):
        data, change = _npz_mutation(kind, np.random.default_rng(seed), unitree_npz)
        case = f"{kind}, seed {seed}: {change}"
        src = tmp_path / "low.npz"
        src.write_bytes(data)
        out = tmp_path / "out.mcap"
        try:
            code = main(["sysid", "import", str(src), "--out", str(out)])
        except Exception:
            pytest.fail(f"{case}: {traceback.format_exc(limit=-3)}")
        err = capsys.readouterr().err
        assert code in (0, 2), f"{case}: exit {code}: {err}"
        if code == 2:
            assert err.startswith("humimic: error: ") and err.count("\n") == 1, f"{case}: {err}"
            assert not out.exists(), case
        assert src.read_bytes() == data, case
        assert sorted(p.name for p in tmp_path.iterdir()) in (["low.npz"], ["low.npz", "out.mcap"])
        out.unlink(missing_ok=True)


# --- checkpoints and run folders -----------------------------------------------------------------


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1-iteration run of the G1 standing (2 envs, rollouts of 4 steps)."""
    folder = tmp_path_factory.mktemp("run")
    m = nominal_model(get_robot("g1"))
    save_motion(motion_from_qpos(m, np.tile(m.key_qpos[0], (20, 1)), 30.0, "g1"),
                folder / "stand.npz")  # fmt: skip
    out = folder / "run"
    assert main(["train", "--motion", str(folder / "stand.npz"), "--out", str(out),
                 "--num-envs", "2", "--max-iterations", "1", "--num-steps-per-env", "4",
                 "--dr", "none", "--task.action-base", "default", "--quiet"]) == 0  # fmt: skip
    return out


def _checkpoint_mutation(kind: str, rng: np.random.Generator, good: Path) -> tuple[bytes, str]:
    data = good.read_bytes()
    if kind == "flip":
        return flip_bytes(rng, data)
    if kind == "truncate":
        return truncate_bytes(rng, data)
    blob = torch.load(good, weights_only=True)
    group = sorted(k for k in blob if k.endswith("_state_dict"))[int(rng.integers(2))]
    keys = sorted(blob[group])
    key = keys[int(rng.integers(len(keys)))]
    choice = int(rng.integers(4))
    if choice == 0:
        blob[group][key] = torch.full_like(blob[group][key], float("nan"))
        change = f"{group}.{key} NaN"
    elif choice == 1:
        del blob[group][key]
        change = f"{group}.{key} deleted"
    elif choice == 2:
        blob["iter"] = ["one", -1, 1.5, None][int(rng.integers(4))]
        change = f"iter {blob['iter']!r}"
    else:
        blob[group][key] = blob[group][key].reshape(-1)[:1].clone()
        change = f"{group}.{key} cut to one value"
    buf = io.BytesIO()
    torch.save(blob, buf)
    return buf.getvalue(), change


@pytest.mark.parametrize("kind", ["flip", "truncate", "content"])
def test_export_of_a_mutated_checkpoint(
    kind: str, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Read by ``humimic export --checkpoint``: refused with one line naming the file, or a
    policy that holds only finite weights."""
    good = sorted((run / "checkpoints").glob("model_*.pt"))[-1]
    for seed in range(CASES // 2):
        data, change = _checkpoint_mutation(kind, np.random.default_rng(seed), good)
        case = f"{kind}, seed {seed}: {change}"
        bad = tmp_path / "model.pt"
        bad.write_bytes(data)
        out = tmp_path / "policy.onnx"
        try:
            code = main(["export", str(run), "--checkpoint", str(bad), "--out", str(out)])
        except Exception:
            pytest.fail(f"{case}: {traceback.format_exc(limit=-3)}")
        err = capsys.readouterr().err
        assert code in (0, 2), f"{case}: exit {code}: {err}"
        if code == 2:
            assert str(bad) in err and err.count("\n") == 1, f"{case}: {err}"
            assert not out.exists(), case
        else:
            import onnx

            weights = [onnx.numpy_helper.to_array(t) for t in onnx.load(str(out)).graph.initializer]
            assert all(np.isfinite(w).all() for w in weights if w.dtype.kind == "f"), case
            out.unlink()
        assert bad.read_bytes() == data, case


def _config_mutation(rng: np.random.Generator, text: str) -> tuple[str, str]:
    choice = int(rng.integers(4))
    if choice == 0:
        raw, change = flip_bytes(rng, text.encode())
        return raw.decode("utf-8", errors="replace"), change
    if choice == 1:
        n = int(rng.integers(len(text)))
        return text[:n], f"cut at {n} of {len(text)} characters"
    config = yaml.safe_load(text)
    section = ["settings", "tracking", "ppo"][int(rng.integers(3))]
    keys = sorted(config[section])
    key = keys[int(rng.integers(len(keys)))]
    if choice == 2:
        del config[section][key]
        return yaml.safe_dump(config, sort_keys=False), f"{section}.{key} deleted"
    value = ["nonsense", -1, 1e308, None, [1, 2], {"a": 1}][int(rng.integers(6))]
    config[section][key] = value
    return yaml.safe_dump(config, sort_keys=False), f"{section}.{key} = {value!r}"


def test_a_run_folder_with_a_mutated_config_is_read_or_refused(run: Path, tmp_path: Path) -> None:
    """The run folder's reader (every command that takes a run starts there): one line naming
    the file, never a traceback."""
    from humimic.tracking.runs import run_config, run_rsl_cfg

    text = (run / "config.yaml").read_text()
    for seed in range(4 * CASES):
        mutated, change = _config_mutation(np.random.default_rng(seed), text)
        case = f"seed {seed}: {change}"
        copy = tmp_path / f"run{seed}"
        shutil.copytree(run, copy)
        (copy / "config.yaml").write_text(mutated)
        try:
            run_rsl_cfg(copy, run_config(copy))
        except InputError as e:
            assert "\n" not in str(e) and str(copy) in str(e), f"{case}: {e}"
        except HumimicError:
            pass
        except Exception:
            pytest.fail(f"{case}: {traceback.format_exc(limit=-3)}")
        shutil.rmtree(copy)
