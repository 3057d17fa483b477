"""`kmvipe run … --rerun out.rrd` (issue 17, item 2): a run recorded to Rerun — frames, camera frustums, every
frame's pose, the trajectory, keyframes, map points and query highlights — read back with the Rerun SDK and checked
against what the same run wrote (trajectory.txt, map.ply, summary.json) and against the synthetic source's own
frames; the same recording streamed live to the Rerun viewer binary (headless, saving what it receives).

The run is the synthetic world with the oracle profile (`--text oracle`: no model loads, and the gateway answers
text with the world's label vectors), 20 small frames, so it takes seconds of CPU."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.common.errors import ConfigError
from services.mapstore.export import read_ply
from services.runner import rerun_log as rl
from services.runner.children import free_tcp_endpoint
from services.synth import SynthWorld
from services.synth.spec import config_from_spec
from tests.conftest import wait_until

rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install 'rerun-sdk>=0.41')")

SPEC = "synth:frames=20,width=256,height=192"
KMVIPE = Path(sys.executable).parent / "kmvipe"
ROW_ID = "rerun.controls.RowId"
# the viewer saves what it receives as a stream: a file without the index a file sink writes at its end
pytestmark = pytest.mark.filterwarnings("ignore:RRD file has no footer")


def read_rrd(path: Path) -> dict[str, list[dict]]:
    """Entity path → its rows (column → value) in log order: by frame, then by Rerun's (time-ordered) row id."""
    from rerun.chunk import RrdReader

    rows: dict[str, list[dict]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()  # its components, the frame and the row id (not Rerun's own log_time)
        batch = batch.select([n for n in batch.schema.names if ":" in n or n in (rl.TIMELINE, ROW_ID)])
        rows[chunk.entity_path.lstrip("/")] += batch.to_pylist()
    for entity in rows.values():
        entity.sort(key=lambda row: (row.get(rl.TIMELINE, -1), row[ROW_ID]))
    return dict(rows)  # a missing entity is a KeyError, not an empty one added


def having(rows: list[dict], column: str) -> list[dict]:
    return [row for row in rows if row.get(column) is not None]


def latest_per_frame(rows: list[dict], column: str) -> dict[int, object]:
    """What the viewer shows at each frame: the last value logged at it."""
    return {row[rl.TIMELINE]: row[column] for row in having(rows, column)}


# --- the mapping, alone ----------------------------------------------------------------------------------------
def test_intrinsics_follow_the_resize_rule():
    """docs/CONVENTIONS.md: a centred principal point stays centred at any size."""
    k = rl.scale_intrinsics(np.array([100.0, 90.0, 31.5, 23.5]), (64, 48), (128, 96))
    assert np.allclose(k, [200.0, 180.0, 63.5, 47.5])
    assert np.allclose(rl.scale_intrinsics(k, (128, 96), (128, 96)), k)


def test_the_frustum_puts_the_image_centre_where_rerun_does():
    """KM-ViPE's centre pixel (W-1)/2 is Rerun's default principal point W/2 (its pixel centres are at +0.5)."""
    path, ours = rl.pinhole(np.array([100.0, 90.0, 31.5, 23.5]), (64, 48))
    theirs = rr.Pinhole(focal_length=[100.0, 90.0], width=64, height=48)
    assert path == rl.IMAGE
    assert ours.image_from_camera.as_arrow_array().to_pylist() == theirs.image_from_camera.as_arrow_array().to_pylist()
    assert ours.resolution.as_arrow_array().to_pylist() == [[64.0, 48.0]]


def test_a_query_answer_becomes_labelled_boxes_and_highlighted_points():
    result = {"text": "fire extinguisher", "regions": [
        {"score": 0.75, "box_min": [0, 0, 0], "box_max": [2, 4, 6], "samples": [[1, 1, 1]]}],
        "top_points": [{"xyz": [1, 2, 3], "score": 0.8}, {"xyz": [1, 2, 4], "score": 0.7}]}
    (box_path, boxes), (points_path, points) = rl.query_answer(result)
    assert box_path == rl.query_path("fire extinguisher") and points_path == box_path + "/points"
    assert boxes.centers.as_arrow_array().to_pylist() == [[1.0, 2.0, 3.0]]
    assert boxes.half_sizes.as_arrow_array().to_pylist() == [[1.0, 2.0, 3.0]]
    assert boxes.labels.as_arrow_array().to_pylist() == ["fire extinguisher 0.75"]
    assert len(points.positions.as_arrow_array()) == 3


def test_a_raw_frame_with_sensor_depth_becomes_an_image_and_a_depth_image():
    from services.common.schema import Frame

    rgb = np.random.default_rng(0).integers(0, 255, (6, 8, 3), dtype=np.uint8)
    depth = np.full((6, 8), 2.5, np.float32)
    (image_path, image), (depth_path, depth_image) = rl.frame_image(Frame("cam0", 3, 0, width=8, height=6, image=rgb,
                                                                          depth=depth))
    assert (image_path, depth_path) == (rl.IMAGE, rl.DEPTH)
    assert bytes(image.buffer.as_arrow_array().to_pylist()[0]) == rgb.tobytes()
    assert depth_image.meter.as_arrow_array().to_pylist() == [1.0]  # metres on the wire, metres in Rerun
    (only,) = rl.frame_image(Frame("cam0", 3, 0, width=8, height=6, jpeg=b"\xff\xd8jpeg"))
    assert bytes(only[1].blob.as_arrow_array().to_pylist()[0]) == b"\xff\xd8jpeg"  # as sent, not re-encoded


def test_map_points_are_subsampled_evenly_to_the_limit():
    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    _, points = rl.map_points(xyz, np.zeros((10, 3), np.uint8), max_points=3)
    got = np.array(points.positions.as_arrow_array().to_pylist())
    assert len(got) <= 3 and np.array_equal(got, xyz[::4])


@pytest.mark.parametrize("target, connect, path, viewer", [
    ("out.rrd", None, Path("out.rrd"), None),
    ("rerun+http://10.0.0.5:9876/proxy", None, None, "rerun+http://10.0.0.5:9876/proxy"),
    ("out.rrd", rl.DEFAULT_VIEWER, Path("out.rrd"), rl.DEFAULT_VIEWER),
    (None, rl.DEFAULT_VIEWER, None, rl.DEFAULT_VIEWER),
])
def test_a_file_a_viewer_or_both(target, connect, path, viewer):
    got = rl.target_settings(target, connect)
    assert (got.path, got.connect) == (path, viewer)


def test_bad_recording_settings_say_what_is_wrong(monkeypatch):
    assert rl.target_settings(None, None) is None
    with pytest.raises(ConfigError, match="must start with"):
        rl.target_settings(None, "http://127.0.0.1:9876")
    with pytest.raises(ConfigError, match="at least 1"):
        rl.target_settings("out.rrd", image_every=0)
    monkeypatch.setitem(sys.modules, "rerun", None)  # rerun-sdk not installed: `import rerun` fails
    with pytest.raises(ConfigError, match=r"pip install 'rerun-sdk>=0\.41'"):
        rl.load_rerun()


# --- a run, recorded to a file and to a live viewer ----------------------------------------------------------------
def _start_viewer(tmp_path: Path) -> tuple[subprocess.Popen, str, Path]:
    """The Rerun viewer, headless: it listens where a live viewer does and saves what it receives. The binary
    itself, not the `rerun` script, which runs it as a child a signal to the script would leave behind."""
    import rerun_cli

    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    received = tmp_path / "received.rrd"
    binary = Path(rerun_cli.__file__).parent / "rerun"
    with (tmp_path / "viewer.log").open("wb") as log:
        viewer = subprocess.Popen([str(binary), "--bind", "127.0.0.1", "--port", str(port), "--save", str(received)],
                                  stdout=log, stderr=subprocess.STDOUT)
    wait_until(lambda: viewer.poll() is not None or _listening(port), 60, "the Rerun viewer to listen", poll=0.1)
    assert viewer.poll() is None, (tmp_path / "viewer.log").read_text()[-2000:]
    return viewer, f"rerun+http://127.0.0.1:{port}/proxy", received


def _rows_of(rec: dict[str, list[dict]]) -> dict[str, int]:
    return {entity: len(rows) for entity, rows in rec.items()}


def _rows(path: Path) -> dict[str, int]:
    """Rows per entity of a file still being written ({} while it cannot be read)."""
    try:
        return _rows_of(read_rrd(path)) if path.is_file() else {}
    except Exception:  # noqa: BLE001 - a partly written message at its end
        return {}


def _listening(port: int) -> bool:
    import socket

    with socket.socket() as sock:
        return sock.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("rerun")
    env = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    viewer, url, received = _start_viewer(tmp_path)
    try:
        done = subprocess.run([str(KMVIPE), "run", SPEC, "--text", "oracle", "--out", "out", "--rerun", "out.rrd",
                               "--rerun-connect", url, "--rerun-query", "chair",
                               "--port", free_tcp_endpoint().rsplit(":", 1)[1]],
                              cwd=tmp_path, env=env, capture_output=True, text=True, timeout=280)
        assert done.returncode == 0, done.stdout + done.stderr[-3000:]
        recorded = read_rrd(tmp_path / "out.rrd")
        deadline = time.monotonic() + 30  # the viewer writes asynchronously: its last rows may still be coming
        while _rows(received) != _rows_of(recorded) and time.monotonic() < deadline:
            time.sleep(0.5)
    finally:
        viewer.send_signal(signal.SIGTERM)
        try:
            viewer.wait(timeout=30)
        except subprocess.TimeoutExpired:
            viewer.kill()
            viewer.wait()
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    return tmp_path, summary, recorded, read_rrd(received)


@pytest.mark.slow
def test_every_posed_frame_has_its_final_pose_and_frustum(recorded_run):
    tmp_path, summary, rec, _ = recorded_run
    assert summary["frames"] == 20 and summary["posed_frames"] == 20, summary
    poses = latest_per_frame(rec[rl.CAMERA], "Transform3D:translation")
    rotations = latest_per_frame(rec[rl.CAMERA], "Transform3D:mat3x3")
    tum = np.loadtxt(tmp_path / "out" / "trajectory.txt")  # t x y z qx qy qz qw: each frame's final pose
    assert sorted(poses) == list(range(summary["posed_frames"]))
    assert np.allclose([poses[s][0] for s in sorted(poses)], tum[:, 1:4], atol=1e-5)
    for seq in sorted(rotations):  # a rotation (Rerun keeps it column-major), not a placeholder
        r = np.array(rotations[seq][0]).reshape(3, 3).T
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-5) and np.linalg.det(r) == pytest.approx(1.0, abs=1e-5)
    pinholes = having(rec[rl.IMAGE], "Pinhole:resolution")
    assert pinholes and all(row["Pinhole:resolution"] == [[256.0, 192.0]] for row in pinholes)
    k = np.array(pinholes[-1]["Pinhole:image_from_camera"][0]).reshape(3, 3).T  # BA's refined intrinsics
    assert k[0, 0] > 0 and k[1, 1] > 0 and 0 < k[0, 2] < 256 and 0 < k[1, 2] < 192


