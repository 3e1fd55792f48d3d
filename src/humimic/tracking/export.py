"""``humimic export``: the trained policy as ONNX for deployment.

The exported graph is the actor's deterministic path, observation normalization included:
input ``obs`` (the actor's observation groups concatenated in the order of the run's
``obs_groups``, e.g. ``policy`` then ``proprio_history`` for the ``asymmetric`` variant; Shape:
(batch, D)), output ``actions``
(Shape: (batch, num_joints); PD targets are ``default + scale * actions``, see
docs/tracking.md). A recurrent student (``humimic distill --student gru``) also takes its GRU
state ``h_in`` (Shape: (layers, batch, hidden); zeros at the start of an episode) and returns
the next one as ``h_out``: feed it back at every policy step. The file is written atomically.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
import warnings
from pathlib import Path

import torch

from humimic.configs.runs import ExportSettings
from humimic.errors import InputError, OutputPathError
from humimic.io import check_writable


def load_policy_runner(run: Path, checkpoint: Path | None, device: str = "cpu"):
    """The run's runner (with a one-env environment) loaded from a checkpoint."""
    from humimic.tracking.env import TrackingEnv
    from humimic.tracking.rsl import make_runner
    from humimic.tracking.train import (
        load_reference,
        read_run_settings,
        resolve_checkpoint,
        run_rsl_cfg,
        task_config,
    )

    settings = read_run_settings(run)
    path, blob = resolve_checkpoint(run, checkpoint)
    task = task_config(settings.robot, "none", settings.seed)
    motion = load_reference(settings.motion, settings.robot, 1.0 / task.step_dt)
    env = TrackingEnv(task, motion, 1, device=device)
    runner = make_runner(env, run_rsl_cfg(run), log_dir=None, device=device)
    runner.load_checkpoint(blob)
    return runner, env, path


def export(settings: ExportSettings) -> Path:
    """Write the policy; returns the file."""
    out = settings.out or settings.run / "policy.onnx"
    if out.suffix != ".onnx":
        raise InputError(f"--out {out}: an ONNX file must end in .onnx")
    check_writable(out)
    from humimic.tracking.train import run_rsl_cfg

    cfg = run_rsl_cfg(settings.run)
    if "physics" in cfg["obs_groups"].get("actor", ()):
        raise InputError(
            f"{settings.run}: a teacher's actor reads the simulator's physics parameters, which "
            "a robot does not have; distill it (humimic distill) and export the student"
        )
    runner, env, _ = load_policy_runner(settings.run, settings.checkpoint)
    try:
        model = runner.alg.get_policy().as_onnx(verbose=False).to("cpu").eval()
        fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
        os.close(fd)
        try:
            batch = torch.export.Dim("batch")
            recurrent = bool(getattr(model, "is_recurrent", False))
            # A GRU's state has the batch on its second axis.
            shapes = ({0: batch}, {1: batch}) if recurrent else ({0: batch},)
            with (
                contextlib.redirect_stdout(io.StringIO()),
                torch.no_grad(),
                warnings.catch_warnings(),
            ):
                # torch's exporter notes that a GRU's flat weights are plain attributes; the
                # weights are exported all the same (a test compares the outputs).
                warnings.filterwarnings("ignore", message=".*rnn._flat_weights")
                torch.onnx.export(model, model.get_dummy_inputs(), tmp, export_params=True,
                                  opset_version=18, input_names=model.input_names,
                                  output_names=model.output_names,
                                  dynamo=True, dynamic_shapes=shapes)  # fmt: skip
            os.chmod(tmp, 0o644)
            os.replace(tmp, out)
        except OSError as e:
            raise OutputPathError(f"{out}: cannot write: {e}") from None
        finally:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    finally:
        env.close()
    return out


__all__ = ["export", "load_policy_runner"]
