"""The runner and CLI: `kmvipe demo` streams the synthetic world through every built service and writes a
summary; the real sequences stream end to end through ingest to a consumer process."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from services.runner.children import PIPELINE, free_tcp_endpoint, is_built
from tests.conftest import REPO, wait_until


@pytest.mark.slow
def test_demo_runs_and_reports_what_ran(tmp_path):
    out = tmp_path / "demo"
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "demo", "--frames", "120", "--max-frames", "36", "--out", str(out),
         "--port", free_tcp_endpoint().rsplit(":", 1)[1]],
        cwd=REPO, capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 36 and summary["end_reason"] == "end"
    if "ba" in summary["services_ran"]:
        # every frame posed, and the uncalibrated estimate follows the synthetic ground truth (a ~1.3 m arc;
        # measured 2 mm)
        assert summary["posed_frames"] == 36
        assert summary["ate_rmse_sim3"] < 0.03, summary
        assert (out / "trajectory.txt").is_file() and (out / "map.ply").is_file()
    assert summary["services_ran"] == [name for name in PIPELINE if is_built(name)]
    assert "frames:            36" in result.stdout
    assert "kmvipe cam0" in result.stderr  # the progress bar
    assert (out / "logs" / "ingest.log").is_file()
    timeline = [line.split(",") for line in (out / "resources.csv").read_text().splitlines()]
    assert timeline[0] == ["t_s", "service", "cpu_s", "rss_mb", "pss_mb"]
    assert {row[1] for row in timeline[1:]} == set(summary["services_ran"])  # every service, every sample
    peak = max(float(row[3]) for row in timeline[1:] if row[1] == "ba") if "ba" in summary["services_ran"] else 0
    assert peak == pytest.approx(summary["services"].get("ba", {}).get("rss_peak_mb", 0), abs=0.1)


def test_unknown_service_and_bad_source_are_clear_errors(tmp_path):
    bad = subprocess.run([sys.executable, "-m", "services.cli", "service", "nope"], cwd=REPO, capture_output=True, text=True)
    assert bad.returncode == 2 and "unknown service 'nope'" in bad.stderr


def _stream_through_ingest(source: str, stream: str, endpoint: str, out) -> dict:
    consumer = subprocess.Popen(
        [sys.executable, "-m", "tests.helpers.frame_consumer", endpoint, stream, str(out), "--listen", "--window", "8"],
        cwd=REPO,
    )
    wait_until(lambda: os.path.exists(str(out) + ".ready"), 60, "the consumer to subscribe")
    publish = subprocess.run(
        [sys.executable, "-m", "services.cli", "publish", source, "--connect", endpoint, "--stream", stream,
         "--pacing", "lossless"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    consumer.wait(timeout=60)
    assert publish.returncode == 0, publish.stderr
    return json.loads(out.read_text())


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.parametrize("relative, n_frames", [("vtest/vtest.avi", 795), ("kitti07_160", 160)])
def test_real_sequences_stream_end_to_end(data_dir, unix_endpoint, tmp_path, relative, n_frames):
    result = _stream_through_ingest(str(data_dir / relative), "real", unix_endpoint, tmp_path / "out.json")
    assert result["seqs"] == list(range(n_frames))
    assert result["eos"] == {"seq": n_frames - 1, "count": n_frames}


@pytest.mark.parametrize(
    "env, message",
    [
        ({"KMVIPE_INGEST_PACING": "bogus"}, "invalid settings"),
        ({"KMVIPE_BUS_MODE": "client", "KMVIPE_BUS_CONNECT": '["tcp/127.0.0.1:9"]'}, "cannot open the Zenoh session"),
    ],
)
def test_a_service_with_bad_settings_exits_with_one_clear_message(env, message):
    result = subprocess.run([sys.executable, "-m", "services.cli", "service", "ingest"], cwd=REPO,
                            env={**os.environ, **env}, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr


# --- what a run reports of itself (issue 17, item 5) --------------------------------------------------------------
def test_version_is_the_installed_packages():
    from importlib.metadata import version

    done = subprocess.run([sys.executable, "-m", "services.cli", "--version"], cwd=REPO, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == f"kmvipe {version('kmvipe')}", done.stdout + done.stderr


def test_topic_is_the_bag_topic_ingest_reads(tmp_path):
    from services.cli import build_parser
    from services.runner.pipeline import RunSettings, _service_env

    args = build_parser().parse_args(["run", "drive.mcap", "--topic", "/camera/image_raw/compressed"])
    env = _service_env("ingest", RunSettings(source=args.source, out=tmp_path, topic=args.topic))
    assert env["KMVIPE_INGEST_TOPIC"] == "/camera/image_raw/compressed"
    assert "KMVIPE_INGEST_TOPIC" not in _service_env("ingest", RunSettings(source="drive.mcap", out=tmp_path))
    assert all("TOPIC" not in name for name in _service_env("features", RunSettings("x", tmp_path, topic="/t")))


def test_the_settings_a_service_used_are_its_effective_ones_without_secrets(monkeypatch, tmp_path):
    """The user's environment, then the runner's overrides, over each class's defaults — as the service builds
    them — and no secret value anywhere in what the summary would hold."""
    from services.runner import settings_used as su

    monkeypatch.chdir(tmp_path)  # no .env
    monkeypatch.setenv("KMVIPE_INGEST_JPEG_QUALITY", "77")  # the user's own setting
    monkeypatch.setenv("KMVIPE_BUS_USER", "edge-cam0")
    monkeypatch.setenv("KMVIPE_BUS_PASSWORD", "hunter2-secret")
    before = dict(os.environ)
    got = su.collect({"ingest": su.child_env("tcp/127.0.0.1:7447", {"KMVIPE_INGEST_PACING": "realtime",
                                                                     "KMVIPE_QUERY_API_KEY": "k3y-secret"})})
    assert dict(os.environ) == before
    ingest = got["ingest"]["settings"]
    assert ingest["IngestSettings"]["pacing"] == "realtime" and ingest["IngestSettings"]["jpeg_quality"] == 77
    assert ingest["IngestSettings"]["stride"] == 1  # a default
    assert ingest["BusSettings"]["mode"] == "client" and ingest["BusSettings"]["connect"] == ["tcp/127.0.0.1:7447"]
    assert ingest["BusSettings"]["user"] == "edge-cam0" and ingest["BusSettings"]["password"] == su.REDACTED
    assert got["ingest"]["env"]["KMVIPE_QUERY_API_KEY"] == su.REDACTED
    text = json.dumps(got)
    assert "hunter2" not in text and "k3y" not in text


def test_secret_names_are_redacted_and_secret_files_named():
    from services.runner.settings_used import REDACTED, redact

    got = redact({"password": "p", "api_key": "k", "KMVIPE_QUERY_API_KEY": "k", "password_file": "/run/secrets/pw",
                  "token": None, "nested": {"client_secret": "s", "keyframe_threshold": 2.4}, "user": "u"})
    assert got == {"password": REDACTED, "api_key": REDACTED, "KMVIPE_QUERY_API_KEY": REDACTED,
                   "password_file": "/run/secrets/pw", "token": None,
                   "nested": {"client_secret": REDACTED, "keyframe_threshold": 2.4}, "user": "u"}
