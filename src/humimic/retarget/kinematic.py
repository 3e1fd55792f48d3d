"""Kinematic retargeting: per-frame differential IK with mink and daqp.

Each output frame is solved by a short sequence of QPs (mink), warm-started from the previous
frame, in two stages after GMR (Araujo et al., "Retargeting Matters: General Motion
Retargeting for Humanoid Motion Tracking", 2025): first orientation-led, then position-led.
Hard limits: joint ranges, joint speeds, feet above the floor, and self-collision avoidance.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import daqp
import mink
import mujoco
import numpy as np

from humimic.configs.retarget import RetargetConfig
from humimic.datasets.clip import HumanClip
from humimic.errors import RetargetError
from humimic.retarget.limits import FloorLimit, SelfCollisionLimit
from humimic.retarget.targets import RobotGeometry, Targets, build_targets
from humimic.retarget.tasks import KeypointsTask, OrientationsTask
from humimic.robots.maps import RetargetMap
from humimic.robots.model import nominal_spec
from humimic.robots.registry import RobotConfig

KEYPOINT_SITE_PREFIX = "humimic_kp_"


def ik_model(
    robot: RobotConfig, m: RetargetMap, *, menagerie_root: str | Path | None = None
) -> tuple[mujoco.MjModel, dict[str, float]]:
    """The nominal model plus one site per key point (sites change no physics).

    Returns:
        The model and each actuated joint's speed limit [rad/s].
    """
    spec, acts = nominal_spec(robot, menagerie_root=menagerie_root)
    for name, kp in m.keypoints.items():
        body = spec.body(kp.body)
        if body is None:
            raise RetargetError(f"{m.source}: robot {robot.name} has no body {kp.body!r}")
        body.add_site(name=KEYPOINT_SITE_PREFIX + name, pos=list(kp.offset), group=5)
    return spec.compile(), {j: a.velocity_limit for j, a in acts.items()}


def self_collision_geoms(
    model: mujoco.MjModel, robot: RobotConfig
) -> list[tuple[list[int], list[int]]]:
    """Geom-id groups for the robot's self-collision body pairs."""

    def geoms(bodies: tuple[str, ...]) -> list[int]:
        ids = {model.body(b).id for b in bodies}
        return [
            g
            for g in range(model.ngeom)
            if model.geom_bodyid[g] in ids
            and (model.geom_contype[g] != 0 or model.geom_conaffinity[g] != 0)
        ]

    return [(geoms(a), geoms(b)) for a, b in robot.self_collision]


@dataclass(frozen=True, kw_only=True)
class KinematicResult:
    """Output of :meth:`KinematicRetargeter.run`.

    Attributes:
        qpos: Robot configurations. Shape: (T, nq).
        targets: The IK targets.
        solve_seconds: Wall time of the IK loop alone.
        iterations: QP solves per frame. Shape: (T,).
        relaxed_iterations: QP solves in which conflicting limits had to be made soft.
    """

    qpos: np.ndarray
    targets: Targets
    solve_seconds: float
    iterations: np.ndarray
    relaxed_iterations: int


