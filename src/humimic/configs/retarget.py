"""Kinematic retargeting configuration."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from humimic.errors import InputError

MAX_SCENE_POINTS = 10_000
"""Most scene points one frame's interaction mesh may take (``--mesh.max_scene_points``); the
mesh refuses more than 20,000 points in all (``retarget.interaction_mesh.MAX_MESH_POINTS``)."""

MAX_ITERATIONS = 10_000
"""Most solver iterations per frame (or per window) any ``--ik``, ``--mesh`` or ``--dyn``
iteration flag may ask for."""
MAX_POSITION = 1000.0
"""The largest height [m] a setting may place (as a scene's positions are bounded)."""

MAX_SETTING = 1e6
"""The largest value of any real-valued setting (a weight, a scale, a length): larger ones
overflow the solvers' arithmetic (as the maps' weights, bounded the same)."""

MAX_HORIZON_S = 10.0
"""The longest ``--dyn.horizon_s``: each sample is a rollout of the whole window."""

MAX_SAMPLES = 65_536
"""The most ``--dyn.samples`` (each is a rollout per iteration, held in memory at once)."""

MAX_ENSEMBLE = 256
"""The most ``--dyn.ensemble`` models (every sample is rolled out on each)."""

MAX_SEED = 2**32 - 1
"""The largest ``--dyn.seed`` (numpy's generators take seeds from 0 to it)."""


def _check_numbers(cfg: object, prefix: str, names: tuple[str, ...], *, positive: bool) -> None:
    """Each named field of ``cfg`` must be a finite number > 0 (``positive``) or >= 0, at
    most :data:`MAX_SETTING`; :class:`InputError` names the field as ``<prefix>.<field>``
    (the CLI flag)."""
    for name in names:
        v = getattr(cfg, name)
        if positive and not (math.isfinite(v) and v > 0):
            raise InputError(f"{prefix}.{name}: must be a positive number, got {v}")
        if not positive and not (math.isfinite(v) and v >= 0):
            raise InputError(f"{prefix}.{name}: must be a number >= 0, got {v}")
        if v > MAX_SETTING:
            raise InputError(f"{prefix}.{name}: must be at most {MAX_SETTING:g}, got {v:g}")


@dataclass(frozen=True, kw_only=True)
class RetargetConfig:
    """Settings of the kinematic (mink IK) retargeter.

    Attributes:
        fps: Output frame rate; the human clip is resampled to it before IK.
        damping: Levenberg-Marquardt damping of the IK QP.
        stage1_iters: Most iterations of the orientation-led first stage per frame after the
            first (0: none; the first frame, a cold start, always has this stage). 0 saves a
            third of the QPs and changed the key points by -1.2 to +0.9 % on the climbing
            clips (G1, T1, H1, OP3), but by +70 % on Romeo's walk and +31 % on Talos's jump
            (example-robot-data URDFs): hence 1.
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
        hold_planted_feet: While the human's foot is down, the robot foot's contact points
            that touch the floor (lowest point under 10 mm) move at most ``planted_speed``
            horizontally (a hard limit, frame to frame): a planted foot does not slide.
        planted_speed: That speed [m/s].
        velocity_limit_scale: Joint speed limits = this times the motors' limits (0 disables).
        self_collision: Keep the robot's self-collision pairs apart (a hard limit).
        collision_margin: Minimum distance kept between self-collision pairs [m].
        collision_detection: Pairs closer than this are constrained [m].
        collision_gain: Fraction of the remaining gap a pair may close per iteration.
        smooth_weight: Cost [1/rad] of moving the joints away from the previous frame's
            solution: keeps redundant chains from flipping between frames.
        max_step: Largest joint change per QP iteration [rad] (a trust region, so that the
            linearized collision limits are not tunnelled through).
        repair_iters: Most extra iterations when a self-collision pair ends a frame inside its
            repair line (half the margin under its floor, or 0.5 mm deeper than it overlaps at
            rest), or a held foot point beyond its radius; each is line-searched (halved
            while it would leave a pair deeper). 10: the shared climbing clip 2 on the Apollo
            left forearms up to 5.6 mm into the thighs after 4.
        scale: Human-to-robot scale of positions (root path, ground, scene); ``None``: the
            robot's leg length over the human's, measured on the clip.
        floor_height: Height of the floor in the clip's (and its scene's) world frame [m]:
            a scene is mapped so that this plane lands on the robot's floor. ``None``:
            measured, from how far the human's toe joints rest above the scene's objects
            (:func:`humimic.retarget.scene.scene_floor`; z = 0 where they never rest on
            one, and the report says which). The human is placed from its own planted feet,
            whatever this is.
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
    hold_planted_feet: bool = True
    planted_speed: float = 0.05
    velocity_limit_scale: float = 1.0
    self_collision: bool = True
    collision_margin: float = 0.01
    collision_detection: float = 0.04
    collision_gain: float = 0.85
    smooth_weight: float = 0.5
    max_step: float = 0.3
    repair_iters: int = 10
    scale: float | None = None
    floor_height: float | None = None

    def validate(self) -> None:
        """Check the values; :class:`InputError` names the field (``--ik.<field>`` on the CLI)."""
        positive = ("fps", "max_step", "contact_speed", "contact_height", "plant_radius",
                    "planted_speed")  # fmt: skip
        _check_numbers(self, "ik", positive, positive=True)
        if self.fps > 1000:
            raise InputError(f"ik.fps: {self.fps} frames per second is beyond any motion capture")
        non_negative = (
            "damping", "tol", "stage1_position_scale", "stage2_orientation_scale",
            "contact_weight_scale", "foot_orientation_weight", "foot_contact_orientation_weight",
            "velocity_limit_scale", "collision_margin", "collision_detection", "smooth_weight",
        )  # fmt: skip
        _check_numbers(self, "ik", non_negative, positive=False)
        for name in ("stage1_iters", "stage2_iters", "first_frame_iters", "repair_iters",
                     "contact_min_frames"):  # fmt: skip
            if getattr(self, name) < 0:
                raise InputError(f"ik.{name}: must be >= 0")
            if name != "contact_min_frames" and getattr(self, name) > MAX_ITERATIONS:
                raise InputError(
                    f"ik.{name}: at most {MAX_ITERATIONS} per frame, got {getattr(self, name)}"
                )
        fh = self.floor_height
        if fh is not None and not (math.isfinite(fh) and abs(fh) <= MAX_POSITION):
            raise InputError(
                f"ik.floor_height: must be a height within {MAX_POSITION:g} m, "
                f"got {self.floor_height}"
            )
        if self.stage1_iters + self.stage2_iters < 1:
            raise InputError("ik.stage1_iters + ik.stage2_iters: at least one QP per frame")
        if not 0 < self.collision_gain <= 1:
            raise InputError(f"ik.collision_gain: must be in (0, 1], got {self.collision_gain}")
        if self.scale is not None and not (
            math.isfinite(self.scale) and 0 < self.scale <= MAX_SETTING
        ):
            raise InputError(
                f"ik.scale: must be a positive number up to {MAX_SETTING:g}, got {self.scale}"
            )


def retarget_default() -> RetargetConfig:
    """Default: 50 fps output, two IK stages, floor, self-collision and speed limits on."""
    return RetargetConfig()


def retarget_fast() -> RetargetConfig:
    """Fewer iterations per frame, for previews."""
    return RetargetConfig(stage2_iters=1, first_frame_iters=5)


RETARGET_CONFIGS: dict[str, Callable[[], RetargetConfig]] = {
    "default": retarget_default,
    "fast": retarget_fast,
}
"""Named retargeting configurations (``humimic retarget --preset NAME``): name -> factory."""


@dataclass(frozen=True, kw_only=True)
class InteractionConfig:
    """Settings of interaction-mesh retargeting (on top of the kinematic ones).

    Attributes:
        mesh_weight: Cost of the interaction mesh's deformation, per metre of Laplacian
            coordinate error and mesh vertex.
        weighting: Laplacian weights, ``uniform`` or ``inverse_distance``
            (:mod:`humimic.retarget.interaction_mesh`).
        keypoint_scale: Key-point position costs, relative to the kinematic method's: a weak
            anchor (the mesh alone does not fix the body's place where no scene is near).
        scene_spacing: Spacing of the points sampled on the scene's surfaces [m, robot scale].
        scene_radius: Scene points closer than this to a human key point join the frame's
            mesh [m, robot scale].
        max_scene_points: Most scene points in one frame's mesh (the nearest are kept).
        iterations: Most QP iterations per frame.
        tol: Stop a frame's iterations when the objective improves by less than this fraction.
        penetration_margin: Distance kept between the robot's collision geoms and the scene [m].
        collision_detection: Robot-scene pairs closer than this are constrained [m].
        collision_gain: Fraction of a robot-scene gap that may close per iteration.
        stick_weight: Cost [1/m] holding a foot point where it was in the previous frame
            (horizontally) while the human's foot point is in contact.
        stick_height_scale: The planted foot point's height target is the kinematic warm
            start's (unless the warm start sinks the foot into an object: then the previous
            frame's height), with ``stick_weight`` times this. Holding the previous frame's
            height everywhere kept a foot that landed high floating through its stance.
            Chosen on the climbing clips: 1 costs
            joint jerk as the heel lifts, 0.01 lets feet float again (BENCHMARKS.md).
        contact_weight: Cost [1/m] of the distance between a body and the scene object its
            human key point touches (:func:`humimic.retarget.scene.human_contacts`).
        contact_distance: A robot body within this distance of a surface touches it, for the
            contact-preservation metric [m].
        smooth_weight: Cost [1/rad] of moving the joints away from the previous frame's
            solution (the kinematic method's ``smooth_weight``, for this stage).
        reattach_iterations: Most extra QP iterations per frame that bring back onto their
            surfaces the bodies that a frame's penetration repair moved farther than
            ``contact_distance``; a step is kept only if nothing then lies inside the scene.
        contact_gap: Distance off the surface that those iterations aim for [m] (pulling to
            zero fights the linearized non-penetration limit).
        still_speed: While the human's toe moves slower than this horizontally [m/s, the
            human scaled by the root scale, bone lengths unchanged], in the air too
            (holosoma's notion of foot sticking): the robot's toe target keeps the horizontal
            position it had when the human's toe stopped (until the human's toe drifts farther
            than the IK's ``plant_radius``: :func:`~humimic.retarget.targets.hold_still_points`),
            and the front of the robot's sole moves at most ``still_travel`` times as fast (a
            hard limit, made soft where it conflicts with the non-penetration limits, and
            dropped where the frame's warm start has moved that toe more than
            ``still_reach``). The held targets are also the kinematic warm start's. 0 turns
            both off (the warm start is then exactly ``--method kinematic``). Keep ``still_travel * still_speed / fps`` well
            under 1 cm (holosoma's sliding threshold per frame): the cap bounds the front
            contact points, and a point ahead of them (a toe tip) moves up to 1.2 times as far
            while the foot turns. Planted points are held in all three axes whatever this is.
        still_travel: The share of ``still_speed`` the front of a sole may move while the
            human's toe is still (the cap above). Chosen on the climbing clips, where any
            value from 0.5 to 0.75 gives the same result (BENCHMARKS.md).
        still_reach: The toe travel limit of ``still_speed`` holds a toe only where the frame's
            warm start puts it within this horizontal distance [m] of where it was: farther,
            the targets have moved on and holding the toe back drags the body after it.
            (At 0.10 a toe slid on one climbing clip, where the warm start drifted more than
            that from the output over a long stand: BENCHMARKS.md.)
    """

    mesh_weight: float = 20.0
    weighting: str = "uniform"
    keypoint_scale: float = 0.1
    scene_spacing: float = 0.05
    scene_radius: float = 0.25
    max_scene_points: int = 120
    iterations: int = 5
    tol: float = 1e-3
    penetration_margin: float = 0.0
    collision_detection: float = 0.05
    collision_gain: float = 0.85
    stick_weight: float = 1000.0
    stick_height_scale: float = 0.1
    contact_weight: float = 1000.0
    contact_distance: float = 0.02
    smooth_weight: float = 5.0
    reattach_iterations: int = 3
    contact_gap: float = 0.01
    still_speed: float = 0.32
    still_reach: float = 0.25
    still_travel: float = 0.6

    def validate(self) -> None:
        """Check the values; :class:`InputError` names the field (``--mesh.<field>``)."""
        positive = ("scene_spacing", "scene_radius", "collision_detection", "contact_distance",
                    "still_reach")  # fmt: skip
        _check_numbers(self, "mesh", positive, positive=True)
        non_negative = ("mesh_weight", "keypoint_scale", "tol", "penetration_margin",
                        "stick_weight", "stick_height_scale", "contact_weight", "smooth_weight",
                        "contact_gap", "still_speed")  # fmt: skip
        _check_numbers(self, "mesh", non_negative, positive=False)
        if not 0 < self.still_travel <= 1:
            raise InputError(f"mesh.still_travel: must be in (0, 1], got {self.still_travel}")
        if self.max_scene_points > MAX_SCENE_POINTS:
            raise InputError(
                f"mesh.max_scene_points: at most {MAX_SCENE_POINTS} (a Delaunay mesh of more "
                f"points per frame is beyond this method), got {self.max_scene_points}"
            )
        if max(self.iterations, self.reattach_iterations) > MAX_ITERATIONS:
            raise InputError(
                f"mesh.iterations and mesh.reattach_iterations: at most {MAX_ITERATIONS} per "
                f"frame, got {self.iterations} and {self.reattach_iterations}"
            )
        if self.iterations < 1 or self.max_scene_points < 0 or self.reattach_iterations < 0:
            raise InputError(
                "mesh.iterations must be >= 1, mesh.max_scene_points and "
                "mesh.reattach_iterations >= 0"
            )
        if self.contact_gap >= self.contact_distance:
            raise InputError(
                f"mesh.contact_gap ({self.contact_gap}) must be below mesh.contact_distance "
                f"({self.contact_distance}): the reattached bodies would not count as touching"
            )
        if self.weighting not in ("uniform", "inverse_distance"):
            raise InputError(f"mesh.weighting: uniform or inverse_distance, got {self.weighting!r}")
        if not 0 < self.collision_gain <= 1:
            raise InputError(f"mesh.collision_gain: must be in (0, 1], got {self.collision_gain}")
        if self.penetration_margin >= self.collision_detection:
            raise InputError("mesh.penetration_margin must be below mesh.collision_detection")


@dataclass(frozen=True, kw_only=True)
class DynamicsConfig:
    """Settings of sampling-based dynamics retargeting (:mod:`humimic.retarget.dynamics`).

    The decision variables are offsets added to the reference's joint targets, at knots
    ``knot_dt`` apart over a ``horizon_s`` window, linearly interpolated to the control rate
    (the reference's frame rate) and held over the physics steps of each control step.

    Attributes:
        samples: Rollouts per iteration (the current mean is one of them).
        horizon_s: Planning window [s].
        knot_dt: Spacing of the knots [s].
        commit_s: How much of the best plan is kept before the window moves on [s].
        iterations: Most sampling iterations per window.
        min_improvement: Stop a window's iterations after two in a row improve its best
            cost by less than this fraction.
        noise: Standard deviation of the knot offsets [rad], for the legs, at the window's
            start, in the first iteration; it grows to ``horizon_noise`` times that at the
            window's end, and shrinks by ``anneal`` per iteration (DIAL-MPC's annealing).
        horizon_noise: See ``noise``.
        anneal: See ``noise``.
        upper_body_noise: Noise of the waist and arm joints relative to the legs'.
        temperature: MPPI temperature on costs normalized by the elites' spread.
        elites: The lowest-cost samples that the MPPI mean averages (all of them when there
            are no more samples than this).
        body_weight: Cost of the mean squared tracked-body position error, per (10 cm)^2.
        root_weight: Cost of the pelvis height error per (10 cm)^2 and of its tilt against
            the reference's per (0.3 rad)^2.
        joint_weight: Cost of the mean squared joint error, per (0.3 rad)^2.
        velocity_weight: Cost of the pelvis velocity error, per (1 m/s)^2.
        foot_weight: Cost of a foot's horizontal speed while the reference's foot is on the
            ground (low and slow), per (0.3 m/s)^2.
        effort_weight: Cost of the mean squared torque, relative to the motors' limits.
        feedforward: Scale of the inverse-dynamics torque in the nominal PD targets that
            the sampler's offsets are added to: 1 makes the servo produce the reference's
            inverse-dynamics torque at the middle of each frame
            (:func:`humimic.retarget.dynamics.inverse_dynamics_torques`); 0 targets the next
            frame's joint positions (PD on the reference alone).
        polish_iterations: Iterations of iLQR (:mod:`humimic.retarget.dynamics.ilqr`) that
            refine each window's best sampled plan along the cost's Gauss-Newton model before
            its start is committed (0: sampling alone). Each costs about two thirds of a
            sampling iteration of 128 samples (BENCHMARKS.md, "Dynamics retargeting").
        fall_height: The robot has fallen when its pelvis is lower than this fraction of the
            reference's pelvis height, or tilted more than ``fall_tilt`` [rad] from it.
        fall_tilt: See ``fall_height``.
        fall_cost: Added for every control step from a fall on.
        ensemble: Perturbed physics models every sample is also scored on (0: nominal
            only): friction, masses and PD gains drawn from the ``default`` domain
            randomization ranges, halved, and CoM offsets and armature from the whole ranges.
        robust: ``mean`` or ``worst`` of the costs over the ensemble.
        seed: Seed of the sampling noise and of the ensemble's draws.
    """

    samples: int = 128
    horizon_s: float = 0.5
    knot_dt: float = 0.05
    commit_s: float = 0.1
    iterations: int = 4
    min_improvement: float = 0.01
    noise: float = 0.15
    horizon_noise: float = 2.0
    anneal: float = 0.8
    upper_body_noise: float = 0.5
    temperature: float = 0.1
    elites: int = 16
    body_weight: float = 1.0
    root_weight: float = 1.0
    joint_weight: float = 0.1
    velocity_weight: float = 0.05
    foot_weight: float = 0.2
    effort_weight: float = 0.01
    feedforward: float = 1.0
    polish_iterations: int = 3
    fall_height: float = 0.6
    fall_tilt: float = 0.8
    fall_cost: float = 100.0
    ensemble: int = 0
    robust: str = "mean"
    seed: int = 0

    def validate(self) -> None:
        """Check the values; :class:`InputError` names the field (``--dyn.<field>``)."""
        positive = ("horizon_s", "knot_dt", "commit_s", "temperature", "fall_height")
        _check_numbers(self, "dyn", positive, positive=True)
        non_negative = ("min_improvement", "noise", "horizon_noise", "upper_body_noise",
                        "body_weight", "root_weight", "joint_weight", "velocity_weight",
                        "effort_weight", "fall_cost", "fall_tilt", "foot_weight",
                        "feedforward")  # fmt: skip
        _check_numbers(self, "dyn", non_negative, positive=False)
        least = {"samples": 2, "iterations": 1, "elites": 1, "ensemble": 0, "polish_iterations": 0}
        for name, low in least.items():
            if getattr(self, name) < low:
                raise InputError(f"dyn.{name}: must be >= {low}, got {getattr(self, name)}")
        if not 0 < self.anneal <= 1:
            raise InputError(f"dyn.anneal: must be in (0, 1], got {self.anneal}")
        if self.commit_s > self.horizon_s or self.knot_dt > self.horizon_s:
            raise InputError("dyn.commit_s and dyn.knot_dt must not exceed dyn.horizon_s")
        if self.robust not in ("mean", "worst"):
            raise InputError(f"dyn.robust: mean or worst, got {self.robust!r}")
        if self.horizon_s > MAX_HORIZON_S:
            raise InputError(f"dyn.horizon_s: at most {MAX_HORIZON_S:g} s, got {self.horizon_s:g}")
        most = {"samples": MAX_SAMPLES, "elites": MAX_SAMPLES, "ensemble": MAX_ENSEMBLE,
                "seed": MAX_SEED,
                "iterations": MAX_ITERATIONS, "polish_iterations": MAX_ITERATIONS}  # fmt: skip
        for name, high in most.items():
            if getattr(self, name) > high:
                raise InputError(f"dyn.{name}: must be at most {high}, got {getattr(self, name)}")
        if self.seed < 0:
            raise InputError(f"dyn.seed: must be in 0 to {MAX_SEED}, got {self.seed}")
