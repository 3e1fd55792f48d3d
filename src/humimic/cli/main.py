"""``humimic``: one console script, one subcommand per verb (tyro over dataclasses); each
command group's dataclasses and runners live in a module of this package."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from typing import Annotated, Any

import tyro

from humimic.cli import fetch, retarget, robots, sysid, track, view
from humimic.cli.flags import validate_command
from humimic.configs.jobs import (
    DemoSettings,
    EvalSettings,
    ExportSettings,
    ImitateSettings,
    LoopSettings,
)
from humimic.configs.runs import (
    DistillSettings,
    TrainSettings,
)
from humimic.errors import HumimicError, InputError

RUNNERS: dict[type, Callable[[Any], int | None]] = {
    retarget.RetargetCommand: retarget.run_retarget,
    retarget.RefineCommand: retarget.run_refine,
    retarget.ReplayCommand: retarget.run_replay,
    DemoSettings: track.run_demo,
    retarget.ConvertCommand: retarget.run_convert,
    view.ViewCommand: view.run_view,
    robots.RobotsList: robots.run_list,
    robots.RobotsExport: robots.run_export,
    robots.RobotsAdd: robots.run_add,
    sysid.SysidSimulate: sysid.run_simulate,
    sysid.SysidResidual: sysid.run_residual,
    sysid.SysidDiagnose: sysid.run_diagnose,
    sysid.SysidImport: sysid.run_import,
    fetch.FetchCommand: fetch.run_fetch,
    TrainSettings: track.run_train,
    DistillSettings: track.run_distill,
    EvalSettings: track.run_eval,
    ExportSettings: track.run_export,
    LoopSettings: track.run_loop,
    ImitateSettings: track.run_imitate,
}
"""Command type -> its runner, which returns the exit code (None: 0)."""


def commands(argv: list[str]) -> Any:
    """The subcommands, as the type tyro parses, for a command line: ``retarget``'s
    ``--ik.*`` defaults are those of the ``--preset`` on it (found before parsing)."""
    return (
        Annotated[retarget.RetargetCommand,
                  tyro.conf.subcommand("retarget", default=retarget.retarget_defaults(argv))]
        | Annotated[retarget.RefineCommand, tyro.conf.subcommand("refine")]
        | Annotated[retarget.ReplayCommand, tyro.conf.subcommand("replay")]
        | Annotated[DemoSettings, tyro.conf.subcommand("demo")]
        | Annotated[view.ViewCommand, tyro.conf.subcommand("view")]
        | Annotated[retarget.ConvertCommand, tyro.conf.subcommand("convert")]
        | Annotated[robots.RobotsCommand, tyro.conf.subcommand("robots")]
        | Annotated[sysid.SysidCommand, tyro.conf.subcommand("sysid")]
        | Annotated[fetch.FetchCommand, tyro.conf.subcommand("fetch")]
        | Annotated[TrainSettings, tyro.conf.subcommand("train")]
        | Annotated[DistillSettings, tyro.conf.subcommand("distill")]
        | Annotated[EvalSettings, tyro.conf.subcommand("eval")]
        | Annotated[ExportSettings, tyro.conf.subcommand("export")]
        | Annotated[LoopSettings, tyro.conf.subcommand("loop")]
        | Annotated[ImitateSettings, tyro.conf.subcommand("imitate")]
    )  # fmt: skip


def parse(argv: list[str]) -> Any:
    """The command a command line asks for (a parse error exits with code 2, ``--help``
    with 0); a command group (``robots``, ``sysid``) gives its subcommand."""
    cmd = tyro.cli(
        commands(argv), args=argv, prog="humimic", config=(tyro.conf.OmitSubcommandPrefixes,)
    )
    if isinstance(cmd, robots.RobotsCommand | sysid.SysidCommand):
        return cmd.command
    return cmd


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``humimic`` console script. Bad input exits with code 2; a
    closed output pipe (``humimic ... | head``) ends it quietly with code 141, as a shell
    command killed by SIGPIPE."""
    try:
        return _run(sys.argv[1:] if argv is None else argv)
    except BrokenPipeError:
        # Python's advice (signal docs, "Note on SIGPIPE"): point stdout at devnull so that
        # the interpreter's final flush does not raise again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


def _run(argv: list[str]) -> int:
    cmd = parse(argv)
    try:
        validate_command(cmd)
        return RUNNERS[type(cmd)](cmd) or 0
    except InputError as e:
        print(f"humimic: error: {e}", file=sys.stderr)
        return 2
    except HumimicError as e:
        print(f"humimic: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("humimic: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
