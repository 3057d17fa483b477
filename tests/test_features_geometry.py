"""Working resolution, intrinsics mapping (docs/CONVENTIONS.md), FOV prior, depth prior on the 1/8 grid."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.features.core.depth import DepthParams, sensor_disparity
from services.features.core.geometry import Intrinsics, ResolutionParams, fov_prior, working_size


@given(st.integers(60, 4000), st.integers(60, 4000))
@settings(max_examples=60, deadline=None)
def test_working_size_area_and_multiples(h, w):
    size = working_size(h, w)
    assert size.height % 8 == 0 and size.width % 8 == 0
    target = ResolutionParams().target_area
    if min(size.height, size.width) >= 64:  # away from the 8-px floor, the area stays close to the target
        assert abs(size.height * size.width / target - 1.0) < 0.15
        assert abs(math.log((size.width / size.height) / (w / h))) < 0.15


def test_kitti_working_size():
    size = working_size(370, 1226)
    assert (size.height, size.width) == (240, 808)


def _project(k: Intrinsics, p: np.ndarray) -> np.ndarray:
    return np.array([k.fx * p[0] / p[2] + k.cx, k.fy * p[1] / p[2] + k.cy])


def test_scaled_intrinsics_follow_pixel_centre_rule():
    # a 3D point projects to u in the original image; in an image resized by s its pixel-centre coordinate
    # must be s·(u + 0.5) − 0.5 (pixel (r, c) spans [c − 0.5, c + 0.5])
    k = Intrinsics(707.0, 700.0, 601.9, 183.1)
    p = np.array([1.3, -0.4, 7.0])
    for sx, sy in ((0.659, 0.6486), (0.125, 0.125), (2.0, 1.5)):
        u = _project(k, p)
        u_scaled = _project(k.scaled(sx, sy), p)
        assert np.allclose(u_scaled, [sx * (u[0] + 0.5) - 0.5, sy * (u[1] + 0.5) - 0.5])


def test_grid_intrinsics_centre_cell_rule():
    # grid cell (r, c) has its centre at working pixel (8c + 3.5, 8r + 3.5)
    k = Intrinsics(400.0, 400.0, 255.5, 191.5)
    g = k.to_grid()
    for c, r in ((0, 0), (5, 7), (31, 23)):
        u_work = np.array([8 * c + 3.5, 8 * r + 3.5])
        ray = np.array([(u_work[0] - k.cx) / k.fx, (u_work[1] - k.cy) / k.fy, 1.0])
        assert np.allclose(_project(g, ray), [c, r])


def test_fov_prior():
    k = fov_prior(480, 640, 60.0)
    assert k.fx == pytest.approx(320.0 / math.tan(math.radians(30.0)))
    assert (k.cx, k.cy) == (319.5, 239.5)
    with pytest.raises(ValueError):
        fov_prior(480, 640, 180.0)


def test_sensor_disparity_known_answer():
    depth = np.full((96, 128), 2.0, np.float32)
    depth[:48, :64] = 4.0
    depth[48:, 64:] = 0.0  # missing
    disp = sensor_disparity(depth, (48, 64))
    assert disp.shape == (6, 8) and disp.dtype == np.float32
    assert np.allclose(disp[:3, :4], 0.25) and np.allclose(disp[:3, 4:], 0.5) and np.allclose(disp[3:, :4], 0.5)
    assert np.all(disp[3:, 4:] == 0.0)
    far = sensor_disparity(np.full((16, 16), 500.0, np.float32), (16, 16), DepthParams(max_depth_m=80.0))
    assert np.all(far == 0.0)
