"""The interaction stage's per-frame solve (:class:`InteractionPass`), behind
:meth:`~humimic.retarget.interaction.InteractionMeshRetargeter.run`.

:class:`~humimic.retarget.interaction.InteractionMeshRetargeter` builds the pass (the model
with the scene, its tasks and limits, the human's contacts); the pass then solves each output
frame's QPs in turn, warm-started from the kinematic result.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import mink
import mujoco
import numpy as np

from humimic.configs.retarget import InteractionConfig, RetargetConfig
from humimic.datasets.scene import Scene
from humimic.retarget.interaction_mesh import build_mesh
from humimic.retarget.kinematic import KinematicRetargeter, _Frame
from humimic.retarget.limits import PointTravelLimit
from humimic.retarget.robot_model import SCENE_BODY_PREFIX
from humimic.retarget.targets import Targets
from humimic.retarget.tasks import InteractionMeshTask, KeypointsTask, SceneContactTask

REPAIR_DEPTH = 1e-3
"""A frame ends with repair steps while a robot geom is deeper than this in an object [m]."""

ADVANCE_HALVINGS = 5
"""Bisection steps of a frame's warm start that would enter the scene (to 1/32 of it)."""


def _attached(touch: SceneContactTask, conf: mink.Configuration, distance: float) -> np.ndarray:
    """Which of ``touch``'s contacts are within ``distance`` of their surfaces. Shape: (P,)."""
    return touch.compute_error(conf) + touch.gap <= distance


def _deepest(model: mujoco.MjModel, data: mujoco.MjData, pairs: list[tuple[int, int]]) -> float:
    """The smallest signed distance among ``pairs`` of geoms, capped at 1 cm [m]."""
    fromto = np.zeros(6)
    return min(
        (mujoco.mj_geomDistance(model, data, g1, g2, 0.01, fromto) for g1, g2 in pairs),
        default=0.01,
    )


def set_scene_pose(model: mujoco.MjModel, data: mujoco.MjData, scene: Scene, t: int) -> None:
    """Move the scene's mocap bodies to frame ``t``."""
    for obj in scene.objects:
        mocap = int(model.body(SCENE_BODY_PREFIX + obj.name).mocapid[0])
        p = obj.poses[min(t, obj.poses.shape[0] - 1)]
        data.mocap_pos[mocap] = p[:3]
        data.mocap_quat[mocap] = p[3:]


def advance(
    model: mujoco.MjModel,
    conf: mink.Configuration,
    prev: np.ndarray,
    vel: np.ndarray,
    scene_pairs: list[tuple[int, int]],
    kin: KinematicRetargeter,
) -> np.ndarray:
    """``prev`` moved by ``vel`` (the warm start's motion), or by the largest share of it
    (halved up to :data:`ADVANCE_HALVINGS` times) that puts no robot geom more than
    :data:`REPAIR_DEPTH` into the scene or the floor, where ``prev`` had none there.

    The warm start ignores the scene: moved all the way, a landing foot ends inside a
    step, nearer its bottom than its top, and the QPs' linearized limits then push it
    down, into the floor's limit: every QP relaxed and the foot stayed 6.9 mm in a 6 cm
    pad for the rest of the walk.
    """

    def moved(share: float) -> np.ndarray:
        q = prev.copy()
        mujoco.mj_integratePos(model, q, vel, share)
        q[7:] = np.clip(q[7:], kin._range_lo, kin._range_hi)
        return q

    q = moved(1.0)
    conf.update(q)
    if _deepest(model, conf.data, scene_pairs) >= -REPAIR_DEPTH:
        return q
    conf.update(prev)
    if _deepest(model, conf.data, scene_pairs) < -REPAIR_DEPTH:
        return q  # Already inside: the repair steps deal with it.
    lo, best = 0.0, prev
    hi = 1.0
    for _ in range(ADVANCE_HALVINGS):
        mid = 0.5 * (lo + hi)
        cand = moved(mid)
        conf.update(cand)
        if _deepest(model, conf.data, scene_pairs) >= -REPAIR_DEPTH:
            lo, best = mid, cand
        else:
            hi = mid
    return best


