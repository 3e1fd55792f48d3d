"""Where a log's joints live in a model (fixed or floating base; it may carry backlash joints)."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.errors import InputError

PLAY_SUFFIX = "_backlash"
"""A joint named ``<joint>_backlash`` is the play of ``<joint>``'s transmission (see
:func:`~humimic.sim.effects`): the drive turns ``<joint>`` (the motor side),
the link sits at the sum of both, and the log reports the link."""


@dataclass(frozen=True, kw_only=True)
class JointMap:
    """Where a log's joints live in a model, which may carry backlash joints and, for a robot
    on the floor, a free joint (its base, not one of the log's joints).

    Attributes:
        names: The log's joints: the model's joints without the play joints and the free
            joint, in model order.
        jid, qadr, dadr: Model joint id, qpos and dof address of each (its motor side).
        play_q, play_d: qpos and dof address of its play joint, or -1. Shape: (J,).
        act_log: The log joint each actuator drives. Shape: (nu,).
    """

    names: tuple[str, ...]
    jid: np.ndarray
    qadr: np.ndarray
    dadr: np.ndarray
    play_q: np.ndarray
    play_d: np.ndarray
    act_log: np.ndarray

    @classmethod
    def of(cls, model: mujoco.MjModel) -> JointMap:
        all_names = [model.joint(j).name for j in range(model.njnt)]
        free = mujoco.mjtJoint.mjJNT_FREE
        jid = np.array([j for j, n in enumerate(all_names)
                        if not n.endswith(PLAY_SUFFIX) and model.jnt_type[j] != free])  # fmt: skip
        names = tuple(all_names[j] for j in jid)
        play = {
            n[: -len(PLAY_SUFFIX)]: j for j, n in enumerate(all_names) if n.endswith(PLAY_SUFFIX)
        }
        pid = np.array([play.get(n, -1) for n in names])
        where = {int(j): i for i, j in enumerate(jid)}
        act_log = np.array(
            [where.get(int(model.actuator_trnid[a, 0]), -1) for a in range(model.nu)]
        )
        if (act_log < 0).any():
            raise InputError("an actuator drives a joint that is not one of the robot's joints")
        return cls(
            names=names, jid=jid, qadr=model.jnt_qposadr[jid], dadr=model.jnt_dofadr[jid],
            play_q=np.where(pid >= 0, model.jnt_qposadr[np.maximum(pid, 0)], -1),
            play_d=np.where(pid >= 0, model.jnt_dofadr[np.maximum(pid, 0)], -1), act_log=act_log,
        )  # fmt: skip

    def link(self, x: np.ndarray, play: np.ndarray, base: np.ndarray) -> np.ndarray:
        """Per log joint, ``x[base]`` plus ``x[play]`` where there is play (``x``: (..., n))."""
        out = x[..., base].copy()
        has = play >= 0
        out[..., has] += x[..., play[has]]
        return out
