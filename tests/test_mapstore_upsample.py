"""Disparity upsampling of keyframe points (services/mapstore/core/upsample.py): known answers on planes and at a
colour-aligned depth edge."""
from __future__ import annotations

import numpy as np
import pytest

from services.mapstore.core.upsample import UpsampleParams, output_centres, upsample_disparity


def plane_disparity(h: int, w: int, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Disparity of a tilted plane (affine in image coordinates) on the 1/8 grid and on the factor-f grid."""
    f = lambda r, c: 0.2 + 0.01 * r[:, None] + 0.005 * c[None, :]  # noqa: E731 - in 1/8-grid coordinates
    return f(np.arange(h, dtype=float), np.arange(w, dtype=float)), f(*output_centres(h, w, factor))


def test_output_centres_follow_the_pixel_centre_convention():
    rows, cols = output_centres(2, 3, 2)  # 4-pixel cells: centres at pixels 1.5, 5.5, ... = grid (1.5 - 3.5) / 8
    np.testing.assert_allclose(cols, (4 * np.arange(6) + 1.5 - 3.5) / 8)
    np.testing.assert_allclose(output_centres(2, 3, 1)[1], [0, 1, 2])  # factor 1: the 1/8 cells themselves


@pytest.mark.parametrize("factor", [2, 4])
def test_bilinear_is_exact_on_a_plane_inside_the_grid(factor):
    low, truth = plane_disparity(6, 8, factor)
    up = upsample_disparity(low, None, UpsampleParams(factor=factor, method="bilinear"))
    assert up.shape == truth.shape
    inner = (slice(factor, -factor), slice(factor, -factor))  # border cells extrapolate (clamped)
    np.testing.assert_allclose(up[inner], truth[inner], rtol=1e-6)


def test_guided_keeps_a_colour_aligned_depth_edge_sharp_where_bilinear_smears_it():
    h, w, f = 6, 8, 4
    image = np.zeros((8 * h, 8 * w, 3), np.uint8)
    image[:, 8 * 4 + 2:] = 200  # the edge lies 2 pixels into 1/8 column 4
    low = np.where(np.arange(w)[None, :] >= 4, 0.5, 0.25) * np.ones((h, 1))  # that cell takes the far side
    cols_px = 2 * np.arange(w * f) + 0.5 + 0.5  # 2-pixel cells: centres at 2c + 0.5
    truth = np.where(cols_px >= 8 * 4 + 2, 0.5, 0.25)[None, :] * np.ones((h * f, 1))
    guided = upsample_disparity(low, image, UpsampleParams(factor=f, method="guided"))
    bilinear = upsample_disparity(low, image, UpsampleParams(factor=f, method="bilinear"))
    err = lambda up: np.abs(up - truth).mean()  # noqa: E731
    assert err(guided) < 0.2 * err(bilinear)
    nearest = upsample_disparity(low, image, UpsampleParams(factor=f, method="nearest"))
    np.testing.assert_array_equal(nearest, np.repeat(np.repeat(low, f, 0), f, 1).astype(np.float32))


def test_unknown_cells_stay_unknown_and_do_not_pull_values_to_zero():
    low = np.full((4, 4), 0.5)
    low[:2] = 0.0
    for method in ("bilinear", "guided"):
        up = upsample_disparity(low, np.full((32, 32, 3), 90, np.uint8), UpsampleParams(factor=2, method=method))
        known = up > 0
        np.testing.assert_allclose(up[known], 0.5, rtol=1e-6)
        assert not known[:2].any() and known[4:].all()


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError):
        UpsampleParams(factor=3)
    with pytest.raises(ValueError):
        upsample_disparity(np.ones((4, 4)), np.zeros((16, 16, 3), np.uint8), UpsampleParams(method="guided"))
