"""``humimic demo``: the whole job on a short real clip ending with the report and a verdict
(issue 59), the CMU clip it fetches, and the verdict's wording from measured numbers."""

from __future__ import annotations

import urllib.request
from pathlib import Path

import pytest

from humimic.cli.main import main
from humimic.datasets import fetch_cmu_clip
from humimic.errors import FetchError
from humimic.pipeline.imitate import verdict
from test_imitate import _short_bvh


def test_demo_on_a_short_clip_ends_with_the_report_and_a_verdict(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Half a second of the CMU walk, a few seconds of training: every stage runs, the
    rollout is rendered by MuJoCo, and the last lines name the report and say what the
    policy does."""
    clip = _short_bvh(shared_data / "cmu" / "35_01.bvh", tmp_path / "walk.bvh", 62)
    out = tmp_path / "demo"
    assert main(["demo", "--clip", str(clip), "--out", str(out), "--minutes", "0.1",
                 "--quiet"]) == 0  # fmt: skip
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-2] == f"report: {out / 'report.md'}"
    assert lines[-1].startswith("verdict: the g1 ") and "randomized episodes" in lines[-1]
    for name in ("report.md", "policy.onnx", "rollout.png", "rollout.gif"):
        assert (out / name).is_file(), name
    assert "rendered by MuJoCo" in (out / "report.md").read_text()


def test_the_cmu_clip_is_found_checked_and_never_taken_changed(
    shared_data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []

    def offline(url: str, timeout: float) -> None:
        calls.append(url)
        raise OSError("no network here")

    monkeypatch.setattr(urllib.request, "urlopen", offline)
    monkeypatch.setenv("HUMIMIC_DATA", str(shared_data))
    assert fetch_cmu_clip(cache_dir=tmp_path) == shared_data / "cmu" / "35_01.bvh"
    # The same clip with other line ends (a copy made on another system) is the clip.
    data = tmp_path / "data"
    (data / "cmu").mkdir(parents=True)
    lf = (shared_data / "cmu" / "35_01.bvh").read_bytes().replace(b"\r\n", b"\n")
    (data / "cmu" / "35_01.bvh").write_bytes(lf)
    monkeypatch.setenv("HUMIMIC_DATA", str(data))
    assert fetch_cmu_clip(cache_dir=tmp_path) == data / "cmu" / "35_01.bvh"
    assert not calls
    # A changed file is not the clip: it is downloaded instead (here: no network, an error).
    (data / "cmu" / "35_01.bvh").write_bytes(lf.replace(b"Frames: 359", b"Frames: 358"))
    with pytest.raises(FetchError, match=r"cannot download .*35_01\.bvh: no network here"):
        fetch_cmu_clip(cache_dir=tmp_path, quiet=True)
    assert calls and calls[0].endswith("/035/35_01.bvh")
    with pytest.raises(FetchError, match="humimic fetches 35_01"):
        fetch_cmu_clip("01_01", cache_dir=tmp_path)


def _report(success: float, failed_clips: int, phc: float) -> dict:
    proto = {"beyondmimic": {"failed_clips": failed_clips, "clips": 1},
             "phc": {"success_rate": phc}}  # fmt: skip
    return {"robot": "g1", "minutes": 6.0,
            "eval": {"dr_default": {"policy": {"success_rate": success, "episodes": 32,
                                               "mpjpe_global_mm": 84.6}},
                     "nominal": {"protocols": proto}}}  # fmt: skip


def test_the_verdict_says_what_was_measured() -> None:
    good = verdict(_report(0.9375, 0, 1.0))
    assert good == (
        "verdict: the g1 tracks the clip: 94% of 32 randomized episodes complete it (global "
        "MPJPE 85 mm); on the nominal robot 0 of 1 clips fail BeyondMimic's protocol and 100% "
        "pass PHC's."
    )
    part = verdict(_report(0.5, 1, 0.0))
    assert "tracks the clip in part: 50% of 32" in part and "1 of 1 clips fail" in part
    assert part.endswith("6 min of training: more minutes (--minutes) help.")
    assert "does not track the clip yet: 12%" in verdict(_report(0.125, 1, 0.0))
