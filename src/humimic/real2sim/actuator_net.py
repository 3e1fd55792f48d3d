"""A learned residual for what no known effect explains: a residual actuator network
(:class:`ResidualActuatorNet`, trained by :func:`fit_residual_net`).
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

import mujoco
import numpy as np
import torch
from scipy.signal import savgol_filter

from humimic.errors import InputError
from humimic.io import atomic_write
from humimic.real2sim.residual import Correction, set_gains
from humimic.real2sim.robotlog import RobotLog
from humimic.sim.joints import JointMap
from humimic.sim.models import PHYSICS_DT

_HALF_WINDOW = 4
"""Half the Savitzky-Golay window [samples] that smooths velocities and accelerations."""


@dataclass(frozen=True, kw_only=True)
class NetConfig:
    """Residual actuator network and its training.

    Attributes:
        history: State samples of position error and velocity per joint (4 = 20 ms at 200 Hz).
        hidden: Hidden layer widths.
        steps: Adam steps. batch: Rows (sample x joint) per step. lr: Learning rate.
        seed: Torch seed (training is deterministic on the CPU).
    """

    history: int = 4
    hidden: tuple[int, ...] = (64, 64)
    steps: int = 1500
    batch: int = 8192
    lr: float = 3e-3
    seed: int = 0


class ResidualActuatorNet(torch.nn.Module):
    """Joint history -> residual joint torque [N m], for every joint at once.

    After the diagnosis has added the effects it can name, the torque the corrected model
    still misses is measured by inverse dynamics on the fit part of the log
    (:func:`residual_torque`: measured positions, Savitzky-Golay smoothed velocities and
    accelerations, ``mj_inverse``, minus the modelled drive torque). A small MLP, shared by all
    joints (a one-hot joint code tells them apart), learns it from the joint's recent history
    of position errors (command in force minus measured position) and velocities, as in the
    actuator network of Hwangbo et al. ("Learning agile and dynamic motor skills for legged
    robots", Science Robotics 2019), and of positions (for what depends on where the joint is,
    such as a cable pulling on it). At prediction time it runs at the state rate, closed loop,
    adding its torque to the corrected model (see
    :meth:`~humimic.real2sim.residual.Predictor.run_with_torque`).
    """

    in_shift: torch.Tensor
    in_scale: torch.Tensor
    out_scale: torch.Tensor

    def __init__(self, joint_names: tuple[str, ...], config: NetConfig) -> None:
        super().__init__()
        self.joint_names = tuple(joint_names)
        self.config = config
        J, H = len(joint_names), config.history
        layers: list[torch.nn.Module] = []
        width = 3 * H + J
        for h in config.hidden:
            layers += [torch.nn.Linear(width, h), torch.nn.Softsign()]
            width = h
        layers.append(torch.nn.Linear(width, 1))
        self.mlp = torch.nn.Sequential(*layers)
        self.register_buffer("in_shift", torch.zeros(3, J, dtype=torch.float64))
        self.register_buffer("in_scale", torch.ones(3, J, dtype=torch.float64))
        self.register_buffer("out_scale", torch.ones(J, dtype=torch.float64))

    def forward(
        self, errors: torch.Tensor, velocities: torch.Tensor, positions: torch.Tensor
    ) -> torch.Tensor:
        """errors, velocities, positions: (B, H, J) oldest first -> torque (B, J)."""
        B, _, J = errors.shape
        x = torch.cat([(v - self.in_shift[i]) / self.in_scale[i]
                       for i, v in enumerate((errors, velocities, positions))], dim=1)  # fmt: skip
        x = x.permute(0, 2, 1)  # (B, J, 3H)
        code = torch.eye(J, dtype=x.dtype).expand(B, J, J)
        y = self.mlp(torch.cat([x, code], dim=2).float()).squeeze(-1).double()
        return y * self.out_scale

    def torque(
        self, errors: np.ndarray, velocities: np.ndarray, positions: np.ndarray
    ) -> np.ndarray:
        """NumPy in and out (for the predictor)."""
        with torch.no_grad():
            return self(*(torch.from_numpy(a) for a in (errors, velocities, positions))).numpy()

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write weights, scales and configuration (loadable with ``weights_only=True``)."""
        blob = {
            "format": "humimic-residual-actuator-net/1",
            "joint_names": list(self.joint_names),
            "config": {**asdict(self.config), "hidden": list(self.config.hidden)},
            "state_dict": self.state_dict(),
        }
        with atomic_write(path) as f:
            torch.save(blob, f)
        return Path(path)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> ResidualActuatorNet:
        try:
            blob = torch.load(path, weights_only=True)
            cfg = dict(blob["config"])
            net = cls(tuple(blob["joint_names"]),
                      NetConfig(**{**cfg, "hidden": tuple(cfg["hidden"])}))  # fmt: skip
            net.load_state_dict(blob["state_dict"])
        except (OSError, KeyError, TypeError, RuntimeError) as e:
            raise InputError(f"{path}: not a residual actuator network ({e})") from None
        return net.eval()


def _filter_states(c: Correction, log: RobotLog, idx: np.ndarray) -> np.ndarray:
    """Drive filter states (``lag``) at the given state samples, from the command stream."""
    m = c.model
    act = np.zeros((idx.size, m.nu))
    tau = m.actuator_dynprm[:, 0]
    for a in np.flatnonzero(tau > 0):
        j = int(JointMap.of(m).act_log[a])
        clock = np.arange(0.0, float(log.t[idx[-1]]) + PHYSICS_DT / 2, PHYSICS_DT)
        u = log.cmd_q[log.command_index(clock - c.delay[a] + 1e-7), j] - c.offset[j]
        alpha = 1.0 - np.exp(-PHYSICS_DT / tau[a])
        x, trace = u[0], np.empty_like(u)
        for k in range(u.size):
            trace[k] = x
            x += alpha * (u[k] - x)
        act[:, a] = trace[np.minimum(np.round(log.t[idx] / PHYSICS_DT).astype(int), u.size - 1)]
    return act


