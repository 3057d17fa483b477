"""Semantic evidence in free-space carving: a later view that sees another label at about a point's depth."""

from __future__ import annotations

import numpy as np
import pytest

from services.mapstore.config import CarvingParams, ConsistencyParams, MapParams, MapstoreSettings
from services.mapstore.core.carving import best_cosine_at, free_space_votes, unit_codes
from services.mapstore.core.map import KeyframeMap, code_maps_to_latest
from services.mapstore.core.scoring import PcaBasis
from tests.helpers.carving_scene import (BOX, CHAIR, FLOOR, LABEL_CODES, MOVED_BOX, OCCLUDER, PERSON, PULLED_FLOOR,
                                         WALL, WALL_Z, H, W, Rect, add_keyframe, cam_pose, cell_labels, label_codes,
                                         labelled_points, labelled_view, near_rect, render)


def test_a_point_whose_later_views_see_another_label_at_about_its_depth_is_carved():
    pts, codes, on_box = labelled_points(0.0, [BOX], [CHAIR])
    views = [labelled_view(0.3, [PULLED_FLOOR], [FLOOR], seed=2), labelled_view(0.15, [PULLED_FLOOR], [FLOOR], seed=3)]
    geometric = free_space_votes(pts, views, CarvingParams(), None)
    assert not geometric.carved.any()  # depth alone: the pulled floor looks like an occluder
    semantic = free_space_votes(pts, views, CarvingParams(), codes)
    np.testing.assert_array_equal(semantic.carved, on_box)
    np.testing.assert_array_equal(semantic.contradicted[on_box], 2)
    assert (semantic.deciding[~on_box] >= 1).mean() > 0.5 and not semantic.contradicted[~on_box].any()  # wall agrees
    off = free_space_votes(pts, views, CarvingParams(semantic=False), codes)
    np.testing.assert_array_equal(off.carved, geometric.carved)
    # BA marks the place that changed as not static: by default its codes still count, with a gate they do not
    changed = np.zeros((H, W), np.float32)
    unreliable = [labelled_view(0.3, [PULLED_FLOOR], [FLOOR], changed),
                  labelled_view(0.15, [PULLED_FLOOR], [FLOOR], changed)]
    np.testing.assert_array_equal(free_space_votes(pts, unreliable, CarvingParams(), codes).carved, on_box)
    gated = free_space_votes(pts, unreliable, CarvingParams(min_code_reliability=0.1), codes)
    assert not gated.carved.any() and not gated.contradicted.any()
    # a floor at the chair's very depth: depth agrees, but a view that sees something else there does not vouch
    flush = Rect(PULLED_FLOOR.x0, PULLED_FLOOR.x1, PULLED_FLOOR.y0, PULLED_FLOOR.y1, 0.99 * BOX.z)
    flush_views = [labelled_view(0.3, [flush], [FLOOR], changed), labelled_view(0.15, [flush], [FLOOR], changed)]
    assert not free_space_votes(pts, flush_views, CarvingParams(semantic=False), codes).seen_through.any()
    assert free_space_votes(pts, flush_views, CarvingParams(semantic=False), codes).deciding[on_box].all()
    assert not free_space_votes(pts, flush_views, CarvingParams(min_code_reliability=0.1), codes).deciding[on_box].any()


def test_a_point_behind_a_much_nearer_occluder_of_another_label_is_not_carved():
    pts, codes, on_box = labelled_points(0.0, [BOX], [CHAIR])
    walking = np.zeros((H, W), np.float32)  # BA marks the person (and here everything) as not static
    views = [labelled_view(0.3, [BOX, OCCLUDER], [CHAIR, PERSON], walking, seed=2),
             labelled_view(0.15, [BOX, OCCLUDER], [CHAIR, PERSON], walking, seed=3)]
    votes = free_space_votes(pts, views, CarvingParams(), codes)
    hidden = on_box & (votes.deciding == 0)
    assert hidden.sum() >= 0.8 * on_box.sum()  # the person hides (nearly) all of the box from both views
    assert not votes.carved.any() and not votes.contradicted.any()
    # the same occluder at about the box's depth is no longer "clearly in front": it contradicts the box
    near_box = Rect(OCCLUDER.x0, OCCLUDER.x1, OCCLUDER.y0, OCCLUDER.y1, 0.8 * BOX.z)
    close = [labelled_view(0.3, [near_box], [PERSON], seed=2), labelled_view(0.15, [near_box], [PERSON], seed=3)]
    assert free_space_votes(pts, close, CarvingParams(), codes).carved[on_box].all()
    assert not free_space_votes(pts, close, CarvingParams(occluder_margin=0.1), codes).carved.any()


