"""Turn a human clip into robot-sized IK targets (:func:`build_targets`). Pure numpy: no
simulator imports.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from humimic.configs.retarget import RetargetConfig
from humimic.datasets.clip import HumanClip, estimate_height
from humimic.errors import MotionDataError
from humimic.retarget.contacts import detect_contacts, plant_segments, runs, step_speed
from humimic.robots.maps import RetargetMap
from humimic.transforms import axis_angle_matrix, frame_from_left_up


@dataclass(frozen=True, kw_only=True)
class RobotGeometry:
    """The robot measured in its zero pose with the soles on the floor (z = 0).

    Attributes:
        keypoints: Key point positions, in map order. Shape: (K, 3).
        frame_body_rot: World rotation of each frame's body. Shape: (F, 3, 3).
        foot_body_rot: World rotation of each foot body, in map ``feet`` order. Shape: (2, 3, 3).
        foot_points: Per foot, its contact points relative to the ankle key point, in the foot
            body's frame, and their radii: ``[..., :3]`` position, ``[..., 3]`` radius.
            Shape: (2, N, 4).
    """

    keypoints: np.ndarray
    frame_body_rot: np.ndarray
    foot_body_rot: np.ndarray
    foot_points: np.ndarray


@dataclass(frozen=True, kw_only=True)
class Targets:
    """IK targets for every output frame.

    Attributes:
        positions: Key point targets after contact handling. Shape: (T, K, 3).
        scaled: Key point targets before contact handling: the scaled human. Shape: (T, K, 3).
        human: The human's key points turned and moved as the root is and scaled by ``scale``,
            bone lengths unchanged (how the human's own points move). Shape: (T, K, 3).
        position_weights: Position cost per key point and frame. Shape: (T, K).
        frame_rots: Body orientation targets of the map's frames. Shape: (T, F, 3, 3).
        foot_rots: Foot body orientation targets. Shape: (T, 2, 3, 3).
        foot_weights: Foot orientation costs. Shape: (T, 2).
        contacts: Human contact flags per foot and point (ankle, toe). Shape: (T, 2, 2).
        scale: Root (leg-length) scale factor robot/human.
        human_ground: Measured human ground height [m], in the clip's frame.
        human_height: Estimated performer height [m].
        fps: Frame rate.
        yaw: Rotation about z applied to the human clip (heading alignment) [rad].
        origin: Point of the human clip moved to the world origin (before the rotation) [m].
        z_offset: Height added after scaling: a point of the scene at height ``z`` above the
            human ground maps to ``scale * z + z_offset`` on the robot's side: the clip's
            floor (``floor_height``) onto the robot's floor. (Not the planted toe joints onto
            the robot's toes: a toe joint rests 3-4 cm above the surface under it, so that
            mapping sank the scene by as much and lost every contact of a climbing clip.)
            [m].
    """

    positions: np.ndarray
    scaled: np.ndarray
    human: np.ndarray
    position_weights: np.ndarray
    frame_rots: np.ndarray
    foot_rots: np.ndarray
    foot_weights: np.ndarray
    contacts: np.ndarray
    scale: float
    human_ground: float
    human_height: float
    fps: float
    yaw: float
    origin: np.ndarray
    z_offset: float


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-9)


def _derived_frames(p: np.ndarray, m: RetargetMap, names: list[str]) -> np.ndarray:
    """Frames from key points. p: (..., K, 3) -> (..., F, 3, 3)."""
    idx = {n: i for i, n in enumerate(names)}
    out = []
    for fr in m.frames.values():
        left = p[..., idx[fr.left[1]], :] - p[..., idx[fr.left[0]], :]
        up = p[..., idx[fr.up[1]], :] - p[..., idx[fr.up[0]], :]
        out.append(frame_from_left_up(left, up))
    return np.stack(out, axis=-3) if out else np.zeros((*p.shape[:-2], 0, 3, 3))


def build_targets(
    clip: HumanClip, m: RetargetMap, robot: RobotGeometry, cfg: RetargetConfig
) -> Targets:
    """Build robot IK targets from a human clip (already at the output frame rate).

    Steps (all documented in docs/retargeting.md):

    1. Key points and derived frames are read from the human clip.
    2. Heading: the clip is turned about z so that the first frame's pelvis faces +x, and
       shifted so that the first frame's pelvis is above the origin.
    3. Heights are measured from the data, never a hard-coded offset: the body is shifted so
       that the planted toes stand at the robot's standing toe height, and each foot point's
       height is the robot's standing height plus the scaled height of the human point above
       its planted height (the 2nd percentile over the clip).
    4. Scale per segment: the root moves by the ratio of robot to human leg length; every
       other key point hangs from its parent along the human bone direction with the robot's
       own bone length, or, for points rigid on a body (hips on the pelvis, shoulders on the
       chest), at the robot's offset rotated by the human's derived frame.
    5. Feet: contacts are detected on the human; a planted heel or toe keeps the position
       where it landed for the whole contact, at the robot's standing height; a foot flat on
       the ground gets a flat orientation target.
    """
    names = list(m.keypoints)
    idx = {n: i for i, n in enumerate(names)}
    kps = list(m.keypoints.values())
    human = np.stack([clip.position(kp.human) for kp in kps], axis=1)  # (T, K, 3)
    T = human.shape[0]
    human, frames_h, yaw0, origin = _align_heading(clip, m, human, names)
    ground = _human_ground(human, m, idx)
    scale = _leg_scale(human, m, idx, robot, cfg)
    pos, frame_rots = _hang_keypoints(human, frames_h, m, names, robot, scale, ground)

    # Contacts on the human, per foot point (ankle, toe); a point's planted height is the 2nd
    # percentile of its height over the clip.
    sides = list(m.feet.values())
    foot_keys = np.array([[idx[f.ankle], idx[f.toe]] for f in sides])  # (2, 2)
    planted_h = np.percentile(human[:, foot_keys, 2], 2.0, axis=0)  # (2, 2)
    contacts = _detect_foot_contacts(human, foot_keys, planted_h, clip.fps, cfg)
    _calibrate_toes(pos, contacts, [idx[f.toe] for f in sides], robot)
    # Foot heights follow the human's clearance over the ground, scaled: a heel that skims the
    # floor at 3 cm on the human skims it at 3 cm x scale on the robot, whatever the leg
    # proportions make of the chain.
    above = human[:, foot_keys, 2] - planted_h  # (T, 2, 2)
    pos[:, foot_keys, 2] = robot.keypoints[foot_keys, 2] + scale * above
    heading = frames_h[:, 0, :, 0] if m.frames else None
    foot_rots, foot_weights = _foot_rotations(human, m, idx, contacts, robot, cfg, heading)
    # Soles keep the human's clearance: where the target foot pose (ankle position, foot
    # orientation) would put a contact point lower than the human foot's scaled clearance,
    # the foot's targets are lifted (a heel-down swing foot must not skim the floor).
    clearance = scale * np.maximum(above.min(axis=2), 0.0)  # (T, 2)
    _lift_soles(pos, foot_keys, foot_rots, clearance, robot)
    scaled = pos.copy()
    weights = np.tile(np.array([kp.weight for kp in kps]), (T, 1))
    _plant_points(pos, weights, contacts, foot_keys, robot, cfg)

    return Targets(
        positions=pos,
        scaled=scaled,
        human=scale * human,
        position_weights=weights,
        frame_rots=frame_rots,
        foot_rots=foot_rots,
        foot_weights=foot_weights,
        contacts=contacts,
        scale=scale,
        human_ground=ground,
        human_height=estimate_height(clip),
        fps=clip.fps,
        yaw=-yaw0,
        origin=origin,
        z_offset=scale * (ground - (cfg.floor_height or 0.0)),
    )


def _align_heading(
    clip: HumanClip, m: RetargetMap, human: np.ndarray, names: list[str]
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """The human's key points (T, K, 3) and derived frames (T, F, 3, 3) turned about z so that
    the first frame's pelvis faces +x and moved so that it stands above the origin; the yaw
    taken off [rad] and the point moved to the origin.

    Raises:
        MotionDataError: A frame's derived frame is undefined (its key points coincide or
            are aligned).
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        frames_h = _derived_frames(human, m, names)  # (T, F, 3, 3)
    bad = np.flatnonzero(~np.isfinite(frames_h).all(axis=(1, 2, 3)))
    if bad.size:
        raise MotionDataError(
            f"{clip.source}: key points coincide or are aligned (no left-right or up direction) "
            f"in {bad.size} frame(s), first at t = {bad[0] / clip.fps:.2f} s: a capture dropout? "
            f"(frames used: {', '.join(f'{n}: {fr.left} {fr.up}' for n, fr in m.frames.items())})"
        )
    root = names.index(m.root)
    if m.frames:
        fwd = frames_h[0, 0, :, 0]
        yaw0 = float(np.arctan2(fwd[1], fwd[0]))
    else:
        yaw0 = 0.0
    rot = axis_angle_matrix("z", np.asarray(-yaw0))
    origin = human[0, root].copy()
    origin[2] = 0.0
    human = (human - origin) @ rot.T
    frames_h = np.einsum("ij,tfjk->tfik", rot, frames_h)
    return human, frames_h, yaw0, origin


