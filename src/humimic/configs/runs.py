"""Settings of tracking runs (``humimic train``, ``humimic eval``): light to import."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro


@dataclass(frozen=True, kw_only=True)
class TrainSettings:
    """What ``humimic train`` runs.

    Attributes:
        motion: Reference motion file (``.npz`` from ``humimic retarget``).
        out: Run folder.
        robot: Registry name; must match the motion's.
        num_envs: Parallel environments.
        max_iterations: Total PPO iterations of the run (a resumed run continues up to it).
        device: Torch device of the learner (``cpu`` or ``cuda``). Under torchrun each process
            takes the GPU of its local rank.
        backend: The simulator: ``cpu`` (MuJoCo on the CPU) or ``warp`` (MuJoCo Warp on
            ``--device``: GPU throughput; needs ``humimic[gpu]``).
        dr: Domain randomization: a profile name (``none``, ``default``) or a YAML file.
        physics: Train on a fixed model: a physics file (docs/tracking.md, "Physics files"),
            e.g. the correction ``humimic sysid diagnose`` found; DR acts on top of it.
        init_from: Start from another run's weights (its newest checkpoint, or a checkpoint
            file): fine-tuning. Actor and critic must have the same inputs (same variant and
            task).
        variant: What actor and critic observe (docs/tracking.md, "Variants"):
            ``beyondmimic`` (actor: deployable observations; critic: privileged),
            ``robust`` (both deployable only), ``asymmetric`` (actor: deployable plus the
            proprioceptive history; critic: privileged), ``teacher`` (actor: deployable plus
            the physics parameters e; critic: privileged; distill it with ``humimic distill``).
        resume: Continue the run in ``out`` from its newest checkpoint.
        seed: Seed of torch and of the environment.
        checkpoint_every: Iterations between checkpoints (the last one is always written).
        num_steps_per_env: Rollout length per env and iteration (default: the PPO config's).
        max_minutes: Stop (with a checkpoint) after the iteration that passes this wall time.
        compile: Compile the env's tensor math with ``torch.compile`` (on the CPU: needs a C++
            compiler, seconds at the start; cuts the env's own cost per step, BENCHMARKS.md).
        quiet: No progress bar.
    """

    motion: Path
    out: Path
    robot: str = "g1"
    num_envs: int = 4096
    max_iterations: int = 1000
    device: str = "cpu"
    backend: Literal["cpu", "warp"] = "cpu"
    dr: str = "default"
    physics: str | None = None
    init_from: Path | None = None
    variant: Literal["beyondmimic", "robust", "asymmetric", "teacher"] = "beyondmimic"
    resume: bool = False
    seed: int = 0
    checkpoint_every: int = 50
    num_steps_per_env: int | None = None
    max_minutes: float | None = None
    compile: bool = False
    quiet: bool = False


@dataclass(frozen=True, kw_only=True)
class DistillSettings:
    """What ``humimic distill`` runs: DAgger-style distillation of a teacher run into a
    proprioceptive student (rsl_rl's Distillation: the student acts, the teacher labels every
    visited state).

    Attributes:
        teacher: Run folder of ``humimic train`` (any variant; ``teacher`` is the usual one).
        out: The student's run folder.
        student: ``mlp-history`` (an MLP on the policy observations and their history) or
            ``gru`` (a recurrent network on the policy observations).
        teacher_checkpoint: The teacher's checkpoint (default: its newest).
        num_envs: Parallel environments.
        max_iterations: Total distillation iterations (a resumed run continues up to it).
        device: Torch device (``cpu`` or ``cuda``).
        dr: Domain randomization (default: the teacher's).
        resume: Continue the run in ``out`` from its newest checkpoint.
        seed: Seed of torch and of the environment.
        checkpoint_every: Iterations between checkpoints.
        max_minutes: Stop (with a checkpoint) after the iteration that passes this wall time.
        compile: Compile the env's tensor math with ``torch.compile`` (on the CPU: needs a C++
            compiler, seconds at the start; cuts the env's own cost per step, BENCHMARKS.md).
        quiet: No progress bar.
    """

    teacher: Path
    out: Path
    student: Literal["mlp-history", "gru"] = "mlp-history"
    teacher_checkpoint: Path | None = None
    num_envs: int = 4096
    max_iterations: int = 300
    device: str = "cpu"
    dr: str | None = None
    resume: bool = False
    seed: int = 0
    checkpoint_every: int = 50
    max_minutes: float | None = None
    compile: bool = False
    quiet: bool = False


@dataclass(frozen=True, kw_only=True)
class EvalSettings:
    """What ``humimic eval`` runs.

    Attributes:
        run: Run folder of ``humimic train``.
        episodes: Episodes to run (each plays the whole clip from its first frame).
        motion: Evaluate on this clip (a motion file of the run's robot) instead of the run's.
        dr: Physics of the evaluation: a DR profile (``none``, ``default``) or a YAML file.
        physics: Evaluate on a fixed robot: a physics file or a shipped one (``backpack``,
            ``worn_knees``; docs/tracking.md, "Physics files"), e.g. a "real" robot training
            never saw. DR (``--dr``) acts on top of it.
        out: Write the metrics as JSON here.
        mcap: Write the first episode (policy and open loop) with the reference as MCAP here,
            for ``humimic view MCAP`` and Foxglove (default: ``out`` with the suffix ``.mcap``
            when ``out`` is given, else nothing).
        checkpoint: A checkpoint file (default: the run's newest).
        num_envs: Envs run in parallel, at least ``episodes`` (default: ``episodes``).
        device: Torch device of the policy.
        seed: Seed of the evaluation's randomness.
    """

    run: Annotated[Path, tyro.conf.Positional]
    episodes: int = 16
    motion: Path | None = None
    dr: str = "none"
    physics: str | None = None
    out: Path | None = None
    mcap: Path | None = None
    checkpoint: Path | None = None
    num_envs: int | None = None
    device: str = "cpu"
    seed: int = 1


@dataclass(frozen=True, kw_only=True)
class LoopSettings:
    """What ``humimic loop`` runs: deploy a policy on a "real" robot (a physics file that no
    training step reads), diagnose the gap with sysid on a gantry log of that robot, fine-tune
    in the corrected model, redeploy, report before and after (docs/tracking.md, "The loop").

    Attributes:
        run: The policy's run folder (``humimic train``; not a teacher or a student).
        real: The "real" robot: a physics file or a shipped one (``backpack``, ``worn_knees``).
        out: The loop's folder (new or empty).
        motion: The clip to deploy and fine-tune on (default: the run's).
        episodes: Episodes per deployment.
        iterations: Fine-tuning PPO iterations.
        num_envs: Fine-tuning envs.
        sysid_duration: Seconds of the gantry log.
        control: Also fine-tune in the nominal model for the same iterations, and deploy that.
        device: Torch device.
        seed: Seed of everything.
        max_minutes: Time budget of each fine-tuning run.
        quiet: No progress bars.
    """

    run: Path
    real: str
    out: Path
    motion: Path | None = None
    episodes: int = 16
    iterations: int = 100
    num_envs: int = 256
    sysid_duration: float = 40.0
    control: bool = False
    device: str = "cpu"
    seed: int = 0
    max_minutes: float | None = None
    quiet: bool = False


@dataclass(frozen=True, kw_only=True)
class ExportSettings:
    """What ``humimic export`` writes.

    Attributes:
        run: Run folder of ``humimic train``.
        format: ``onnx``: the deterministic policy (observation normalization included), one
            input ``obs`` (the ``policy`` observation group), one output ``actions``.
        out: Output file (default: ``RUN/policy.onnx``).
        checkpoint: A checkpoint file (default: the run's newest).
    """

    run: Annotated[Path, tyro.conf.Positional]
    format: Literal["onnx"] = "onnx"
    out: Path | None = None
    checkpoint: Path | None = None