def test_a_point_seen_with_the_same_label_is_not_carved():
    pts, codes, on_box = labelled_points(0.0, [BOX], [CHAIR])
    same_place = [labelled_view(0.3, [BOX], [CHAIR], seed=2), labelled_view(0.15, [BOX], [CHAIR], seed=3)]
    votes = free_space_votes(pts, same_place, CarvingParams(), codes)
    assert not votes.carved.any() and not votes.contradicted.any()
    assert np.all(votes.deciding[on_box] >= 1)
    # the same chair at a slightly wrong depth (0.85×): neither seen through nor contradicted
    pulled = Rect(PULLED_FLOOR.x0, PULLED_FLOOR.x1, PULLED_FLOOR.y0, PULLED_FLOOR.y1, PULLED_FLOOR.z)
    near = [labelled_view(0.3, [pulled], [CHAIR], seed=2), labelled_view(0.15, [pulled], [CHAIR], seed=3)]
    assert not free_space_votes(pts, near, CarvingParams(), codes).carved.any()
    # a threshold stricter than the codes' own noise allows makes even the same label disagree
    assert free_space_votes(pts, same_place, CarvingParams(max_code_cosine=1.01), codes).carved[on_box].all()


def test_without_codes_carving_is_geometric():
    pts, codes, on_box = labelled_points(0.0, [BOX], [CHAIR])
    cases = [[labelled_view(0.3, [], []), labelled_view(0.15, [], [])],  # seen through
             [labelled_view(0.3, [PULLED_FLOOR], [FLOOR]), labelled_view(0.15, [PULLED_FLOOR], [FLOOR])],
             [labelled_view(0.3, [OCCLUDER], [PERSON]), labelled_view(0.15, [OCCLUDER], [PERSON])]]
    for views in cases:
        plain = free_space_votes(pts, [v._replace(codes=None) for v in views], CarvingParams())
        no_point_codes = free_space_votes(pts, views, CarvingParams(), None)
        no_view_codes = free_space_votes(pts, [v._replace(codes=None) for v in views], CarvingParams(), codes)
        zero_codes = free_space_votes(pts, views, CarvingParams(), np.zeros_like(codes))  # no direction: no evidence
        for other in (no_point_codes, no_view_codes, zero_codes):
            for a, b in zip(plain, other):
                np.testing.assert_array_equal(a, b)
        assert not plain.contradicted.any()
    with pytest.raises(ValueError):
        free_space_votes(pts, cases[0], CarvingParams(), codes[:-1])


