"""Retarget a human clip to a robot: the one call behind ``humimic retarget``."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from humimic.configs.retarget import RetargetConfig
from humimic.datasets.clip import HumanClip
from humimic.motion import Motion, motion_from_qpos
from humimic.retarget.kinematic import (
    KEYPOINT_SITE_PREFIX,
    KinematicRetargeter,
    self_collision_geoms,
)
from humimic.retarget.metrics import evaluate
from humimic.robots.maps import RetargetMap, get_map, load_map_file
from humimic.robots.registry import get_robot


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
    ) -> None:
        t0 = time.perf_counter()
        self.robot = get_robot(robot)
        self.map: RetargetMap = (
            load_map_file(map_file) if map_file is not None else get_map(skeleton, robot)
        )
        self.cfg = cfg
        self.ik = KinematicRetargeter(self.robot, self.map, cfg, menagerie_root=menagerie_root)
        self.setup_seconds = time.perf_counter() - t0

    def validate(self, clip: HumanClip) -> None:
        """Check that the map fits this clip's joints (raises :class:`MapError`)."""
        self.map.validate(
            clip.names, {self.ik.model.body(b).name for b in range(self.ik.model.nbody)}
        )

    def check(self, clip: HumanClip) -> None:
        """Everything that can be wrong with a clip, before any IK: the map fits its joints,
        and targets can be built from every frame (raises :class:`InputError`)."""
        self.validate(clip)
        self.ik.targets(clip)

    def run(self, clip: HumanClip, progress: Callable[[int], Any] | None = None) -> RetargetOutput:
        """Retarget one clip; the report holds the speed and the quality metrics."""
        self.validate(clip)
        t0 = time.perf_counter()
        res = self.ik.run(clip, progress=progress)
        tg = res.targets
        motion = motion_from_qpos(
            self.ik.model,
            res.qpos,
            tg.fps,
            self.robot.name,
            extras={"human_contacts": tg.contacts, "keypoint_targets": tg.scaled},
            info={
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
                "human_z_offset": tg.z_offset,
                "keypoints": list(self.map.keypoints),
            },
        )
        seconds = time.perf_counter() - t0
        quality, per_frame = evaluate(
            self.ik.model,
            res.qpos,
            tg.fps,
            keypoint_sites=[KEYPOINT_SITE_PREFIX + n for n in self.map.keypoints],
            keypoint_targets=tg.scaled,
            foot_bodies=[f.body for f in self.map.feet.values()],
            self_collision=self_collision_geoms(self.ik.model, self.robot),
            floor_geom=self.robot.floor_geom,
            human_contact=np.asarray(tg.contacts.any(axis=(1, 2))),
        )
        T = motion.num_frames
        report: dict[str, Any] = {
            "input": clip.source,
            "robot": self.robot.name,
            "skeleton": clip.skeleton,
            "map": self.map.source,
            "method": "kinematic",
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
            "human_height_m": tg.human_height,
            "human_ground_m": tg.human_ground,
            "leg_scale": tg.scale,
            **dataclasses.asdict(quality),
        }
        extras = {**(motion.extras or {}), **{f"metric_{k}": v for k, v in per_frame.items()}}
        motion = dataclasses.replace(motion, extras=extras)
        return RetargetOutput(motion=motion, report=report)