def residual_torque(c: Correction, log: RobotLog, idx: np.ndarray) -> np.ndarray:
    """Torque the corrected model misses at the given state samples (N, J): inverse dynamics
    of the measured motion minus the modelled drive torque and feed-forward."""
    m = c.model
    dt = float(np.median(np.diff(log.t)))
    window = 2 * _HALF_WINDOW + 1
    qd = savgol_filter(log.qd, window, 2, axis=0)
    qdd = savgol_filter(log.qd, window, 2, deriv=1, delta=dt, axis=0)
    jm = JointMap.of(m)
    act_joint = jm.act_log  # The log joint of each actuator.
    saved = m.actuator_gainprm.copy(), m.actuator_biasprm.copy()
    data = mujoco.MjData(m)
    out = np.empty((idx.size, len(jm.names)))
    acts = _filter_states(c, log, idx)
    scale = np.ones(len(jm.names))
    scale[act_joint] = c.gain_scale
    filtered = np.flatnonzero(m.actuator_actadr >= 0)
    lagged = m.actuator_dynprm[:, 0] > 0
    # The command each drive acts on (after its delay) at every sample.
    in_force = np.stack([log.command_index(log.t[idx] - c.delay[a] + 1e-7)
                         for a in range(m.nu)], axis=1)  # fmt: skip
    try:
        set_gains(c, log.kp[0][act_joint], log.kd[0][act_joint])
        for n, i in enumerate(idx):
            # Play joints (backlash) are taken as closed: the motion is the link's.
            data.qpos[:] = 0.0
            data.qvel[:] = 0.0
            data.qacc[:] = 0.0
            data.qpos[jm.qadr] = log.q[i] - c.offset
            data.qvel[jm.dadr] = qd[i]
            data.qacc[jm.dadr] = qdd[i]
            data.ctrl[:] = log.cmd_q[in_force[n], act_joint] - c.offset[act_joint]
            for a in filtered:
                data.act[m.actuator_actadr[a]] = acts[n, a] if lagged[a] else data.ctrl[a]
            now = log.command_index(log.t[i] + 1e-7)
            ff = log.cmd_tau[now] + scale * log.kd[now] * log.cmd_qd[now]
            mujoco.mj_inverse(m, data)
            mujoco.mj_fwdActuation(m, data)
            out[n] = (data.qfrc_inverse - data.qfrc_actuator)[jm.dadr] - ff
    finally:
        m.actuator_gainprm[:], m.actuator_biasprm[:] = saved
    return out


def _history(log: RobotLog, idx: np.ndarray, H: int) -> tuple[np.ndarray, ...]:
    hist = np.maximum(idx[:, None] + np.arange(1 - H, 1)[None, :], 0)
    cmd = log.cmd_q[log.command_index(log.t[hist] + 1e-7)]
    return cmd - log.q[hist], log.qd[hist].copy(), log.q[hist].copy()


def fit_residual_net(
    c: Correction, log: RobotLog, span: tuple[float, float], config: NetConfig | None = None
) -> tuple[ResidualActuatorNet, dict]:
    """Train the network on a span of the log. Returns it and training figures."""
    config = config or NetConfig()
    torch.manual_seed(config.seed)
    lo = int(np.searchsorted(log.t, log.t[0] + span[0] * log.duration))
    hi = int(np.searchsorted(log.t, log.t[0] + span[1] * log.duration, side="right"))
    idx = np.arange(max(lo, config.history), hi)
    # Samples whose history or smoothing window (residual_torque) spans a gap are left out.
    back = np.maximum(idx - max(config.history - 1, _HALF_WINDOW), 0)
    idx = idx[log.unbroken(back, np.minimum(idx + _HALF_WINDOW, log.t.size - 1) - back)]
    if idx.size == 0:
        raise InputError(f"{log.where}: no state sample of the fit part lies away from a gap")
    target = residual_torque(c, log, idx)
    inputs = _history(log, idx, config.history)
    net = ResidualActuatorNet(log.joint_names, config)
    for i, (a, least) in enumerate(zip(inputs, (1e-4, 1e-3, 1e-3), strict=True)):
        net.in_shift[i] = torch.from_numpy(a.mean(axis=(0, 1)))
        net.in_scale[i] = torch.from_numpy(np.maximum(a.std(axis=(0, 1)), least))
    net.out_scale[:] = torch.from_numpy(np.maximum(target.std(axis=0), 1e-3))
    E, V, P = (torch.from_numpy(a) for a in inputs)
    Y = torch.from_numpy(target)
    opt = torch.optim.Adam(net.mlp.parameters(), lr=config.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, config.steps)
    per = max(1, config.batch // len(log.joint_names))
    gen = torch.Generator().manual_seed(config.seed)
    for _ in range(config.steps):
        b = torch.randint(0, idx.size, (per,), generator=gen)
        loss = torch.mean(((net(E[b], V[b], P[b]) - Y[b]) / net.out_scale) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    net.eval()
    with torch.no_grad():
        fit = net(E, V, P).numpy()
    explained = 1.0 - float(np.sum((target - fit) ** 2) / max(np.sum(target**2), 1e-30))
    return net, {"samples": int(idx.size), "torque_variance_explained": explained,
                 "residual_torque_rms": float(np.sqrt(np.mean(target**2)))}  # fmt: skip
