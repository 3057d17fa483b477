"""The carried-depth math tracking's corrections rest on (services/ba/frontend/carried_depth.py), on exact arrays."""
from __future__ import annotations

import numpy as np
import pytest

from services.ba.core import se3_numpy as se3
from services.ba.frontend.carried_depth import MAX_SCALE_FIX, depth_scale, similarity_about


def test_depth_scale_is_the_median_ratio_where_a_point_landed():
    rng = np.random.default_rng(3)
    mapped = rng.uniform(0.1, 2.0, (12, 16))
    carried = mapped * 1.3  # carried disparity 1.3x: the carried depth 1.3x too near, mapping's 1.3x farther
    known = np.ones_like(mapped)
    known[:, :4] = 0
    carried[:, :4] = 50.0  # filled-in cells say nothing
    assert depth_scale(carried, known, mapped) == pytest.approx(1.3, rel=1e-12)


def test_depth_scale_says_nothing_from_too_few_cells_and_is_bounded():
    mapped = np.ones((10, 10))
    few = np.zeros((10, 10))
    few[0, :5] = 1  # 5 % of the grid
    assert depth_scale(mapped * 1.5, few, mapped) == 1.0
    everywhere = np.ones((10, 10))
    assert depth_scale(mapped * 10.0, everywhere, mapped) == MAX_SCALE_FIX
    assert depth_scale(mapped / 10.0, everywhere, mapped) == 1.0 / MAX_SCALE_FIX


def test_the_similarity_takes_the_keyframe_to_mappings_pose_and_stretches_offsets_from_it():
    rng = np.random.default_rng(4)
    tracked, mapped, later = (se3.exp(rng.normal(size=6)) for _ in range(3))
    fix = similarity_about(mapped, tracked, 1.7)
    np.testing.assert_allclose(fix(tracked), mapped, atol=1e-12)
    offset = se3.inverse(tracked) @ later  # where ``later`` lies from the keyframe, in tracking's chain
    moved = se3.inverse(mapped) @ fix(later)  # ... and from mapping's keyframe after the fix
    np.testing.assert_allclose(moved[:3, :3], offset[:3, :3], atol=1e-12)
    np.testing.assert_allclose(moved[:3, 3], 1.7 * offset[:3, 3], atol=1e-12)
