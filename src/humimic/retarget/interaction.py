"""Interaction-mesh retargeting: keep the body's spatial relations to boxes, terrain, objects.

:class:`InteractionMeshRetargeter` retargets a clip in a scene; :class:`InteractionResult` is
what it returns.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mink
import mujoco
import numpy as np

from humimic.configs.retarget import InteractionConfig, RetargetConfig
from humimic.datasets.clip import HumanClip
from humimic.datasets.scene import Scene
from humimic.errors import RetargetError
from humimic.retarget.contacts import step_speed
from humimic.retarget.interaction_mesh import build_mesh
from humimic.retarget.kinematic import (
    KEYPOINT_SITE_PREFIX,
    SCENE_BODY_PREFIX,
    KinematicResult,
    KinematicRetargeter,
    _Frame,
    robot_collision_geoms,
    scene_geoms,
    sole_corner_geoms,
)
from humimic.retarget.limits import PointTravelLimit, SelfCollisionLimit
from humimic.retarget.scene import human_contacts, scene_floor
from humimic.retarget.targets import RobotGeometry, Targets, hold_still_points
from humimic.retarget.tasks import InteractionMeshTask, KeypointsTask, SceneContactTask
from humimic.robots.maps import RetargetMap
from humimic.robots.registry import RobotConfig


@dataclass(frozen=True, kw_only=True)
class InteractionResult:
    """Output of :meth:`InteractionMeshRetargeter.run`.

    Attributes:
        qpos: Robot configurations. Shape: (T, nq).
        kinematic: The kinematic result it started from.
        scene: The scene in the robot's frame, one pose per output frame for moving objects.
        model: The robot model with the scene's objects (mocap bodies).
        solve_seconds: Wall time of the interaction stage alone.
        iterations: QPs per frame. Shape: (T,).
        relaxed_iterations: QPs whose conflicting limits had to be made soft.
        yielded_iterations: QPs in which the toes' travel limit alone was made soft.
        mesh_scene_points: Scene points in each frame's mesh. Shape: (T,).
        scene_spacings: The spacing each object's surface was sampled with [m]: the
            requested ``scene_spacing``, or more for an object too large to sample that
            finely (:meth:`~humimic.datasets.scene.Scene.sampling_spacings`).
        human_contacts: The scene object each human key point touches (-1: none), from
            :func:`~humimic.retarget.scene.human_contacts`. Shape: (T, K).
        scene_floor: Where the clip's floor was put (:meth:`InteractionMeshRetargeter.scene_placement`).
        retried_frames: Frames solved again with guarded steps after a self-collision the
            report would count.
    """

    qpos: np.ndarray
    kinematic: KinematicResult
    scene: Scene
    model: mujoco.MjModel
    solve_seconds: float
    iterations: np.ndarray
    relaxed_iterations: int
    yielded_iterations: int
    mesh_scene_points: np.ndarray
    scene_spacings: list[float]
    human_contacts: np.ndarray
    scene_floor: dict[str, Any]
    retried_frames: int = 0


REPAIR_DEPTH = 1e-3
"""A frame ends with repair steps while a robot geom is deeper than this in an object [m]."""

ADVANCE_HALVINGS = 5
"""Bisection steps of a frame's warm start that would enter the scene (to 1/32 of it)."""

HAND_CONTACT_RADIUS = 0.05
"""Contact radius of key points that are not foot points, at human scale [m] (a joint centre
inside a limb)."""


def contact_radii(m: RetargetMap, geometry: RobotGeometry, scale: float) -> np.ndarray:
    """How far each key point of the targets sits from a surface it rests on: its height in
    the robot's standing pose for the feet's ankle and toe points (the targets put the feet
    there), :data:`HAND_CONTACT_RADIUS` times ``scale`` (the targets' robot/human scale) for
    the others, whose targets are the human's joint centres scaled. Shape: (K,)."""
    feet = {n for f in m.feet.values() for n in (f.ankle, f.toe)}
    return np.array(
        [geometry.keypoints[k, 2] if n in feet else HAND_CONTACT_RADIUS * scale
         for k, n in enumerate(m.keypoints)]
    )  # fmt: skip


