"""The plots of ``humimic sysid diagnose``'s report (:func:`write_plots`): the held-out error
per joint, the worst joint's prediction over a held-out window, and the signature of each
claimed effect."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from humimic.io import atomic_write
from humimic.real2sim.correction import Correction
from humimic.real2sim.diagnose import FIT_END, Diagnosis, Finding
from humimic.real2sim.residual import KStepError, Predictor
from humimic.real2sim.robotlog import RobotLog
from humimic.sim.effects import EFFECTS


def write_plots(
    out: Path,
    log: RobotLog,
    nominal: Correction,
    corrected: Correction,
    diagnosis: Diagnosis,
    before: KStepError,
    after: KStepError,
    net_error: KStepError | None,
    held: Predictor,
) -> list[Path]:
    """Write the report's plots into ``out`` (PNG): the held-out error per joint, the worst
    joint over one held-out window, and each claimed effect's signature (gantry logs only).

    Returns:
        The plots' paths, in the order written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths: list[Path] = []

    def save(fig, name: str) -> None:
        path = out / name
        with atomic_write(path) as fh:
            fig.savefig(fh, format="png", dpi=90, bbox_inches="tight")
        plt.close(fig)
        paths.append(path)

    save(_error_bars(plt, log.joint_names, before, after, net_error), "residual_per_joint.png")
    save(_worst_window(plt, log, held, before, after, net_error), "prediction_window.png")
    _signature_plots(plt, save, log, nominal, corrected, diagnosis)
    return paths


def _error_bars(
    plt, names: tuple[str, ...], before: KStepError, after: KStepError, net_error: KStepError | None
):
    """The held-out error per joint: nominal, corrected (and with the residual net)."""
    fig, ax = plt.subplots(figsize=(8, 0.22 * len(names) + 1.2))
    y = np.arange(len(names))
    rows = [("nominal", before), ("corrected", after)]
    if net_error is not None:
        rows.append(("corrected + residual net", net_error))
    h = 0.8 / len(rows)
    for k, (label, e) in enumerate(rows):
        ax.barh(y + k * h, e.per_joint * 1e3, height=h, label=label)
    ax.set_yticks(y + 0.4 - h / 2, names, fontsize=7)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel("held-out k-step RMSE [mrad]")
    ax.legend(fontsize=8)
    ax.set_title("Prediction error per joint, last 30% of the log")
    return fig


def _worst_window(
    plt,
    log: RobotLog,
    held: Predictor,
    before: KStepError,
    after: KStepError,
    net_error: KStepError | None,
):
    """The worst joint (nominal) over its worst held-out window: log, nominal, corrected."""
    names = log.joint_names
    j = int(np.argmax(before.per_joint))
    w = int(np.argmax(np.abs(before.residual[:, :, j]).max(axis=1)))
    s = held.starts[w]
    t = log.t[s + 1 : s + 1 + held.samples] - log.t[s]
    measured = log.q[s + 1 : s + 1 + held.samples, j]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.plot(t, measured, "k.", ms=3, label="log")
    ax.plot(t, measured + before.residual[w, :, j], label="nominal")
    ax.plot(t, measured + after.residual[w, :, j], label="corrected")
    if net_error is not None:
        ax.plot(t, measured + net_error.residual[w, :, j], label="corrected + residual net")
    ax.set_xlabel("time in the window [s]")
    ax.set_ylabel(f"{names[j]} [rad]")
    ax.legend(fontsize=8)
    ax.set_title("Open-loop prediction from a logged state (held-out window)")
    return fig


