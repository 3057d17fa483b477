"""The README's commands as a new user runs them (issue 11): `kmvipe run` from any working directory with relative
paths, stopped by a signal (SIGTERM, or the runner SIGKILLed), `--serve` with its outputs on disk at end of stream,
and one default stream name for every command and service.

The pipeline runs on the synthetic world with the features service's synth-oracle backbone (no model to load), so
a run takes seconds; every run is the installed `kmvipe` command in a subprocess, as a user types it.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import psutil
import pytest

from services.cli import build_parser
from services.common import keys
from services.runner import children as kids
from services.runner.pipeline import RunSettings, StopSignals, absolute_paths, absolute_source
from services.synth import SynthWorld
from services.synth.io import write_image_folder
from services.synth.spec import config_from_spec
from tests.conftest import REPO, wait_until

SPEC = "synth:frames=120,seed=0"
SERVICES = ("ingest", "features", "ba", "mapstore")  # what a run with --skip query_api starts
KMVIPE = Path(sys.executable).parent / "kmvipe"


def oracle_env(spec: str = SPEC) -> dict[str, str]:
    """The environment of a user's shell, plus the synthetic oracle instead of the DINO backbone."""
    return {**os.environ, "KMVIPE_FEATURES_BACKBONE": "synth-oracle", "KMVIPE_FEATURES_ORACLE_SOURCE": spec,
            "KMVIPE_QUERY_TEXT_ENCODER": "oracle", "KMVIPE_QUERY_ORACLE_SYNTH_SEED": "0"}


def kmvipe(*args: str) -> list[str]:
    assert KMVIPE.is_file(), f"the kmvipe command is not installed beside {sys.executable} (make install)"
    return [str(KMVIPE), *args]


def alive(pid: int) -> bool:
    """Running (a zombie waiting for a parent that never reaps it has stopped running)."""
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def files_under(folder: Path) -> dict[Path, int]:
    """Relative path → mtime of every file under ``folder`` (empty when it does not exist)."""
    if not folder.is_dir():
        return {}
    return {p.relative_to(folder): p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}


def start_run(cwd: Path, *args: str) -> tuple[subprocess.Popen, psutil.Process]:
    proc = subprocess.Popen(kmvipe("run", *args), cwd=cwd, env=oracle_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    return proc, psutil.Process(proc.pid)


def wait_for_services(proc: subprocess.Popen, runner: psutil.Process, n: int) -> list[int]:
    """Pids of the runner's service processes once ``n`` of them run (ingest starts last, when the rest are up)."""
    def started() -> bool:
        if proc.poll() is not None:
            pytest.fail(f"kmvipe run exited early ({proc.returncode}): {proc.communicate()[1][-2000:]}")
        return len(runner.children()) >= n

    wait_until(started, 240, f"the runner to start its {n} services", poll=0.2)
    return [child.pid for child in runner.children()]


# --- paths ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("source", ["synth:frames=3", "0", "12", "/dev/video0", "rtsp://cam/stream",
                                    "http://cam/video.mjpg", "no/such/file.mp4"])
def test_sources_that_are_not_local_files_stay_as_given(source, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert absolute_source(source) == source


def test_local_sources_and_the_output_folder_become_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "video.avi").write_bytes(b"")
    (tmp_path / "frames").mkdir()
    assert absolute_source("video.avi") == str(tmp_path / "video.avi")
    assert absolute_source("./frames/../frames") == str(tmp_path / "frames")
    assert absolute_source(str(tmp_path / "frames")) == str(tmp_path / "frames")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert absolute_source("~/video.avi") == str(tmp_path / "video.avi")
    cfg = absolute_paths(RunSettings(source="frames", out=Path("out/run")))
    assert cfg.out == tmp_path / "out" / "run" and cfg.source == str(tmp_path / "frames")