class KinematicRetargeter:
    """Retarget human clips to one robot with one map. Build once, run on many clips."""

    def __init__(
        self,
        robot: RobotConfig,
        m: RetargetMap,
        cfg: RetargetConfig,
        *,
        menagerie_root: str | Path | None = None,
    ) -> None:
        self.robot = robot
        self.map = m
        self.cfg = cfg
        self.model, speed = ik_model(robot, m, menagerie_root=menagerie_root)
        m.validate(None, {self.model.body(b).name for b in range(self.model.nbody)})
        self.configuration = mink.Configuration(self.model)
        self.keypoints = KeypointsTask(self.model, [KEYPOINT_SITE_PREFIX + n for n in m.keypoints])
        self.orientations = OrientationsTask(
            self.model,
            [fr.body for fr in m.frames.values()] + [f.body for f in m.feet.values()],
        )
        self.posture = mink.PostureTask(self.model, cost=m.posture_weight)
        self.posture.set_target(self.rest_qpos())
        self.smooth = mink.PostureTask(self.model, cost=cfg.smooth_weight)
        self.tasks: list[mink.Task] = [self.keypoints, self.orientations, self.posture]
        if self.model.nq - 7 != self.model.nv - 6 or self.model.njnt - 1 != self.model.nv - 6:
            raise RetargetError(f"{robot.name}: expected one free joint and hinge/slide joints")
        self._range_lo = self.model.jnt_range[1:, 0].copy()
        self._range_hi = self.model.jnt_range[1:, 1].copy()
        joint_names = [self.model.joint(j).name for j in range(1, self.model.njnt)]
        self.speed_limits = np.array([speed.get(j, np.inf) for j in joint_names])
        self.limits: list[mink.Limit] = []
        if cfg.floor_limit and m.feet:
            self.limits.append(FloorLimit(self.model, [f.body for f in m.feet.values()]))
        if cfg.self_collision and robot.self_collision:
            self.limits.append(
                SelfCollisionLimit(
                    self.model,
                    self_collision_geoms(self.model, robot),  # type: ignore[arg-type]
                    gain=cfg.collision_gain,
                    minimum_distance_from_collisions=cfg.collision_margin,
                    collision_detection_distance=cfg.collision_detection,
                )
            )
        # The orientation-led first stage skips the (costly) self-collision rows: the position
        # stage that follows always enforces them, pushing apart any pair stage 1 brought close.
        self._stage1_limits = [
            lim for lim in self.limits if not isinstance(lim, SelfCollisionLimit)
        ]
        self.geometry = self._measure_geometry()
        self.relaxed = 0

    def rest_qpos(self) -> np.ndarray:
        """Zero joint angles, identity base orientation, base at its default height."""
        q = self.model.qpos0.copy()
        return q

    def _measure_geometry(self) -> RobotGeometry:
        model = self.model
        data = mujoco.MjData(model)
        data.qpos[:] = self.rest_qpos()
        mujoco.mj_kinematics(model, data)
        sole = 0.0
        for lim in self.limits:
            if isinstance(lim, FloorLimit):
                from humimic.retarget.limits import contact_point_heights

                _, bottom = contact_point_heights(data, lim.ids, lim.pts, lim.rad)
                sole = float(bottom.min())
        kp = np.array([data.site(KEYPOINT_SITE_PREFIX + n).xpos.copy() for n in self.map.keypoints])
        kp[:, 2] -= sole

        def rot(body: str) -> np.ndarray:
            return data.body(body).xmat.reshape(3, 3).copy()

        feet = []
        floor = next((lim for lim in self.limits if isinstance(lim, FloorLimit)), None)
        for foot in self.map.feet.values():
            b = model.body(foot.body).id
            if floor is None:
                feet.append(np.zeros((1, 4)))
                continue
            sel = floor.ids == b
            off = np.asarray(self.map.keypoints[foot.ankle].offset)
            feet.append(np.column_stack([floor.pts[sel] - off, floor.rad[sel]]))
        n = max((len(f) for f in feet), default=1)
        foot_points = np.array([np.pad(f, ((0, n - len(f)), (0, 0)), mode="edge") for f in feet])
        return RobotGeometry(
            foot_points=foot_points.reshape(len(feet), n, 4),
            keypoints=kp,
            frame_body_rot=np.array([rot(f.body) for f in self.map.frames.values()]).reshape(
                -1, 3, 3
            ),
            foot_body_rot=np.array([rot(f.body) for f in self.map.feet.values()]).reshape(-1, 3, 3),
        )

    def targets(self, clip: HumanClip) -> Targets:
        """IK targets for ``clip`` resampled to the output frame rate."""
        return build_targets(clip.resample(self.cfg.fps), self.map, self.geometry, self.cfg)

    def run(self, clip: HumanClip, progress: Callable[[int], Any] | None = None) -> KinematicResult:
        """Retarget a clip. ``progress(n)`` is called after every frame."""
        cfg = self.cfg
        targets = self.targets(clip)
        T = targets.positions.shape[0]
        conf = self.configuration
        step = (
            self.speed_limits * cfg.velocity_limit_scale / targets.fps
            if cfg.velocity_limit_scale > 0
            else None
        )
        # Cold start: rest pose under the first root target, facing +x.
        q = self.rest_qpos()
        root = list(self.map.keypoints).index(self.map.root)
        q[:3] = targets.positions[0, root]
        conf.update(q)
        out = np.zeros((T, self.model.nq))
        iters = np.zeros(T, dtype=int)
        self.relaxed = 0
        t0 = time.perf_counter()
        for t in range(T):
            self._set_targets(targets, t)
            tasks = self.tasks
            if t > 0 and cfg.smooth_weight > 0:
                self.smooth.set_target(out[t - 1])
                tasks = [*self.tasks, self.smooth]
            q_prev = None if (t == 0 or step is None) else out[t - 1, 7:]
            budget = cfg.first_frame_iters if t == 0 else 1
            n = 0
            for stage, max_iters in ((1, cfg.stage1_iters), (2, cfg.stage2_iters)):
                self._set_stage_costs(targets, t, stage)
                prev = np.inf
                for _ in range(max_iters * budget):
                    limits = self._stage1_limits if stage == 1 and t > 0 else None
                    dq = self._solve(tasks, q_prev, step, clip.source, t, limits)
                    conf.integrate_inplace(dq, 1.0)
                    n += 1
                    err = self._task_error()  # At the start of this QP.
                    if prev - err < cfg.tol * prev:
                        break
                    prev = err
            n += self._repair(tasks, q_prev, step, clip.source, t)
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
            relaxed_iterations=self.relaxed,
        )

    def _repair(
        self,
        tasks: list[mink.Task],
        q_prev: np.ndarray | None,
        step: np.ndarray | None,
        source: str,
        t: int,
    ) -> int:
        """Extra iterations while a self-collision pair is closer than half the margin."""
        limit = next((lim for lim in self.limits if isinstance(lim, SelfCollisionLimit)), None)
        if limit is None:
            return 0
        n = 0
        for _ in range(self.cfg.repair_iters):
            if limit.active_min_distance(self.configuration) >= 0.5 * self.cfg.collision_margin:
                break
            dq = self._solve(tasks, q_prev, step, source, t)
            self.configuration.integrate_inplace(dq, 1.0)
            n += 1
        return n

    def _solve(
        self,
        tasks: list[mink.Task],
        q_prev: np.ndarray | None,
        step: np.ndarray | None,
        source: str,
        t: int,
        limits: list[mink.Limit] | None = None,
    ) -> np.ndarray:
        """One QP: tasks as the objective, joint box as bounds, limits as inequalities."""
        conf = self.configuration
        nv = self.model.nv
        H = np.eye(nv) * self.cfg.damping
        c = np.zeros(nv)
        for task in tasks:
            obj = task.compute_qp_objective(conf)
            H += obj.H
            c += obj.c
        # Joint box: the range (with mink's 0.95 gain) and the per-frame speed limit.
        q = conf.q[7:]
        lo = 0.95 * (self._range_lo - q)
        hi = 0.95 * (self._range_hi - q)
        if q_prev is not None and step is not None:
            lo = np.maximum(lo, q_prev - step - q)
            hi = np.minimum(hi, q_prev + step - q)
        lo = np.maximum(lo, -self.cfg.max_step)
        hi = np.minimum(hi, self.cfg.max_step)
        lo = np.minimum(lo, 0.0)
        hi = np.maximum(hi, 0.0)
        rows, ub = [], []
        for lim in self.limits if limits is None else limits:
            cons = lim.compute_qp_inequalities(conf, 1.0)
            if cons.G is None or cons.h is None:
                continue
            keep = np.isfinite(cons.h)
            rows.append(cons.G[keep])
            ub.append(cons.h[keep])
        A = np.vstack(rows) if rows else np.zeros((0, nv))
        bupper = np.concatenate([np.full(6, 1e30), hi, *ub])
        blower = np.concatenate([np.full(6, -1e30), lo, np.full(A.shape[0], -1e30)])
        sense = np.zeros(bupper.size, dtype=np.int32)
        x, _, exitflag, _ = daqp.solve(H, c, A, bupper, blower, sense)
        if exitflag < 1 and A.shape[0]:
            # The limits conflict (e.g. the speed limit forbids resolving a collision in one
            # frame): solve with the floor and collision rows soft, and count it.
            sense[nv:] = 8
            x, _, exitflag, _ = daqp.solve(H, c, A, bupper, blower, sense)
            self.relaxed += 1
        if exitflag < 1:
            raise RetargetError(
                f"{source}: IK QP has no solution at output frame {t} (daqp exit flag {exitflag})"
            )
        return np.asarray(x)

    def _set_targets(self, targets: Targets, t: int) -> None:
        self.keypoints.targets = targets.positions[t]
        self.orientations.targets = np.concatenate([targets.frame_rots[t], targets.foot_rots[t]])

    def _set_stage_costs(self, targets: Targets, t: int, stage: int) -> None:
        cfg = self.cfg
        pos_scale = cfg.stage1_position_scale if stage == 1 else 1.0
        ori_scale = 1.0 if stage == 1 else cfg.stage2_orientation_scale
        costs = targets.position_weights[t] * pos_scale
        root = list(self.map.keypoints).index(self.map.root)
        costs[root] = targets.position_weights[t, root]
        self.keypoints.set_costs(costs)
        frame_w = np.array([fr.weight for fr in self.map.frames.values()])
        self.orientations.set_costs(np.concatenate([frame_w, targets.foot_weights[t]]) * ori_scale)

    def _task_error(self) -> float:
        """Weighted key-point and orientation error at the start of the last QP."""
        k, o = self.keypoints, self.orientations
        return float(np.sum((k.cost * k.last_error) ** 2) + np.sum((o.cost * o.last_error) ** 2))
