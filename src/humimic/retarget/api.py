"""Retarget a human clip to a robot: the one call behind ``humimic retarget``."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from humimic.configs.retarget import InteractionConfig, RetargetConfig
from humimic.datasets.clip import HumanClip
from humimic.datasets.scene import Scene
from humimic.errors import InputError
from humimic.motion import Motion, motion_from_qpos
from humimic.retarget.interaction import (
    InteractionMeshRetargeter,
    InteractionResult,
    contact_bodies,
    feet_planted,
)
from humimic.retarget.kinematic import KEYPOINT_SITE_PREFIX, KinematicRetargeter
from humimic.retarget.metrics import QualityReport, evaluate, evaluate_scene
from humimic.retarget.scene import scene_arrays
from humimic.retarget.targets import Targets
from humimic.robots.collision import self_collision_pairs
from humimic.robots.maps import RetargetMap, get_map, load_map_file
from humimic.robots.registry import get_robot

METHODS = ("kinematic", "interaction-mesh")
"""Retargeting methods (``humimic retarget --method``)."""


@dataclass(frozen=True, kw_only=True)
class RetargetOutput:
    """A retargeted motion and its report (a JSON-ready dict)."""

    motion: Motion
    report: dict[str, Any]


class Retargeter:
    """Kinematic retargeting of clips of one skeleton to one robot.

    Building it compiles the robot model once; :meth:`run` can then be called on many clips.
    """

    def __init__(
        self,
        robot: str,
        skeleton: str,
        cfg: RetargetConfig,
        map_file: str | Path | None = None,
        menagerie_root: str | Path | None = None,
        *,
        retarget_map: RetargetMap | None = None,
        method: str = "kinematic",
        mesh: InteractionConfig | None = None,
    ) -> None:
        t0 = time.perf_counter()
        if method not in METHODS:
            raise InputError(f"method {method!r}: expected one of {', '.join(METHODS)}")
        self.method = method
        self.robot = get_robot(robot)
        if retarget_map is not None:
            self.map: RetargetMap = retarget_map
        else:
            self.map = load_map_file(map_file) if map_file is not None else get_map(skeleton, robot)
        self.cfg = cfg
        self.interaction: InteractionMeshRetargeter | None = None
        if method == "interaction-mesh":
            self.interaction = InteractionMeshRetargeter(
                self.robot, self.map, cfg, mesh or InteractionConfig(),
                menagerie_root=menagerie_root,
            )  # fmt: skip
            self.ik = self.interaction.kin
        else:
            self.ik = KinematicRetargeter(self.robot, self.map, cfg, menagerie_root=menagerie_root)
        self.setup_seconds = time.perf_counter() - t0

    def validate(self, clip: HumanClip) -> None:
        """Check that the map fits this clip's joints (raises :class:`~humimic.errors.MapError`)."""
        self.map.validate(
            clip.names, {self.ik.model.body(b).name for b in range(self.ik.model.nbody)}
        )

    def check(self, clip: HumanClip) -> None:
        """Everything that can be wrong with a clip, before any IK: the map fits its joints,
        and targets can be built from every frame (raises :class:`InputError`)."""
        self.validate(clip)
        self.ik.targets(clip)

    def run(
        self,
        clip: HumanClip,
        progress: Callable[[int], Any] | None = None,
        scene: Scene | None = None,
    ) -> RetargetOutput:
        """Retarget one clip; the report holds the speed and the quality metrics.

        Args:
            clip: The human clip.
            progress: Called with the number of frames done (the interaction-mesh method
                makes two passes over the clip: kinematic, then interaction).
            scene: The clip's scene (required by, and only used by, ``interaction-mesh``).
        """
        self.validate(clip)
        if (scene is None) != (self.interaction is None):
            raise InputError(
                f"{clip.source}: the {self.method} method "
                + ("needs a scene (--scene)" if scene is None else "takes no scene")
            )
        t0 = time.perf_counter()
        extras: dict[str, np.ndarray] = {}
        scene_part: dict[str, Any] = {}
        if self.interaction is not None and scene is not None:
            ires = self.interaction.run(clip, scene, progress=progress)
            res, qpos, model = ires.kinematic, ires.qpos, ires.model
            scene_part, extras = self._scene_report(ires)
            z_offset = float(ires.scene_floor["z_offset_m"])
        else:
            res = self.ik.run(clip, progress=progress)
            z_offset = res.targets.z_offset
            qpos, model = res.qpos, self.ik.model
        tg = res.targets
        motion = motion_from_qpos(
            model,
            qpos,
            tg.fps,
            self.robot.name,
            extras={"human_contacts": tg.contacts, "keypoint_targets": tg.scaled, **extras},
            info=self._motion_info(clip, tg, z_offset),
        )
        seconds = time.perf_counter() - t0
        quality, per_frame = self._evaluate(model, qpos, tg)
        T = motion.num_frames
        report: dict[str, Any] = {
            "input": clip.source,
            "robot": self.robot.name,
            "skeleton": clip.skeleton,
            "map": self.map.source,
            "method": self.method,
            "frames": T,
            "fps": tg.fps,
            "source_frames": clip.num_frames,
            "source_fps": clip.fps,
            "seconds": seconds,
            "ik_seconds": res.solve_seconds,
            "setup_seconds": self.setup_seconds,
            "frames_per_second": T / seconds,
            "source_frames_per_second": clip.num_frames / seconds,
            "qp_iterations_per_frame": float(np.mean(res.iterations)),
            "relaxed_qp_iterations": res.relaxed_iterations,
            "retried_frames": res.retried_frames,
            "human_height_m": tg.human_height,
            "human_ground_m": tg.human_ground,
            "leg_scale": tg.scale,
            **dataclasses.asdict(quality),
            **scene_part,
        }
        extras = {**(motion.extras or {}), **{f"metric_{k}": v for k, v in per_frame.items()}}
        motion = dataclasses.replace(motion, extras=extras)
        return RetargetOutput(motion=motion, report=report)

    def _motion_info(self, clip: HumanClip, tg: Targets, z_offset: float) -> dict[str, Any]:
        """The motion file's ``info``: the clip's source and how it was mapped onto the robot
        (heading, origin, ground, scale, the scene's height offset, the key points)."""
        return {
            "source": str(Path(clip.source).resolve())
            if Path(clip.source).exists()
            else clip.source,
            "skeleton": clip.skeleton,
            "source_fps": clip.fps,
            "start_frame": int(clip.meta.get("start_frame", 0)),
            "human_yaw": tg.yaw,
            "human_origin": [float(x) for x in tg.origin],
            "human_ground": tg.human_ground,
            "human_scale": tg.scale,
            "human_z_offset": z_offset,  # The scene's placement: the clip's floor on ours.
            "keypoints": list(self.map.keypoints),
        }

    def _evaluate(
        self, model: mujoco.MjModel, qpos: np.ndarray, tg: Targets
    ) -> tuple[QualityReport, dict[str, np.ndarray]]:
        """The quality metrics of ``qpos`` on ``model`` against the targets
        (:func:`~humimic.retarget.metrics.evaluate`): the report and the per-frame arrays."""
        return evaluate(
            model,
            qpos,
            tg.fps,
            keypoint_sites=[KEYPOINT_SITE_PREFIX + n for n in self.map.keypoints],
            keypoint_targets=tg.scaled,
            foot_bodies=[f.body for f in self.map.feet.values()],
            # The pairs of the model measured (the interaction method's has the scene and the
            # sole corners, which renumber the robot's geoms after them).
            self_collision=self_collision_pairs(model, self.robot.root_body),
            floor_geom=self.robot.floor_geom,
            human_contact=np.asarray(tg.contacts.any(axis=(1, 2))),
            human_foot_contact=np.asarray(tg.contacts.any(axis=2)),
        )

    def _scene_report(
        self, ires: InteractionResult
    ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The scene metrics of the result and of its kinematic warm start (side by side), and
        the motion file's scene arrays (object tracks and meshes, per-frame metrics)."""
        assert self.interaction is not None
        tg, icfg = ires.kinematic.targets, self.interaction.icfg
        args = {
            "keypoint_bodies": contact_bodies(self.map),
            "human_contacts": ires.human_contacts,
            "foot_bodies": [f.body for f in self.map.feet.values()],
            "feet_planted": feet_planted(self.map, tg.contacts, ires.human_contacts),
            "contact_distance": icfg.contact_distance,
        }
        mine, frames = evaluate_scene(ires.model, ires.qpos, ires.scene, tg.fps, **args)
        kin, _ = evaluate_scene(ires.model, ires.kinematic.qpos, ires.scene, tg.fps, **args)
        T = ires.qpos.shape[0]
        part: dict[str, Any] = {
            **dataclasses.asdict(mine),
            "kinematic": dataclasses.asdict(kin),
            "interaction_seconds": ires.solve_seconds,
            "interaction_frames_per_second": T / ires.solve_seconds,
            "kinematic_seconds": ires.kinematic.solve_seconds,
            "interaction_qp_iterations_per_frame": float(np.mean(ires.iterations)),
            "interaction_relaxed_qp_iterations": ires.relaxed_iterations,
            "interaction_retried_frames": ires.retried_frames,
            "interaction_toe_limit_yielded_qp_iterations": ires.yielded_iterations,
            "mesh_scene_points_mean": float(np.mean(ires.mesh_scene_points)),
            "scene_spacing_mm": {
                o.name: 1e3 * s
                for o, s in zip(ires.scene.objects, ires.scene_spacings, strict=True)
            },
            "scene": ires.scene.source,
            "scene_objects": [o.name for o in ires.scene.objects],
            "scene_floor": ires.scene_floor,
        }
        extras = {
            **scene_arrays(ires.scene, T),
            "scene_contacts": ires.human_contacts,
            **{f"metric_{k}": v for k, v in frames.items()},
        }
        return part, extras
