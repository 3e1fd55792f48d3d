"""Kinematic retargeting: per-frame differential IK with mink and daqp.

Each output frame is solved by a short sequence of QPs (mink), warm-started from the previous
frame, in two stages after GMR (Araujo et al., "Retargeting Matters: General Motion
Retargeting for Humanoid Motion Tracking", 2025): first orientation-led, then position-led.
Hard limits: joint ranges, joint speeds, feet above the floor, and self-collision avoidance.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import daqp
import mink
import mujoco
import numpy as np

from humimic.configs.retarget import RetargetConfig
from humimic.datasets.clip import HumanClip
from humimic.datasets.scene import Scene
from humimic.errors import MapError, RetargetError
from humimic.retarget.limits import (
    CONTACT_HEIGHT,
    FloorLimit,
    PointTravelLimit,
    SelfCollisionLimit,
    contact_point_heights,
    foot_contact_points,
)
from humimic.retarget.robot_model import KEYPOINT_SITE_PREFIX, ik_model

# Defined here before; still importable from here.
from humimic.retarget.robot_model import SCENE_BODY_PREFIX as SCENE_BODY_PREFIX
from humimic.retarget.robot_model import SOLE_CORNER_PREFIX as SOLE_CORNER_PREFIX
from humimic.retarget.robot_model import SOLE_CORNER_RADIUS as SOLE_CORNER_RADIUS
from humimic.retarget.robot_model import robot_collision_geoms as robot_collision_geoms
from humimic.retarget.robot_model import scene_geoms as scene_geoms
from humimic.retarget.robot_model import sole_corner_geoms as sole_corner_geoms
from humimic.retarget.targets import RobotGeometry, Targets, build_targets
from humimic.retarget.tasks import KeypointsTask, OrientationsTask, PostureTask
from humimic.robots.collision import self_collision_floors, self_collision_pairs
from humimic.robots.maps import RetargetMap
from humimic.robots.registry import RobotConfig

PLANTED_SLACK = 0.02
"""A held foot point may end a frame this fraction of its travel radius beyond it before the
repair steps in."""

FLOOR_SLACK = 5e-4
"""A foot point may end a frame this far [m] below the floor before the repair steps in."""

DAQP_SOFT = 8
"""daqp's sense flag of a soft constraint (its slack is penalized, not forbidden)."""

QP_FEASIBILITY_TOL = 1e-5
"""How far (per unit of a row's norm) a QP solution may lie outside a hard bound or row before
it is rejected: ten times daqp's default primal tolerance, which it applies to normalized rows."""


def solve_qp(
    H: np.ndarray,
    c: np.ndarray,
    A: np.ndarray,
    bupper: np.ndarray,
    blower: np.ndarray,
    sense: np.ndarray,
) -> tuple[np.ndarray | None, int]:
    """Solve ``min 0.5 x'Hx + c'x`` s.t. ``blower <= [x[:nb]; A x] <= bupper`` with daqp, and
    check the answer instead of trusting the exit flag.

    The first ``len(bupper) - A.shape[0]`` bounds are simple bounds on ``x``; rows whose
    ``sense`` is :data:`DAQP_SOFT` may be violated. A solution counts only when daqp reports it
    optimal (exit flag 1, or 2 with soft rows in use), it is finite, and it satisfies every
    hard bound and row within :data:`QP_FEASIBILITY_TOL` times the row's norm.
    daqp releases differ in the flags they return for a failed solve (0.11 answers 4 with a
    step outside the trust region where 0.10 answered -1), so the check is what makes the
    result the same whatever the version.

    Returns:
        The solution (``None`` when there is none) and daqp's exit flag.
    """
    x, _, exitflag, _ = daqp.solve(H, c, A, bupper, blower, sense)
    if exitflag not in (1, 2):
        return None, int(exitflag)
    x = np.asarray(x)
    if not np.all(np.isfinite(x)):
        return None, int(exitflag)
    nb = bupper.size - A.shape[0]
    val = np.concatenate([x[:nb], A @ x])
    norms = np.concatenate([np.ones(nb), np.linalg.norm(A, axis=1)])
    tol = QP_FEASIBILITY_TOL * np.maximum(norms, 1.0)
    hard = (sense & DAQP_SOFT) == 0
    bad = hard & ((val > bupper + tol) | (val < blower - tol))
    if bad.any():
        return None, int(exitflag)
    return x, int(exitflag)


