"""Free-space carving against exact geometry (depth evidence; the scene is tests/helpers/carving_scene.py)."""

from __future__ import annotations

import numpy as np
import pytest

from services.mapstore.config import CarvingParams, ConsistencyParams, MapParams, MapstoreSettings
from services.mapstore.core.carving import CarveView, free_space_votes, nearest_disparity_at, unit_codes
from services.mapstore.core.map import KeyframeMap
from tests.helpers.carving_scene import (BOX, MOVED_BOX, OCCLUDER, WALL_Z, H, W, Rect, add_keyframe, cam_pose,
                                         near_rect, points_of, render_disparity, view)


def test_a_box_that_later_views_see_through_is_carved_and_the_wall_stays():
    pts, on_box = points_of(0.0, [BOX])
    assert on_box.sum() >= 12  # the box covers a real part of the image
    votes = free_space_votes(pts, [view(0.3, []), view(0.15, [])], CarvingParams())
    np.testing.assert_array_equal(votes.carved, on_box)
    np.testing.assert_array_equal(votes.seen_through[on_box], 2)
    assert np.all(votes.deciding[~on_box] >= 1)  # the wall points were checked, and agreed


def test_a_static_box_seen_by_the_later_views_stays():
    pts, on_box = points_of(0.0, [BOX])
    votes = free_space_votes(pts, [view(0.3, [BOX]), view(0.15, [BOX])], CarvingParams())
    assert not votes.carved.any()
    assert np.all(votes.seen_through == 0)


def test_an_occluder_in_front_is_no_evidence_of_free_space():
    pts, on_box = points_of(0.0, [BOX])
    votes = free_space_votes(pts, [view(0.3, [OCCLUDER]), view(0.15, [OCCLUDER])], CarvingParams())
    hidden = on_box & (votes.deciding == 0)
    assert hidden.sum() >= 0.8 * on_box.sum()  # the occluder hides (nearly) all of the box from both views
    assert not votes.carved[on_box].any()


def test_a_wider_footprint_keeps_edges_that_later_depths_misplace():
    # a later depth map whose box is 0.15 m (0.6 cell at z = 3) too small on each side, as blurred BA depth edges are
    pts, on_box = points_of(0.0, [BOX])
    thin = Rect(BOX.x0 + 0.15, BOX.x1 - 0.15, BOX.y0 + 0.15, BOX.y1 - 0.15, BOX.z)
    views = [view(0.3, [thin]), view(0.15, [thin])]
    carved = {f: free_space_votes(pts, views, CarvingParams(footprint=f)).carved for f in ("cell", "corners", "3x3")}
    assert carved["cell"].sum() > carved["corners"].sum() > carved["3x3"].sum() == 0
    inner = near_rect(pts, Rect(thin.x0, thin.x1, thin.y0, thin.y1, BOX.z), tol=0.0)
    assert on_box[carved["cell"]].all() and not inner[carved["cell"]].any()  # only the misplaced rim is carved


def test_one_view_seeing_through_is_not_enough_and_unreliable_cells_do_not_carve():
    pts, on_box = points_of(0.0, [BOX])
    one = free_space_votes(pts, [view(0.15, [])], CarvingParams())
    assert one.seen_through[on_box].min() == 1 and not one.carved.any()
    allowed = free_space_votes(pts, [view(0.15, [])], CarvingParams(min_violations=1))
    np.testing.assert_array_equal(allowed.carved, on_box)
    moving = np.zeros((H, W), np.float32)  # e.g. ARK marks the whole view dynamic
    unreliable = free_space_votes(pts, [view(0.3, [], moving), view(0.15, [], moving)], CarvingParams())
    assert not unreliable.carved.any()


def test_the_most_recent_views_decide():
    pts, on_box = points_of(0.0, [BOX])
    back, gone = view(0.1, [BOX]), view(0.2, [])
    params = CarvingParams(recent_views=3, min_violations=2)
    # newest first: gone, gone, back  → 2 of 3 see through: carved
    assert free_space_votes(pts, [gone, gone, back], params).carved[on_box].all()
    # the box came back: back, back, gone → kept
    assert not free_space_votes(pts, [back, back, gone, gone], params).carved.any()


def test_nearest_disparity_at_takes_the_nearest_known_cell_of_the_footprint():
    d = np.zeros((3, 4))
    d[1, 1] = 0.5
    d[2, 3] = 0.2
    u, v = np.array([1.6, 2.4, 0.0, 3.0]), np.array([1.6, 0.4, 2.0, 2.0])
    np.testing.assert_array_equal(nearest_disparity_at(d, u, v, "cell"), [0.0, 0.0, 0.0, 0.2])
    # corners of (1.6, 1.6): cells (1..2, 1..2); of (2.4, 0.4): cells (0..1, 2..3); outside cells count as unknown
    np.testing.assert_array_equal(nearest_disparity_at(d, u, v, "corners"), [0.5, 0.0, 0.0, 0.2])
    np.testing.assert_array_equal(nearest_disparity_at(d, u, v, "3x3"), [0.5, 0.5, 0.5, 0.2])
    with pytest.raises(ValueError):
        nearest_disparity_at(d, u, v, "5x5")
    with pytest.raises(ValueError):
        nearest_disparity_at(np.zeros(3), u, v, "cell")