def contact_bodies(m: RetargetMap) -> list[list[str]]:
    """The robot bodies that may make each key point's contact: a foot point's own body; for
    the others, the body and its parent key point's body (the limb segment that ends at the
    joint: a hip's contact when sitting is the pelvis's as much as the thigh's)."""
    feet = {n for f in m.feet.values() for n in (f.ankle, f.toe)}
    out = []
    for name, kp in m.keypoints.items():
        bodies = [kp.body]
        if name not in feet and kp.parent is not None:
            parent = m.keypoints[kp.parent].body
            if parent != kp.body:
                bodies.append(parent)
        out.append(bodies)
    return out


def feet_planted(m: RetargetMap, floor: np.ndarray, scene: np.ndarray) -> np.ndarray:
    """Frames where the human's foot rests, per foot of ``m.feet``: a floor contact of its
    ankle or toe (``floor``: :attr:`~humimic.retarget.targets.Targets.contacts`,
    (T, feet, 2)), or either touches an object (``scene``: the object per key point, -1 for
    none, (T, K)). Shape: (T, feet)."""
    names = list(m.keypoints)
    on_object = [
        (scene[:, [names.index(f.ankle), names.index(f.toe)]] >= 0).any(axis=1)
        for f in m.feet.values()
    ]
    return floor.any(axis=-1) | np.stack(on_object, axis=1)


def body_geoms(model: mujoco.MjModel, bodies: list[list[str]]) -> list[list[int]]:
    """All geoms (collision and visual: the real surface) of each set of bodies."""
    out = []
    for names in bodies:
        ids = {model.body(b).id for b in names}
        out.append([g for g in range(model.ngeom) if model.geom_bodyid[g] in ids])
    return out


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


TOE_DEPTH = 0.01
"""A sole's contact points within this distance [m] of its foremost one are its front."""


