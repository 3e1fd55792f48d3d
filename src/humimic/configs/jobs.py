"""Settings of the commands that use a trained run (``humimic eval``, ``export``, ``loop``,
``imitate``): light to import. Each has ``validate()``, which the command calls before any
work."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from humimic.configs.choices import DrChoice, PhysicsChoice, RobotName
from humimic.configs.limits import (
    MAX_NUM_ENVS,
    at_least,
    at_most,
    check_device,
    check_minutes,
    check_seed,
)
from humimic.errors import InputError


@dataclass(frozen=True, kw_only=True)
class EvalSettings:
    """Evaluate a run's policy closed-loop against the open-loop replay of its reference:
    success rate, MPJPE and joint errors; optionally JSON metrics and an MCAP of the first
    episode."""

    run: Annotated[Path, tyro.conf.Positional]
    """Run folder of ``humimic train`` or ``humimic distill``."""
    episodes: int = 16
    """Episodes to run (each plays the whole clip from its first frame)."""
    motion: Path | None = None
    """Evaluate on this clip (a motion file of the run's robot) instead of the run's, or on
    every clip of a library (a folder or a .yaml list; a library run's own by default)."""
    dr: DrChoice = "none"
    """Physics of the evaluation: a DR profile (``none``, ``default``) or a YAML file."""
    physics: PhysicsChoice | None = None
    """Evaluate on a fixed robot: a physics file or a shipped one (``backpack``,
    ``worn_knees``; docs/tracking.md, "Physics files"), e.g. a "real" robot training never saw.
    DR (``--dr``) acts on top of it."""
    out: Path | None = None
    """Write the metrics as JSON here."""
    mcap: Path | None = None
    """Write the first episode (policy and open loop) with the reference as MCAP here, for
    ``humimic view MCAP`` and Foxglove (default: ``--out`` with the suffix ``.mcap`` when
    ``--out`` is given, else nothing)."""
    checkpoint: Path | None = None
    """A checkpoint file (default: the run's newest)."""
    num_envs: int | None = None
    """Envs run in parallel, at least ``--episodes`` (default: ``--episodes``)."""
    device: str = "cpu"
    """Torch device of the policy (``cpu``, ``cuda`` or ``cuda:N``)."""
    seed: int = 1
    """Seed of the evaluation's randomness."""
    start_noise: bool = False
    """Start each episode from the training's reset noise about the first frame (root pose
    and velocity, joint positions) instead of exactly on it: how much the policy depends on
    starting where the clip does."""

    def validate(self) -> None:
        """Check the numbers and the device; :class:`InputError` names the flag."""
        at_least(self, ("episodes", "num_envs"))
        at_most(self, {"episodes": MAX_NUM_ENVS, "num_envs": MAX_NUM_ENVS})
        if self.num_envs is not None and self.num_envs < self.episodes:
            raise InputError(
                f"--num-envs {self.num_envs}: evaluate at least as many envs as --episodes "
                f"({self.episodes})"
            )
        check_seed(self.seed)
        check_device(self.device)


@dataclass(frozen=True, kw_only=True)
class LoopSettings:
    """Deploy a policy on a "real" robot (a physics file that no training step reads),
    diagnose the gap with sysid on a log of that robot, fine-tune in the corrected
    model, redeploy, report before and after (docs/tracking.md, "The loop")."""

    run: Path
    """The policy's run folder (``humimic train``; not a teacher or a student)."""
    real: PhysicsChoice
    """The "real" robot: a physics file or a shipped one (``backpack``, ``worn_knees``)."""
    out: Path
    """The loop's folder (new or empty)."""
    motion: Path | None = None
    """The clip to deploy and fine-tune on (default: the run's)."""
    episodes: int = 16
    """Episodes per deployment."""
    iterations: int = 100
    """Fine-tuning PPO iterations."""
    num_envs: int | None = None
    """Fine-tuning envs (default: as many as the run trained with)."""
    learning_rate: float = 3e-5
    """Fine-tuning learning rate, on a fixed schedule: a policy that has converged moves away
    from its optimum at a training run's rate (1e-3, adaptive) on the loop's batches
    (BENCHMARKS.md, issue 26)."""
    sysid_log: Literal["deployment", "gantry"] = "deployment"
    """What sysid diagnoses: the policy's deployment on the real robot (episodes of the clip,
    logged with IMU and motion capture) or a gantry session (hanging, multi-sine targets)."""
    sysid_duration: float = 40.0
    """Seconds of the sysid log (5 to 3600; a deployment log: whole episodes, up to 64)."""
    control: bool = False
    """Also fine-tune in the nominal model for the same iterations, and deploy that."""
    device: str = "cpu"
    """Torch device (``cpu``, ``cuda`` or ``cuda:N``)."""
    seed: int = 0
    """Seed of everything."""
    max_minutes: float | None = None
    """Time budget of each fine-tuning run."""
    quiet: bool = False
    """No progress bars."""

    def validate(self) -> None:
        """Check the numbers and the device; :class:`InputError` names the flag."""
        at_least(self, ("episodes", "iterations", "num_envs"))
        at_most(self, {"episodes": MAX_NUM_ENVS, "num_envs": MAX_NUM_ENVS})
        if not 5.0 <= self.sysid_duration <= 3600.0:  # NaN fails too.
            raise InputError(f"--sysid-duration {self.sysid_duration}: choose 5 to 3600 s")
        if not 0.0 < self.learning_rate <= 0.1:  # NaN fails too.
            raise InputError(f"--learning-rate {self.learning_rate}: choose a rate in (0, 0.1]")
        check_minutes(self.max_minutes)
        check_seed(self.seed)
        check_device(self.device)


@dataclass(frozen=True, kw_only=True)
class ImitateSettings:
    """The whole job on one clip or a folder of them: retarget, train one tracking policy
    (refining the motions first where the recipe needs it), evaluate it on nominal,
    randomized and unseen physics (clip by clip, and by the field's protocols), export it to
    ONNX, and write ``OUT/report.md``."""

    clip: Annotated[Path, tyro.conf.Positional]
    """The human clip (``.bvh``, ``.npy``, ``.npz`` joint positions), or a robot motion
    (``.npz`` from ``humimic retarget``) to skip retargeting; or a folder of either (one
    policy for all its clips; clips that fail to retarget or refine are reported and left
    out)."""
    robot: RobotName = "g1"
    """Registry name."""
    out: Path
    """The job's folder (new or empty): motion.npz, run/, eval_*.json, policy.onnx, the
    plots, report.md."""
    minutes: float = 30.0
    """Wall-time budget of training, refining included (the evaluations come after)."""
    episodes: int = 32
    """Evaluation episodes per physics."""
    num_envs: int | None = None
    """Training envs (default: 128 on the CPU, 4096 on a GPU)."""
    device: str = "cpu"
    """Torch device (``cpu``, ``cuda`` or ``cuda:N``)."""
    seed: int = 0
    """Seed of training (evaluations use seed 1, as ``humimic eval``)."""
    screenshot: bool = True
    """Render the first randomized episode beside its reference with MuJoCo's renderer
    (``rollout.png``, a filmstrip; ``rollout.gif``, the whole episode; EGL or OSMesa, no
    display or GPU needed; the report says why when it cannot)."""
    quiet: bool = False
    """No progress bars."""

    def validate(self) -> None:
        """Check the numbers and the device; :class:`InputError` names the flag."""
        if not (math.isfinite(self.minutes) and self.minutes > 0):
            raise InputError(f"--minutes {self.minutes}: must be a positive number of minutes")
        at_least(self, ("episodes", "num_envs"))
        at_most(self, {"episodes": MAX_NUM_ENVS, "num_envs": MAX_NUM_ENVS})
        check_seed(self.seed)
        check_device(self.device)


@dataclass(frozen=True, kw_only=True)
class DemoSettings:
    """The product's whole job on a short real clip, in about 7 minutes on a 2-core CPU:
    fetch a CMU walk (35_01, 3 s; about 270 kB, once), retarget it to the robot, refine it,
    train a tracking policy, evaluate it (nominal, randomized and unseen robots, and the
    field's protocols), export it to ONNX and write ``report.md`` with its pictures; ends with
    the report's path and a one-line verdict (``humimic imitate`` with these settings)."""

    robot: RobotName = "g1"
    """Registry name."""
    out: Path | None = None
    """The job's folder (new or empty; default: ``out/demo/<date>-<time>``)."""
    minutes: float = 6.0
    """Wall-time budget of training, refining included (the evaluations, the export and the
    pictures take about 1 more: 6.9 minutes in all on this project's 2-core machine)."""
    clip: Path | None = None
    """A clip of your own instead of the CMU walk (anything ``humimic imitate`` takes)."""
    quiet: bool = False
    """No progress bars."""

    def imitate_settings(self, clip: Path, out: Path) -> ImitateSettings:
        """The ``humimic imitate`` job this demo runs."""
        return ImitateSettings(clip=clip, robot=self.robot, out=out, minutes=self.minutes,
                               quiet=self.quiet)  # fmt: skip

    def validate(self) -> None:
        """Check the numbers; :class:`InputError` names the flag."""
        self.imitate_settings(Path("clip.bvh"), Path("out")).validate()


@dataclass(frozen=True, kw_only=True)
class ExportSettings:
    """Export a run's deterministic policy as one self-contained ONNX file for deployment."""

    run: Annotated[Path, tyro.conf.Positional]
    """Run folder of ``humimic train`` or ``humimic distill`` (not a teacher)."""
    format: Literal["onnx"] = "onnx"
    """``onnx``: the deterministic policy (observation normalization included), input ``obs``
    (the actor's observation groups), output ``actions``."""
    out: Path | None = None
    """Output file, ending in ``.onnx`` (default: ``RUN/policy.onnx``)."""
    checkpoint: Path | None = None
    """A checkpoint file (default: the run's newest)."""

    def validate(self) -> None:
        """Check the output's name; :class:`InputError` names the flag."""
        out = self.out or self.run / "policy.onnx"
        if out.suffix != ".onnx":
            raise InputError(f"--out {out}: an ONNX file must end in .onnx")


__all__ = ["DemoSettings", "EvalSettings", "ExportSettings", "ImitateSettings", "LoopSettings"]