def _signature_plots(
    plt,
    save: Callable[[Any, str], None],
    log: RobotLog,
    nominal: Correction,
    corrected: Correction,
    diagnosis: Diagnosis,
) -> None:
    """The signature that convinced the tool, per claimed effect, each saved by ``save``.

    Inverse dynamics of the logged motion on the floor needs the contact forces, which the
    log lacks, so a floating-base log gets no signature plot.
    """
    from humimic.real2sim.actuator_net import residual_torque

    claimed = diagnosis.claimed if log.base == "fixed" else []
    res_nom = res_cor = np.zeros(0)
    if claimed:  # Residual torques once, for every signature plot.
        idx = _fit_samples(log)
        res_nom, res_cor = residual_torque(nominal, log, idx), residual_torque(corrected, log, idx)
    for f in claimed:
        label, x, r0, r1, joint = _signature(f, log, nominal, res_nom, res_cor)
        fig, ax = plt.subplots(figsize=(5.5, 3.6))
        ax.plot(x, r0, ".", ms=2, alpha=0.5, label="nominal model")
        ax.plot(x, r1, ".", ms=2, alpha=0.5, label=f"with {f.effect}")
        lo, hi = np.percentile(np.concatenate([r0, r1]), [0.5, 99.5])
        pad = 0.1 * (hi - lo) + 1e-3
        ax.set_ylim(lo - pad, hi + pad)
        ax.set_xlabel(label)
        ax.set_ylabel(f"residual torque at {joint} [N m]")
        ax.legend(fontsize=8, markerscale=4)
        ax.set_title(f"{f.effect} on {f.target}: {f.value:.3g} {EFFECTS[f.effect].unit}")
        save(fig, f"signature_{f.effect}_{f.target}.png")


def _signature(
    f: Finding,
    log: RobotLog,
    nominal: Correction,
    res_nominal: np.ndarray,
    res_corrected: np.ndarray,
) -> tuple[str, np.ndarray, np.ndarray, np.ndarray, str]:
    """The signature plot of a claimed effect: the residual torque of its joint (nominal and
    corrected model, inverse dynamics on the fit part) against the variable the effect acts
    through."""

    names = log.joint_names
    idx = _fit_samples(log)
    cols = [names.index(n) for n in f.joints]
    nom_all = res_nominal[:, cols]
    cor_all = res_corrected[:, cols]
    # The joint where the correction changes the residual most.
    k = int(np.argmax(np.median(np.abs(nom_all), axis=0) - np.median(np.abs(cor_all), axis=0)))
    j, res_nom, res_cor = cols[k], nom_all[:, k], cor_all[:, k]
    c = log.command_index(log.t[idx] + 1e-7)
    err = log.cmd_q[c, j] - log.q[idx, j]
    if f.effect in ("coulomb_friction", "viscous_damping"):
        x, label = log.qd[idx, j], f"{names[j]} velocity [rad/s]"
    elif f.effect == "armature":
        dt = float(np.median(np.diff(log.t)))
        x, label = np.gradient(log.qd[:, j], dt)[idx], f"{names[j]} acceleration [rad/s^2]"
    elif f.effect in ("gain_mismatch", "torque_limit"):
        x = log.kp[c, j] * err - log.kd[c, j] * log.qd[idx, j]
        label = f"{names[j]} commanded PD torque [N m]"
    elif f.effect in ("delay", "lag"):
        rate = np.gradient(log.cmd_q[:, j], log.t_cmd)
        x, label = log.kp[c, j] * rate[c], f"kp x command rate at {names[j]} [N m/s]"
    else:  # Payload, encoder offset: through gravity.
        m, d = nominal.model, mujoco.MjData(nominal.model)
        x = np.empty(idx.size)
        for n, i in enumerate(idx):
            d.qpos[:] = log.q[i]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            mujoco.mj_rne(m, d, 0, d.qfrc_bias)
            x[n] = d.qfrc_bias[j]
        label = f"gravity torque at {names[j]} [N m]"
    return label, x, res_nom, res_cor, names[j]


def _fit_samples(log: RobotLog) -> np.ndarray:
    """Every other state sample of the fit part, after the first second (filters settle; in
    a short log, after the first half of the fit part)."""
    lo = int(np.searchsorted(log.t, log.t[0] + min(1.0, 0.5 * FIT_END * log.duration)))
    hi = int(np.searchsorted(log.t, log.t[0] + FIT_END * log.duration))
    return np.arange(lo, hi, 2)