@dataclass(kw_only=True, eq=False)
class InteractionPass:
    """The interaction stage over one clip: every output frame's QPs, in order.

    Built by :meth:`~humimic.retarget.interaction.InteractionMeshRetargeter.run` once the
    kinematic pass is done; :meth:`run` fills :attr:`out`, :attr:`iters`, :attr:`n_scene` and
    :attr:`retried`.

    Attributes:
        kin: The retargeter of the model with the scene (its configuration is the solve's).
        cfg: The IK's config.
        icfg: The interaction stage's config.
        targets: The targets (with the still toes held).
        warm_start: The kinematic result's configurations. Shape: (T, nq).
        scene: The scene in the robot's frame.
        samples: Each object's surface points in its own frame.
        contacts: The scene object each human key point touches (-1: none). Shape: (T, K).
        firm: How firmly it touches. Shape: (T, K).
        planted: Frames where each foot point is planted (floor or object). Shape: (T, 2F).
        still: Frames where each sole front's human toe is still. Shape: (T, P).
        cap: How far a still toe's sole front may travel in a frame [m].
        feet_flat: Key-point index of each foot point (ankle, toe per foot). Shape: (2F,).
        toe_feet: The foot of each sole-front point of ``travel``. Shape: (P,).
        obj_geoms: The scene objects' geom ids.
        scene_pairs: Every robot geom (and sole corner) against every object and the floor.
        foot_pairs: Each foot's collision geoms against the objects.
        limits: The QPs' limits.
        travel: The sole fronts' travel limit (the first to yield where limits conflict).
        mesh_task: The interaction-mesh task.
        stick: The task that holds planted foot points.
        stick_foot: The foot of each of ``stick``'s points. Shape: (2F,).
        smooth: Smoothness to the previous output frame.
        touch: The pull of a touching body onto its object's surface.
        frame: The QPs' per-frame state.
    """

    kin: KinematicRetargeter
    cfg: RetargetConfig
    icfg: InteractionConfig
    targets: Targets
    warm_start: np.ndarray
    scene: Scene
    samples: list[np.ndarray]
    contacts: np.ndarray
    firm: np.ndarray
    planted: np.ndarray
    still: np.ndarray
    cap: float
    feet_flat: np.ndarray
    toe_feet: np.ndarray
    obj_geoms: list[int]
    scene_pairs: list[tuple[int, int]]
    foot_pairs: list[list[tuple[int, int]]]
    limits: list[mink.Limit]
    travel: PointTravelLimit
    mesh_task: InteractionMeshTask
    stick: KeypointsTask
    stick_foot: np.ndarray
    smooth: mink.PostureTask
    touch: SceneContactTask
    frame: _Frame
    out: np.ndarray = field(init=False)
    iters: np.ndarray = field(init=False)
    n_scene: np.ndarray = field(init=False)
    retried: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        model, tg = self.kin.model, self.targets
        T = tg.positions.shape[0]
        self.prev = mujoco.MjData(model)  # The previous output frame, for its foot sites.
        self.warm = mujoco.MjData(model)  # The frame's kinematic warm start.
        self.vel = np.zeros(model.nv)
        self.out = np.zeros((T, model.nq))
        self.iters = np.zeros(T, dtype=int)
        self.n_scene = np.zeros(T, dtype=int)
        self.step = (
            self.kin.speed_limits * self.cfg.velocity_limit_scale / tg.fps
            if self.cfg.velocity_limit_scale > 0
            else None
        )

    def run(self, progress: Callable[[int], Any] | None = None) -> None:
        """Solve every frame; ``progress(1)`` after each."""
        for t in range(self.targets.positions.shape[0]):
            self._run_frame(t)
            if progress is not None:
                progress(1)

    def _run_frame(self, t: int) -> None:
        """Solve frame ``t`` from its warm start, once more with guarded steps where it ends
        in a self-collision the report would count, and store it."""
        kin, frame, out = self.kin, self.frame, self.out
        conf = kin.configuration
        set_scene_pose(kin.model, conf.data, self.scene, t)
        self._warm_start(t)
        tasks = self._tasks(t)
        frame.t, frame.tasks = t, tasks
        frame.q_prev = None if (t == 0 or self.step is None) else out[t - 1, 7:]
        frame.step = self.step

        start = conf.q.copy()
        n = self._solve_frame(tasks, guarded=False)
        depth = kin._self_check()[1]
        if depth > 0.0:
            # A self-collision the report would count, as in the kinematic pass
            # (KinematicRetargeter.run): once more from the frame's start with guarded
            # steps, the less deep kept.
            first = conf.q.copy()
            conf.update(start)
            n += self._solve_frame(tasks, guarded=True)
            self.retried += 1
            if kin._self_check()[1] > depth:
                conf.update(first)
        q = conf.q.copy()
        q[7:] = np.clip(q[7:], kin._range_lo, kin._range_hi)
        out[t] = q
        self.iters[t] = n

    def _warm_start(self, t: int) -> None:
        """Pose the warm start of frame ``t`` and start the configuration from it."""
        kin, warm, qpos = self.kin, self.warm, self.warm_start
        model, conf = kin.model, kin.configuration
        # Start from the previous output moved as the warm start moves (within the joint
        # ranges), not from the warm start: the kinematic method ignores the scene, and a
        # warm start inside a box on most frames once failed to pull out within a frame's
        # QPs.
        warm.qpos[:] = qpos[t]
        warm.mocap_pos[:], warm.mocap_quat[:] = conf.data.mocap_pos, conf.data.mocap_quat
        mujoco.mj_kinematics(model, warm)
        if t > 0:
            mujoco.mj_differentiatePos(model, self.vel, 1.0, qpos[t - 1], qpos[t])
            conf.update(advance(model, conf, self.out[t - 1], self.vel, self.scene_pairs, kin))
        else:
            conf.update(qpos[0])

    def _tasks(self, t: int) -> list[mink.Task]:
        """Frame ``t``'s tasks, their targets and costs set: the interaction mesh, the weak
        key-point anchors, orientations and posture, the pull onto touched surfaces, and
        from frame 1 on the smoothness and the held feet (:meth:`_hold_feet`)."""
        kin, tg, icfg = self.kin, self.targets, self.icfg
        contacts, feet_flat, touch = self.contacts, self.feet_flat, self.touch
        pts = self._scene_points(tg.scaled[t], t)
        self.n_scene[t] = len(pts)
        self.mesh_task.set_mesh(build_mesh(tg.scaled[t], pts, weighting=icfg.weighting))
        kin._set_targets(tg, t)
        kin._set_stage_costs(tg, t, 2)
        # Weak anchors, except for planted foot points: they keep the kinematic weight.
        costs = tg.position_weights[t] * icfg.keypoint_scale
        costs[feet_flat] = np.where(self.planted[t], tg.position_weights[t, feet_flat],
                                    costs[feet_flat])  # fmt: skip
        kin.keypoints.set_costs(costs)
        tasks = [self.mesh_task, kin.keypoints, kin.orientations, kin.posture]
        touching = np.flatnonzero(contacts[t] >= 0)
        touch.gap = 0.0
        if touching.size and icfg.contact_weight > 0:
            touch.set_contacts(
                [(int(k), self.obj_geoms[contacts[t, k]]) for k in touching],
                self.firm[t, touching],
            )
            tasks.append(touch)
        self.travel.set(self.travel.anchors, np.full(len(self.toe_feet), np.inf))
        if t > 0:
            self.smooth.set_target(self.out[t - 1])
            tasks.append(self.smooth)
            self._hold_feet(t, tasks)
        return tasks

    def _hold_feet(self, t: int, tasks: list[mink.Task]) -> None:
        """Frame ``t``'s (``t > 0``) travel cap on the fronts of soles whose human toe is
        still, and the stick task (appended to ``tasks``) on the foot points planted in this
        frame and the previous one."""
        icfg, travel, stick, prev, warm = self.icfg, self.travel, self.stick, self.prev, self.warm
        model, conf = self.kin.model, self.kin.configuration
        planted, still = self.planted, self.still
        held = planted[t] & planted[t - 1]  # (4,) per foot point
        if held.any() or still[t].any():
            prev.qpos[:] = self.out[t - 1]
            prev.mocap_pos[:] = conf.data.mocap_pos
            prev.mocap_quat[:] = conf.data.mocap_quat
            mujoco.mj_kinematics(model, prev)
        if still[t].any():
            # Only where the warm start's toe is near: a limit far from it would drag
            # the whole body after a foot the targets have moved on.
            anchors = travel.positions(prev)
            moved = travel.positions(warm)[:, :2] - anchors[:, :2]
            near = np.linalg.norm(moved, axis=1) < icfg.still_reach
            travel.set(anchors, np.where(still[t] & near, self.cap, np.inf))
        if held.any():
            # Planted points stay where they were horizontally, at the warm start's
            # height, held more loosely (stick_height_scale): holding the previous
            # height kept a foot that landed high floating through its stance. The
            # warm start knows the floor, not the scene: a foot it sinks into an
            # object keeps its previous height.
            sunk = np.array([_deepest(model, warm, p) < -REPAIR_DEPTH for p in self.foot_pairs])
            stick.targets = prev.site_xpos[stick.site_ids].copy()
            stick.targets[:, 2] = np.where(sunk[self.stick_foot], stick.targets[:, 2],
                                           warm.site_xpos[stick.site_ids, 2])  # fmt: skip
            cost = np.zeros((held.size, 3))
            cost[held] = icfg.stick_weight * np.array([1.0, 1.0, icfg.stick_height_scale])
            stick.cost = cost.ravel()
            tasks.append(stick)

    def _solve(self) -> np.ndarray:
        """One QP; where the limits conflict, the toes' travel limit yields first."""
        return self.kin._solve(self.frame, self.limits, yielding=self.travel)

    def _solve_frame(self, tasks: list[mink.Task], guarded: bool) -> int:
        """The frame's QPs, repair and reattachment from the configuration as it is;
        ``guarded``: each step halved while it takes a self-collision pair deeper
        (:meth:`KinematicRetargeter._step`). Returns the QPs solved."""
        kin, icfg, frame, touch = self.kin, self.icfg, self.frame, self.touch
        n = 0
        frame.tasks = tasks
        touch.gap = 0.0
        for _ in range(icfg.iterations):
            dq = self._solve()
            kin._step(dq, guarded=guarded)
            n += 1
            if float(np.abs(dq).max()) < icfg.tol:
                break
        n += self._repair(tasks, guarded)
        if touch in tasks and icfg.reattach_iterations > 0:
            n += self._reattach(tasks)
        return n

    def _repair(self, tasks: list[mink.Task], guarded: bool) -> int:
        """Steps without the pull onto surfaces while a robot geom is inside the scene or a
        self-collision pair inside its repair line. Returns the QPs solved."""
        # The limits are linearized, so the last step can end inside an object; step again
        # without the pull onto surfaces while it does. Every robot-scene pair is checked: a
        # step can carry a geom into an object it was farther from than the limit's
        # detection distance (a foot 20 mm inside a box, seq_1 of the climbing clips, went
        # unseen by a check of the pairs that were near before the step). The same while a
        # self-collision pair is inside its repair line (SelfCollisionLimit.repair_slack), as
        # in the kinematic pass.
        kin = self.kin
        n = 0
        self.frame.tasks = [task for task in tasks if task is not self.touch]
        for _ in range(self.cfg.repair_iters):
            if (_deepest(kin.model, kin.configuration.data, self.scene_pairs) >= -REPAIR_DEPTH
                    and kin._self_check()[0] >= 0.0):  # fmt: skip
                break
            kin._step(self._solve(), guarded=guarded)
            n += 1
        return n

    def _reattach(self, tasks: list[mink.Task]) -> int:
        """Steps that pull touching bodies the repair moved off their surfaces back onto them.
        Returns the QPs solved."""
        # Step again with the pull aiming contact_gap off the surface (at zero gap it fights
        # the linearized limit), keeping a step only if it reattaches more contacts than it
        # loses and nothing ends inside the scene or deeper in a pair.
        kin, icfg, touch = self.kin, self.icfg, self.touch
        model, conf = kin.model, kin.configuration
        n = 0
        self.frame.tasks, touch.gap = tasks, icfg.contact_gap
        attached = _attached(touch, conf, icfg.contact_distance)
        for _ in range(icfg.reattach_iterations):
            if attached.all():
                break
            before = conf.q.copy()
            conf.integrate_inplace(self._solve(), 1.0)
            n += 1
            now = _attached(touch, conf, icfg.contact_distance)
            deep = (_deepest(model, conf.data, self.scene_pairs) < -REPAIR_DEPTH
                    or kin._self_check()[0] < 0.0)  # fmt: skip
            if deep or now.sum() <= attached.sum():
                conf.update(before)
                break
            attached = now
        return n

    def _scene_points(self, keypoints: np.ndarray, t: int) -> np.ndarray:
        """The scene points of frame ``t`` within ``scene_radius`` of a key point, nearest
        first, at most ``max_scene_points``. Shape: (S, 3)."""
        icfg = self.icfg
        world = []
        for obj, local in zip(self.scene.objects, self.samples, strict=True):
            rot, pos = obj.pose(t)
            world.append(local @ rot.T + pos)
        pts = np.concatenate(world) if world else np.zeros((0, 3))
        d = np.sqrt(((pts[:, None, :] - keypoints[None]) ** 2).sum(-1)).min(axis=1)
        near = np.flatnonzero(d < icfg.scene_radius)
        near = near[np.argsort(d[near])[: icfg.max_scene_points]]
        return pts[near]


__all__ = ["ADVANCE_HALVINGS", "REPAIR_DEPTH", "InteractionPass", "advance", "set_scene_pose"]
