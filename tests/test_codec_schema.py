"""The wire layer: array codec round trips, every message kind round trips, and bad payloads only ever raise
DecodeError (never another exception)."""
from __future__ import annotations

import dataclasses
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from services.common import codec, schema
from services.common.errors import DecodeError
from tests.helpers.fuzz import bad_payloads

DTYPES = st.sampled_from([np.uint8, np.int32, np.int64, np.float16, np.float32, np.float64, np.bool_])


@settings(max_examples=200, deadline=None)
@given(hnp.arrays(DTYPES, hnp.array_shapes(min_dims=0, max_dims=4, max_side=7)))
def test_array_round_trip_is_exact(array):
    out = codec.unpack(codec.pack({"a": array}))["a"]
    assert out.dtype == array.dtype and out.shape == array.shape
    np.testing.assert_array_equal(out, array)


def test_decoded_arrays_share_the_payload_buffer():
    payload = codec.pack({"a": np.arange(1000, dtype=np.float32)})
    out = codec.unpack(payload)["a"]
    assert not out.flags.owndata and not out.flags.writeable  # a view on the payload, not a copy


def _examples() -> list[schema.Message]:
    eye = np.tile(np.eye(4), (3, 1, 1))
    img = np.random.default_rng(0).integers(0, 255, (16, 24, 3), dtype=np.uint8)
    k = np.array([20.0, 20.0, 12.0, 8.0])
    return [
        schema.Frame("s", 1, 10, 24, 16, image=img, intrinsics=k, depth=np.ones((16, 24), np.float32)),
        schema.Frame("s", 2, 10, 24, 16, jpeg=b"\xff\xd8abc"),
        schema.Credit("s", 9, 3, consumer="features-1"),
        schema.Keyframe("s", 4, 5, image=img, intrinsics=k, orig_width=48, orig_height=32, pca_version=1,
                        codes=np.zeros((2, 3, 32), np.float16), disparity_prior=np.ones((2, 3), np.float32)),
        schema.KeyframeCodes("s", 4, 7, pca_version=2, codes=np.ones((2, 3, 32), np.float16)),
        schema.FrameLite("s", 5, 6, image=img[..., 0], intrinsics=k, ref_seq=4, realtime=True),
        schema.PcaBasis("s", 0, 0, version=1, backbone="dinov2_vits14", mean=np.zeros(8, np.float32),
                        components=np.eye(3, 8, dtype=np.float32)),
        schema.Graph("s", 4, 0, kf_seqs=np.arange(3), poses=eye, intrinsics=k, width=24, height=16,
                     updated_seqs=np.array([2]), disparities=np.ones((1, 2, 3), np.float32)),
        schema.Poses("s", 4, 0, frame_seqs=np.arange(3), stamps_ns=np.arange(3) * 10, poses=eye, final=True),
        schema.Intrinsics("s", 4, 0, intrinsics=k, width=24, height=16),
        schema.Eos("s", 7, 0, stage="ingest", count=8),
        schema.Eos("s", 7, 0, stage="features", count=3, dropped=2, codes_skipped=1, lost=4),
        schema.Eos("s", 7, 0, stage="ba", count=3, views_lost=np.array([[2, 3]], np.int64), work_s=4.25,
                    frames_strayed=5),
        schema.MapQuery("s", 1, 0, vectors=np.ones((2, 8), np.float32), space="x"),
        schema.KeyframeList("s", 2, 0, seqs=np.array([0, 4]), stamps_ns=np.array([0, 9]),
                            widths=np.array([24, 24], np.int32), heights=np.array([16, 16], np.int32),
                            has_codes=np.array([1, 0], np.uint8), has_thumbnail=np.array([1, 1], np.uint8)),
        schema.KeyframeThumbnail("s", 4, 0, jpeg=b"\xff\xd8abc", width=12, height=8),
        schema.KeyframeQuery("s", 1, 0, keyframe=4, box=np.array([0.1, 0.2, 0.5, 0.6])),
        schema.KeyframeRefusal("s", 4, 0, status="no_codes", reason="not yet"),
        schema.MapSessions("s", 0, 0, current="b", names="a\nb", keyframes=np.array([3, 1]),
                           finished=np.array([1, 0], np.uint8)),
    ]


@pytest.mark.parametrize("msg", _examples(), ids=lambda m: m.KIND)
def test_every_message_round_trips(msg):
    out = schema.decode(msg.encode())
    assert type(out) is type(msg)
    for f in dataclasses.fields(msg):
        a, b = getattr(msg, f.name), getattr(out, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b, f.name


def test_every_kind_has_an_example():
    assert {m.KIND for m in _examples()} | {"map_answer", "map_segment", "map_chunk", "map_stats"} == set(schema.MESSAGES)


@pytest.mark.parametrize(
    "body, error",
    [
        ({"kind": "frame", "v": 99}, "version"),
        ({"kind": "nope", "v": 1}, "unknown message kind"),
        ({"kind": "credit", "v": 1, "stream": "s", "seq": "x", "t_ns": 0}, "field 'seq' must be int"),
        ({"kind": "credit", "v": 1, "stream": "s", "t_ns": 0}, "missing field 'seq'"),
        ({"kind": "frame", "v": 1, "stream": "s", "seq": 0, "t_ns": 0, "width": 4, "height": 2}, "exactly one"),
        ({"kind": "frame", "v": 1, "stream": "s", "seq": 0, "t_ns": 0, "width": 4, "height": 2,
          "image": np.zeros((2, 4), np.uint8)}, "expected 3 dims"),
        ({"kind": "frame", "v": 1, "stream": "s", "seq": 0, "t_ns": 0, "width": 4, "height": 2,
          "image": np.zeros((2, 4, 3), np.float32)}, "dtype float32"),
        ({"kind": "pca", "v": 1, "stream": "s", "seq": 0, "t_ns": 0, "version": 1, "backbone": "b",
          "mean": np.zeros(5, np.float32), "components": np.zeros((2, 6), np.float32)}, "disagrees"),
    ],
)
def test_invalid_messages_say_what_is_wrong(body, error):
    with pytest.raises(DecodeError, match=error):
        schema.decode(codec.pack(body))


def test_expected_kind_is_enforced():
    with pytest.raises(DecodeError, match="expected a 'frame'"):
        schema.decode(schema.Credit("s", 1, 0).encode(), expect=schema.Frame)


def test_garbage_only_ever_raises_decode_error():
    """10,000 random, truncated and bit-flipped payloads: DecodeError or a valid message, nothing else."""
    for payload in bad_payloads([m.encode() for m in _examples()], 10_000):
        try:
            schema.decode(payload)
        except DecodeError:
            pass
