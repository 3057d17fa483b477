"""Free-space carving against exact geometry: rectangles parallel to a wall, depth maps ray-cast on the 1/8 grid.

World: a wall in the plane z = 5 (facing the cameras, which look along +z), optional boxes (their front
faces, rectangles at a given z) in front of it. A keyframe's points are back-projected from its exact depth.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest

from services.mapstore.config import CarvingParams, ConsistencyParams, MapParams, MapstoreSettings
from services.mapstore.core.carving import CarveView, best_cosine_at, free_space_votes, nearest_disparity_at, unit_codes
from services.mapstore.core.geometry import backproject_grid, grid_intrinsics, transform_points
from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth
from services.mapstore.core.map import KeyframeMap, code_maps_to_latest
from services.mapstore.core.scoring import PcaBasis

H, W = 12, 16  # 1/8 grid of a 96x128 working image
INTR = np.array([100.0, 100.0, 63.5, 47.5])
WALL_Z = 5.0


class Rect(NamedTuple):
    """A rectangle facing the cameras: x in [x0, x1], y in [y0, y1] at world depth z."""

    x0: float
    x1: float
    y0: float
    y1: float
    z: float


BOX = Rect(-0.6, 0.6, -0.5, 0.5, 3.0)
MOVED_BOX = Rect(1.4, 2.4, -0.5, 0.5, 3.0)
OCCLUDER = Rect(-1.5, 1.5, -1.2, 1.2, 1.5)


def cam_pose(tx: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = tx
    return pose


def render_disparity(world_from_cam: np.ndarray, rects: list[Rect]) -> np.ndarray:
    """(H, W) float32 exact disparity of the wall and the nearest rectangle hit by each cell's centre ray."""
    return render(world_from_cam, rects)[0]


def render(world_from_cam: np.ndarray, rects: list[Rect]) -> tuple[np.ndarray, np.ndarray]:
    """((H, W) float32 exact disparity, (H, W) int64 index of the rectangle each cell sees, −1 = the wall)."""
    gk = grid_intrinsics(INTR)
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    rays = np.stack([(u - gk[2]) / gk[0], (v - gk[3]) / gk[1], np.ones_like(u)], -1) @ world_from_cam[:3, :3].T
    origin = world_from_cam[:3, 3]
    depth = (WALL_Z - origin[2]) / rays[..., 2]  # camera z of the hit = ray parameter (camera-frame ray has z = 1)
    which = np.full(depth.shape, -1, np.int64)
    for i, r in enumerate(rects):
        s = (r.z - origin[2]) / rays[..., 2]
        x, y = origin[0] + s * rays[..., 0], origin[1] + s * rays[..., 1]
        hit = (x >= r.x0) & (x <= r.x1) & (y >= r.y0) & (y <= r.y1) & (s > 0) & (s < depth)
        depth = np.where(hit, s, depth)
        which = np.where(hit, i, which)
    return (1.0 / depth).astype(np.float32), which


def view(tx: float, rects: list[Rect], reliability: np.ndarray | None = None) -> CarveView:
    pose = cam_pose(tx)
    return CarveView(np.linalg.inv(pose), render_disparity(pose, rects), INTR, reliability)


def points_of(tx: float, rects: list[Rect]) -> tuple[np.ndarray, np.ndarray]:
    """World points (H·W, 3) of a keyframe at x = tx and whether each lies on a rectangle (not the wall)."""
    pose = cam_pose(tx)
    pts = backproject_grid(render_disparity(pose, rects), grid_intrinsics(INTR)).reshape(-1, 3)
    world = transform_points(pose, pts)
    return world, world[:, 2] < WALL_Z - 1e-6


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
        codes = np.zeros((H, W, 2), np.float16)
        m.add_content(KeyframeContent(kf, kf * 1000, codes, np.zeros((H, W, 3), np.uint8), (8 * H, 8 * W), 1))
        m.set_depth(kf, KeyframeDepth(render_disparity(pose, rects), INTR))
        m.set_pose(kf, pose)
        if refresh_each:
            m.refresh()
    m.refresh()
    return m


