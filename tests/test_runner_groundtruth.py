"""The true intrinsics of a run's source, read the way the datasets store them: ``camera.txt`` (fx fy cx cy w h),
KITTI's ``calib.txt`` (its P0 projection row), the synthetic world's camera; none where there are none or they do
not parse (a run's summary then has no focal error, and nothing fails)."""
from __future__ import annotations

import numpy as np

from services.runner.groundtruth import source_intrinsics
from services.synth import SynthConfig
from services.synth.camera import intrinsics as synth_intrinsics


def test_camera_txt_gives_fx_fy_cx_cy(tmp_path):
    (tmp_path / "camera.txt").write_text("420.5 420.6 355.2 250.3 752 480\n")
    np.testing.assert_array_equal(source_intrinsics(str(tmp_path)), [420.5, 420.6, 355.2, 250.3])


def test_kittis_calib_txt_gives_its_p0_row(tmp_path):
    (tmp_path / "calib.txt").write_text(
        "P0: 7.070912e+02 0 6.018873e+02 0 0 7.070912e+02 1.831104e+02 0 0 0 1 0\n"
        "P1: 7.070912e+02 0 6.018873e+02 -3.798145e+02 0 7.070912e+02 1.831104e+02 0 0 0 1 0\n")
    np.testing.assert_allclose(source_intrinsics(str(tmp_path)), [707.0912, 707.0912, 601.8873, 183.1104])


def test_the_synthetic_world_gives_its_camera():
    spec = "synth:frames=10,width=256,height=192"
    np.testing.assert_allclose(source_intrinsics(spec), synth_intrinsics(SynthConfig(width=256, height=192)))


def test_none_where_there_are_none_or_they_do_not_parse(tmp_path):
    assert source_intrinsics(str(tmp_path)) is None
    assert source_intrinsics("0") is None  # a webcam
    for text in ("fx fy cx cy\n", "420 420\n"):
        (tmp_path / "camera.txt").write_text(text)
        assert source_intrinsics(str(tmp_path)) is None, text
