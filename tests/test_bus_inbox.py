"""The inbox's drop policy: lossless never drops; real-time drops the oldest frames first and never keyframes,
codes, bases or EOS."""
from __future__ import annotations

import numpy as np

from services.common.bus import Delivery, Inbox
from services.common.schema import Eos, FrameLite, Keyframe, KeyframeCodes

K = np.array([10.0, 10.0, 4.0, 4.0])


def _lite(seq: int) -> Delivery:
    return Delivery("kmvipe/s/frame_lite", FrameLite("s", seq, seq, image=np.zeros((4, 4), np.uint8), intrinsics=K))


def _keyframe(seq: int) -> Delivery:
    return Delivery("kmvipe/s/keyframe", Keyframe("s", seq, seq, image=np.zeros((8, 8, 3), np.uint8), intrinsics=K))


def _drain(box: Inbox) -> list[int]:
    out = []
    while (d := box.get(0)) is not None:
        out.append(d.msg.seq)
    return out


def test_lossless_inbox_keeps_everything_past_its_bound():
    box = Inbox(3, lossless=True, droppable=(FrameLite,))
    for seq in range(6):
        box.put(_lite(seq))
    assert _drain(box) == list(range(6))
    assert box.dropped == 0 and box.overflowed == 3


def test_realtime_inbox_drops_the_oldest_frames_first():
    box = Inbox(3, lossless=False, droppable=(FrameLite,))
    for seq in range(6):
        box.put(_lite(seq))
    assert _drain(box) == [3, 4, 5]
    assert box.dropped_by_kind == {"frame_lite": 3}


def test_realtime_inbox_never_drops_keyframes_codes_or_eos():
    box = Inbox(2, lossless=False, droppable=(FrameLite,))
    box.put(_keyframe(0))
    box.put(_lite(1))
    box.put(_keyframe(2))  # full: the frame goes, the keyframe stays
    box.put(Delivery("kmvipe/s/codes", KeyframeCodes("s", 0, 0, pca_version=1, codes=np.zeros((1, 1, 2), np.float16))))
    box.put(Delivery("kmvipe/s/eos", Eos("s", 3, 0, stage="features")))
    box.put(_lite(4))  # full of essentials: the incoming frame is dropped
    assert _drain(box) == [0, 2, 0, 3]
    assert box.dropped_by_kind == {"frame_lite": 2}


def test_get_times_out_on_an_empty_inbox():
    assert Inbox(2).get(0.01) is None


def test_the_inbox_tells_of_every_frame_it_drops():
    told = []
    box = Inbox(2, lossless=False, droppable=(FrameLite,), on_drop=lambda d: told.append(d.msg.seq))
    for seq in range(5):
        box.put(_lite(seq))
    assert told == [0, 1, 2] and _drain(box) == [3, 4]


def test_a_widened_inbox_holds_until_it_drains_back_to_its_bound():
    box = Inbox(3, droppable=(FrameLite,))
    box.widen(10)  # its consumer is starting: what comes is early, not stale
    for seq in range(8):
        box.put(_lite(seq))
    assert box.dropped == 0 and box.qsize() == 8
    assert [box.get(0).msg.seq for _ in range(5)] == [0, 1, 2, 3, 4]  # the consumer catches up
    assert box.bound == 3
    for seq in range(8, 10):
        box.put(_lite(seq))
    assert _drain(box) == [7, 8, 9] and box.dropped_by_kind == {"frame_lite": 2}  # the real-time policy again