@pytest.mark.slow
def test_every_nth_frame_is_the_source_image(recorded_run):
    _, summary, rec, _ = recorded_run
    every = summary["settings"]["run"]["rerun"]["image_every"]
    images = latest_per_frame(rec[rl.IMAGE], "EncodedImage:blob")
    assert sorted(images) == [seq for seq in range(summary["frames"]) if seq % every == 0]
    world = SynthWorld(config_from_spec(SPEC))
    rendered = np.stack([world.render(i).rgb for i in range(summary["frames"])]).astype(np.float32)
    for seq, blob in images.items():
        got = cv2.imdecode(np.frombuffer(bytes(blob[0]), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
        assert got.shape == (192, 256, 3)
        error = np.abs(rendered - got.astype(np.float32)).mean(axis=(1, 2, 3))  # against every frame of the source
        assert error.argmin() == seq and error[seq] < 8.0, error  # its own frame, JPEG's loss only (measured 5.4)


@pytest.mark.slow
def test_the_trajectory_keyframes_and_map_are_the_runs(recorded_run):
    tmp_path, summary, rec, _ = recorded_run
    tum = np.loadtxt(tmp_path / "out" / "trajectory.txt")
    strip = np.array(having(rec[rl.TRAJECTORY], "LineStrips3D:strips")[-1]["LineStrips3D:strips"][0])
    assert np.allclose(strip, tum[:, 1:4], atol=1e-5)
    keyframes = having(rec[rl.KEYFRAMES], "Points3D:positions")[-1]["Points3D:positions"]
    assert len(keyframes) == summary["keyframes"]
    # the final map is the durable one: the map database re-fused by `kmvipe map export`
    final_map = np.array(having(rec[rl.MAP], "Points3D:positions")[-1]["Points3D:positions"])
    done = subprocess.run([str(KMVIPE), "map", "export", "--db", "out/map.db", "--out", "export"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    vertices = read_ply(tmp_path / "export" / "map.ply")
    durable = np.stack([vertices["x"], vertices["y"], vertices["z"]], axis=1)
    assert len(final_map) == len(durable) == summary["rerun"]["map_points"] > 0
    assert np.allclose(final_map[np.lexsort(final_map.T)], durable[np.lexsort(durable.T)], atol=1e-5)


@pytest.mark.slow
def test_the_gateways_answer_is_highlighted(recorded_run):
    _, summary, rec, _ = recorded_run
    path = rl.query_path("chair")
    assert path in rec, summary["rerun"]
    boxes = having(rec[path], "Boxes3D:centers")[-1]
    assert 0 < len(boxes["Boxes3D:centers"]) == summary["rerun"]["queries"]["chair"]["regions"]
    assert all(label.startswith("chair ") for label in boxes["Boxes3D:labels"])
    assert len(having(rec[path + "/points"], "Points3D:positions")[-1]["Points3D:positions"]) > 0


@pytest.mark.slow
def test_the_live_viewer_received_the_same_recording(recorded_run):
    _, _, rec, received = recorded_run
    assert _rows_of(received) == _rows_of(rec)
    assert latest_per_frame(received[rl.CAMERA], "Transform3D:translation") == \
        latest_per_frame(rec[rl.CAMERA], "Transform3D:translation")
