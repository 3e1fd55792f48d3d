"""``humimic export``: the trained policy as ONNX for deployment (:func:`export`)."""

from __future__ import annotations

import contextlib
import io
import logging
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from humimic.configs.jobs import ExportSettings
from humimic.errors import InputError
from humimic.io import atomic_write, check_not_input, check_writable


def load_policy_runner(run: Path, checkpoint: Path | None, device: str = "cpu"):
    """The run's runner (with a one-env environment) loaded from a checkpoint.

    Raises:
        InputError: Not a run folder, its motion is missing, or the checkpoint is damaged or
            does not fit the run's networks (names the file).
    """
    from humimic.tracking.env import TrackingEnv
    from humimic.tracking.rsl import make_runner
    from humimic.tracking.runs import (
        load_weights,
        resolve_checkpoint,
        run_config,
        run_rsl_cfg,
    )
    from humimic.tracking.task import library_files, load_reference, task_config

    recorded = run_config(run)
    settings = recorded[1]
    path, blob = resolve_checkpoint(run, checkpoint)
    if not settings.motion.exists():  # The env needs it for the observation sizes.
        raise InputError(f"{run}: the run's motion {settings.motion} is missing (moved?)")
    task = task_config(settings.robot, "none", settings.seed, settings=settings.task)
    # A library's first clip: the observation sizes are every clip's.
    first = library_files(settings.motion)[0]
    motion = load_reference(first, settings.robot, 1.0 / task.step_dt)
    env = TrackingEnv(task, motion, 1, device=device)
    try:
        runner = make_runner(env, run_rsl_cfg(run, recorded), log_dir=None, device=device)
        load_weights(runner, blob, path, "--checkpoint" if checkpoint else "checkpoint")
    except BaseException:
        env.close()
        raise
    return runner, env, path


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence torch's exporter: its progress lines (stdout), its notes on optional packages
    (torchvision, logged) and its deprecation warnings, none of which the user can act on."""
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=FutureWarning)
            # torch's exporter notes that a GRU's flat weights are plain attributes; the
            # weights are exported all the same (a test compares the outputs).
            warnings.filterwarnings("ignore", message=".*rnn._flat_weights")
            yield
    finally:
        logger.setLevel(level)


def onnx_bytes(model: Any) -> bytes:
    """The policy's ONNX model as one self-contained file's bytes: the weights inside it, not
    in an external-data side file (a policy's MLP is far below protobuf's 2 GB limit)."""
    batch = torch.export.Dim("batch")
    recurrent = bool(getattr(model, "is_recurrent", False))
    # A GRU's state has the batch on its second axis.
    shapes = ({0: batch}, {1: batch}) if recurrent else ({0: batch},)
    with _quiet_exporter(), torch.no_grad():
        program = torch.onnx.export(model, model.get_dummy_inputs(), None, export_params=True,
                                    opset_version=18, input_names=model.input_names,
                                    output_names=model.output_names, dynamo=True,
                                    dynamic_shapes=shapes)  # fmt: skip
    assert program is not None  # With dynamo=True and no file, export returns the program.
    return program.model_proto.SerializeToString()


def export(settings: ExportSettings) -> Path:
    """Write the policy; returns the file.

    The exported graph is the actor's deterministic path, observation normalization included:
    input ``obs`` (the actor's observation groups concatenated in the order of the run's
    ``obs_groups``, e.g. ``policy`` then ``proprio_history`` for the ``asymmetric`` variant;
    Shape: (batch, D)), output ``actions`` (Shape: (batch, num_joints); PD targets are the
    run's action base plus ``scale * actions``: the default pose, the reference, or the
    refined motion's stored targets with or without LQR feedback, docs/tracking.md). A recurrent student (``humimic
    distill --student gru``) also takes its GRU state ``h_in`` (Shape: (layers, batch,
    hidden); zeros at the start of an episode) and returns the next one as ``h_out``: feed it
    back at every policy step. An ``rma`` student's graph holds its adaptation module and the
    teacher's base policy: input ``obs`` (``policy`` then ``proprio_history``), output
    ``actions``. The file is self-contained (the weights inside it, no
    external-data side file: :func:`onnx_bytes`) and written atomically.

    Raises:
        InputError: Bad settings, a teacher or rma run, an output that would overwrite one of the
            run's files, the motion or the checkpoint, or a checkpoint that does not load;
            nothing is written.
    """
    from humimic.tracking.runs import run_config, run_files, run_rsl_cfg

    settings.validate()
    out = settings.out or settings.run / "policy.onnx"
    recorded = run_config(settings.run)
    run = recorded[1]
    inputs = {**run_files(settings.run), "the motion": run.motion,
              "--checkpoint": settings.checkpoint}  # fmt: skip
    check_not_input(out, inputs, "--out")
    check_writable(out)
    cfg = run_rsl_cfg(settings.run, recorded)
    if "physics" in cfg["obs_groups"].get("actor", ()):
        student = " --student rma" if run.variant == "rma" else ""
        raise InputError(
            f"{settings.run}: the actor of a --variant {run.variant} run reads the simulator's "
            "physics parameters, which a robot does not have; distill it (humimic distill"
            f"{student}) and export the student"
        )
    runner, env, _ = load_policy_runner(settings.run, settings.checkpoint)
    try:
        model = runner.alg.get_policy().as_onnx(verbose=False).to("cpu").eval()
        data = onnx_bytes(model)
    finally:
        env.close()
    with atomic_write(out) as f:  # One file, renamed into place whole.
        f.write(data)
    return out


__all__ = ["export", "load_policy_runner", "onnx_bytes"]
