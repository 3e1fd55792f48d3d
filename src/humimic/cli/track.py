"""``humimic train``, ``distill``, ``eval``, ``export`` and ``loop``: tracking policies (their
settings are :mod:`humimic.configs.runs`)."""

from __future__ import annotations

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


def run_train(cmd: TrainSettings) -> None:
    """Run ``humimic train`` (refining its motion first when the run needs a refined one:
    :func:`~humimic.pipeline.reference.prepare_reference`, inside ``--max-minutes``)."""
    import time

    from humimic.pipeline.reference import prepare_reference
    from humimic.tracking.distributed import Ranks
    from humimic.tracking.train import train

    started = time.perf_counter()
    ranks = Ranks.from_env()
    settings = prepare_reference(cmd, quiet=cmd.quiet, may_refine=not ranks.distributed)
    last = train(settings, started=started)
    if last and ranks.main:  # Under torchrun, rank 0 speaks for the run.
        print(f"{cmd.out}: {int(last['iteration'])} iterations, mean reward "
              f"{last.get('mean_reward', float('nan')):.4g}, mean episode length "
              f"{last.get('mean_episode_length', float('nan')):.1f} steps")  # fmt: skip


def run_distill(cmd: DistillSettings) -> None:
    """Run ``humimic distill``."""
    from humimic.tracking.distill import distill

    row = distill(cmd)
    if "loss_behavior" in row:
        print(f"{cmd.out}: {int(row['iteration'])} iterations, imitation loss "
              f"{row['loss_behavior']:.4g}, mean episode length "
              f"{row['mean_episode_length']:.1f} steps")  # fmt: skip


def run_eval(cmd: EvalSettings) -> None:
    """Run ``humimic eval``."""
    from humimic.tracking.evaluate import evaluate

    result = evaluate(cmd)
    if "physics" in result:
        print(f"physics {result['physics']['name']}: {result['physics']['description']}")
    for clip, r in result.get("clips", {}).items():
        m = r["policy"]
        print(f"{clip} ({r['frames']} frames): policy success {100 * m['success_rate']:.0f}%, "
              f"global MPJPE {m['mpjpe_global_mm']:.1f} mm, root-relative "
              f"{m['mpjpe_root_mm']:.1f} mm; open loop success "
              f"{100 * r['open_loop']['success_rate']:.0f}%")  # fmt: skip
    if "clips" in result:
        print(f"mean over the {len(result['clips'])} clips:")
    for name in ("policy", "open_loop"):
        m = result[name]
        print(f"{name:9s}: success {100 * m['success_rate']:.0f}%, global MPJPE "
              f"{m['mpjpe_global_mm']:.1f} mm, root-relative {m['mpjpe_root_mm']:.1f} mm, "
              f"joint error {m['joint_error_rad']:.3f} rad")  # fmt: skip
    if "protocols" in result:
        print_protocols(result["protocols"])
    if cmd.out is not None:
        print(f"wrote {cmd.out} and {result['failures_png']} (where episodes fail)")
    if "mcap" in result:
        print(f"wrote {result['mcap']} (humimic view {result['mcap']})")


def print_protocols(p: dict) -> None:
    """The field's protocols (:mod:`humimic.tracking.protocols`): a line per clip, then each
    protocol's totals."""

    def fate(r: dict) -> str:
        return "ok" if not r["failed"] else f"fails at step {r['fail_step']}"

    def mm(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.1f}"

    bm, phc = p["beyondmimic"], p["phc"]
    for clip, r in bm["per_clip"].items():
        q = phc["per_clip"][clip]
        ret = r["normalized_return"]
        print(f"  {clip}: BeyondMimic {fate(r)} (normalized return "
              f"{'n/a' if ret is None else f'{ret:.2f}'}); PHC {fate(q)} (global MPJPE "
              f"{mm(q['mpjpe_global_mm'])} mm)")  # fmt: skip
    from humimic.pipeline.imitate import protocol_lines

    for line in protocol_lines(p):
        if line:
            print(line)


def run_export(cmd: ExportSettings) -> None:
    """Run ``humimic export``."""
    from humimic.tracking.export import export

    print(f"wrote {export(cmd)}")


def run_imitate(cmd: ImitateSettings) -> None:
    """Run ``humimic imitate``; the rollout's pictures come from MuJoCo's renderer
    (:mod:`humimic.viewer.film`)."""
    from humimic.pipeline.imitate import imitate
    from humimic.viewer.film import render_eval_film

    r = imitate(cmd, screenshot=render_eval_film if cmd.screenshot else None)
    dr = r["eval"]["dr_default"]["policy"]
    print(f"DR default: success {100 * dr['success_rate']:.0f}%, global MPJPE "
          f"{dr['mpjpe_global_mm']:.0f} mm, root-relative {dr['mpjpe_root_mm']:.0f} mm")  # fmt: skip


def run_demo(cmd: DemoSettings) -> None:
    """Run ``humimic demo``: ``humimic imitate`` on the CMU walk (fetched once) or
    ``--clip``, then the report's path and a one-line verdict."""
    import time
    from pathlib import Path

    from humimic.datasets import fetch_cmu_clip
    from humimic.pipeline.imitate import imitate, verdict
    from humimic.viewer.film import render_eval_film

    cmd.validate()
    out = cmd.out or Path("out") / "demo" / time.strftime("%Y%m%d-%H%M%S")
    clip = cmd.clip or fetch_cmu_clip(quiet=cmd.quiet)
    r = imitate(cmd.imitate_settings(clip, out), screenshot=render_eval_film)
    print(f"report: {out / 'report.md'}")
    print(verdict(r))


def run_loop(cmd: LoopSettings) -> None:
    """Run ``humimic loop``."""
    from humimic.pipeline.loop import loop

    r = loop(cmd)
    for name in ("before", "after", "after_nominal"):
        if name in r:
            p = r[name]["policy"]
            print(f"{name:13s}: success {100 * p['success_rate']:.0f}%, global MPJPE "
                  f"{p['mpjpe_global_mm']:.1f} mm, joint error {p['joint_error_rad']:.3f} rad")  # fmt: skip
    print(f"sysid claimed: {', '.join(r['sysid']['claimed']) or 'nothing'}")
    print(f"wrote {cmd.out / 'loop.md'}")
