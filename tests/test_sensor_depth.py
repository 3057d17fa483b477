"""Sensor depth is opt-in (``kmvipe run --depth``) and read in each dataset's units: a depth.txt lying in a
folder is not used without it; with it, TUM RGB-D depth (5000 per metre) and the ADT sample's (millimetres) arrive
in metres; ``--depth-scale`` overrides the units."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.cli import build_parser
from services.common.errors import SourceError
from services.ingest.config import IngestSettings
from services.ingest.sources import SourceFrame, depth_units, open_source
from services.runner.pipeline import RunSettings, _service_env
from tests.conftest import DATA_DIR

ADT = DATA_DIR / "adt_sample"


def _tum_folder(root: Path, metres=(1.0, 2.0)) -> Path:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for i, m in enumerate(metres):
        t = 10.0 + i / 30
        cv2.imwrite(str(root / "rgb" / f"{i}.png"), np.zeros((16, 20, 3), np.uint8))
        cv2.imwrite(str(root / "depth" / f"{i}.png"), np.full((16, 20), round(5000 * m), np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{i}.png")
        depth_lines.append(f"{t:.6f} depth/{i}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines))
    (root / "depth.txt").write_text("\n".join(depth_lines))
    return root


def test_depth_txt_is_not_used_without_the_flag(tmp_path):
    folder = _tum_folder(tmp_path / "tum")
    frames = list(open_source(str(folder)).frames())
    assert len(frames) == 2 and all(isinstance(f, SourceFrame) and f.depth is None for f in frames)
    assert IngestSettings().use_depth is False
    assert build_parser().parse_args(["run", str(folder)]).depth is False


def test_tum_depth_in_metres_with_the_flag(tmp_path):
    folder = _tum_folder(tmp_path / "tum", (1.0, 2.5))
    assert depth_units(folder) == 5000.0
    frames = list(open_source(str(folder), use_depth=True).frames())
    assert [float(f.depth.mean()) for f in frames] == [1.0, 2.5]
    halved = list(open_source(str(folder), use_depth=True, depth_scale=10000.0).frames())
    assert [float(f.depth.mean()) for f in halved] == [0.5, 1.25]
    with pytest.raises(SourceError):
        open_source(str(folder), use_depth=True, depth_scale=0.0)


@pytest.mark.skipif(not ADT.is_dir(), reason=f"needs {ADT} (set KMVIPE_DATA_DIR)")
def test_adt_sample_depth_in_metres():
    assert depth_units(ADT) == 1000.0  # uint16 millimetres (its README)
    assert all(f.depth is None for f in open_source(str(ADT)).frames())
    frames = [f for f in open_source(str(ADT), use_depth=True).frames() if isinstance(f, SourceFrame)]
    assert [f.depth is not None for f in frames] == [True, True, False]  # frame 3 has no depth render
    raw = cv2.imread(str(ADT / "depth" / "87551170813262.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(frames[0].depth, raw.astype(np.float32) / 1000.0)
    valid = frames[0].depth[frames[0].depth > 0]
    assert 0.2 < float(np.median(valid)) < 6.0  # a kitchen seen from head height, in metres (/5000: 5x too near)


def test_run_flags_reach_the_ingest_service(tmp_path):
    args = build_parser().parse_args(["run", "some/folder", "--depth", "--depth-scale", "1000"])
    assert args.depth is True and args.depth_scale == 1000.0
    env = _service_env("ingest", RunSettings(source="x", out=tmp_path, depth=True, depth_scale=1000.0))
    assert env["KMVIPE_INGEST_USE_DEPTH"] == "true" and float(env["KMVIPE_INGEST_DEPTH_SCALE"]) == 1000.0
    assert _service_env("ingest", RunSettings(source="x", out=tmp_path))["KMVIPE_INGEST_USE_DEPTH"] == "false"


def test_ingest_settings_read_the_environment(monkeypatch):
    monkeypatch.setenv("KMVIPE_INGEST_USE_DEPTH", "true")
    monkeypatch.setenv("KMVIPE_INGEST_DEPTH_SCALE", "1000")
    cfg = IngestSettings()
    assert cfg.use_depth is True and cfg.depth_scale == 1000.0
