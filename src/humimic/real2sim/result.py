"""What a diagnosis hands on: :class:`SysidResult`, the typed form of its ``report.json``.

``humimic sysid diagnose`` and the loop's sysid stage return one; the claimed effects become a
physics file (:meth:`SysidResult.physics`) that training and evaluation read.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from humimic.errors import InputError
from humimic.sim.delta import RobotDelta
from humimic.sim.effects import EFFECTS, Injection, as_delta
from humimic.sim.physics import Physics

SYSID_SCHEMA = 1
"""Version of ``report.json`` this release writes (its ``schema``; files without one are 1)."""

CLAIM = 0.5
"""Confidence at or above which an effect is claimed."""


@dataclass(frozen=True, kw_only=True)
class ReportedEffect:
    """One effect the diagnosis sized, claimed or not.

    Attributes:
        effect: A name of the vocabulary (:data:`~humimic.sim.effects.EFFECTS`).
        targets: The joints, or bodies, it acts on.
        group: The group it was found for (e.g. ``all_soles``), or ``None``.
        value: Its size, in the effect's unit.
        confidence: 0-1; claimed from :data:`CLAIM`.
        partial: Whether its joints stay far above their noise floor after the correction.
    """

    effect: str
    targets: tuple[str, ...]
    group: str | None
    value: float
    confidence: float
    partial: bool

    @property
    def claimed(self) -> bool:
        return self.confidence >= CLAIM

    @property
    def where(self) -> str:
        """What it acts on, as messages name it."""
        return self.group or ", ".join(self.targets)

    @property
    def unit(self) -> str:
        return EFFECTS[self.effect].unit

    def injection(self) -> Injection:
        return Injection(effect=self.effect, targets=self.targets, value=self.value)


@dataclass(frozen=True, kw_only=True)
class SysidResult:
    """A diagnosis of one robot log.

    Attributes:
        robot: The robot's registry name.
        log: The log's path.
        before_rad: Held-out k-step RMS error of the nominal model [rad].
        after_rad: The same, corrected by the claimed effects [rad].
        findings: Every effect sized, claimed or not.
        unexplained: Whether much of the error is left and some joint still stands out.
        unexplained_joints: Those joints.
        not_identifiable: (effect, number of joints) the log cannot tell apart.
        seconds: The diagnosis's wall time.
        report: The whole ``report.json`` content (plots, noise floors, the residual network).
    """

    robot: str
    log: str
    before_rad: float
    after_rad: float
    findings: tuple[ReportedEffect, ...]
    unexplained: bool
    unexplained_joints: tuple[str, ...]
    not_identifiable: tuple[tuple[str, int], ...]
    seconds: float
    report: dict[str, Any]

    @property
    def claims(self) -> tuple[ReportedEffect, ...]:
        """The claimed findings."""
        return tuple(f for f in self.findings if f.claimed)

    @property
    def delta(self) -> RobotDelta:
        """The claimed effects as a robot delta (a residual network is not part of it)."""
        return as_delta(f.injection() for f in self.claims)

    def physics(self, *, name: str, robot: str | None) -> Physics:
        """The claimed effects as physics (what ``--physics`` reads, once written with
        :func:`~humimic.sim.physics.write_physics`)."""
        return Physics(
            name=name,
            description=f"effects claimed by sysid diagnose on {self.log or 'a log'}",
            robot=robot,
            effects=tuple(f.injection() for f in self.claims),
        )

    @classmethod
    def of(cls, report: Mapping[str, Any], where: str = "report.json") -> SysidResult:
        """The result a ``report.json`` content describes.

        Raises:
            InputError: A newer schema, or a field missing or of the wrong kind (naming
                ``where``).
        """
        schema = report.get("schema", 1)
        if not isinstance(schema, int) or schema > SYSID_SCHEMA:
            raise InputError(
                f"{where}: schema {schema!r} is newer than this humimic reads "
                f"({SYSID_SCHEMA}): upgrade humimic"
            )
        try:
            return cls(
                robot=str(report.get("robot", "")),
                log=str(report.get("log", "")),
                before_rad=float(report["error_before"]["kstep_rmse_rad"]),
                after_rad=float(report["error_after"]["kstep_rmse_rad"]),
                findings=tuple(_finding(e) for e in report.get("effects", [])),
                unexplained=bool(report.get("unexplained", False)),
                unexplained_joints=tuple(report.get("unexplained_joints", [])),
                not_identifiable=tuple(_unidentified(report)),
                seconds=float(report.get("seconds", 0.0)),
                report=dict(report),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{where}: not a sysid report ({type(e).__name__}: {e})") from None

    @classmethod
    def read(cls, path: str | os.PathLike[str]) -> SysidResult:
        """Read a ``report.json`` that ``humimic sysid diagnose`` wrote.

        Raises:
            InputError: A missing or unreadable file, or not a sysid report (naming it).
        """
        p = Path(path)
        try:
            data = json.loads(p.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(f"{p}: cannot read a sysid report: {e}") from None
        if not isinstance(data, dict):
            raise InputError(f"{p}: not a sysid report (expected a JSON object)")
        return cls.of(data, str(p))


def _unidentified(report: Mapping[str, Any]) -> list[tuple[str, int]]:
    return [(str(s["effect"]), len(s["joints"])) for s in report.get("not_identifiable", [])]


def _finding(e: Mapping[str, Any]) -> ReportedEffect:
    if e["effect"] not in EFFECTS:
        raise ValueError(f"unknown effect {e['effect']!r}")
    targets = (e["body"],) if "body" in e else tuple(e.get("bodies") or e["joints"])
    return ReportedEffect(effect=str(e["effect"]), targets=tuple(map(str, targets)), group=e.get("group"),
                   value=float(e["params"]["value"]), confidence=float(e["confidence"]),
                   partial=bool(e.get("partial", False)))  # fmt: skip


__all__ = ["CLAIM", "SYSID_SCHEMA", "ReportedEffect", "SysidResult"]