def build_moving_box_map(params: MapParams, refresh_each: bool) -> KeyframeMap:
    """Keyframes 0-2 see the box at BOX, keyframes 3-5 see it at MOVED_BOX (it moved between 2 and 3)."""
    m = KeyframeMap(params, voxel_size=0.1)
    for kf in range(6):
        rects = [BOX] if kf < 3 else [MOVED_BOX]
        pose = cam_pose(0.1 * kf)
        add_keyframe(m, kf, pose, render_disparity(pose, rects), np.zeros((H, W, 2), np.float16))
        if refresh_each:
            m.refresh()
    m.refresh()
    return m


def test_the_map_drops_the_place_a_box_left_and_keeps_where_it_went_and_the_wall():
    no_check = ConsistencyParams(neighbours=0)  # carving alone, not the neighbours' consistency, must do it
    carving = build_moving_box_map(MapParams(consistency=no_check), refresh_each=True).fused().xyz
    kept = build_moving_box_map(MapParams(consistency=no_check, carving=CarvingParams(later_keyframes=0)),
                                refresh_each=True).fused().xyz
    assert near_rect(kept, BOX).sum() > 10  # without carving the old place stays in the map
    assert near_rect(carving, BOX).sum() == 0
    assert near_rect(carving, MOVED_BOX).sum() == near_rect(kept, MOVED_BOX).sum() > 10
    wall = np.abs(carving[:, 2] - WALL_Z) < 0.05
    assert wall.sum() == (np.abs(kept[:, 2] - WALL_Z) < 0.05).sum()  # the wall behind both places is kept


def test_incremental_carving_matches_fusing_everything_at_once():
    params = MapParams(consistency=ConsistencyParams(neighbours=0))
    step = build_moving_box_map(params, refresh_each=True).fused()
    once = build_moving_box_map(params, refresh_each=False).fused()
    np.testing.assert_array_equal(step.keys, once.keys)
    np.testing.assert_allclose(step.xyz, once.xyz, atol=1e-9)


def test_settings_build_the_carving_parameters():
    carving = MapstoreSettings(carve_keyframes=5, carve_views=4, carve_min_violations=3).map_params().carving
    assert (carving.later_keyframes, carving.recent_views, carving.min_violations) == (5, 4, 3)


def test_a_new_keyframe_re_fuses_only_the_earlier_keyframes_whose_carving_it_changes():
    params = MapParams(consistency=ConsistencyParams(neighbours=0))
    m = KeyframeMap(params, voxel_size=0.1)
    refreshed = []
    for kf in range(6):
        rects = [BOX] if kf < 3 else [MOVED_BOX]
        pose = cam_pose(0.1 * kf)
        add_keyframe(m, kf, pose, render_disparity(pose, rects), np.zeros((H, W, 2), np.float16))
        refreshed.append(m.refresh().refreshed)
    assert refreshed[:4] == [[0], [1], [2], [3]]  # one view seeing through the old place is not enough to carve it
    assert refreshed[4] == [0, 1, 2, 4]  # the second one is: the keyframes that saw the box there are re-fused
    assert refreshed[5] == [5]  # a third changes no verdict (2 of the 3 most recent already see through)
    assert near_rect(m.fused().xyz, BOX).sum() == 0


def test_views_judged_together_vote_as_one_view_at_a_time():
    """`free_space_votes` judges several views at once; each point must still hear only its `recent_views` most
    recent deciding views. The reference judges each view alone and lets the points listen view by view."""
    rng = np.random.default_rng(7)
    m, k = 600, 8
    pts = np.column_stack([rng.uniform(-1.5, 1.5, m), rng.uniform(-1.0, 1.0, m), rng.uniform(2.0, 4.0, m)])
    codes = rng.normal(size=(m, k))
    views = []
    for i in range(13):  # two grid shapes, some views without reliability or codes, depths near and past the points
        h, w = (12, 16) if i % 3 else (9, 12)
        pose = np.eye(4)
        pose[:3, 3] = rng.normal(scale=0.05, size=3)
        grid = np.array([2.0 * w, 2.0 * w, 4.0 * w - 0.5, 4.0 * h - 0.5])  # working-resolution intrinsics
        disparity = (1.0 / (3.0 * rng.choice([0.97, 1.0, 1.3, 0.6]) * rng.uniform(0.9, 1.1, (h, w)))).astype(np.float32)
        disparity[rng.random((h, w)) < 0.1] = 0.0
        reliability = None if i % 4 == 0 else rng.uniform(0.0, 1.0, (h, w))
        view_codes = None if i % 5 == 0 else unit_codes(rng.normal(size=(h, w, k)))
        views.append(CarveView(np.linalg.inv(pose), disparity, grid, reliability, view_codes))
    params = CarvingParams(recent_views=3, min_reliability=0.3)
    together = free_space_votes(pts, views, params, codes)

    deciding, through, contradicted = (np.zeros(m, np.int64) for _ in range(3))
    for v in views:
        alone = free_space_votes(pts, [v], params, codes)  # one view: its own verdict on every point
        listens = deciding < params.recent_views
        deciding += listens * alone.deciding
        through += listens * alone.seen_through
        contradicted += listens * alone.contradicted
    assert deciding.max() == params.recent_views and through.any() and contradicted.any()  # every kind of verdict
    np.testing.assert_array_equal(together.deciding, deciding)
    np.testing.assert_array_equal(together.seen_through, through)
    np.testing.assert_array_equal(together.contradicted, contradicted)
    np.testing.assert_array_equal(together.carved, (through >= params.min_violations) & (2 * through > deciding))
    assert together.carved.any() and not together.carved.all()
