"""The run summary of live operation (issue 12): for every frame ingest read, whether it got a pose and how long
after the runner saw it the first one came; the ATE of those first poses next to the final ones; drops per stage
from the EOS messages; each service's CPU time and peak RSS.

The observer's bookkeeping is checked on messages fed to it directly; then two short real runs (`kmvipe run` in a
subprocess, real time and lossless) on the synthetic world with the features service's synth-oracle backbone (no
model to load), whose summary.json must carry the new fields with sane values. Nothing here asserts speed.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.cli import _print_summary
from services.common.bus import Delivery
from services.common.schema import Eos, Frame, Intrinsics, Poses
from services.runner.observer import Observer, fill_report
from services.runner.outputs import write_camera
from services.runner.pipeline import RunReport
from services.runner.resources import ResourceMonitor

SPEC = "synth:frames=30,width=256,height=192"
STAGES = ("ingest", "features", "ba", "mapstore")
KMVIPE = Path(sys.executable).parent / "kmvipe"


def _deliver(observer: Observer, msg) -> None:
    observer.on_message(Delivery("kmvipe/cam0/x", msg))


def _frame(seq: int) -> Frame:
    return Frame("cam0", seq, seq * 100, 4, 4, jpeg=b"x")


def _poses(seqs, tracked: bool, offset: float = 0.0, final: bool = False) -> Poses:
    poses = np.repeat(np.eye(4)[None], len(seqs), axis=0)
    poses[:, 0, 3] = np.asarray(seqs, float) + offset
    return Poses("cam0", max(seqs), 0, np.asarray(seqs, np.int64), np.asarray(seqs, np.int64) * 100, poses,
                 final=final, tracked=tracked)


def test_the_first_pose_of_each_frame_is_kept_and_frames_ingest_dropped_count_as_not_posed(capsys):
    observer = Observer(last_stage="ba")
    for seq in (0, 1, 3):  # ingest read 0..4, dropped 2 and 4
        _deliver(observer, _frame(seq))
    _deliver(observer, _poses([0], tracked=True))
    _deliver(observer, _poses([1], tracked=True))
    _deliver(observer, _poses([0, 1, 3], tracked=False, offset=0.5))  # mapping's revision, later
    _deliver(observer, _poses([1], tracked=True, offset=9.0))  # a late tracking pose never wins over mapping
    for stage, dropped in (("ingest", 2), ("features", 1), ("ba", 0)):
        lost = np.array([[1, 1]], np.int64) if stage == "ba" else None  # frame 1's view held no evidence
        _deliver(observer, Eos("cam0", 4, 0, stage=stage, count=3, dropped=dropped,
                               codes_skipped=4 if stage == "features" else 0, views_lost=lost,
                               frames_strayed=3 if stage == "ba" else 0,
                               work_s=2.5 if stage == "ba" else 0.0))

    report = RunReport("synth:", "cam0", ["ingest", "features", "ba"], [], duration_s=1.0)
    fill_report(report, observer, ResourceMonitor())
    assert report.frames_read == 5 and report.posed_fraction == pytest.approx(3 / 5)
    lat = report.pose_latency_ms
    assert lat["n"] == 3 and 0 <= lat["p50"] <= lat["p99"] <= lat["max"]
    assert report.drops == {"ingest": 2, "features": 1, "ba": 0}  # only the stages that ran
    assert report.codes_skipped == 4
    assert report.views_lost == [[1, 1]]
    _print_summary(report)
    printed = capsys.readouterr().out
    assert "view lost:         frames 1 (1 frame whose view held no evidence" in printed
    assert report.frames_strayed == 3 and "strayed:           3 frames whose solve" in printed
    assert report.end_of_stream_s is not None and report.end_of_stream_s >= 0
    assert set(report.end_of_stream_stages) == {"features", "ba"}  # ingest's EOS is where the clock starts
    assert report.end_of_stream_stages["ba"]["work_s"] == 2.5
    assert report.end_of_stream_stages["ba"]["after_ingest_s"] == report.end_of_stream_s
    assert "(its own work: ba 2.5 s)" in printed
    # the first pose is the tracked one (x = seq), the latest the mapped one (x = seq + 0.5)
    assert observer.first_pose[1][2][0, 3] == 1.0 and observer.first_pose[3][2][0, 3] == 3.5
    assert observer.poses[1][1][0, 3] == 1.5


def test_no_ingest_eos_counts_the_frames_seen_and_a_stage_without_eos_reports_none():
    observer = Observer(last_stage="ba")
    for seq in range(4):
        _deliver(observer, _frame(seq))
    report = RunReport("synth:", "cam0", ["ingest", "features", "ba"], [])
    fill_report(report, observer, ResourceMonitor())
    assert report.frames_read == 4 and report.posed_fraction == 0.0 and report.pose_latency_ms is None
    assert report.drops == {"ingest": None, "features": None, "ba": None}


def test_bas_latest_intrinsics_are_reported_in_the_source_pixels_against_the_true_ones(tmp_path, capsys):
    """ba publishes its intrinsics at the working resolution (here 256x192 of a 640x480 source, 2.5x): the run
    reports the latest in the source's pixels (pixel centres at integers: cx' = 2.5 (cx + 0.5) - 0.5), writes them
    as camera.txt and, where the source has a camera.txt, the focal error against it."""
    observer = Observer(last_stage="ba")
    _deliver(observer, Frame("cam0", 0, 0, 640, 480, jpeg=b"x"))
    for fx in (180.0, 200.0):  # the latest wins
        _deliver(observer, Intrinsics("cam0", 0, 0, intrinsics=np.array([fx, fx, 127.5, 95.5]), width=256, height=192))
    report = RunReport("folder", "cam0", ["ingest", "features", "ba"], [])
    fill_report(report, observer, ResourceMonitor())
    assert report.intrinsics == [500.0, 500.0, 319.5, 239.5] and report.image_size == [640, 480]
    source = tmp_path / "source"
    source.mkdir()
    (source / "camera.txt").write_text("505 505 319.5 239.5 640 480\n")
    assert write_camera(tmp_path, str(source), report) == [str(tmp_path / "camera.txt")]
    assert (tmp_path / "camera.txt").read_text() == "500.000 500.000 319.500 239.500 640 480\n"
    assert report.focal_error_pct == pytest.approx(100 * (500 / 505 - 1), abs=1e-3)
    _print_summary(report)
    printed = capsys.readouterr().out
    assert "intrinsics:        fx 500.0 fy 500.0 cx 319.5 cy 239.5 source px (fx -0.99 % from the true)" in printed
    empty = RunReport("folder", "cam0", ["ingest"], [])
    fill_report(empty, Observer(last_stage="ingest"), ResourceMonitor())
    assert empty.intrinsics is None and write_camera(tmp_path / "none", str(source), empty) == []


def _run(tmp_path: Path, pacing: str) -> tuple[dict, str]:
    assert KMVIPE.is_file(), f"the kmvipe command is not installed beside {sys.executable} (make install)"
    env = {**os.environ, "KMVIPE_FEATURES_BACKBONE": "synth-oracle", "KMVIPE_FEATURES_ORACLE_SOURCE": SPEC}
    out = tmp_path / pacing
    result = subprocess.run([str(KMVIPE), "run", SPEC, "--skip", "query_api", "--pacing", pacing, "--out", str(out)],
                            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=400)
    assert result.returncode == 0, result.stdout + result.stderr[-3000:]
    return json.loads((out / "summary.json").read_text()), result.stdout


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("pacing", ["realtime", "lossless"])
def test_a_real_run_reports_posed_fraction_latency_drops_and_resources(tmp_path, pacing):
    summary, stdout = _run(tmp_path, pacing)
    assert summary["end_reason"] == "end"
    assert summary["frames_read"] == 30
    assert 0 < summary["posed_fraction"] <= 1
    lat = summary["pose_latency_ms"]
    assert 0 <= lat["p50"] <= lat["p99"] <= lat["max"] and 1 <= lat["n"] <= 30
    assert set(summary["drops"]) == set(STAGES)
    assert all(isinstance(n, int) and n >= 0 for n in summary["drops"].values())
    assert isinstance(summary["codes_skipped"], int) and summary["codes_skipped"] >= 0
    # the synthetic world has ground truth: both the final poses and the first ones are evaluated
    assert summary["ate_rmse_sim3"] is not None and summary["ate_first_poses"] is not None
    assert summary["ate_first_poses_pairs"] == round(summary["posed_fraction"] * 30)
    # ba's refined intrinsics in the source's pixels, against the synthetic camera's (no calibration was given)
    assert summary["image_size"] == [256, 192] and len(summary["intrinsics"]) == 4
    assert abs(summary["focal_error_pct"]) < 5, summary["intrinsics"]
    assert summary["end_of_stream_s"] >= 0
    # ba's final BA and the mapstore's export are timed by the stage itself, inside its time after ingest's EOS
    stages = summary["end_of_stream_stages"]
    assert set(stages) == {"features", "ba", "mapstore"}
    assert stages["ba"]["work_s"] > 0  # its final BA
    for stage in ("ba", "mapstore"):
        assert 0 <= stages[stage]["work_s"] <= stages[stage]["after_ingest_s"] + 0.5, stage
    assert stages["mapstore"]["after_ingest_s"] == summary["end_of_stream_s"]
    assert list(summary["services"]) == list(STAGES)
    for name, use in summary["services"].items():
        assert use["cpu_s"] > 0 and 0 <= use["cpu_stream_s"] <= use["cpu_s"] and use["rss_peak_mb"] > 10, name
    peaks = [use["rss_peak_mb"] for use in summary["services"].values()]
    assert max(peaks) <= summary["rss_total_peak_mb"] <= sum(peaks) + 1
    # PSS splits the libraries every service maps among them: their sum holds less than the sum of RSS
    assert 0 < summary["pss_total_peak_mb"] < summary["rss_total_peak_mb"]
    for name, use in summary["services"].items():
        assert 0 < use["pss_peak_mb"] <= use["rss_peak_mb"], name
    assert summary["rss_mb_at_frames"] and summary["rss_mb_at_frames"][-1]["frames"] == summary["frames"]
    if pacing == "lossless":
        assert summary["drops"] == {stage: 0 for stage in STAGES} and summary["posed_fraction"] == 1.0
    for line in ("posed (any pose):", "ATE first poses:", "dropped:", "CPU, peak RSS:"):
        assert line in stdout


@pytest.mark.slow
def test_a_service_s_own_child_processes_count_in_its_cpu_and_memory():
    """ba starts a tracking process of its own: the summary's CPU and RSS of a service include its children."""
    import subprocess
    import sys as _sys
    import time as _time

    import psutil

    hold = "import time; x = bytearray(200 * 1024 * 1024); t = time.time()\nwhile time.time() - t < 1.5: pass\ntime.sleep(60)"
    parent = subprocess.Popen([_sys.executable, "-c", f"import subprocess, sys, time; "
                               f"subprocess.Popen([sys.executable, '-c', {hold!r}]); time.sleep(60)"])
    try:
        proc = psutil.Process(parent.pid)
        deadline = _time.monotonic() + 30
        while _time.monotonic() < deadline and not (proc.children() and proc.children()[0].cpu_times().user > 1.0):
            _time.sleep(0.1)
        monitor = ResourceMonitor()
        monitor.watch("svc", parent.pid)
        monitor.sample()
        use = monitor.usage["svc"]
        own = proc.memory_info().rss / 2**20
        assert use.rss_mb > own + 190  # the child's 200 MB are the service's
        assert use.cpu_s > 1.0  # the child's busy second and a half, not the sleeping parent's
    finally:
        for child in psutil.Process(parent.pid).children(recursive=True):
            child.kill()
        parent.kill()
        parent.wait()