def _human_ground(human: np.ndarray, m: RetargetMap, idx: dict[str, int]) -> float:
    """The human's ground height: the lowest foot point (any point without feet), robustly
    over the clip (its 1st percentile) [m]."""
    foot_pts = [idx[f.ankle] for f in m.feet.values()] + [idx[f.toe] for f in m.feet.values()]
    if foot_pts:
        lowest = human[:, foot_pts, 2].min(axis=1)
        return float(np.percentile(lowest, 1.0))
    return float(np.percentile(human[:, :, 2].min(axis=1), 1.0))


def _bone(p: np.ndarray, a: int, b: int) -> np.ndarray:
    """The distance of key points ``a`` and ``b`` in ``p`` (..., K, 3). Shape: (...)."""
    return np.linalg.norm(p[..., a, :] - p[..., b, :], axis=-1)


def _leg_scale(
    human: np.ndarray, m: RetargetMap, idx: dict[str, int], robot: RobotGeometry,
    cfg: RetargetConfig,
) -> float:  # fmt: skip
    """The root's scale robot/human: ``cfg.scale``, or the ratio of the legs' mean lengths
    (ankle-knee-hip; the robot's from its zero pose, the human's bones as medians over the
    clip), or 1 without legs."""
    leg_h, leg_r = [], []
    for foot in m.feet.values():
        knee = m.keypoints[foot.ankle].parent
        hip = m.keypoints[knee].parent if knee else None
        if knee and hip:
            a, k, h = idx[foot.ankle], idx[knee], idx[hip]
            leg_h.append(np.median(_bone(human, a, k)) + np.median(_bone(human, k, h)))
            leg_r.append(_bone(robot.keypoints, a, k) + _bone(robot.keypoints, k, h))
    if cfg.scale is not None:
        return float(cfg.scale)
    return float(np.mean(leg_r) / np.mean(leg_h)) if leg_h else 1.0


