"""A compiled model and the effects that act around it (what sysid scores without recompiling).

:class:`Correction` is the model sysid's predictor steps; :func:`apply_effect` adds an effect
of the vocabulary (:data:`~humimic.sim.effects.EFFECTS`) to it in place, meaning what the
effect's delta items (:meth:`~humimic.sim.effects.Effect.items`) mean on a spec.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.sim.contacts import floor_colliders, soft_geoms
from humimic.sim.joints import PLAY_SUFFIX, JointMap


@dataclass(kw_only=True)
class Correction:
    """A compiled fixed-base model and the effects that act around it.

    The model's own parameters hold friction, damping, armature, force limits, filter time
    constants and masses; three effects act outside it: a transport delay of the commands, an
    encoder offset (the drive and the log see ``q + offset``) and a gain scale (applied /
    commanded kp, kd).

    Attributes:
        model: Compiled fixed-base model; its joints are the log's joints, in order.
        delay: Transport delay of the commands per actuator [s]. Shape: (nu,).
        offset: Encoder offset per joint [rad]. Shape: (J,).
        gain_scale: Applied / commanded gains per actuator. Shape: (nu,).
    """

    model: mujoco.MjModel
    delay: np.ndarray
    offset: np.ndarray
    gain_scale: np.ndarray

    @classmethod
    def of(cls, model: mujoco.MjModel) -> Correction:
        """The model as it is. Transport delays the model carries natively (actuator
        ``delay``, as in a written model.xml) move to the correction, on a copy of the model:
        predictions start from logged states, which hold no control history."""
        delay = np.asarray(model.actuator_delay, dtype=np.float64).copy()
        if delay.any():
            model = copy.copy(model)
            model.actuator_delay[:] = 0.0
        return cls(model=model, delay=delay, offset=np.zeros(len(JointMap.of(model).names)),
                   gain_scale=np.ones(model.nu))  # fmt: skip

    def copy(self) -> Correction:
        return Correction(model=copy.copy(self.model), delay=self.delay.copy(),
                          offset=self.offset.copy(), gain_scale=self.gain_scale.copy())  # fmt: skip


def _dof(c: Correction, index: int) -> int:
    """The dof of log joint ``index`` (its motor side)."""
    return int(c.model.jnt_dofadr[int(JointMap.of(c.model).jid[index])])


def _act(c: Correction, index: int) -> int:
    """The actuator that drives log joint ``index``."""
    return int(np.flatnonzero(JointMap.of(c.model).act_log == index)[0])


def _set_const(m: mujoco.MjModel) -> None:
    mujoco.mj_setConst(m, mujoco.MjData(m))  # Constraint scaling depends on the inertia.


def _coulomb_friction(c: Correction, index: int, value: float) -> None:
    c.model.dof_frictionloss[_dof(c, index)] += value


def _viscous_damping(c: Correction, index: int, value: float) -> None:
    c.model.dof_damping[_dof(c, index)] += value


def _armature(c: Correction, index: int, value: float) -> None:
    c.model.dof_armature[_dof(c, index)] += value
    _set_const(c.model)


def _delay(c: Correction, index: int, value: float) -> None:
    """A transport delay: in a spec, the actuator's history buffer; on a compiled model, the
    correction's command delay (a history buffer changes the model's structure)."""
    c.delay[_act(c, index)] = value


def _lag(c: Correction, index: int, value: float) -> None:
    """A first-order filter between command and torque; on a compiled model the actuator must
    already be a ``filterexact`` one (see :func:`~humimic.sim.models.prediction_spec`)."""
    c.model.actuator_dynprm[_act(c, index), 0] = value


def _torque_limit(c: Correction, index: int, value: float) -> None:
    act = _act(c, index)
    c.model.actuator_forcelimited[act] = 1
    c.model.actuator_forcerange[act] = (-value, value)


def _gain_mismatch(c: Correction, index: int, value: float) -> None:
    c.gain_scale[_act(c, index)] *= value


def _encoder_offset(c: Correction, index: int, value: float) -> None:
    """The encoder reads ``value`` more than the true angle: in a spec, a joint whose reference
    (the coordinate of the body's modelled pose) is ``value``, its range moved with it; on a
    compiled model, the correction's offset of what the drive and the log see."""
    c.offset[index] = value


def _payload_mass(c: Correction, index: int, value: float) -> None:
    c.model.body_mass[index] += value
    _set_const(c.model)


def _contact_softness(c: Correction, index: int, value: float) -> None:
    """The time constant of the contact between a body's floor colliders and the floor
    (MuJoCo's solref[0], the damping ratio kept): a softer sole, or a softer floor under it,
    lets the foot sink and rock further under load. ``value`` replaces the model's. On a
    spec the body's colliding geoms get it; a body whose colliders do not decide the floor's
    contact (:func:`soft_geoms`) is refused."""
    ids = soft_geoms(c.model, index)
    if ids.size == 0:
        raise InputError(f"body {c.model.body(index).name!r} decides no floor contact")
    c.model.geom_solref[ids, 0] = value


def _contact_friction(c: Correction, index: int, value: float) -> None:
    """The sliding friction coefficient of a body's contact with the floor (MuJoCo's
    ``friction[0]`` of its floor colliders, which decide the contact: :func:`floor_colliders`):
    a polished or wet floor, or worn soles, let a loaded foot slide. ``value`` replaces the
    model's; torsional and rolling friction are kept."""
    ids = floor_colliders(c.model, index)
    if ids.size == 0:
        raise InputError(f"body {c.model.body(index).name!r} decides no floor contact")
    c.model.geom_friction[ids, 0] = value


def _backlash(c: Correction, index: int, value: float) -> None:
    """Play of ``value`` rad in the transmission: a second hinge on the same axis (the link
    side), free within +-value/2 and stopped stiffly at the ends; the drive turns the first
    (the motor side, with the rotor's armature) and the log reports the link, the sum of both.
    On a compiled model the play joint must exist (a model built with it); its range is set."""
    m = c.model
    play = m.joint(JointMap.of(m).names[index] + PLAY_SUFFIX).id
    m.jnt_range[play] = (-value / 2, value / 2)


ON_MODEL: dict[str, Callable[[Correction, int, float], None]] = {
    "coulomb_friction": _coulomb_friction,
    "viscous_damping": _viscous_damping,
    "armature": _armature,
    "delay": _delay,
    "lag": _lag,
    "torque_limit": _torque_limit,
    "gain_mismatch": _gain_mismatch,
    "encoder_offset": _encoder_offset,
    "payload_mass": _payload_mass,
    "contact_softness": _contact_softness,
    "contact_friction": _contact_friction,
    "backlash": _backlash,
}
"""How each effect acts on a compiled model: on its own parameters, or on the correction's
delay, offset and gain scale (a history buffer, an encoder reference and a gain change the
model's structure or what the log sees)."""


def apply_effect(c: Correction, effect: str, index: int, value: float) -> None:
    """Add one effect of the vocabulary to a compiled model in place (``index``: a joint of
    the log, or a body id for a body effect). Backlash needs a model with the joint's play
    joint."""
    ON_MODEL[effect](c, index, value)
