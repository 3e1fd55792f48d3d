"""Quality metrics of a retargeted motion, measured with MuJoCo on the robot model."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from humimic.datasets.scene import Scene
from humimic.retarget.limits import CONTACT_HEIGHT, contact_point_heights, foot_contact_points
from humimic.robots.collision import rest_distances


@dataclass(frozen=True, kw_only=True)
class QualityReport:
    """Numbers that say how good a retargeted motion is. Lengths in mm, times in s.

    Attributes:
        keypoint_error_mm_mean: Mean distance of robot key points to the scaled human ones.
        keypoint_error_mm_p95: Its 95th percentile.
        foot_skating_mm_per_s: Mean horizontal speed of foot contact points while they touch
            the ground (lowest point below 10 mm in two consecutive frames).
        planted_foot_skating_mm_per_s: The same over the frames in which the human's foot
            (that point's foot) is also in contact in both frames: a planted foot that slides
            (None without per-foot human contacts, or without such frames).
        foot_contact_frames: Share of frames in which some foot point touches the ground.
        max_ground_penetration_mm: Deepest penetration of any robot collision geom into the floor.
        median_lowest_foot_mm: Median over frames of the lowest foot point's height.
        median_lowest_foot_in_contact_mm: The same over the frames in which the human has a
            foot on the ground (flight phases of a run excluded); NaN without contact frames.
        joint_limit_violations: (frame, joint) pairs outside the joint range.
        self_collision_pairs: Geom pairs checked for self-collision: every pair of the
            robot's collision geoms that MuJoCo could collide and that do not touch in the
            default pose (:func:`~humimic.robots.collision.self_collision_pairs`).
        self_collision_frames: Frames in which a self-collision pair penetrates deeper than 1 mm
            beyond its overlap at rest (0 for a pair apart at rest).
        max_self_penetration_mm: Deepest penetration among the self-collision pairs, beyond
            each pair's overlap at rest.
        self_collision_rest_overlaps: Pairs whose geoms overlap in the model's own rest poses
            (``qpos0`` and keyframes; the Apollo's arm and wrist capsules): the coarse
            geometry's, not the motion's, so they count only where the motion puts them deeper.
        worst_self_collision: The bodies of the deepest penetrating pair, ``"a | b"`` (empty
            when no pair penetrates).
        mean_joint_jerk: Mean absolute third derivative of the joint angles [rad/s^3].
        turned_knee_frames: Frames in which a knee's hinge axis is more than 90 degrees off
            its direction relative to the root body in the zero pose (:data:`KNEE_TURN_DEG`:
            a leg turned about itself, the knee facing sideways or backward;
            :func:`knee_joints`); None where the model has no knee to check.
        worst_knee_turn_deg: The largest such angle over the clip [deg]; None likewise.
    """

    keypoint_error_mm_mean: float
    keypoint_error_mm_p95: float
    foot_skating_mm_per_s: float | None
    planted_foot_skating_mm_per_s: float | None
    foot_contact_frames: float
    max_ground_penetration_mm: float
    median_lowest_foot_mm: float
    median_lowest_foot_in_contact_mm: float
    joint_limit_violations: int
    self_collision_pairs: int
    self_collision_frames: int
    max_self_penetration_mm: float
    worst_self_collision: str
    mean_joint_jerk: float
    self_collision_rest_overlaps: int = 0
    turned_knee_frames: int | None = None
    worst_knee_turn_deg: float | None = None


KNEE_TURN_DEG = 90.0
"""A knee axis further than this from its zero-pose direction (in the root's frame) is turned:
the knee faces sideways or backward. A human hip's rotation and abduction turn it by up to
about 70 degrees (the climbing clips: 61-71); a leg turned about itself, by 150 or more."""


def knee_joints(model: mujoco.MjModel, foot_bodies: list[str]) -> list[int]:
    """The knees of a floating-base model: the hinge joints named ``*knee*`` (any case) on
    the chain from each foot body up to the root body (the free joint's), whose axis lies
    along the root's left-right axis in the zero pose (within 25 degrees). Empty if none."""
    root = _root_body(model)
    if root is None:
        return []
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    mujoco.mj_kinematics(model, data)
    left = data.xmat[root].reshape(3, 3)[:, 1]
    out = []
    for name in foot_bodies:
        b = model.body(name).id
        while b not in (0, root):
            for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]):
                hinge = model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
                knee = hinge and "knee" in model.joint(j).name.lower()
                if knee and abs(float(data.xaxis[j] @ left)) >= np.cos(np.radians(25.0)):
                    out.append(j)
            b = int(model.body_parentid[b])
    return out


def _root_body(model: mujoco.MjModel) -> int | None:
    """The body of the model's (first) free joint, or None for a fixed base."""
    free = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    return int(model.jnt_bodyid[free[0]]) if free else None


def _knee_axes(
    model: mujoco.MjModel, data: mujoco.MjData, knees: list[int], root: int
) -> np.ndarray:
    """The knees' axes in the root body's frame, at ``data``'s kinematics. Shape: (K, 3)."""
    r = data.xmat[root].reshape(3, 3)
    return data.xaxis[knees] @ r


def evaluate(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    fps: float,
    *,
    keypoint_sites: list[str],
    keypoint_targets: np.ndarray,
    foot_bodies: list[str],
    self_collision: np.ndarray,
    floor_geom: str = "floor",
    human_contact: np.ndarray | None = None,
    human_foot_contact: np.ndarray | None = None,
) -> tuple[QualityReport, dict[str, np.ndarray]]:
    """Measure a motion: the summary report, and per-frame arrays for the viewer.

    Args:
        model: Robot model with key point sites and a floor.
        qpos: Configurations. Shape: (T, nq).
        fps: Frame rate.
        keypoint_sites: Site names of the key points, in target order.
        keypoint_targets: Scaled human key points. Shape: (T, K, 3).
        foot_bodies: Foot bodies (their collision geoms give the contact points).
        self_collision: Geom-id pairs that must not interpenetrate. Shape: (P, 2).
        floor_geom: Name of the floor geom.
        human_contact: Frames in which the human has a foot on the ground. Shape: (T,).
        human_foot_contact: Frames in which each of the human's feet is on the ground, in the
            order of ``foot_bodies``. Shape: (T, len(foot_bodies)).

    Returns:
        The report, and per-frame arrays: ``keypoint_error`` (T,) [m], ``ground_penetration``
        (T,) [m], ``self_penetration`` (T,) [m], ``lowest_foot`` (T,) [m], ``foot_touching``
        (T, N) for the N foot contact points.
    """
    site_ids = np.array([model.site(s).id for s in keypoint_sites], dtype=int)
    feet = foot_contact_points(model, foot_bodies)
    from humimic.retarget.robot_model import robot_collision_geoms

    floor = model.geom(floor_geom).id
    robot_geoms = robot_collision_geoms(model)  # Not the floor's, not a scene's.
    selfpen = _SelfPenetration(model, self_collision)
    knees = _KneeTurns(model, foot_bodies, qpos.shape[0])
    kp_err, foot_xy, foot_bottom, ground_pen, self_pen = _measure_frames(
        model, qpos, site_ids, keypoint_targets, feet, floor, robot_geoms, selfpen, knees
    )

    touching = foot_bottom < CONTACT_HEIGHT
    skating, planted_skating = _foot_skating(
        model, touching, foot_xy, fps, feet[0], foot_bodies, human_foot_contact
    )
    report = QualityReport(
        keypoint_error_mm_mean=float(kp_err.mean() * 1e3),
        keypoint_error_mm_p95=float(np.percentile(kp_err, 95) * 1e3),
        foot_skating_mm_per_s=None if skating is None else skating * 1e3,
        planted_foot_skating_mm_per_s=None if planted_skating is None else planted_skating * 1e3,
        foot_contact_frames=float(touching.any(axis=1).mean()),
        max_ground_penetration_mm=float(ground_pen.max() * 1e3),
        median_lowest_foot_mm=float(np.median(foot_bottom.min(axis=1)) * 1e3),
        median_lowest_foot_in_contact_mm=(
            float(np.median(foot_bottom.min(axis=1)[human_contact]) * 1e3)
            if human_contact is not None and human_contact.any()
            else float("nan")
        ),
        self_collision_pairs=len(selfpen.pairs),
        self_collision_frames=int(np.sum(self_pen > 1e-3)),
        max_self_penetration_mm=float(self_pen.max() * 1e3),
        worst_self_collision=selfpen.worst_pair,
        self_collision_rest_overlaps=int(np.sum(selfpen.at_rest > 0.0)),
        **_joint_metrics(model, qpos, fps),
        **knees.metrics(),
    )
    frames = {
        "keypoint_error": kp_err.mean(axis=1),
        "ground_penetration": ground_pen,
        "self_penetration": self_pen,
        "lowest_foot": foot_bottom.min(axis=1),
        "foot_touching": touching,
    }
    return report, frames


class _SelfPenetration:
    """The self-collision pairs' penetration beyond each pair's overlap at rest, frame by
    frame, and the deepest pair over all the frames measured.

    Attributes:
        pairs: Geom-id pairs. Shape: (P, 2).
        at_rest: Each pair's overlap in the model's rest poses [m], >= 0. Shape: (P,).
        worst_pair: The bodies of the deepest pair so far, ``"a | b"`` (empty: none).
        worst_depth: Its depth beyond its overlap at rest [m] (0: none).
    """

    def __init__(self, model: mujoco.MjModel, self_collision: np.ndarray) -> None:
        self.model = model
        self.pairs = np.asarray(self_collision, dtype=int).reshape(-1, 2)
        # Each pair's overlap in the rest poses [m], >= 0: depth is measured beyond it.
        self.at_rest = -rest_distances(model, self.pairs, 0.0) if len(self.pairs) else np.zeros(0)
        self.worst_pair, self.worst_depth = "", 0.0
        self._fromto = np.zeros(6)

    def measure(self, data: mujoco.MjData) -> float:
        """The deepest penetration beyond rest among the pairs whose bounding spheres meet,
        at ``data``'s kinematics (0 if none) [m]; updates the deepest pair."""
        model, fromto = self.model, self._fromto
        pair_a, pair_b = self.pairs[:, 0], self.pairs[:, 1]
        diff = data.geom_xpos[pair_a] - data.geom_xpos[pair_b]
        near = (
            np.einsum("ij,ij->i", diff, diff)
            <= (model.geom_rbound[pair_a] + model.geom_rbound[pair_b]) ** 2
        )
        worst = 0.0
        for a, b, rest in zip(pair_a[near], pair_b[near], self.at_rest[near], strict=True):
            d = mujoco.mj_geomDistance(model, data, int(a), int(b), 0.01, fromto)
            worst = max(worst, -d - rest)
            if -d - rest > self.worst_depth:
                self.worst_depth = -d - rest
                self.worst_pair = " | ".join(model.body(model.geom_bodyid[g]).name for g in (a, b))
        return worst


def _ground_penetration(
    model: mujoco.MjModel, data: mujoco.MjData, floor: int, robot_geoms: list[int]
) -> float:
    """The deepest penetration of a robot geom into the floor at ``data``'s kinematics (0 if
    none) [m]; geoms whose bounding sphere is above the floor are skipped."""
    fromto = np.zeros(6)
    pen = 0.0
    for g in robot_geoms:
        if data.geom_xpos[g, 2] - model.geom_rbound[g] > 0.0:
            continue  # Its bounding sphere is above the floor.
        d = mujoco.mj_geomDistance(model, data, floor, g, 0.01, fromto)
        pen = max(pen, -d)
    return pen


def _foot_skating(
    model: mujoco.MjModel, touching: np.ndarray, foot_xy: np.ndarray, fps: float,
    ids: np.ndarray, foot_bodies: list[str], human_foot_contact: np.ndarray | None,
) -> tuple[float | None, float | None]:  # fmt: skip
    """Mean horizontal speed [m/s] of the foot contact points touching the ground in two
    consecutive frames, and the same over the frames where the human's foot is down in both
    too (None: no such frames, or no per-foot human contacts)."""
    both = touching[1:] & touching[:-1]
    speed = np.linalg.norm(np.diff(foot_xy, axis=0), axis=-1) * fps
    skating = float(speed[both].mean()) if both.any() else None  # No foot ever rests.
    planted_skating = None
    if human_foot_contact is not None:
        foot_of = np.array([[model.body(b).id for b in foot_bodies].index(int(i)) for i in ids])
        human = np.asarray(human_foot_contact, dtype=bool)[:, foot_of]  # (T, N)
        planted = both & human[1:] & human[:-1]
        planted_skating = float(speed[planted].mean()) if planted.any() else None
    return skating, planted_skating


def _joint_metrics(model: mujoco.MjModel, qpos: np.ndarray, fps: float) -> dict[str, Any]:
    """The report's ``joint_limit_violations`` and ``mean_joint_jerk``."""
    T = qpos.shape[0]
    joints = qpos[:, 7:]
    limited = model.jnt_limited[1:].astype(bool)  # A joint without a range has no limit.
    lo = np.where(limited, model.jnt_range[1:, 0], -np.inf)
    hi = np.where(limited, model.jnt_range[1:, 1], np.inf)
    violations = int(np.sum((joints < lo - 1e-6) | (joints > hi + 1e-6)))
    jerk = np.diff(joints, n=3, axis=0) * fps**3 if T > 3 else np.zeros((1, joints.shape[1]))
    return {"joint_limit_violations": violations, "mean_joint_jerk": float(np.abs(jerk).mean())}


class _KneeTurns:
    """How far each knee's axis turns from its zero-pose direction in the root's frame, frame
    by frame (:func:`knee_joints`; nothing measured for a model without knees).

    Attributes:
        knees: The knee joints.
        cos: Each frame's cosine of each knee's turn. Shape: (T, knees).
    """

    def __init__(self, model: mujoco.MjModel, foot_bodies: list[str], frames: int) -> None:
        self.model = model
        self.knees = knee_joints(model, foot_bodies)
        self.root = _root_body(model) or 0
        self.cos = np.ones((frames, len(self.knees)))
        self.rest = np.zeros((len(self.knees), 3))
        if self.knees:
            data = mujoco.MjData(model)
            data.qpos[:] = model.qpos0
            mujoco.mj_kinematics(model, data)
            self.rest = _knee_axes(model, data, self.knees, self.root)

    def measure(self, data: mujoco.MjData, t: int) -> None:
        """Frame ``t``'s cosines, at ``data``'s kinematics."""
        if self.knees:
            axes = _knee_axes(self.model, data, self.knees, self.root)
            self.cos[t] = np.einsum("kj,kj->k", axes, self.rest)

    def metrics(self) -> dict[str, Any]:
        """The report's ``turned_knee_frames`` and ``worst_knee_turn_deg`` (None: no knees)."""
        knee_cos, has_knees = self.cos, bool(self.knees)
        return {
            "turned_knee_frames": (
                int(np.sum((knee_cos < np.cos(np.radians(KNEE_TURN_DEG))).any(axis=1)))
                if has_knees
                else None
            ),
            "worst_knee_turn_deg": (
                float(np.degrees(np.arccos(np.clip(knee_cos.min(), -1.0, 1.0))))
                if has_knees
                else None
            ),
        }


def _measure_frames(
    model: mujoco.MjModel, qpos: np.ndarray, site_ids: np.ndarray, keypoint_targets: np.ndarray,
    feet: tuple[np.ndarray, np.ndarray, np.ndarray], floor: int, robot_geoms: list[int],
    selfpen: _SelfPenetration, knees: _KneeTurns,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Pose the model in every frame of ``qpos`` and measure it (the knees' turns into
    ``knees``, the deepest self-collision pair into ``selfpen``).

    Returns:
        Key-point errors (T, K) [m], the foot contact points' horizontal positions (T, N, 2)
        and heights of their lowest points (T, N) [m], the ground penetration (T,) and the
        self-penetration (T,) [m].
    """
    data = mujoco.MjData(model)
    T = qpos.shape[0]
    ids, pts, rad = feet
    kp_err = np.zeros((T, len(site_ids)))
    foot_xy = np.zeros((T, len(ids), 2))
    foot_bottom = np.zeros((T, len(ids)))
    ground_pen = np.zeros(T)
    self_pen = np.zeros(T)
    for t in range(T):
        data.qpos[:] = qpos[t]
        mujoco.mj_kinematics(model, data)
        kp_err[t] = np.linalg.norm(data.site_xpos[site_ids] - keypoint_targets[t], axis=-1)
        knees.measure(data, t)
        world, bottom = contact_point_heights(data, ids, pts, rad)
        foot_xy[t] = world[:, :2]
        foot_bottom[t] = bottom
        ground_pen[t] = _ground_penetration(model, data, floor, robot_geoms)
        if len(selfpen.pairs):
            self_pen[t] = selfpen.measure(data)
    return kp_err, foot_xy, foot_bottom, ground_pen, self_pen


@dataclass(frozen=True, kw_only=True)
class SceneReport:
    """How a motion respects its scene. Lengths in mm.

    Attributes:
        max_scene_penetration_mm: Deepest penetration of a robot collision geom into a scene
            object, over all frames.
        mean_scene_penetration_mm: Mean over frames of each frame's deepest penetration (0 in
            frames without).
        scene_penetration_frames: Frames with a penetration deeper than 1 mm.
        human_contacts: (frame, key point) pairs in which the scaled human's key point touches
            a scene object (:func:`~humimic.retarget.scene.human_contacts`).
        contact_preservation: Share of those in which the robot's body of that key point (any
            of its geoms, visual ones included) is within ``contact_distance`` of the same
            object (None when there are none: nothing was measured).
        scene_foot_skating_mm_per_s: Mean horizontal speed of the feet's contact points while
            they rest (lowest point within 10 mm) on the floor or an object, in two
            consecutive frames.
        planted_foot_gap_mm: Mean height of a robot foot's lowest contact point over the
            nearest surface (the floor or an object) in the frames where the human's foot
            rests (``feet_planted``): a foot that floats above the step raises it.
        floating_planted_feet: (frame, foot) pairs among those in which the robot's foot is
            more than 10 mm above every surface.
    """

    max_scene_penetration_mm: float
    mean_scene_penetration_mm: float
    scene_penetration_frames: int
    human_contacts: int
    contact_preservation: float | None
    scene_foot_skating_mm_per_s: float | None
    planted_foot_gap_mm: float | None
    floating_planted_feet: int


def evaluate_scene(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    scene: Scene,
    fps: float,
    *,
    keypoint_bodies: list[list[str]],
    human_contacts: np.ndarray,
    foot_bodies: list[str],
    feet_planted: np.ndarray,
    contact_distance: float = 0.02,
) -> tuple[SceneReport, dict[str, np.ndarray]]:
    """Measure a motion against its scene (a :class:`~humimic.datasets.scene.Scene` in the
    robot's frame, whose objects are the mocap bodies of ``model``, see
    :func:`~humimic.retarget.robot_model.ik_model`).

    Args:
        model: Robot model with the scene.
        qpos: Configurations. Shape: (T, nq).
        scene: The scene, posed per output frame.
        fps: Frame rate.
        keypoint_bodies: The robot bodies that make each key point's contacts (K,)
            (:func:`~humimic.retarget.interaction.contact_bodies`).
        human_contacts: The scene object each human key point touches, -1 for none
            (:func:`~humimic.retarget.scene.human_contacts`). Shape: (T, K).
        foot_bodies: Foot bodies (their collision geoms give the contact points).
        feet_planted: Frames where the human's foot of each foot body rests (on the floor or
            an object). Shape: (T, len(foot_bodies)).
        contact_distance: Touching distance [m].

    Returns:
        The report, and per-frame arrays ``scene_penetration`` (T,) [m] and
        ``contact_preserved`` (T, K) (1 preserved, 0 lost, -1 no human contact).
    """
    from humimic.retarget.interaction import body_geoms, set_scene_pose
    from humimic.retarget.robot_model import robot_collision_geoms, scene_geoms

    data = mujoco.MjData(model)
    T, K = human_contacts.shape
    robot = robot_collision_geoms(model)
    objs = scene_geoms(model)
    geoms_of = body_geoms(model, keypoint_bodies)
    ids, pts, rad = foot_contact_points(model, foot_bodies)
    pen = np.zeros(T)
    preserved = np.full((T, K), -1, dtype=np.int8)
    foot_xy = np.zeros((T, len(ids), 2))
    resting = np.zeros((T, len(ids)), dtype=bool)
    gap = np.zeros((T, len(ids)))  # Each contact point's height over the nearest surface.
    reach = 0.1  # Distance queries beyond this are not needed [m].
    for t in range(T):
        data.qpos[:] = qpos[t]
        set_scene_pose(model, data, scene, t)
        mujoco.mj_kinematics(model, data)
        tris = [o.world_vertices(t)[o.faces] for o in scene.objects]
        pen[t] = _scene_penetration(model, data, robot, objs, reach)
        preserved[t] = _contacts_preserved(
            model, data, human_contacts[t], objs, geoms_of, reach, contact_distance
        )
        world, bottom = contact_point_heights(data, ids, pts, rad)
        foot_xy[t] = world[:, :2]
        d_scene = _surface_distance(world, rad, tris)
        resting[t] = (bottom < CONTACT_HEIGHT) | (d_scene < CONTACT_HEIGHT)
        gap[t] = np.minimum(bottom, d_scene)
    both = resting[1:] & resting[:-1]
    speed = np.linalg.norm(np.diff(foot_xy, axis=0), axis=-1) * fps
    contacts = int(np.sum(preserved >= 0))
    foot_gap = np.stack([gap[:, ids == model.body(b).id].min(axis=1) for b in foot_bodies], 1)
    planted_gap = foot_gap[feet_planted]
    report = SceneReport(
        max_scene_penetration_mm=float(pen.max() * 1e3) if T else 0.0,
        mean_scene_penetration_mm=float(pen.mean() * 1e3) if T else 0.0,
        scene_penetration_frames=int(np.sum(pen > 1e-3)),
        human_contacts=contacts,
        # Over zero events a share or a mean is not measured: None, never a perfect score.
        contact_preservation=float(np.sum(preserved == 1) / contacts) if contacts else None,
        scene_foot_skating_mm_per_s=float(speed[both].mean() * 1e3) if both.any() else None,
        planted_foot_gap_mm=float(planted_gap.mean() * 1e3) if planted_gap.size else None,
        floating_planted_feet=int(np.sum(planted_gap > CONTACT_HEIGHT)),
    )
    return report, {"scene_penetration": pen, "contact_preserved": preserved}


def _scene_penetration(
    model: mujoco.MjModel, data: mujoco.MjData, robot: list[int], objs: list[int], reach: float
) -> float:
    """The deepest penetration of a robot geom into a scene object at ``data``'s kinematics (0
    if none) [m]; only pairs whose bounding spheres come within ``reach`` are queried."""
    fromto = np.zeros(6)
    worst = 0.0
    for o in objs:
        near = np.linalg.norm(data.geom_xpos[robot] - data.geom_xpos[o], axis=1) <= (
            model.geom_rbound[robot] + model.geom_rbound[o] + reach
        )
        for g in np.asarray(robot)[near]:
            worst = max(worst, -mujoco.mj_geomDistance(model, data, int(g), o, reach, fromto))
    return worst


def _contacts_preserved(
    model: mujoco.MjModel, data: mujoco.MjData, contacts: np.ndarray, objs: list[int],
    geoms_of: list[list[int]], reach: float, contact_distance: float,
) -> np.ndarray:  # fmt: skip
    """Whether the robot's body touches the object its human key point touches (``contacts``:
    the object per key point, -1 for none), at ``data``'s kinematics: 1 preserved, 0 lost, -1
    no human contact. Shape: (K,)."""
    fromto = np.zeros(6)
    out = np.full(len(contacts), -1, dtype=np.int8)
    for k in np.flatnonzero(contacts >= 0):
        o = objs[contacts[k]]
        d_r = min(
            (mujoco.mj_geomDistance(model, data, g, o, reach, fromto) for g in geoms_of[k]),
            default=np.inf,
        )
        out[k] = int(d_r <= contact_distance)
    return out


def _surface_distance(world: np.ndarray, rad: np.ndarray, tris: list[np.ndarray]) -> np.ndarray:
    """Each foot contact point's lowest point (its centre ``world`` (N, 3) less its radius
    ``rad`` (N,)) to the nearest of the objects' triangles ``tris`` (inf without objects).
    Shape: (N,)."""
    from humimic.retarget.interaction_mesh import point_triangle_distance

    low = world - np.array([0.0, 0.0, 1.0]) * rad[:, None]
    return (
        np.min([point_triangle_distance(low, tri).min(axis=1) for tri in tris], axis=0)
        if tris
        else np.full(len(world), np.inf)
    )
