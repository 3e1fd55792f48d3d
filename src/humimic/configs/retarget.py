"""Kinematic retargeting configuration."""

from __future__ import annotations

import math
from dataclasses import dataclass

from humimic.errors import InputError


@dataclass(frozen=True, kw_only=True)
class RetargetConfig:
    """Settings of the kinematic (mink IK) retargeter.

    Attributes:
        fps: Output frame rate; the human clip is resampled to it before IK.
        damping: Levenberg-Marquardt damping of the IK QP.
        stage1_iters: Most iterations of the orientation-led first stage, per frame.
        stage2_iters: Most iterations of the position stage, per frame.
        first_frame_iters: Iteration budget multiplier for the first frame (cold start).
        tol: Stop a stage when the weighted task error improves by less than this fraction.
        stage1_position_scale: Position costs in stage 1, relative to stage 2.
        stage2_orientation_scale: Orientation costs in stage 2, relative to stage 1.
        contact_height: A human foot point lower than this above the measured ground [m] may
            be in contact.
        contact_speed: ...and slower than this horizontally [m/s].
        contact_min_frames: Shorter contact runs are dropped.
        plant_radius: A planted point is held at one place while the human's stays within this
            distance [m] of where it landed; beyond it, the point is planted anew.
        contact_weight_scale: Foot position costs are multiplied by this in contact.
        foot_orientation_weight: Foot orientation cost (per radian) in swing.
        foot_contact_orientation_weight: Foot orientation cost while flat on the ground.
        floor_limit: Keep the feet's contact points above the floor (a hard limit).
        velocity_limit_scale: Joint speed limits = this times the motors' limits (0 disables).
        self_collision: Keep the robot's self-collision pairs apart (a hard limit).
        collision_margin: Minimum distance kept between self-collision pairs [m].
        collision_detection: Pairs closer than this are constrained [m].
        collision_gain: Fraction of the remaining gap a pair may close per iteration.
        smooth_weight: Cost [1/rad] of moving the joints away from the previous frame's
            solution: keeps redundant chains from flipping between frames.
        max_step: Largest joint change per QP iteration [rad] (a trust region, so that the
            linearized collision limits are not tunnelled through).
        repair_iters: Extra iterations when a self-collision pair ends a frame closer than
            half the margin.
    """

    fps: float = 50.0
    damping: float = 1e-3
    stage1_iters: int = 1
    stage2_iters: int = 4
    first_frame_iters: int = 10
    tol: float = 5e-2
    stage1_position_scale: float = 0.1
    stage2_orientation_scale: float = 0.5
    contact_height: float = 0.05
    contact_speed: float = 0.5
    contact_min_frames: int = 2
    plant_radius: float = 0.03
    contact_weight_scale: float = 3.0
    foot_orientation_weight: float = 1.0
    foot_contact_orientation_weight: float = 10.0
    floor_limit: bool = True
    velocity_limit_scale: float = 1.0
    self_collision: bool = True
    collision_margin: float = 0.01
    collision_detection: float = 0.04
    collision_gain: float = 0.85
    smooth_weight: float = 0.5
    max_step: float = 0.3
    repair_iters: int = 4

    def validate(self) -> None:
        """Check the values; :class:`InputError` names the field (``--ik.<field>`` on the CLI)."""
        positive = ("fps", "max_step", "contact_speed", "contact_height", "plant_radius")
        for name in positive:
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"ik.{name}: must be a positive number, got {v}")
        if self.fps > 1000:
            raise InputError(f"ik.fps: {self.fps} frames per second is beyond any motion capture")
        non_negative = (
            "damping", "tol", "stage1_position_scale", "stage2_orientation_scale",
            "contact_weight_scale", "foot_orientation_weight", "foot_contact_orientation_weight",
            "velocity_limit_scale", "collision_margin", "collision_detection", "smooth_weight",
        )  # fmt: skip
        for name in non_negative:
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"ik.{name}: must be a number >= 0, got {v}")
        for name in ("stage1_iters", "stage2_iters", "first_frame_iters", "repair_iters"):
            if getattr(self, name) < 0:
                raise InputError(f"ik.{name}: must be >= 0")
        if self.stage1_iters + self.stage2_iters < 1:
            raise InputError("ik.stage1_iters + ik.stage2_iters: at least one QP per frame")
        if not 0 < self.collision_gain <= 1:
            raise InputError(f"ik.collision_gain: must be in (0, 1], got {self.collision_gain}")


def retarget_default() -> RetargetConfig:
    """Default: 50 fps output, two IK stages, floor, self-collision and speed limits on."""
    return RetargetConfig()


def retarget_fast() -> RetargetConfig:
    """Fewer iterations per frame, for previews."""
    return RetargetConfig(stage1_iters=1, stage2_iters=2, first_frame_iters=5)