def test_services_import_the_runners_package_from_any_directory(tmp_path, monkeypatch):
    """Children run in the caller's directory with ``python -P``: a ``services`` folder there is not imported."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "services").mkdir()
    (tmp_path / "services" / "__init__.py").write_text("raise ImportError('the decoy services package')\n")
    env = {**os.environ, "KMVIPE_INGEST_PACING": "bogus"}  # exits at once with a settings error
    child = kids.start("ingest", kids.free_tcp_endpoint(), tmp_path / "logs", env)
    assert child.process.wait(timeout=60) == 2
    log = child.log_path.read_text()
    assert "decoy" not in log and "Traceback" not in log, log
    assert "invalid settings" in log or "cannot open the Zenoh session" in log, log  # the real package's errors


@pytest.mark.slow
def test_a_run_from_any_directory_reads_and_writes_there_only(tmp_path):
    """`kmvipe run frames --out out` in a user's folder: relative source and output, nothing written elsewhere."""
    work = tmp_path / "work"
    n = 10
    write_image_folder(SynthWorld(config_from_spec(SPEC)), work / "frames", n)  # TUM layout + groundtruth.txt
    (work / "services").mkdir()  # a user's own folder of that name changes nothing
    repo_out_before = files_under(REPO / "out")

    result = subprocess.run(kmvipe("run", "frames", "--out", "out", "--skip", "query_api", "--max-frames", str(n)),
                            cwd=work, env=oracle_env(), capture_output=True, text=True, timeout=280)

    assert result.returncode == 0, result.stdout + result.stderr[-3000:]
    out = work / "out"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == n and summary["end_reason"] == "end", summary
    # the first thing it says: which queries its map supports, as the summary records them (the oracle's text
    # vectors here; without them, why not: tests/test_text_profile.py)
    first = result.stdout.splitlines()[0]
    assert first.startswith("kmvipe: semantic queries of this map: text: available"), result.stdout
    queries = summary["queries"]
    assert queries["text"] is True and queries["example"] is True and queries["text_why"] in first
    assert summary["source"] == str(work / "frames")
    assert summary["ate_rmse_sim3"] is not None  # the groundtruth.txt beside the relative source was found
    used = summary["settings"]  # what each service ran with: the user's environment, then the runner's overrides
    assert used["run"]["source"] == str(work / "frames") and used["run"]["out"] == str(out)
    assert sorted(used["services"]) == sorted(SERVICES)
    ingest = used["services"]["ingest"]["settings"]
    assert ingest["IngestSettings"]["source"] == str(work / "frames") and ingest["IngestSettings"]["max_frames"] == n
    assert ingest["BusSettings"]["mode"] == "client"
    assert used["services"]["features"]["settings"]["FeaturesSettings"]["backbone"] == "synth-oracle"  # the user's
    assert used["services"]["mapstore"]["settings"]["MapstoreSettings"]["db_path"] == str(out / "map.db")
    for name in ("map.db", "map.ply", "trajectory.txt", *(f"logs/{s}.log" for s in SERVICES)):
        assert (out / name).is_file(), name
    assert all(Path(p).is_relative_to(out) for p in summary["outputs"]), summary["outputs"]
    assert sorted(p.name for p in work.iterdir()) == ["frames", "out", "services"]
    produced = set(files_under(out))
    repo_out_after = files_under(REPO / "out")
    changed = {p for p, mtime in repo_out_after.items() if repo_out_before.get(p) != mtime}
    assert not changed & produced, f"the run wrote into {REPO / 'out'}: {sorted(changed & produced)}"


# --- signals ----------------------------------------------------------------------------------------------------
def test_sigterm_stops_every_service_and_writes_what_was_produced(tmp_path):
    proc, runner = start_run(tmp_path, "synth:frames=400,seed=0", "--out", "out", "--skip", "query_api")
    pids = wait_for_services(proc, runner, len(SERVICES))
    assert len(pids) == len(SERVICES)

    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=90)

    assert proc.returncode == 128 + signal.SIGTERM, stdout + stderr[-3000:]
    message = [line for line in stderr.splitlines() if line.startswith("kmvipe:")]
    assert len(message) == 1 and "stopped by SIGTERM" in message[0], stderr[-3000:]
    assert not [pid for pid in pids if alive(pid)], "services outlived the runner"
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["stopped_by"] == "SIGTERM" and summary["end_reason"] == "stopped by SIGTERM"
    assert summary["frames"] < 400


def test_stop_signals_set_a_flag_and_leave_ignored_signals_ignored():
    """A signal ends the run through its clean path; `nohup kmvipe run` still survives the terminal's SIGHUP."""
    term_before = signal.getsignal(signal.SIGTERM)
    hup_before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with StopSignals() as stop:
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGTERM)
            wait_until(stop.is_set, 5, "the SIGTERM flag")
            os.kill(os.getpid(), signal.SIGINT)  # a second signal: recorded, no KeyboardInterrupt
            time.sleep(0.05)
        assert stop.name == "SIGTERM"
        assert signal.getsignal(signal.SIGTERM) is term_before
    finally:
        signal.signal(signal.SIGHUP, hup_before)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux only")