def near_rect(xyz: np.ndarray, r: Rect, tol: float = 0.05) -> np.ndarray:
    return ((np.abs(xyz[:, 2] - r.z) < tol) & (xyz[:, 0] > r.x0 - tol) & (xyz[:, 0] < r.x1 + tol)
            & (xyz[:, 1] > r.y0 - tol) & (xyz[:, 1] < r.y1 + tol))


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
        codes = np.zeros((H, W, 2), np.float16)
        m.add_content(KeyframeContent(kf, kf * 1000, codes, np.zeros((H, W, 3), np.uint8), (8 * H, 8 * W), 1))
        m.set_depth(kf, KeyframeDepth(render_disparity(pose, rects), INTR))
        m.set_pose(kf, pose)
        refreshed.append(m.refresh().refreshed)
    assert refreshed[:4] == [[0], [1], [2], [3]]  # one view seeing through the old place is not enough to carve it
    assert refreshed[4] == [0, 1, 2, 4]  # the second one is: the keyframes that saw the box there are re-fused
    assert refreshed[5] == [5]  # a third changes no verdict (2 of the 3 most recent already see through)
    assert near_rect(m.fused().xyz, BOX).sum() == 0


# ----- semantic evidence: codes of labels (near-orthogonal unit vectors plus noise, as oracle features are) -----
WALL, CHAIR, FLOOR, PERSON = 0, 1, 2, 3
LABEL_CODES = np.linalg.qr(np.random.default_rng(7).normal(size=(8, 4)))[0].T  # (4 labels, K = 8) orthonormal


def label_codes(labels: np.ndarray, noise: float = 0.1, seed: int = 0) -> np.ndarray:
    """(…, K) float16 codes of an (…) label map: each label's unit vector plus Gaussian noise of relative size
    `noise`."""
    rng = np.random.default_rng(seed)
    codes = LABEL_CODES[labels] + noise / np.sqrt(LABEL_CODES.shape[1]) * rng.normal(size=(*labels.shape, 8))
    return codes.astype(np.float16)


def cell_labels(which: np.ndarray, rect_labels: list[int]) -> np.ndarray:
    """(H, W) labels of a render's rectangle indices (−1 = the wall)."""
    return np.where(which < 0, WALL, np.asarray(rect_labels + [WALL])[which])


def labelled_view(tx: float, rects: list[Rect], rect_labels: list[int], reliability: np.ndarray | None = None,
                  seed: int = 1) -> CarveView:
    pose = cam_pose(tx)
    disparity, which = render(pose, rects)
    codes = unit_codes(label_codes(cell_labels(which, rect_labels), seed=seed))
    return CarveView(np.linalg.inv(pose), disparity, INTR, reliability, codes)


def labelled_points(tx: float, rects: list[Rect], rect_labels: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(world points (H·W, 3), their codes (H·W, K), whether each lies on a rectangle) of a keyframe at x = tx."""
    pts, on_rect = points_of(tx, rects)
    _, which = render(cam_pose(tx), rects)
    return pts, label_codes(cell_labels(which, rect_labels).reshape(-1)), on_rect


# Where the chair stood, later monocular depth puts the floor at 0.85× the chair's depth (pulled towards it): a
# floor-labelled surface in front of the old chair points, wider than the chair, that no depth test sees through.
PULLED_FLOOR = Rect(BOX.x0 - 0.3, BOX.x1 + 0.3, BOX.y0 - 0.3, BOX.y1 + 0.3, 0.85 * BOX.z)


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
        if bases is not None:  # code the label vectors with this version's basis: z = V (f − μ)
            codes = ((codes.astype(np.float64) - bases[version].mean) @ bases[version].components.T).astype(np.float16)
        add_keyframe(m, kf, pose, disparity, codes, version)
    return m


def add_keyframe(m: KeyframeMap, kf: int, pose: np.ndarray, disparity: np.ndarray, codes: np.ndarray,
                 version: int) -> None:
    m.add_content(KeyframeContent(kf, kf * 1000, codes, np.zeros((H, W, 3), np.uint8), (8 * H, 8 * W), version))
    m.set_depth(kf, KeyframeDepth(disparity, INTR))
    m.set_pose(kf, pose)
    m.refresh()


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
        codes = label_codes(cell_labels(which, [CHAIR]), seed=kf).astype(np.float64)
        codes = ((codes - bases[version].mean) @ bases[version].components.T).astype(np.float16)
        add_keyframe(m, kf, pose, disparity, codes, version)
    return m


def test_settings_build_the_semantic_carving_parameters():
    carving = MapstoreSettings(carve_semantic=False, carve_max_code_cosine=0.3, carve_occluder_margin=0.2,
                               carve_min_code_reliability=0.4).map_params().carving
    assert (carving.semantic, carving.max_code_cosine, carving.occluder_margin, carving.min_code_reliability) == \
        (False, 0.3, 0.2, 0.4)
