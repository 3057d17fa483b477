"""Sources: every kind opens, yields RGB frames in order, reports unreadable frames and goes on, and refuses
what it cannot open with a message that says how to fix it."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.common.errors import SourceError
from services.ingest.sources import BadFrame, SourceFrame, open_source


def _write_images(folder: Path, n: int, size=(40, 32)) -> list[np.ndarray]:
    folder.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        rgb = np.zeros((size[1], size[0], 3), np.uint8)
        rgb[..., 0] = 10 * i  # red channel encodes the index, so order and colour order are both checked
        cv2.imwrite(str(folder / f"{i:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        frames.append(rgb)
    return frames


def test_plain_image_folder_in_order_and_rgb(tmp_path):
    expected = _write_images(tmp_path, 5)
    got = list(open_source(str(tmp_path)).frames())
    assert [f.index for f in got] == list(range(5))
    for f, e in zip(got, expected):
        np.testing.assert_array_equal(f.rgb, e)


def test_corrupt_image_is_reported_and_stream_goes_on(tmp_path):
    _write_images(tmp_path, 4)
    (tmp_path / "000002.png").write_bytes(b"not a png")
    got = list(open_source(str(tmp_path)).frames())
    assert [type(f) for f in got] == [SourceFrame, SourceFrame, BadFrame, SourceFrame]
    assert "000002.png" in got[2].reason


def test_tum_folder_with_depth(tmp_path):
    _write_images(tmp_path / "rgb", 3)
    (tmp_path / "depth").mkdir()
    lines, dlines = [], []
    for i in range(3):
        t = 100.0 + i / 30
        lines.append(f"{t:.6f} rgb/{i:06d}.png")
        cv2.imwrite(str(tmp_path / "depth" / f"{i}.png"), np.full((32, 40), 5000 * (i + 1), np.uint16))
        dlines.append(f"{t + 0.005:.6f} depth/{i}.png")
    (tmp_path / "rgb.txt").write_text("# rgb\n" + "\n".join(lines))
    (tmp_path / "depth.txt").write_text("\n".join(dlines))
    got = list(open_source(str(tmp_path), use_depth=True).frames())  # depth is opt-in
    assert [f.t_ns for f in got] == [int(round(float(f"{100.0 + i / 30:.6f}") * 1e9)) for i in range(3)]
    assert [float(f.depth.mean()) for f in got] == [1.0, 2.0, 3.0]  # metres (TUM: 5000 per metre)


def test_kitti_layout(tmp_path):
    _write_images(tmp_path / "image_0", 3)
    (tmp_path / "times.txt").write_text("0.0\n0.103\n0.207\n")
    src = open_source(str(tmp_path))
    assert [f.t_ns for f in src.frames()] == [0, 103_000_000, 207_000_000]


def test_video_file(tmp_path):
    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (64, 48))
    for i in range(12):
        writer.write(np.full((48, 64, 3), 20 * i, np.uint8))
    writer.release()
    src = open_source(str(path))
    frames = list(src.frames())
    assert src.fps == pytest.approx(25)
    assert len(frames) == 12 and all(isinstance(f, SourceFrame) for f in frames)
    assert [round(float(f.rgb.mean()) / 20) for f in frames] == list(range(12))
    assert frames[5].t_ns == int(5 * 1e9 / 25)


@pytest.mark.parametrize(
    "spec, message",
    [
        ("", "no source given"),
        ("/nonexistent/video.mp4", "not found"),
        ("57", "camera index"),
        ("synth:frames=x", "bad synthetic source option"),
        ("synth:bogus=1", "unknown synthetic source option"),
    ],
)
def test_unopenable_sources_say_how_to_fix(spec, message):
    with pytest.raises(SourceError, match=message):
        open_source(spec)


def test_empty_folder(tmp_path):
    with pytest.raises(SourceError, match="no images found"):
        open_source(str(tmp_path))


def test_synthetic_source_is_the_synthetic_world():
    from services.synth import SynthConfig, SynthWorld

    frames = list(open_source("synth:frames=3,seed=4,width=64,height=48").frames())
    world = SynthWorld(SynthConfig(n_frames=3, seed=4, width=64, height=48))
    np.testing.assert_array_equal(frames[2].rgb, world.render(2).rgb)
    assert frames[2].depth is None


@pytest.mark.data
def test_real_sequences_open(data_dir):
    kitti = open_source(str(data_dir / "kitti07_160"))
    first = next(iter(kitti.frames()))
    assert first.rgb.shape == (370, 1226, 3)
    assert len(kitti.entries) == 160
    vtest = open_source(str(data_dir / "vtest" / "vtest.avi"))
    assert next(iter(vtest.frames())).rgb.shape == (576, 768, 3)
