"""The one PLY writer (services/common/ply.py): the gateway's streamed PLY — the header for the announced count, then
the vertex blocks of each chunk — is byte for byte the file plyfile (the reference implementation, a test-only
dependency: it is GPL) writes for the whole map; plyfile reads the export's files, binary and ascii."""
from __future__ import annotations

import io

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from services.common import ply
from services.query_api.core import ply as gateway_ply


def whole_file(vertices: np.ndarray, comments: list[str]) -> bytes:
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(vertices, "vertex")], byte_order="<", comments=comments).write(buffer)
    return buffer.getvalue()


@pytest.mark.parametrize("labelled", [False, True])
def test_a_streamed_map_is_the_file_plyfile_writes(labelled):
    rng = np.random.default_rng(0)
    n = 1000
    xyz, rgb = rng.normal(size=(n, 3)).astype(np.float32), rng.integers(0, 256, (n, 3), dtype=np.uint8)
    label, score = (rng.integers(-1, 5, n), rng.random(n).astype(np.float32)) if labelled else (None, None)
    chunks = np.split(np.arange(n), [300, 301, 700])  # uneven chunks, one of a single point
    streamed = gateway_ply.header(n, labelled, comment="KM-ViPE map of stream cam0") + b"".join(
        gateway_ply.vertices(xyz[c], rgb[c], None if label is None else label[c], None if score is None else score[c])
        for c in chunks)
    layout = ply.SCORED if labelled else ply.VERTEX
    fields = {"label": label, "score": score} if labelled else {}
    assert streamed == whole_file(ply.records(layout, xyz, rgb, **fields), ["KM-ViPE map of stream cam0"])
    back = gateway_ply.read(streamed)
    np.testing.assert_array_equal(np.stack([back["x"], back["y"], back["z"]], 1), xyz)
    np.testing.assert_array_equal(np.stack([back["red"], back["green"], back["blue"]], 1), rgb)
    if labelled:
        np.testing.assert_array_equal(back["label"], label)
        np.testing.assert_array_equal(back["score"], score)


def test_reading_refuses_a_body_that_does_not_match_its_header():
    xyz, rgb = np.zeros((7, 3), np.float32), np.zeros((7, 3), np.uint8)
    with pytest.raises(ValueError, match="announces 8"):
        gateway_ply.read(gateway_ply.header(8) + gateway_ply.vertices(xyz, rgb))
    with pytest.raises(ValueError, match="announces 6"):
        gateway_ply.read(gateway_ply.header(6) + gateway_ply.vertices(xyz, rgb))
    with pytest.raises(ValueError, match="not a vertex PLY"):
        ply.read(b"not a ply\n")


@pytest.mark.parametrize("text", [False, True])
def test_plyfile_reads_what_the_export_writes(tmp_path, text):
    rng = np.random.default_rng(1)
    xyz, rgb = rng.normal(size=(50, 3)).astype(np.float32), rng.integers(0, 256, (50, 3), dtype=np.uint8)
    labels = {f"label_{c}": rng.integers(0, 256, 50).astype(np.uint8) for c in ("red", "green", "blue")}
    rec = ply.records(ply.LABEL_COLOURED, xyz, rgb, **labels)
    path = ply.write(tmp_path / "map.ply", rec, text=text, comments=["KM-ViPE map"])
    theirs = PlyData.read(str(path))
    assert theirs.text == text and theirs.comments == ["KM-ViPE map"]
    np.testing.assert_array_equal(np.asarray(theirs["vertex"].data.tolist()), np.asarray(rec.tolist()))
    np.testing.assert_array_equal(ply.read(path), rec)


def test_a_comment_stays_on_its_header_line_and_bad_fields_are_refused():
    head = gateway_ply.header(0, comment="labels: chair |\ntable").decode()
    assert "comment labels: chair | table\n" in head and ply.read(head.encode()).shape == (0,)
    with pytest.raises(ValueError, match="must be"):
        gateway_ply.vertices(np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="both"):
        gateway_ply.vertices(np.zeros((3, 3)), np.zeros((3, 3)), label=np.zeros(3))
    with pytest.raises(ValueError, match="do not match the layout"):
        ply.records(ply.SCORED, np.zeros((3, 3)), np.zeros((3, 3)), label=np.zeros(3))