def _hang_keypoints(
    human: np.ndarray, frames_h: np.ndarray, m: RetargetMap, names: list[str],
    robot: RobotGeometry, scale: float, ground: float,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Key-point targets before contact handling (T, K, 3), and the frames' body rotation
    targets (T, F, 3, 3): the root scaled by ``scale`` over the ground, every other point
    from its parent with the robot's bone length along the human bone, or at the robot's
    offset turned by the human's derived frame for a point rigid on a body."""
    idx = {n: i for i, n in enumerate(names)}
    root = idx[m.root]
    # Robot-frame offsets measured in the zero pose.
    frame_names = list(m.frames)
    frames_r = _derived_frames(robot.keypoints, m, names)  # (F, 3, 3)
    body_offsets = np.einsum("fji,fjk->fik", frames_r, robot.frame_body_rot)  # R_fr^T R_body

    pos = np.zeros_like(human)
    pos[:, root, :2] = scale * human[:, root, :2]
    pos[:, root, 2] = scale * (human[:, root, 2] - ground)
    for k, kp in enumerate(m.keypoints.values()):
        if kp.parent is None:
            continue
        par = idx[kp.parent]
        if kp.frame is not None:
            f = frame_names.index(kp.frame)
            local = frames_r[f].T @ (robot.keypoints[k] - robot.keypoints[par])
            pos[:, k] = pos[:, par] + frames_h[:, f] @ local
        else:
            length = _bone(robot.keypoints, k, par)
            pos[:, k] = pos[:, par] + length * _unit(human[:, k] - human[:, par])
    frame_rots = np.einsum("tfij,fjk->tfik", frames_h, body_offsets)
    return pos, frame_rots


def _detect_foot_contacts(
    human: np.ndarray, foot_keys: np.ndarray, planted_h: np.ndarray, fps: float,
    cfg: RetargetConfig,
) -> np.ndarray:  # fmt: skip
    """The human's floor contacts per foot and point (ankle, toe), from each point's height
    over its planted height ``planted_h`` (F, 2) and its horizontal speed. Shape: (T, F, 2)."""
    contacts = np.zeros((human.shape[0], len(foot_keys), 2), dtype=bool)
    for s_ in range(len(foot_keys)):
        for j in range(2):
            key = foot_keys[s_, j]
            contacts[:, s_, j] = detect_contacts(
                human[:, key, 2] - planted_h[s_, j],
                human[:, key, :2],
                fps,
                max_height=cfg.contact_height,
                max_speed=cfg.contact_speed,
                min_frames=cfg.contact_min_frames,
            )
    return contacts


def _calibrate_toes(
    pos: np.ndarray, contacts: np.ndarray, toe_idx: list[int], robot: RobotGeometry
) -> None:
    """Vertical calibration, in place: ``pos`` (T, K, 3) moved up or down so that the planted
    toes (the lowest toes' 1st percentile without plants) stand at the robot's standing toe
    height."""
    if toe_idx:
        toe_z = pos[:, toe_idx, 2]
        planted = contacts[:, :, 1]
        ref = np.median(toe_z[planted]) if planted.any() else np.percentile(toe_z.min(axis=1), 1)
        dz = float(robot.keypoints[toe_idx, 2].mean() - ref)
        pos[:, :, 2] += dz


def _lift_soles(
    pos: np.ndarray, foot_keys: np.ndarray, foot_rots: np.ndarray, clearance: np.ndarray,
    robot: RobotGeometry,
) -> None:  # fmt: skip
    """Lift each foot's ankle and toe targets in ``pos`` (in place) where the foot's contact
    points, at the target ankle position and foot orientation ``foot_rots`` (T, F, 3, 3),
    would be lower than the human foot's scaled ``clearance`` (T, F)."""
    for s_ in range(len(foot_keys)):
        a, t_ = foot_keys[s_]
        pts = robot.foot_points[s_]
        lowest = (
            pos[:, a, 2][:, None]
            + np.einsum("tj,nj->tn", foot_rots[:, s_, 2, :], pts[:, :3])
            - pts[:, 3]
        ).min(axis=1)
        lift = np.maximum(clearance[:, s_] - lowest, 0.0)
        pos[:, a, 2] += lift
        pos[:, t_, 2] += lift


def _plant_points(
    pos: np.ndarray, weights: np.ndarray, contacts: np.ndarray, foot_keys: np.ndarray,
    robot: RobotGeometry, cfg: RetargetConfig,
) -> None:  # fmt: skip
    """Planted foot points, in place: each keeps one position (the mean over the plant) at
    the robot's standing height, its weight times ``contact_weight_scale``; a plant ends where
    the human point drifts further than ``plant_radius``."""
    for s_ in range(len(foot_keys)):
        for j, key in enumerate(foot_keys[s_]):
            for start, stop in plant_segments(
                contacts[:, s_, j], pos[:, key, :2], cfg.plant_radius
            ):
                pos[start:stop, key, :2] = pos[start:stop, key, :2].mean(axis=0)
                pos[start:stop, key, 2] = robot.keypoints[key, 2]
                weights[start:stop, key] *= cfg.contact_weight_scale


def hold_still_points(
    tg: Targets,
    keys: np.ndarray,
    planted: np.ndarray,
    *,
    speed: float,
    radius: float,
    weight_scale: float,
) -> Targets:
    """Targets whose points ``keys`` stand still horizontally where the human's own points do.

    A robot key point's target hangs from its parent with the robot's bone length along the
    human's bone, so it moves when the human's body moves over a still foot (a toe resting on a
    box while the human climbs onto it). Where the human's point (``tg.human``) moves slower
    than ``speed`` horizontally, off the floor contacts (planted already), the target keeps the
    horizontal position it had when the point stopped, with its weight times ``weight_scale``;
    a hold ends where the human's point drifts further than ``radius`` from where it stopped
    (:func:`~humimic.retarget.contacts.plant_segments`).

    Args:
        tg: The targets. keys: Key point indices. Shape: (N,).
        planted: Frames where a point is planted on the floor already. Shape: (T, N).
        speed: Horizontal speed under which a human point is still [m/s].
        radius: Largest drift within one hold [m].
        weight_scale: Weight factor of a held point.
    """
    pos, weights = tg.positions.copy(), tg.position_weights.copy()
    for n, key in enumerate(keys):
        still = (step_speed(tg.human[:, key, :2], tg.fps) < speed) & ~planted[:, n]
        for start, stop in plant_segments(still, tg.human[:, key, :2], radius):
            if stop - start < 2:
                continue
            pos[start:stop, key, :2] = pos[start, key, :2]
            weights[start:stop, key] *= weight_scale
    return replace(tg, positions=pos, position_weights=weights)


def _foot_rotations(
    human: np.ndarray,
    m: RetargetMap,
    idx: dict[str, int],
    contacts: np.ndarray,
    robot: RobotGeometry,
    cfg: RetargetConfig,
    heading: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Foot orientation targets and costs.

    Yaw follows the human ankle-to-toe direction; pitch follows its elevation relative to the
    foot's elevation when flat on the ground; roll is zero. A foot whose heel and toe are both
    planted gets a flat target at the contact's mean yaw, with the contact cost.

    A foot pitched past the vertical (a running back-kick: the toe below and behind the
    ankle, the sole facing back or up) has its toe's horizontal direction opposite to where
    the foot faces. Where that direction points backward relative to ``heading`` (the body's
    forward direction per frame, the map's first frame: a foot cannot turn more than 90
    degrees from the pelvis), the foot faces the other way and is pitched by more than 90
    degrees; read naively, the target turns the foot, and the IK the whole leg, by 180 degrees
    (seen on CMU 09_01: hip yaw at its 2.8 rad limit for half the clip).

    Args:
        heading: The body's forward direction. Shape: (T, 3). None: every toe direction is
            taken as forward.

    Returns:
        Rotations (T, 2, 3, 3) and costs (T, 2).
    """
    sides = list(m.feet.values())
    T = human.shape[0]
    rots = np.zeros((T, len(sides), 3, 3))
    weights = np.full((T, len(sides)), cfg.foot_orientation_weight)
    for s, foot in enumerate(sides):
        d = human[:, idx[foot.toe]] - human[:, idx[foot.ankle]]
        back = np.zeros(T, dtype=bool)
        if heading is not None:
            back = np.einsum("tj,tj->t", d[:, :2], heading[:, :2]) < 0.0
        sign = np.where(back, -1.0, 1.0)
        yaw = np.unwrap(np.arctan2(sign * d[:, 1], sign * d[:, 0]))
        pitch = np.unwrap(np.arctan2(d[:, 2], sign * np.linalg.norm(d[:, :2], axis=-1)))
        both = contacts[:, s, 0] & contacts[:, s, 1]
        flat_pitch = float(np.median(pitch[both] if both.any() else pitch))
        pitch_rel = flat_pitch - pitch
        for start, stop in runs(both):
            pitch_rel[start:stop] = 0.0
            yaw[start:stop] = yaw[start:stop].mean()
            weights[start:stop, s] = cfg.foot_contact_orientation_weight
        rots[:, s] = (
            axis_angle_matrix("z", yaw) @ axis_angle_matrix("y", pitch_rel) @ robot.foot_body_rot[s]
        )
    return rots, weights
