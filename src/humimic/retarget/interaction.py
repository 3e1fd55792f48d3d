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
from humimic.retarget.interaction_pass import InteractionPass, set_scene_pose
from humimic.retarget.kinematic import KinematicResult, KinematicRetargeter, _Frame
from humimic.retarget.limits import PointTravelLimit, SelfCollisionLimit
from humimic.retarget.robot_model import (
    KEYPOINT_SITE_PREFIX,
    robot_collision_geoms,
    scene_geoms,
    sole_corner_geoms,
)
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
        set_scene_pose(kin.model, kin.configuration.data, scene_r, 0)
        names = list(self.map.keypoints)
        foot_idx = np.array([[names.index(k) for k in pair] for pair in self._foot_keys])
        if icfg.still_speed > 0:  # Toe targets still where the human's toes are.
            tg = hold_still_points(tg, foot_idx[:, 1], tg.contacts[:, :, 1],
                                   speed=icfg.still_speed, radius=self.cfg.plant_radius,
                                   weight_scale=self.cfg.contact_weight_scale)  # fmt: skip
        kres = kin.run(clip, progress=progress, targets=tg)
        solver, spacings = self._interaction_pass(clip, kin, kres, tg, scene_r, foot_idx)
        t0 = time.perf_counter()
        solver.run(progress)
        return InteractionResult(
            qpos=solver.out,
            kinematic=kres,
            scene=scene_r,
            model=kin.model,
            solve_seconds=time.perf_counter() - t0,
            iterations=solver.iters,
            relaxed_iterations=solver.frame.relaxed,
            yielded_iterations=solver.frame.yielded,
            retried_frames=solver.retried,
            mesh_scene_points=solver.n_scene,
            scene_spacings=spacings,
            human_contacts=solver.contacts,
            scene_floor=placement,
        )

    def _interaction_pass(
        self,
        clip: HumanClip,
        kin: KinematicRetargeter,
        kres: KinematicResult,
        tg: Targets,
        scene_r: Scene,
        foot_idx: np.ndarray,
    ) -> tuple[InteractionPass, list[float]]:
        """The interaction stage of :meth:`run`, set up after its kinematic pass: the tasks
        and limits on ``kin``'s model (with the scene), the human's contacts with the scene
        and the planted and still foot points; and each object's sampling spacing.

        Args:
            clip: The clip (for its name in errors).
            kin: The retargeter of the model with the scene.
            kres: Its kinematic result, the warm start.
            tg: The targets (still toes held).
            scene_r: The scene in the robot's frame.
            foot_idx: Key-point index of each foot's ankle and toe. Shape: (F, 2).
        """
        icfg = self.icfg
        model = kin.model
        T = tg.positions.shape[0]
        robot_geoms, obj_geoms, scene_pairs, scene_limit = self._scene_limit(clip, model)
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
        solver = InteractionPass(
            kin=kin, cfg=self.cfg, icfg=icfg, targets=tg, warm_start=kres.qpos, scene=scene_r,
            samples=samples, contacts=contacts, firm=firm, planted=planted,
            still=toe_speed[:, toe_feet] < icfg.still_speed,  # (T, toe points)
            cap=icfg.still_travel * icfg.still_speed / tg.fps,
            feet_flat=feet_flat, toe_feet=toe_feet, obj_geoms=obj_geoms,
            scene_pairs=scene_pairs, foot_pairs=foot_pairs, limits=limits, travel=travel,
            mesh_task=mesh_task, stick=stick, stick_foot=stick_foot,
            smooth=mink.PostureTask(model, cost=icfg.smooth_weight),
            touch=SceneContactTask(model, body_geoms(model, contact_bodies(self.map)),
                                   cost=icfg.contact_weight),
            frame=_Frame(source=clip.source),
        )  # fmt: skip
        return solver, spacings

    def _scene_limit(
        self, clip: HumanClip, model: mujoco.MjModel
    ) -> tuple[list[int], list[int], list[tuple[int, int]], SelfCollisionLimit]:
        """The robot's collision geoms, the scene's geoms, the pairs kept apart (every robot
        geom against every object and the floor, every sole corner against every object),
        and the limit that keeps them apart.

        Raises:
            RetargetError: The model has no robot collision geoms or no scene geoms.
        """
        icfg = self.icfg
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
        return robot_geoms, obj_geoms, scene_pairs, scene_limit

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
