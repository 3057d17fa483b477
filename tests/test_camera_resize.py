"""The resize rule (docs/CONVENTIONS.md) every service uses: services.common.camera.scale_intrinsics."""
from __future__ import annotations

import numpy as np
import pytest

from services.common.camera import scale_intrinsics


@pytest.mark.parametrize("sx, sy", [(0.5, 0.5), (1 / 8, 1 / 8), (0.625, 0.6), (8.0, 8.0)])
def test_a_point_projects_where_its_pixel_lands_after_the_resize(sx, sy):
    """A 3D point projected with the resized intrinsics lands where its pixel in the original image goes under the
    resize (pixel centres at integers: u' = sx (u + 0.5) - 0.5)."""
    k = np.array([500.0, 480.0, 319.5, 241.0])
    points = np.random.default_rng(0).uniform([-1, -1, 2], [1, 1, 6], (20, 3))
    u, v = k[0] * points[:, 0] / points[:, 2] + k[2], k[1] * points[:, 1] / points[:, 2] + k[3]
    fx, fy, cx, cy = scale_intrinsics(k, sx, sy)
    np.testing.assert_allclose(fx * points[:, 0] / points[:, 2] + cx, sx * (u + 0.5) - 0.5, atol=1e-9)
    np.testing.assert_allclose(fy * points[:, 1] / points[:, 2] + cy, sy * (v + 0.5) - 0.5, atol=1e-9)


def test_the_centre_of_an_image_stays_its_centre_and_a_resize_undoes():
    k = np.array([400.0, 400.0, 255.5, 191.5])  # the centre of 512 x 384
    np.testing.assert_allclose(scale_intrinsics(k, 1 / 8, 1 / 8)[2:], [31.5, 23.5])  # the centre of 64 x 48
    np.testing.assert_allclose(scale_intrinsics(scale_intrinsics(k, 0.3, 0.7), 1 / 0.3, 1 / 0.7), k)
