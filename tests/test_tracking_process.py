"""Tracking in a child process (services/ba/tracking_process.py): the same poses as the tracker on the calling
thread, against the synthetic world's exact trajectory; a child that is killed is started again from the last
reference and the frame in hand still gets its pose."""
from __future__ import annotations

import os
import pickle
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from services.ba.settings import BaSettings
from services.ba.tracking_process import LocalTracker, TrackerProcess, pack_reference, unpack_reference
from tests.test_ba_tracker import _errors, _grey, _reference

synth = pytest.importorskip("services.synth")


@pytest.fixture(scope="module")
def world():
    return synth.SynthWorld(synth.SynthConfig(n_frames=60, width=512, height=384))


@pytest.fixture
def process():
    proc = BaSettings(tracking_process=True).tracking_core()
    assert isinstance(proc, TrackerProcess)
    proc.start()
    yield proc
    proc.close()


def _track(tracker, world, frames):
    out = []
    for i in frames:
        f = world.render(i)
        grey = _grey(f.rgb, half=True)
        out.append(tracker.step(False, i, f.t_ns, grey, np.asarray(f.intrinsics) / 2))
    return out


def test_a_reference_crosses_the_pipe_unchanged(world):
    ref = _reference(world, 0)._replace(previous=(5, np.eye(4)), speed=2e-10)
    back = unpack_reference(pickle.loads(pickle.dumps(pack_reference(ref))))
    assert back.speed == ref.speed
    for name in ("pose", "disparity", "intrinsics"):
        assert np.array_equal(getattr(back, name), getattr(ref, name))
    assert back.seq == ref.seq and np.array_equal(back.image, ref.image) and np.array_equal(back.previous[1],
                                                                                            ref.previous[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the child's /proc/<pid>/maps")
def test_the_tracking_process_runs_without_torch(world, process):
    """The child maps only the tracker's libraries (numpy and OpenCV): torch would cost it ~200 MB of memory and
    seconds of start. Checked on the spawned child itself, after it tracked a frame."""
    process.set_reference(_reference(world, 0))
    assert _track(process, world, [1])[0].ok
    libraries = Path(f"/proc/{process._proc.pid}/maps").read_text()
    assert "libtorch" not in libraries and "libc10" not in libraries


def test_the_child_tracks_as_the_thread_does_to_the_exact_trajectory(world, process):
    local = LocalTracker(BaSettings(tracking_process=False).tracker_factory())
    for tracker in (local, process):
        tracker.set_reference(_reference(world, 0))
    step = float(np.linalg.norm(world.poses[5, :3, 3] - world.poses[0, :3, 3]))
    ours, theirs = _track(process, world, range(1, 6)), _track(local, world, range(1, 6))
    for i, (a, b) in enumerate(zip(ours, theirs), start=1):
        assert a.ok and a.ref_seq == 0 and np.allclose(a.pose, b.pose, atol=1e-9)
        trans, rot = _errors(a.pose, world.poses[i])
        assert trans < 0.05 * step + 2e-3 and rot < 0.3, (i, trans, rot)
        assert np.allclose(world.poses[0] @ a.ref_from_cam, a.pose)  # relative to the reference keyframe
    predicted = process.predict(world.render(6).t_ns)
    assert predicted is not None and np.allclose(predicted, local.predict(world.render(6).t_ns), atol=1e-9)


def test_a_pose_the_child_refuses_for_mappings_speed_comes_back_marked(world, process):
    """Tracking's speed bound (tests/test_ba_tracker.py) holds in the child too, and the parent learns which frames
    kept the prediction for it (the tracking loop counts and logs them)."""
    ref = _reference(world, 0)
    process.set_reference(ref._replace(speed=1e-6 / max(world.render(1).t_ns - ref.stamp, 1)))
    out = _track(process, world, [1])[0]
    assert not out.ok and out.refused and out.ref_from_cam is None


def test_a_killed_child_is_started_again_from_the_last_reference(world, process):
    process.set_reference(_reference(world, 0))
    first = _track(process, world, [1])[0]
    os.kill(process._proc.pid, signal.SIGKILL)
    process._proc.join(timeout=5)
    again = _track(process, world, [2])[0]
    assert process.restarts == 1
    assert again is not None and again.ok and again.ref_seq == 0  # it tracked against mapping's reference
    fresh = LocalTracker(BaSettings(tracking_process=False).tracker_factory())  # no motion history, as the new child
    fresh.set_reference(_reference(world, 0))
    assert first.ok and np.allclose(again.pose, _track(fresh, world, [2])[0].pose, atol=1e-9)
    trans, _ = _errors(again.pose, world.poses[2])
    assert trans < 0.1 * float(np.linalg.norm(world.poses[2, :3, 3] - world.poses[0, :3, 3]))


def test_an_error_in_the_child_is_raised_here_and_the_child_serves_on(world, process):
    process.set_reference(_reference(world, 0))
    with pytest.raises(RuntimeError, match="image expected"):  # the child's error, raised on this side
        process.step(False, 1, 0, np.zeros((2, 2, 2, 2), np.uint8), np.array([1.0, 1.0, 0.0, 0.0]))
    assert _track(process, world, [1])[0].ok and process.restarts == 0


def test_keyframes_tracking_moves_on_to_keep_the_following_frames_on_the_exact_trajectory(world, process):
    """Mapping stays at keyframe 0 while keyframes 3 and 6 come (its BA is behind): tracking promotes keyframe 6 with
    its working-size image and carried-over depth, and frames after it are tracked against it."""
    process.set_reference(_reference(world, 0))
    for i in (1, 2, 3, 4, 5, 6, 7, 8):
        f = world.render(i)
        if i in (3, 6):  # keyframes come at working size, in colour, with their working intrinsics
            out = process.step(True, i, f.t_ns, f.rgb, np.asarray(f.intrinsics, np.float64))
        else:
            out = process.step(False, i, f.t_ns, _grey(f.rgb, half=True), np.asarray(f.intrinsics) / 2)
        assert out is not None and out.ok, i
        trans, rot = _errors(out.pose, world.poses[i])
        travelled = float(np.linalg.norm(world.poses[i, :3, 3] - world.poses[0, :3, 3]))
        assert trans < 0.1 * travelled + 5e-3 and rot < 0.5, (i, trans, rot)
        assert out.ref_seq == (6 if i > 6 else 0), (i, out.ref_seq)  # after keyframe 6, aligned to it


def test_a_process_started_ahead_is_taken_by_the_first_stream_with_the_same_settings(world):
    from services.ba import tracking_process

    settings = BaSettings()
    tracking_process.prewarm(settings.tracker_factory())
    other = TrackerProcess(BaSettings(tracking_promote_after=3).tracker_factory())
    same = settings.tracking_core()
    try:
        other_started = tracking_process._take_spare(other.make_tracker, other.niceness)
        assert other_started is None  # other settings: the spare is not theirs (and is closed)
        tracking_process._Spare.starting = None
        tracking_process.prewarm(settings.tracker_factory())
        spare_pid = None
        tracking_process._Spare.starting.join(60)
        spare_pid = tracking_process._Spare.ready._proc.pid
        same.start()
        assert same._proc.pid == spare_pid and tracking_process._Spare.ready is None
        same.set_reference(_reference(world, 0))
        assert _track(same, world, [1])[0].ok
    finally:
        same.close()
        tracking_process._Spare.starting = tracking_process._Spare.ready = None


def test_frames_that_come_while_the_tracking_process_starts_are_held_and_all_posed(world, unix_endpoint):
    """A stream's first frames arrive while its tracking process starts (no process started ahead): the
    real-time inbox holds them rather than drop them (a frame before the map that is dropped gets no pose at all),
    and once tracking caught up the inbox is back at its real-time bound."""
    from services.ba.tracking import TrackingLoop
    from services.common import keys
    from services.common.bus import Bus, Delivery, Inbox
    from services.common.config import BusSettings
    from services.common.schema import FrameLite

    frames = []
    for i in range(12):  # rendered first: they must all arrive while the process starts, not as fast as a loaded
        f = world.render(i)  # machine renders them (the startup backlog ends once the tracker is up)
        frames.append(FrameLite("cam1", i, f.t_ns, image=_grey(f.rgb, half=True),
                                intrinsics=np.asarray(f.intrinsics, np.float64) / 2, realtime=True))
    with Bus(BusSettings(listen=[unix_endpoint]), "ba", "test") as bus:
        inbox = Inbox(3, droppable=(FrameLite,))
        loop = TrackingLoop(TrackerProcess(BaSettings().tracker_factory()), bus, inbox, "cam1", {})
        loop.start()
        for lite in frames:
            inbox.put(Delivery(keys.topic("cam1", keys.FRAME_LITE), lite))
        deadline = time.monotonic() + 60
        while loop.tracked < len(frames) and time.monotonic() < deadline:
            time.sleep(0.05)
        loop.stop()
    assert inbox.dropped == 0 and loop.tracked == len(frames)  # each one a provisional pose before the map
    assert loop.in_process and inbox.maxsize == 3 and inbox.bound == 3  # back at its real-time bound


def test_a_process_started_ahead_that_no_stream_took_is_closed_once_it_is_up():
    """ba stopped right after it started: the spare finishes coming up and is closed, not cut off mid-spawn (that
    left an EOFError traceback in ba's log)."""
    import multiprocessing

    from services.ba import tracking_process

    def tracking_children():
        return [p for p in multiprocessing.active_children() if p.name == "kmvipe-tracking"]

    try:
        tracking_process.prewarm(BaSettings().tracker_factory())
        tracking_process.discard_spare()  # at once: while the child is still coming up
        assert tracking_process._Spare.ready is None and not tracking_children()
        tracking_process._Spare.starting = None  # again, with the spare up before it is discarded
        tracking_process.prewarm(BaSettings().tracker_factory())
        tracking_process._Spare.starting.join(60)
        spare = tracking_process._Spare.ready._proc
        assert spare.is_alive() and tracking_children() == [spare]
        tracking_process.discard_spare()
        assert not spare.is_alive() and spare.exitcode == 0 and not tracking_children()
    finally:
        tracking_process._Spare.starting = tracking_process._Spare.ready = None