def test_best_cosine_takes_the_most_similar_cell_of_the_footprint():
    view_codes = unit_codes(np.stack([LABEL_CODES[WALL], LABEL_CODES[CHAIR]])[np.array([[0, 0, 1], [0, 1, 1]])])
    point = unit_codes(LABEL_CODES[[CHAIR, CHAIR, FLOOR]])
    u, v = np.array([0.2, 0.4, 1.5]), np.array([0.2, 0.2, 0.5])
    np.testing.assert_allclose(best_cosine_at(view_codes, point, u, v, "cell"), [0.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(best_cosine_at(view_codes, point, u, v, "corners"), [1.0, 1.0, 0.0], atol=1e-6)
    far = best_cosine_at(view_codes, point[:1], np.array([9.0]), np.array([9.0]), "3x3")
    assert np.isnan(far).all()  # no cell of the footprint inside the view: no evidence
    assert np.isnan(unit_codes(np.zeros((2, 8)))).all()


def build_moved_chair_map(params: MapParams, pulled_floor: bool, versions: tuple[int, int] = (0, 0),
                          bases: dict | None = None) -> KeyframeMap:
    """Keyframes 0-2 see the chair at BOX; 3-5 see it at MOVED_BOX and, where it stood, floor at a depth pulled
    towards it (PULLED_FLOOR) or the wall behind. Codes are coded with PCA version versions[0] before the move and
    versions[1] after; `bases` (version → basis) makes the map versioned."""
    m = KeyframeMap(params, voxel_size=0.1, versioned=bases is not None)
    if bases is not None:
        m.set_code_space(*code_maps_to_latest(bases))
    for kf in range(6):
        rects, labels = ([BOX], [CHAIR]) if kf < 3 else ([MOVED_BOX] + [PULLED_FLOOR] * pulled_floor,
                                                         [CHAIR] + [FLOOR] * pulled_floor)
        pose = cam_pose(0.1 * kf)
        disparity, which = render(pose, rects)
        version = versions[kf >= 3]
        codes = label_codes(cell_labels(which, labels), seed=kf)
        if bases is not None:
            codes = coded(codes, bases[version])
        add_keyframe(m, kf, pose, disparity, codes, version)
        m.refresh()
    return m


def coded(label_vectors: np.ndarray, basis: PcaBasis) -> np.ndarray:
    """(…, K) float16 codes of label vectors under ``basis``: z = V (f − μ)."""
    return ((label_vectors.astype(np.float64) - basis.mean) @ basis.components.T).astype(np.float16)


def test_the_map_drops_a_vacated_place_that_later_depths_do_not_see_through():
    no_check = ConsistencyParams(neighbours=0)
    semantic = build_moved_chair_map(MapParams(consistency=no_check), pulled_floor=True).fused().xyz
    geometric = build_moved_chair_map(MapParams(consistency=no_check, carving=CarvingParams(semantic=False)),
                                      pulled_floor=True).fused().xyz
    assert near_rect(geometric, BOX).sum() > 10  # depth alone keeps the old place
    assert near_rect(semantic, BOX).sum() == 0
    assert near_rect(semantic, MOVED_BOX).sum() == near_rect(geometric, MOVED_BOX).sum() > 10  # where it went stays
    wall = lambda xyz: (np.abs(xyz[:, 2] - WALL_Z) < 0.05).sum()  # noqa: E731
    assert wall(semantic) == wall(geometric) > 50


def test_the_map_compares_codes_of_different_pca_versions_in_the_newest_space():
    """Keyframes after the move are coded with another basis (rotated components, shifted mean): compared raw, the
    chair's codes would disagree with themselves; mapped into one space they agree, and a chair that did not move
    stays. With the floor pulled over the vacated place, the old place still goes."""
    rng = np.random.default_rng(3)
    mean0, mean1 = np.zeros(8), 0.05 * rng.normal(size=8)
    rot = np.linalg.qr(rng.normal(size=(8, 8)))[0]
    bases = {0: PcaBasis(0, mean0.astype(np.float32), np.eye(8, dtype=np.float32)),
             1: PcaBasis(1, mean1.astype(np.float32), rot.T.astype(np.float32))}
    params = MapParams(consistency=ConsistencyParams(neighbours=0))
    stayed = build_static_chair_map(params, bases)
    assert near_rect(stayed.fused().xyz, BOX).sum() > 10 and stayed.code_version == 1
    moved = build_moved_chair_map(params, pulled_floor=True, versions=(0, 1), bases=bases).fused().xyz
    assert near_rect(moved, BOX).sum() == 0 and near_rect(moved, MOVED_BOX).sum() > 10


def build_static_chair_map(params: MapParams, bases: dict) -> KeyframeMap:
    """Six keyframes that all see the chair at BOX, 0-2 coded with basis 0 and 3-5 with basis 1; the depth of 3-5
    is 0.85× too near over the chair (as a moved object's would be) so the codes alone decide."""
    m = KeyframeMap(params, voxel_size=0.1, versioned=True)
    m.set_code_space(*code_maps_to_latest(bases))
    for kf in range(6):
        pose = cam_pose(0.1 * kf)
        disparity, which = render(pose, [BOX] if kf < 3 else [PULLED_FLOOR])
        version = int(kf >= 3)
        add_keyframe(m, kf, pose, disparity, coded(label_codes(cell_labels(which, [CHAIR]), seed=kf), bases[version]),
                     version)
        m.refresh()
    return m


def test_settings_build_the_semantic_carving_parameters():
    carving = MapstoreSettings(carve_semantic=False, carve_max_code_cosine=0.3, carve_occluder_margin=0.2,
                               carve_min_code_reliability=0.4).map_params().carving
    assert (carving.semantic, carving.max_code_cosine, carving.occluder_margin, carving.min_code_reliability) == \
        (False, 0.3, 0.2, 0.4)
