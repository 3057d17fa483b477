"""ba's checkpoints (issue 15 item 1) and features' replay of what ba has not checkpointed: a state restored from a
checkpoint continues exactly as the uninterrupted one; a kill mid-write leaves the previous checkpoint; features
sends a resumed ba everything after its checkpoint, once, and keeps nothing while no ba checkpoints."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from services.ba import recovery, service
from services.ba.checkpoint import Checkpointer, path_for, snapshot
from services.ba.settings import BaSettings
from services.common import keys
from services.common.schema import Credit, Eos, FrameLite, Keyframe, KeyframeCodes, Poses
from services.features.replay import ReplayBuffer
from tests.test_ba_pipeline_synth import synth_stream

STREAM = "t0"


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device here (bench/gpu_check.sh runs it on a lent GPU)"))]


def _settings(device: str = "cpu") -> BaSettings:
    return BaSettings(stream=STREAM, device=device, threads=1, init_min_flow=0.5, focal_after=3, iterations=2,
                      global_iterations=3)


def _final_poses(outputs) -> Poses:
    return [m for _, m in outputs if isinstance(m, Poses)][-1]


def _state_after(handled: int, rendered: int, width: int, device: str = "cpu"):
    """(settings, every message of a synthetic stream, a ba state that has handled the first ``handled``)."""
    cfg = _settings(device)
    _, msgs = synth_stream(n_frames=40, rendered=rendered, every=4, stream=STREAM, width=width)
    state = service.build_state(cfg)
    for msg in msgs[:handled]:
        service.handle(state, msg, cfg)
    return cfg, msgs, state


# on CUDA too: ba keeps flow targets, codes and priors on the CPU, and a restore must not move them to the device
@pytest.mark.parametrize("device", DEVICES)
def test_a_state_restored_from_its_checkpoint_continues_exactly_like_the_uninterrupted_one(tmp_path, device):
    cfg, msgs, uninterrupted = _state_after(14, rendered=25, width=256, device=device)
    saver = Checkpointer(str(tmp_path), STREAM, "s1", period_s=0.0)
    assert saver.due()
    saver.save(uninterrupted)
    assert saver.durable == 13 and path_for(tmp_path, STREAM, "s1").is_file()

    resumed = service.build_state(cfg)  # a new process: nothing but the file
    loader = Checkpointer(str(tmp_path), STREAM, "s1", period_s=2.0)
    assert recovery.resume(resumed, loader, cfg) == 13 and loader.durable == 13
    assert resumed.frontend.graph.seqs == uninterrupted.frontend.graph.seqs and resumed.keyframes == 4
    for msg in msgs[14:]:
        a, b = service.handle(uninterrupted, msg, cfg), service.handle(resumed, msg, cfg)
    pa, pb = _final_poses(a), _final_poses(b)
    assert pa.final and pa.frame_seqs.tolist() == pb.frame_seqs.tolist() == list(range(25))
    # the same world frame, the same numbers (CUDA's reductions may differ in the last bits)
    np.testing.assert_allclose(pa.poses, pb.poses, rtol=0, atol=0 if device == "cpu" else 1e-6)

    other = Checkpointer(str(tmp_path), STREAM, "s2", period_s=0.0)  # another session never resumes this one
    assert other.load(resumed.frontend.device) is None


def test_a_checkpoint_of_the_version_before_the_principal_point_resumes(tmp_path):
    """Written before the principal point was refined: no ``first_principal`` in the graph (the principal point was
    held at its first guess, so that is where it still is), and ``_focal`` where the frontend now keeps
    ``_published``. A ba upgraded mid-stream resumes from it and ends the stream."""
    cfg, msgs, old = _state_after(14, rendered=25, width=256)
    held = tuple(float(v) for v in old.frontend.graph.intrinsics[2:])
    del old.frontend.graph.first_principal, old.frontend._published
    old.frontend._focal = float(old.frontend.graph.intrinsics[0])
    Checkpointer(str(tmp_path), STREAM, "s1", period_s=0.0).save(old)
    resumed = service.build_state(cfg)
    assert recovery.resume(resumed, Checkpointer(str(tmp_path), STREAM, "s1", period_s=2.0), cfg) == 13
    assert resumed.frontend.graph.first_principal == held
    for msg in msgs[14:]:
        out = service.handle(resumed, msg, cfg)
    final = _final_poses(out)
    assert final.final and final.frame_seqs.tolist() == list(range(25))
    assert np.isfinite(final.poses).all()


def test_landmarks_survive_a_restart(tmp_path):
    # 4 keyframes held, so the stream's first keyframes leave early and some stay as landmarks
    cfg = _settings().model_copy(update={"window": 3, "keep_keyframes": 4, "landmark_keyframes": 2})
    _, msgs = synth_stream(n_frames=40, rendered=40, every=4, stream=STREAM, width=128)
    uninterrupted = service.build_state(cfg)
    for msg in msgs[:30]:
        service.handle(uninterrupted, msg, cfg)
    assert uninterrupted.frontend.graph.landmarks
    Checkpointer(str(tmp_path), STREAM, "s1", period_s=0.0).save(uninterrupted)
    resumed = service.build_state(cfg)
    assert recovery.resume(resumed, Checkpointer(str(tmp_path), STREAM, "s1", period_s=2.0), cfg) == 29
    assert resumed.frontend.graph.landmarks == uninterrupted.frontend.graph.landmarks
    for msg in msgs[30:-1]:
        service.handle(uninterrupted, msg, cfg), service.handle(resumed, msg, cfg)
    assert resumed.frontend.graph.landmarks == uninterrupted.frontend.graph.landmarks
    a, b = service.handle(uninterrupted, msgs[-1], cfg), service.handle(resumed, msgs[-1], cfg)  # the EOS
    pa, pb = _final_poses(a), _final_poses(b)
    assert pa.final and pa.frame_seqs.tolist() == pb.frame_seqs.tolist()  # those still held; the rest went out before
    np.testing.assert_allclose(pa.poses, pb.poses, rtol=0, atol=0)


def test_a_kill_while_writing_leaves_the_previous_checkpoint(tmp_path):
    _, _, state = _state_after(6, rendered=9, width=128)
    saver = Checkpointer(str(tmp_path), STREAM, "s1", period_s=0.0)
    saver.save(state)
    # a process killed mid-write leaves a partial temporary file; the checkpoint itself is the last whole one
    partial = snapshot(state)[:1000]
    saver.path.with_suffix(saver.path.suffix + ".tmp").write_bytes(partial)
    loaded = Checkpointer(str(tmp_path), STREAM, "s1", period_s=0.0).load(state.frontend.device)
    assert loaded is not None and loaded.seq == 5
    saver.path.write_bytes(partial)  # a damaged checkpoint: logged, the stream starts afresh instead of crashing
    assert Checkpointer(str(tmp_path), STREAM, "s1", period_s=0.0).load(state.frontend.device) is None
    saver.remove()
    assert not saver.path.exists()


def _frame(seq: int) -> FrameLite:
    return FrameLite(STREAM, seq, seq, image=np.zeros((4, 4), np.uint8), intrinsics=np.ones(4), ref_seq=0)


def _keyframe(seq: int) -> Keyframe:
    return Keyframe(STREAM, seq, seq, image=np.zeros((8, 8, 3), np.uint8), intrinsics=np.ones(4))


def _progress(consumer: str, seq: int, durable: int, checkpoints: bool = True) -> Credit:
    return Credit(STREAM, seq, 0, consumer=consumer, checkpoints=checkpoints, durable=durable)


def test_features_sends_a_resumed_ba_what_came_after_its_checkpoint_once():
    replay = ReplayBuffer(max_messages=100)
    key = lambda m: keys.topic(STREAM, m.KIND if not isinstance(m, FrameLite) else keys.FRAME_LITE)  # noqa: E731
    replay.record(key(_frame(0)), _frame(0))  # no ba has said it checkpoints: nothing kept
    assert replay.on_progress(_progress("ba-a.1", -1, -1, checkpoints=False)) == []
    assert not replay.active
    assert replay.on_progress(_progress("ba-a.1", 0, -1)) == [] and replay.active
    sent = [_frame(1), _keyframe(2), _frame(3), _keyframe(4), _frame(5), _frame(6)]
    for msg in sent:
        replay.record(key(msg), msg)
    codes = KeyframeCodes(STREAM, 2, 0, pca_version=1, codes=np.zeros((1, 1, 2), np.float16))
    replay.record(keys.topic(STREAM, keys.CODES), codes)
    replay.on_progress(_progress("ba-a.1", 6, 3))  # its checkpoint holds up to frame 3
    replay.on_progress(_progress("mapstore-x", 6, -1))  # not ba: ignored
    eos = Eos(STREAM, 6, 0, stage="features", count=3)
    replay.record(keys.topic(STREAM, keys.EOS), eos)
    assert replay.due() == []  # nobody resumed
    # ba is killed; a new instance resumes from the checkpoint and says so
    assert replay.on_progress(_progress("ba-b.2", 3, 3)) == ["ba-a.1"]
    again = replay.due()
    assert [(type(m).__name__, m.seq) for _, m in again] == [
        ("Keyframe", 4), ("FrameLite", 5), ("FrameLite", 6), ("Eos", 6), ("KeyframeCodes", 2)]
    assert replay.due() == [] and replay.replayed == 5  # once
    assert replay.on_progress(_progress("ba-b.2", 6, 6)) == []  # the same instance again: no replay
    assert replay.due() == []


def test_a_consumer_that_resumes_past_a_gap_gets_what_was_sent_while_none_was_up():
    """The mapstore had committed keyframe 2 when it was killed; keyframe 4 went out while none was up and 6 after
    the new instance subscribed, so its first report says 6: features must send 4 again (and 6, taken once)."""
    replay = ReplayBuffer(prefix="mapstore-", kinds=(Keyframe,))
    key = keys.topic(STREAM, keys.KEYFRAME)
    replay.on_progress(_progress("mapstore-a.1", 0, 0))
    for seq in (0, 2):
        replay.record(key, _keyframe(seq))
    replay.on_progress(_progress("mapstore-a.1", 2, 2))  # committed up to 2, then killed
    for seq in (4, 6):
        replay.record(key, _keyframe(seq))
    assert replay.on_progress(_progress("mapstore-b.2", 6, 6)) == ["mapstore-a.1"]
    replay.record(key, _keyframe(8))  # the loop keeps sending before it gets to the replay
    assert [m.seq for _, m in replay.due()] == [4, 6, 8]


def test_a_full_replay_buffer_gives_up_the_oldest_and_counts_them():
    replay = ReplayBuffer(max_messages=3)
    replay.on_progress(_progress("ba-a.1", -1, -1))
    for seq in range(5):
        replay.record(keys.topic(STREAM, keys.FRAME_LITE), _frame(seq))
    assert replay.given_up == 2
    replay.on_progress(_progress("ba-b.2", -1, -1))  # resumed with no checkpoint at all
    assert [m.seq for _, m in replay.due()] == [2, 3, 4]


def test_ingest_sends_a_restarted_features_the_frames_it_had_not_handled():
    from services.common.schema import Frame
    from services.ingest.resend import ResendBuffer

    def frame(seq: int) -> Frame:
        return Frame(STREAM, seq, seq, 2, 2, image=np.zeros((2, 2, 3), np.uint8))

    resend = ResendBuffer()
    resend.on_credit(Credit(STREAM, 5, 0, consumer="features-a.1", checkpoints=True, durable=1))
    for seq in range(5):
        resend.record(frame(seq))
    resend.on_credit(Credit(STREAM, 7, 0, consumer="features-a.1", checkpoints=True, durable=3))
    resend.on_credit(Credit(STREAM, 9, 0, consumer="ingest-x", checkpoints=True, durable=9))  # not features
    resend.record(Eos(STREAM, 4, 0, stage="ingest", count=5))
    assert resend.due() == []  # nobody restarted
    resend.on_credit(Credit(STREAM, 3, 0, consumer="features-b.2", checkpoints=True, durable=-1))
    again = resend.due()
    assert [(type(m).__name__, m.seq) for m in again] == [("Frame", 4), ("Eos", 4)]  # after 3, once
    assert again[0].features_handled == 3  # the new instance answers for what came after it
    assert resend.due() == []
    resend.on_credit(Credit(STREAM, 9, 0, consumer="features-b.2", checkpoints=True, durable=4))
    resend.on_credit(Credit(STREAM, 3, 0, consumer="features-c.3", checkpoints=True, durable=-1))
    # everything was handled: the newest frame again, so the new instance learns where the stream is
    assert [(type(m).__name__, m.seq) for m in resend.due()] == [("Frame", 4), ("Eos", 4)]


def test_ingest_keeps_no_frames_for_a_consumer_that_never_reports_what_it_handled():
    from services.common.schema import Frame
    from services.ingest.resend import ResendBuffer

    resend = ResendBuffer()
    resend.on_credit(Credit(STREAM, 500, 0, consumer="recorder", checkpoints=False))  # not features
    for seq in range(200):
        resend.record(Frame(STREAM, seq, seq, 2, 2, image=np.zeros((2, 2, 3), np.uint8)))
    assert len(resend._frames) == 0  # a lossless stream to it must not hold every frame it sent
    resend.on_credit(Credit(STREAM, 300, 0, consumer="features-a.1", checkpoints=True, durable=199))
    resend.record(Frame(STREAM, 200, 200, 2, 2, image=np.zeros((2, 2, 3), np.uint8)))
    assert [f.seq for f in resend._frames] == [200]  # from its first report on, it is kept until handled