class InteractionMeshRetargeter:
    """Retarget clips with a scene to one robot with one map.

    After OmniRetarget (Yang et al., "OmniRetarget: Interaction-Preserving Data Generation for
    Humanoid Whole-Body Loco-Manipulation and Scene Interaction", 2025), which builds on the
    interaction mesh of Ho, Komura and Tai (SIGGRAPH 2010). For every output frame:

    1. The kinematic result (:class:`~humimic.retarget.kinematic.KinematicRetargeter`, on the
       same targets, whose toe targets ``still_speed`` holds where the human's toes are still:
       :func:`~humimic.retarget.targets.hold_still_points`) is the warm start: a frame's QPs
       start from the previous output moved as the warm start moves.
    2. The frame's interaction mesh is the Delaunay tetrahedralization of the scaled human's
       key points and the scene points near them (the scene is mapped into the robot's frame
       with the human's heading, origin, scale and height calibration: :meth:`robot_scene`);
       its Laplacian coordinates are the target (:mod:`humimic.retarget.interaction_mesh`).
    3. A few QPs, each solved directly with daqp: minimize the mesh's deformation, weak
       key-point anchors, the body orientations, posture and smoothness to the previous frame,
       and hold a foot point still while the human's is in contact (at the warm start's
       height); subject to joint ranges and speeds, a trust region, the floor under the feet,
       self-collision, no penetration of the robot's collision geoms into the scene (MuJoCo
       distance queries, linearized with the contact normal's Jacobian) and, with
       ``still_speed``, a cap on how far the front of a sole travels while the human's toe is
       still (:class:`~humimic.retarget.limits.PointTravelLimit`).
    """

    def __init__(
        self,
        robot: RobotConfig,
        m: RetargetMap,
        cfg: RetargetConfig,
        icfg: InteractionConfig,
        *,
        menagerie_root: str | Path | None = None,
    ) -> None:
        icfg.validate()
        self.robot, self.map, self.cfg, self.icfg = robot, m, cfg, icfg
        self.menagerie_root = menagerie_root
        # Targets only depend on the robot's geometry: this scene-less retargeter builds them.
        self.kin = KinematicRetargeter(robot, m, cfg, menagerie_root=menagerie_root)
        feet = list(m.feet.values())
        self._foot_keys = [[f.ankle, f.toe] for f in feet]  # (2, 2) key-point names

    def robot_scene(self, clip: HumanClip, scene: Scene) -> Scene:
        """The scene in the robot's frame at the output frame rate, mapped as ``clip`` is."""
        return self.scene_placement(clip, scene, self.kin.targets(clip))[0]

    def scene_placement(
        self, clip: HumanClip, scene: Scene, tg: Targets
    ) -> tuple[Scene, dict[str, Any]]:
        """:meth:`robot_scene`, given the clip's targets, and where the clip's floor was put
        (the report's ``scene_floor``: its height in the clip's frame, where that comes from,
        the human toe joints' resting clearance over the objects, and the height offset
        used)."""
        T = tg.positions.shape[0]
        start_s = float(clip.meta.get("start_frame", 0)) / clip.fps
        world = scene.resample(tg.fps, T, start_s=start_s)
        human = clip.resample(tg.fps)
        toes = np.stack([human.position(self.map.keypoints[f.toe].human)
                         for f in self.map.feet.values()], axis=1)[:T]  # fmt: skip
        floor, source, clearance = scene_floor(world, toes, tg.fps, self.cfg.floor_height)
        z_offset = tg.scale * (tg.human_ground - floor)
        placed = world.to_robot(scale=tg.scale, yaw=tg.yaw, origin=tg.origin,
                                ground=tg.human_ground, z_offset=z_offset)  # fmt: skip
        info = {"floor_m": floor, "from": source, "toe_clearance_m": clearance,
                "z_offset_m": z_offset}  # fmt: skip
        return placed, info

    def human_contacts(self, scene: Scene, tg: Targets) -> tuple[np.ndarray, np.ndarray]:
        """The scene object each key point of the human touches, and how firmly
        (:func:`~humimic.retarget.scene.human_contacts`), in ``scene`` mapped as the targets
        are (:meth:`scene_placement`).

        Found on the human, not on the robot's targets: the feet's ankle and toe points are
        the targets' (at the robot's standing heights over the human's clearance), the other
        key points the human's own joint centres (``tg.human``) under the targets' vertical
        calibration (the planted toes at the robot's standing toe height), taken
        :data:`HAND_CONTACT_RADIUS` inside the limb and with ``contact_distance`` of slack,
        both at human scale and scaled as the scene is. The targets hang the robot's bone
        lengths along the human's bones, so a robot with long arms "touched" boxes the
        human's hands never reached (climbing clip 1, radii scaled: the T1's wrists 456 times,
        the G1's never), and a fixed 5 + 2 cm on the 0.5 m OP3 stood for 26 cm of the human (its pelvis,
        knees and elbows touched the boxes wherever the human passed them).
        """
        m = self.map
        names = list(m.keypoints)
        feet = [names.index(n) for f in m.feet.values() for n in (f.ankle, f.toe)]
        toes = [names.index(f.toe) for f in m.feet.values()]
        human = tg.human.copy()
        planted = tg.contacts[:, :, 1]
        z = human[:, toes, 2]
        ref = np.median(z[planted]) if planted.any() else np.percentile(z.min(axis=1), 1)
        human[..., 2] += self.kin.geometry.keypoints[toes, 2].mean() - ref
        human[:, feet] = tg.scaled[:, feet]
        radius = contact_radii(m, self.kin.geometry, tg.scale)
        return human_contacts(scene, human, radius, self.icfg.contact_distance * tg.scale)

    def run(
        self, clip: HumanClip, scene: Scene, progress: Callable[[int], Any] | None = None
    ) -> InteractionResult:
        """Retarget ``clip`` in ``scene`` (both in the clip's world frame). ``progress(n)`` is
        called after every frame of each of the two passes (kinematic, then interaction)."""
        icfg = self.icfg
        # The targets depend on the robot's geometry alone: the scene-less retargeter's are
        # the ones the scene's retargeter below would build.
        tg = self.kin.targets(clip)
        scene_r, placement = self.scene_placement(clip, scene, tg)
        kin = KinematicRetargeter(self.robot, self.map, self.cfg,
                                  menagerie_root=self.menagerie_root, scene=scene_r)  # fmt: skip
        model, conf = kin.model, kin.configuration
        set_scene_pose(model, conf.data, scene_r, 0)
        names = list(self.map.keypoints)
        foot_idx = np.array([[names.index(k) for k in pair] for pair in self._foot_keys])
        if icfg.still_speed > 0:  # Toe targets still where the human's toes are.
            tg = hold_still_points(tg, foot_idx[:, 1], tg.contacts[:, :, 1],
                                   speed=icfg.still_speed, radius=self.cfg.plant_radius,
                                   weight_scale=self.cfg.contact_weight_scale)  # fmt: skip
        kres = kin.run(clip, progress=progress, targets=tg)
        T = tg.positions.shape[0]

        robot_geoms, obj_geoms = robot_collision_geoms(model), scene_geoms(model)
        if not robot_geoms or not obj_geoms:
            raise RetargetError(f"{clip.source}: no robot collision geoms or no scene geoms")
        floor = model.geom(self.robot.floor_geom).id
        scene_pairs = [(g, o) for g in robot_geoms for o in [*obj_geoms, floor]]
        scene_pairs += [(c, o) for c in sole_corner_geoms(model) for o in obj_geoms]
        scene_limit = SelfCollisionLimit(
            model,
            np.array(scene_pairs, dtype=int),
            np.full(len(scene_pairs), icfg.penetration_margin),
            gain=icfg.collision_gain,
            collision_detection_distance=icfg.collision_detection,
        )
        sites = [KEYPOINT_SITE_PREFIX + n for n in self.map.keypoints]
        mesh_task = InteractionMeshTask(model, sites, cost=icfg.mesh_weight)
        stick = KeypointsTask(model, [sites[i] for i in foot_idx.ravel()])
        stick_foot = np.repeat(np.arange(len(foot_idx)), foot_idx.shape[1])  # Foot per point.
        foot_pairs = [  # Each foot's collision geoms against the objects.
            [(g, o) for g in robot_geoms if model.geom_bodyid[g] == model.body(foot.body).id
             for o in obj_geoms]
            for foot in self.map.feet.values()
        ]  # fmt: skip
        # A toe the human barely moves horizontally: the front of the robot's sole moves at
        # most still_travel times as fast.
        toe_feet, travel = self._toe_travel(model, kin.foot_points)
        # Not the kinematic pass's planted-foot limit: planted points here are held by the
        # stick task below (on the floor or on an object), the limit's anchors are stale.
        limits = [*(lim for lim in kin.limits if lim is not kin.planted), scene_limit, travel]
        samples = scene_r.surface_points(icfg.scene_spacing)
        spacings = scene_r.sampling_spacings(icfg.scene_spacing)
        contacts, firm = self.human_contacts(scene_r, tg)
        # A foot point is planted on the floor (the kinematic targets' contacts) or on an
        # object (a scene contact while the human's point moves slower than contact_speed).
        feet_flat = foot_idx.ravel()
        speed = step_speed(tg.scaled[:, feet_flat, :2], tg.fps)
        planted = tg.contacts.reshape(T, -1) | (
            (contacts[:, feet_flat] >= 0) & (speed < self.cfg.contact_speed)
        )
        toe_speed = step_speed(tg.human[:, foot_idx[:, 1], :2], tg.fps)
        still = toe_speed[:, toe_feet] < icfg.still_speed  # (T, toe points)
        cap = icfg.still_travel * icfg.still_speed / tg.fps
        smooth = mink.PostureTask(model, cost=icfg.smooth_weight)
        touch = SceneContactTask(
            model, body_geoms(model, contact_bodies(self.map)),
            cost=icfg.contact_weight,
        )  # fmt: skip

        prev = mujoco.MjData(model)  # The previous output frame, for its foot sites.
        warm = mujoco.MjData(model)  # The frame's kinematic warm start.
        vel = np.zeros(model.nv)
        out = np.zeros((T, model.nq))
        iters = np.zeros(T, dtype=int)
        n_scene = np.zeros(T, dtype=int)
        frame = _Frame(source=clip.source)
        step = (
            kin.speed_limits * self.cfg.velocity_limit_scale / tg.fps
            if self.cfg.velocity_limit_scale > 0
            else None
        )

        def solve(frame: _Frame) -> np.ndarray:
            """One QP; where the limits conflict, the toes' travel limit yields first."""
            return kin._solve(frame, limits, yielding=travel)

        def solve_frame(tasks: list[mink.Task], guarded: bool) -> int:
            """The frame's QPs, repair and reattachment from the configuration as it is;
            ``guarded``: each step halved while it takes a self-collision pair deeper
            (:meth:`KinematicRetargeter._step`). Returns the QPs solved."""
            n = 0
            frame.tasks = tasks
            touch.gap = 0.0
            for _ in range(icfg.iterations):
                dq = solve(frame)
                kin._step(dq, guarded=guarded)
                n += 1
                if float(np.abs(dq).max()) < icfg.tol:
                    break
            # Repair: the limits are linearized, so the last step can end inside an object;
            # step again without the pull onto surfaces while it does. Every robot-scene pair
            # is checked: a step can carry a geom into an object it was farther from than the
            # limit's detection distance (a foot 20 mm inside a box, seq_1 of the climbing
            # clips, went unseen by a check of the pairs that were near before the step). The
            # same while a self-collision pair is inside its repair line
            # (SelfCollisionLimit.repair_slack), as in the kinematic pass.
            frame.tasks = [task for task in tasks if task is not touch]
            for _ in range(self.cfg.repair_iters):
                if (_deepest(model, conf.data, scene_pairs) >= -REPAIR_DEPTH
                        and kin._self_check()[0] >= 0.0):  # fmt: skip
                    break
                kin._step(solve(frame), guarded=guarded)
                n += 1
            # Reattach: the repair may have moved a touching body off its surface. Step again
            # with the pull aiming contact_gap off the surface (at zero gap it fights the
            # linearized limit), keeping a step only if it reattaches more contacts than it
            # loses and nothing ends inside the scene or deeper in a pair.
            if touch in tasks and icfg.reattach_iterations > 0:
                frame.tasks, touch.gap = tasks, icfg.contact_gap
                attached = _attached(touch, conf, icfg.contact_distance)
                for _ in range(icfg.reattach_iterations):
                    if attached.all():
                        break
                    before = conf.q.copy()
                    conf.integrate_inplace(solve(frame), 1.0)
                    n += 1
                    now = _attached(touch, conf, icfg.contact_distance)
                    deep = (_deepest(model, conf.data, scene_pairs) < -REPAIR_DEPTH
                            or kin._self_check()[0] < 0.0)  # fmt: skip
                    if deep or now.sum() <= attached.sum():
                        conf.update(before)
                        break
                    attached = now
            return n

        retried = 0
        t0 = time.perf_counter()
        for t in range(T):
            set_scene_pose(model, conf.data, scene_r, t)
            # Start from the previous output moved as the warm start moves (within the joint
            # ranges), not from the warm start: the kinematic method ignores the scene, and a
            # warm start inside a box on most frames once failed to pull out within a frame's
            # QPs.
            warm.qpos[:] = kres.qpos[t]
            warm.mocap_pos[:], warm.mocap_quat[:] = conf.data.mocap_pos, conf.data.mocap_quat
            mujoco.mj_kinematics(model, warm)
            if t > 0:
                mujoco.mj_differentiatePos(model, vel, 1.0, kres.qpos[t - 1], kres.qpos[t])
                conf.update(self._advance(model, conf, out[t - 1], vel, scene_pairs, kin))
            else:
                conf.update(kres.qpos[0])
            pts = self._scene_points(scene_r, samples, tg.scaled[t], t)
            n_scene[t] = len(pts)
            mesh_task.set_mesh(build_mesh(tg.scaled[t], pts, weighting=icfg.weighting))
            kin._set_targets(tg, t)
            kin._set_stage_costs(tg, t, 2)
            # Weak anchors, except for planted foot points: they keep the kinematic weight.
            costs = tg.position_weights[t] * icfg.keypoint_scale
            costs[feet_flat] = np.where(planted[t], tg.position_weights[t, feet_flat],
                                        costs[feet_flat])  # fmt: skip
            kin.keypoints.set_costs(costs)
            tasks = [mesh_task, kin.keypoints, kin.orientations, kin.posture]
            touching = np.flatnonzero(contacts[t] >= 0)
            touch.gap = 0.0
            if touching.size and icfg.contact_weight > 0:
                touch.set_contacts(
                    [(int(k), obj_geoms[contacts[t, k]]) for k in touching], firm[t, touching]
                )
                tasks.append(touch)
            travel.set(travel.anchors, np.full(len(toe_feet), np.inf))
            if t > 0:
                smooth.set_target(out[t - 1])
                tasks.append(smooth)
                held = planted[t] & planted[t - 1]  # (4,) per foot point
                if held.any() or still[t].any():
                    prev.qpos[:] = out[t - 1]
                    prev.mocap_pos[:] = conf.data.mocap_pos
                    prev.mocap_quat[:] = conf.data.mocap_quat
                    mujoco.mj_kinematics(model, prev)
                if still[t].any():
                    # Only where the warm start's toe is near: a limit far from it would drag
                    # the whole body after a foot the targets have moved on.
                    anchors = travel.positions(prev)
                    moved = travel.positions(warm)[:, :2] - anchors[:, :2]
                    near = np.linalg.norm(moved, axis=1) < icfg.still_reach
                    travel.set(anchors, np.where(still[t] & near, cap, np.inf))
                if held.any():
                    # Planted points stay where they were horizontally, at the warm start's
                    # height, held more loosely (stick_height_scale): holding the previous
                    # height kept a foot that landed high floating through its stance. The
                    # warm start knows the floor, not the scene: a foot it sinks into an
                    # object keeps its previous height.
                    sunk = np.array([_deepest(model, warm, p) < -REPAIR_DEPTH for p in foot_pairs])
                    stick.targets = prev.site_xpos[stick.site_ids].copy()
                    stick.targets[:, 2] = np.where(sunk[stick_foot], stick.targets[:, 2],
                                                   warm.site_xpos[stick.site_ids, 2])  # fmt: skip
                    cost = np.zeros((held.size, 3))
                    cost[held] = icfg.stick_weight * np.array([1.0, 1.0, icfg.stick_height_scale])
                    stick.cost = cost.ravel()
                    tasks.append(stick)
            frame.t, frame.tasks = t, tasks
            frame.q_prev = None if (t == 0 or step is None) else out[t - 1, 7:]
            frame.step = step

            start = conf.q.copy()
            n = solve_frame(tasks, guarded=False)
            depth = kin._self_check()[1]
            if depth > 0.0:
                # A self-collision the report would count, as in the kinematic pass
                # (KinematicRetargeter.run): once more from the frame's start with guarded
                # steps, the less deep kept.
                first = conf.q.copy()
                conf.update(start)
                n += solve_frame(tasks, guarded=True)
                retried += 1
                if kin._self_check()[1] > depth:
                    conf.update(first)
            q = conf.q.copy()
            q[7:] = np.clip(q[7:], kin._range_lo, kin._range_hi)
            out[t] = q
            iters[t] = n
            if progress is not None:
                progress(1)
        return InteractionResult(
            qpos=out,
            kinematic=kres,
            scene=scene_r,
            model=model,
            solve_seconds=time.perf_counter() - t0,
            iterations=iters,
            relaxed_iterations=frame.relaxed,
            yielded_iterations=frame.yielded,
            retried_frames=retried,
            mesh_scene_points=n_scene,
            scene_spacings=spacings,
            human_contacts=contacts,
            scene_floor=placement,
        )

    @staticmethod
    def _advance(
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

    def _toe_travel(
        self, model: mujoco.MjModel, foot_points: tuple[np.ndarray, np.ndarray, np.ndarray]
    ) -> tuple[np.ndarray, PointTravelLimit]:
        """The front of each sole (its contact points within :data:`TOE_DEPTH` of the foremost)
        under a travel limit. Returns the foot of each point and the limit."""
        ids, pts, _ = foot_points
        feet, chosen = [], []
        for k, foot in enumerate(self.map.feet.values()):
            sel = np.flatnonzero(ids == model.body(foot.body).id)
            front = sel[pts[sel, 0] >= pts[sel, 0].max() - TOE_DEPTH]
            chosen.append(front)
            feet += [k] * front.size
        at = np.concatenate(chosen)
        return np.array(feet), PointTravelLimit(model, ids[at], pts[at])

    def _scene_points(
        self, scene: Scene, samples: list[np.ndarray], keypoints: np.ndarray, t: int
    ) -> np.ndarray:
        """The scene points of frame ``t`` within ``scene_radius`` of a key point, nearest
        first, at most ``max_scene_points``. Shape: (S, 3)."""
        icfg = self.icfg
        world = []
        for obj, local in zip(scene.objects, samples, strict=True):
            rot, pos = obj.pose(t)
            world.append(local @ rot.T + pos)
        pts = np.concatenate(world) if world else np.zeros((0, 3))
        d = np.sqrt(((pts[:, None, :] - keypoints[None]) ** 2).sum(-1)).min(axis=1)
        near = np.flatnonzero(d < icfg.scene_radius)
        near = near[np.argsort(d[near])[: icfg.max_scene_points]]
        return pts[near]


__all__ = [
    "HAND_CONTACT_RADIUS",
    "InteractionMeshRetargeter",
    "InteractionResult",
    "body_geoms",
    "contact_bodies",
    "contact_radii",
    "feet_planted",
    "set_scene_pose",
]