@dataclass(frozen=True, kw_only=True)
class KinematicResult:
    """Output of :meth:`KinematicRetargeter.run`.

    Attributes:
        qpos: Robot configurations. Shape: (T, nq).
        targets: The IK targets.
        solve_seconds: Wall time of the IK loop alone.
        iterations: QP solves per frame. Shape: (T,).
        relaxed_iterations: QP solves in which conflicting limits had to be made soft.
        retried_frames: Frames solved a second time, with guarded steps, because the
            first left a pair deeper than the report counts.
    """

    qpos: np.ndarray
    targets: Targets
    solve_seconds: float
    iterations: np.ndarray
    relaxed_iterations: int
    retried_frames: int = 0


REPAIR_HALVINGS = 4
"""Halvings of a repair step that would leave a self-collision pair deeper than before."""


@dataclass(kw_only=True)
class _Frame:
    """Per-frame solver state (kept out of the retargeter, which is reused across clips)."""

    source: str
    t: int = 0
    tasks: list[mink.Task] = field(default_factory=list)
    q_prev: np.ndarray | None = None
    step: np.ndarray | None = None
    relaxed: int = 0
    yielded: int = 0
    retried: int = 0


class KinematicRetargeter:
    """Retarget human clips to one robot with one map. Build once, run on many clips."""

    def __init__(
        self,
        robot: RobotConfig,
        m: RetargetMap,
        cfg: RetargetConfig,
        *,
        menagerie_root: str | Path | None = None,
        scene: Scene | None = None,
    ) -> None:
        cfg.validate()
        self.robot = robot
        self.map = m
        self.cfg = cfg
        self.model, speed = ik_model(robot, m, menagerie_root=menagerie_root, scene=scene)
        model = self.model
        self._check_model()
        self.configuration = mink.Configuration(model)
        self.keypoints = KeypointsTask(model, [KEYPOINT_SITE_PREFIX + n for n in m.keypoints])
        self.orientations = OrientationsTask(
            model, [fr.body for fr in m.frames.values()] + [f.body for f in m.feet.values()]
        )
        self.posture = PostureTask(model, cost=m.posture_weight)
        self.posture.set_target(model.qpos0)
        self.smooth = PostureTask(model, cost=cfg.smooth_weight)
        self.tasks: list[mink.Task] = [self.keypoints, self.orientations, self.posture]
        self._root = list(m.keypoints).index(m.root)
        self._frame_weights = np.array([fr.weight for fr in m.frames.values()])
        # Joints without a range (jnt_limited 0: the OP3's) are free, not held at [0, 0].
        limited = model.jnt_limited[1:].astype(bool)
        self._range_lo = np.where(limited, model.jnt_range[1:, 0], -np.inf)
        self._range_hi = np.where(limited, model.jnt_range[1:, 1], np.inf)
        joint_names = [model.joint(j).name for j in range(1, model.njnt)]
        self.speed_limits = np.array([speed.get(j, np.inf) for j in joint_names])
        self._build_limits()
        self.geometry = self._measure_geometry()

    def _check_model(self) -> None:
        """Check that the map fits the model (its bodies, the robot's feet) and that the model
        is one the IK can drive: one free joint, then hinge or slide joints only.

        Raises:
            MapError: The map names a body the model lacks, or a foot that is not the robot's.
            RetargetError: Other joints than one free joint and hinge/slide joints.
        """
        robot, m, model = self.robot, self.map, self.model
        m.validate(None, {model.body(b).name for b in range(model.nbody)})
        for side, foot in m.feet.items():
            if foot.body not in robot.feet.values():
                raise MapError(
                    f"{m.source}: feet.{side}.body: {foot.body!r} is not a foot of {robot.name} "
                    f"({', '.join(robot.feet.values())})"
                )
        if model.nq - 7 != model.nv - 6 or model.njnt - 1 != model.nv - 6:
            raise RetargetError(f"{robot.name}: expected one free joint and hinge/slide joints")

    def _build_limits(self) -> None:
        """The feet's contact points and the hard limits the config asks for (floor, planted
        feet, self-collision), in :attr:`limits`, and the first stage's subset of them.

        Raises:
            MapError: The foot bodies have no geoms to stand on.
        """
        model, m, cfg = self.model, self.map, self.cfg
        foot_bodies = [f.body for f in m.feet.values()]
        try:
            self.foot_points = foot_contact_points(model, foot_bodies)
        except ValueError:
            raise MapError(
                f"{m.source}: feet: the foot bodies {foot_bodies} have no sphere, box or capsule "
                "collision geoms to stand on"
            ) from None
        self.limits: list[mink.Limit] = []
        self.floor: FloorLimit | None = None
        if cfg.floor_limit:
            self.floor = FloorLimit(model, foot_bodies)
            self.limits.append(self.floor)
        # Planted feet: a foot contact point on the floor while the human's foot is down is
        # held (horizontally) where the previous frame left it; set per frame (_hold_planted).
        self.planted: PointTravelLimit | None = None
        if cfg.hold_planted_feet:
            ids = self.foot_points[0]
            self.planted = PointTravelLimit(model, ids, self.foot_points[1])
            self._point_foot = np.array([foot_bodies.index(model.body(int(b)).name) for b in ids])
            self.limits.append(self.planted)
        # One set of pairs, all of them: what the IK keeps apart is what the report
        # measures. Each pair's floor: the margin, less for one mechanism's links, and never
        # more than its distance at rest (self_collision_floors).
        self.self_collision_pairs = self_collision_pairs(model, self.robot.root_body)
        self.self_collision: SelfCollisionLimit | None = None
        self._checked: tuple[np.ndarray, float, float] | None = None  # _self_check's last.
        if cfg.self_collision:
            pairs = self.self_collision_pairs
            self.self_collision = SelfCollisionLimit(
                model,
                pairs,
                self_collision_floors(model, pairs, cfg.collision_margin),
                gain=cfg.collision_gain,
                collision_detection_distance=cfg.collision_detection,
            )
            self.limits.append(self.self_collision)
        # The orientation-led first stage skips the (costly) self-collision rows: the position
        # stage that follows always enforces them, pushing apart any pair stage 1 brought close.
        self._stage1_limits = [lim for lim in self.limits if lim is not self.self_collision]

    def _measure_geometry(self) -> RobotGeometry:
        """The robot in its zero pose, soles on the floor (for the target construction)."""
        model = self.model
        data = mujoco.MjData(model)
        data.qpos[:] = model.qpos0
        mujoco.mj_kinematics(model, data)
        ids, pts, rad = self.foot_points
        _, bottom = contact_point_heights(data, ids, pts, rad)
        kp = np.array([data.site(KEYPOINT_SITE_PREFIX + n).xpos.copy() for n in self.map.keypoints])
        kp[:, 2] -= float(bottom.min())

        def rot(body: str) -> np.ndarray:
            return data.body(body).xmat.reshape(3, 3).copy()

        feet = []
        for foot in self.map.feet.values():
            sel = ids == model.body(foot.body).id
            off = np.asarray(self.map.keypoints[foot.ankle].offset)
            feet.append(np.column_stack([pts[sel] - off, rad[sel]]))
        n = max(len(f) for f in feet)
        foot_points = np.array([np.pad(f, ((0, n - len(f)), (0, 0)), mode="edge") for f in feet])
        return RobotGeometry(
            foot_points=foot_points,
            keypoints=kp,
            frame_body_rot=np.array([rot(f.body) for f in self.map.frames.values()]),
            foot_body_rot=np.array([rot(f.body) for f in self.map.feet.values()]),
        )

    def targets(self, clip: HumanClip) -> Targets:
        """IK targets for ``clip`` resampled to the output frame rate."""
        return build_targets(clip.resample(self.cfg.fps), self.map, self.geometry, self.cfg)

    def run(
        self,
        clip: HumanClip,
        progress: Callable[[int], Any] | None = None,
        targets: Targets | None = None,
    ) -> KinematicResult:
        """Retarget a clip. ``progress(n)`` is called after every frame. ``targets``: the
        clip's targets, changed by the caller (default: :meth:`targets`)."""
        cfg = self.cfg
        targets = self.targets(clip) if targets is None else targets
        T = targets.positions.shape[0]
        conf = self.configuration
        step = (
            self.speed_limits * cfg.velocity_limit_scale / targets.fps
            if cfg.velocity_limit_scale > 0
            else None
        )
        # Cold start: zero pose under the first root target, facing +x.
        q = self.model.qpos0.copy()
        q[:3] = targets.positions[0, self._root]
        conf.update(q)
        out = np.zeros((T, self.model.nq))
        iters = np.zeros(T, dtype=int)
        frame = _Frame(source=clip.source)
        t0 = time.perf_counter()
        for t in range(T):
            frame.t = t
            frame.q_prev = None if (t == 0 or step is None) else out[t - 1, 7:]
            frame.step = step
            self._set_targets(targets, t)
            self._hold_planted(targets, t)
            frame.tasks = self.tasks
            if t > 0 and cfg.smooth_weight > 0:
                self.smooth.set_target(out[t - 1])
                frame.tasks = [*self.tasks, self.smooth]
            start = conf.q.copy()
            n, depth = self._solve_frame(frame, targets, guarded=False)
            if depth > 0.0:
                # A self-collision frame by the report's count, which the repair could not
                # undo (two limbs crossed: the first stage skips the self-collision rows, and
                # one step can carry a thigh through the other from beyond the detection
                # distance). Once more from the frame's start, every limit in both stages and
                # no step that takes a pair deeper inside its line; the less deep kept.
                first = conf.q.copy()
                conf.update(start)
                more, again = self._solve_frame(frame, targets, guarded=True)
                n += more
                frame.retried += 1
                if again > depth:
                    conf.update(first)
            q = conf.q.copy()
            # Project away round-off beyond the joint ranges (the limit keeps it below 1e-9).
            q[7:] = np.clip(q[7:], self._range_lo, self._range_hi)
            conf.update(q)
            out[t] = q
            iters[t] = n
            if progress is not None:
                progress(1)
        return KinematicResult(
            qpos=out,
            targets=targets,
            solve_seconds=time.perf_counter() - t0,
            iterations=iters,
            relaxed_iterations=frame.relaxed,
            retried_frames=frame.retried,
        )

    def _solve_frame(self, frame: _Frame, targets: Targets, *, guarded: bool) -> tuple[int, float]:
        """The frame's two stages of QPs and its repair, from the configuration as it is.
        ``guarded``: self-collision rows in both stages, and a step that leaves some pair
        deeper inside its repair line than before (and inside it) halved
        (:data:`REPAIR_HALVINGS` times, then not taken). Returns the QPs solved and how far
        the frame ends beyond the depth the report counts (:meth:`_repair`)."""
        cfg, t = self.cfg, frame.t
        budget = cfg.first_frame_iters if t == 0 else 1
        n = 0
        for stage, max_iters in ((1, cfg.stage1_iters), (2, cfg.stage2_iters)):
            self._set_stage_costs(targets, t, stage)
            limits = self._stage1_limits if stage == 1 and t > 0 and not guarded else self.limits
            # The cold start of frame 0 always begins with the orientation-led stage (it may
            # have to turn the whole body); a warm-started frame only if stage1_iters asks.
            allowed = (max(max_iters, 1) if stage == 1 and t == 0 else max_iters) * budget
            prev = np.inf
            for i in range(allowed):
                self._step(self._solve(frame, limits), guarded=guarded)
                n += 1
                if i + 1 == allowed:
                    break  # No next iteration for the error to decide on.
                err = self._task_error()
                if prev - err < cfg.tol * prev:
                    break
                prev = err
        repairs, depth = self._repair(frame)
        return n + repairs, depth

    def _self_check(self) -> tuple[float, float]:
        """:meth:`SelfCollisionLimit.repair_slack` and the
        :attr:`~SelfCollisionLimit.counted_depth` it sets, for the configuration as it is
        (``(inf, -inf)`` without the limit). Kept for the last configuration checked: the
        repair, a guarded step and a retried frame ask again of the same one."""
        limit = self.self_collision
        if limit is None:
            return np.inf, -np.inf
        q = self.configuration.q
        if self._checked is None or not np.array_equal(self._checked[0], q):
            slack = limit.repair_slack(self.configuration, self.cfg.collision_margin)
            self._checked = (q.copy(), slack, limit.counted_depth)
        return self._checked[1], self._checked[2]

    def _step(self, dq: np.ndarray, *, guarded: bool) -> None:
        """Take ``dq``; ``guarded``: halved while it leaves a pair deeper inside its repair
        line than before, not at all if :data:`REPAIR_HALVINGS` halvings do not help."""
        conf = self.configuration
        if not guarded:
            conf.integrate_inplace(dq, 1.0)
            return
        q0, before = conf.q.copy(), self._self_check()[0]
        for _ in range(REPAIR_HALVINGS + 1):
            conf.integrate_inplace(dq, 1.0)
            if self._self_check()[0] >= min(before, 0.0):
                return
            conf.update(q0)
            dq = 0.5 * dq

    def _repair(self, frame: _Frame) -> tuple[int, float]:
        """Extra QPs while a self-collision pair is inside its repair line
        (:meth:`SelfCollisionLimit.repair_slack`), a held foot point has travelled more than
        :data:`PLANTED_SLACK` beyond its radius, or a foot point is more than
        :data:`FLOOR_SLACK` under the floor (the limits are linearized: a large last step
        can overshoot them). No step is taken that leaves any of the three worse. The
        metrics check every pair in every frame, and report what this leaves.

        Returns:
            The QPs solved, and how far the configuration it leaves is beyond the depth the
            report counts (:attr:`SelfCollisionLimit.counted_depth`; positive: a
            self-collision frame; ``-inf`` without the limit).
        """
        planted, floor = self.planted, self.floor
        if self.self_collision is None and planted is None and floor is None:
            return 0, -np.inf
        conf = self.configuration
        n = 0
        now, counted = self._self_check()

        def excess() -> tuple[float, float]:
            """How far a held point is beyond its travel (fraction of its radius), and how
            deep the lowest foot point is under the floor [m] (``-inf`` without the limit)."""
            travel = -np.inf if planted is None else planted.max_excess(conf.data)
            sunk = -np.inf if floor is None else floor.max_depth(conf.data)
            return travel, sunk

        travel, sunk = excess()
        for _ in range(self.cfg.repair_iters):
            if now >= 0.0 and travel <= PLANTED_SLACK and sunk <= FLOOR_SLACK:
                break
            # A step that leaves some pair deeper inside its repair line than before, a held
            # point farther beyond its travel or a foot deeper in the floor is halved (the
            # limits are linearized: a full step can tunnel a hand into a thigh that was apart
            # when the rows were made, or swing a held toe past its anchor); none found, the
            # frame stays as it is.
            q0, dq = conf.q.copy(), self._solve(frame, self.limits)
            n += 1
            for _ in range(REPAIR_HALVINGS + 1):
                conf.update(q0)
                conf.integrate_inplace(dq, 1.0)
                after, depth = self._self_check()
                moved, deeper = excess()
                if (
                    after >= min(now, 0.0)
                    and moved <= max(travel, PLANTED_SLACK)
                    and deeper <= max(sunk, FLOOR_SLACK)
                ):
                    now, counted, travel, sunk = after, depth, moved, deeper
                    break
                dq = 0.5 * dq
            else:
                conf.update(q0)
                break
        return n, counted

    def _solve(
        self, frame: _Frame, limits: list[mink.Limit], yielding: mink.Limit | None = None
    ) -> np.ndarray:
        """One QP: tasks as the objective, joint box as bounds, limits as inequalities. Where
        the limits conflict, ``yielding``'s rows are made soft first, then all of them."""
        conf = self.configuration
        nv = self.model.nv
        H = np.eye(nv) * self.cfg.damping
        c = np.zeros(nv)
        for task in frame.tasks:
            obj = task.compute_qp_objective(conf)
            H += obj.H
            c += obj.c
        # Joint box: the range (with mink's 0.95 gain), the per-frame speed limit, the trust
        # region; always admitting zero (round-off can leave q a hair outside).
        q = conf.q[7:]
        lo = 0.95 * (self._range_lo - q)
        hi = 0.95 * (self._range_hi - q)
        if frame.q_prev is not None and frame.step is not None:
            lo = np.maximum(lo, frame.q_prev - frame.step - q)
            hi = np.minimum(hi, frame.q_prev + frame.step - q)
        lo = np.minimum(np.maximum(lo, -self.cfg.max_step), 0.0)
        hi = np.maximum(np.minimum(hi, self.cfg.max_step), 0.0)
        rows, ub, owner = [], [], []
        for lim in limits:
            cons = lim.compute_qp_inequalities(conf, 1.0)
            if cons.G is None or cons.h is None:
                continue
            keep = np.isfinite(cons.h)
            rows.append(cons.G[keep])
            ub.append(cons.h[keep])
            owner += [lim is yielding] * int(keep.sum())
        A = np.vstack(rows) if rows else np.zeros((0, nv))
        # The floating base under the same trust region, except from the cold start of frame 0
        # (which may have to turn the whole body): unbounded, limits linearized in its rotation
        # can be met by a step far beyond the joints' (seen in a climbing clip, frame 679).
        base = 1e30 if frame.t == 0 else self.cfg.max_step
        bupper = np.concatenate([np.full(6, base), hi, *ub])
        blower = np.concatenate([np.full(6, -base), lo, np.full(A.shape[0], -1e30)])
        sense = np.zeros(bupper.size, dtype=np.int32)
        x, exitflag = solve_qp(H, c, A, bupper, blower, sense)
        if x is None and any(owner):
            sense[nv:][np.array(owner)] = DAQP_SOFT
            x, exitflag = solve_qp(H, c, A, bupper, blower, sense)
            frame.yielded += 1
        if x is None and A.shape[0]:
            # The limits conflict (e.g. the speed limit forbids resolving a collision in one
            # frame): solve with the floor and collision rows soft, and count it.
            sense[nv:] = DAQP_SOFT
            x, exitflag = solve_qp(H, c, A, bupper, blower, sense)
            frame.relaxed += 1
        if x is None:
            raise RetargetError(
                f"{frame.source}: IK QP has no solution at output frame {frame.t} "
                f"(daqp exit flag {exitflag})"
            )
        return x

    def _hold_planted(self, targets: Targets, t: int) -> None:
        """Set the planted-foot limit for frame ``t`` (the configuration is frame t-1's
        solution): a contact point that touches the floor there, on a foot the human has down
        in both frames, may move at most ``planted_speed / fps`` horizontally."""
        limit = self.planted
        if limit is None:
            return
        n = len(limit.body_ids)
        if t == 0:
            limit.set(np.zeros((n, 3)), np.full(n, np.inf))
            return
        down = np.all(np.any(targets.contacts[t - 1 : t + 1], axis=2), axis=0)  # (feet,)
        ids, pts, rad = self.foot_points
        world, bottom = contact_point_heights(self.configuration.data, ids, pts, rad)
        held = down[self._point_foot] & (bottom < CONTACT_HEIGHT)
        radius = self.cfg.planted_speed / targets.fps
        limit.set(world, np.where(held, radius, np.inf))

    def _set_targets(self, targets: Targets, t: int) -> None:
        self.keypoints.targets = targets.positions[t]
        self.orientations.targets = np.concatenate([targets.frame_rots[t], targets.foot_rots[t]])

    def _set_stage_costs(self, targets: Targets, t: int, stage: int) -> None:
        cfg = self.cfg
        pos_scale = cfg.stage1_position_scale if stage == 1 else 1.0
        ori_scale = 1.0 if stage == 1 else cfg.stage2_orientation_scale
        costs = targets.position_weights[t] * pos_scale
        costs[self._root] = targets.position_weights[t, self._root]
        self.keypoints.set_costs(costs)
        self.orientations.set_costs(
            np.concatenate([self._frame_weights, targets.foot_weights[t]]) * ori_scale
        )

    def _task_error(self) -> float:
        """Weighted key-point and orientation error at the current configuration."""
        k, o = self.keypoints, self.orientations
        ek = k.compute_error(self.configuration)
        eo = o.compute_error(self.configuration)
        return float(np.sum((k.cost * ek) ** 2) + np.sum((o.cost * eo) ** 2))