def test_services_stop_when_the_runner_is_killed(tmp_path):
    proc, runner = start_run(tmp_path, "synth:frames=400,seed=0", "--out", "out", "--skip", "query_api")
    pids = wait_for_services(proc, runner, len(SERVICES))

    proc.kill()  # no handler runs: the kernel tells each service (PR_SET_PDEATHSIG), each stops as on SIGTERM
    proc.communicate(timeout=30)

    wait_until(lambda: not any(alive(pid) for pid in pids), 60, "the services to stop after the runner was killed",
               poll=0.2)


@pytest.mark.slow
def test_serve_writes_the_outputs_at_end_of_stream(tmp_path):
    out = tmp_path / "out"
    port = kids.free_tcp_endpoint().rsplit(":", 1)[1]
    proc, runner = start_run(tmp_path, SPEC, "--max-frames", "12", "--out", "out", "--serve", "--port", port)
    try:
        def outputs_written() -> bool:
            if proc.poll() is not None:
                pytest.fail(f"kmvipe run --serve exited ({proc.returncode}): {proc.communicate()[1][-2000:]}")
            return (out / "summary.json").is_file() and (out / "trajectory.txt").is_file()

        wait_until(outputs_written, 240, "summary.json and trajectory.txt while the gateway serves", poll=0.2)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/v1/streams", timeout=30) as res:  # still serving
            assert res.status == 200
        assert proc.poll() is None
        summary = json.loads((out / "summary.json").read_text())
        assert summary["end_reason"] == "end" and summary["frames"] == 12 and summary["posed_frames"] == 12
        written = {name: (out / name).read_bytes() for name in ("summary.json", "trajectory.txt")}
        pids = [child.pid for child in runner.children()]

        proc.send_signal(signal.SIGTERM)  # the way to stop serving (as Ctrl-C): the run itself succeeded
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stdout + stderr[-3000:]
    assert "serving queries at" in stdout and "frames:            12" in stdout
    assert {name: (out / name).read_bytes() for name in written} == written  # stopping kept them as they were
    assert not [pid for pid in pids if alive(pid)]


# --- one default stream -----------------------------------------------------------------------------------------
def test_every_source_defaults_to_one_stream_and_services_serve_every_stream(tmp_path, monkeypatch):
    """Issue 11: services started without settings must meet `kmvipe publish`. Every source and command defaults to
    one stream (cam0) and the services serve every stream a source announces (issue 14), so they meet it and any
    other."""
    from services.ba.config import BASettings
    from services.ba.settings import BaSettings
    from services.features.config import FeaturesSettings
    from services.ingest.config import IngestSettings
    from services.mapstore.config import MapstoreSettings

    monkeypatch.chdir(tmp_path)  # no .env file
    for name in [n for n in os.environ if n.startswith("KMVIPE_")]:
        monkeypatch.delenv(name)
    assert keys.check_name(keys.DEFAULT_STREAM) == "cam0"  # what `kmvipe publish` always sent
    services = {cls.__name__: cls().stream for cls in (FeaturesSettings, BASettings, BaSettings, MapstoreSettings)}
    assert services == dict.fromkeys(services, keys.ALL_STREAMS)
    streams = {"IngestSettings": IngestSettings().stream, "RunSettings": RunSettings(source=SPEC, out=tmp_path).stream}
    parser = build_parser()
    for argv in (["run", "video.mp4"], ["demo"], ["publish", "0", "--connect", "tcp/127.0.0.1:7447"],
                 ["query", "chair"], ["map", "export", "--db", "map.db", "--out", "export"]):
        streams["kmvipe " + argv[0]] = parser.parse_args(argv).stream
    assert streams == dict.fromkeys(streams, keys.DEFAULT_STREAM)


def test_docker_compose_services_serve_every_stream_and_its_ingest_the_default_one():
    import yaml

    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    for name in SERVICES:
        env = compose["services"][name]["environment"]
        if name == "ingest":
            assert env["KMVIPE_INGEST_STREAM"] == "${KMVIPE_STREAM:-" + keys.DEFAULT_STREAM + "}"
        else:  # no stream setting: the default, every stream
            assert f"KMVIPE_{name.upper()}_STREAM" not in env
