"""Synthetic retrieval with oracle features: the map built from exact depth and poses finds every object.

Scene: services.synth (a room with furniture, a walking person and a moved chair). Per keyframe, the map
gets GT disparity on the 1/8 grid, oracle features compressed by a PCA basis fitted here, and colours.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.mapstore.config import ConsistencyParams, FusionParams, MapParams, RegionParams
from services.mapstore.core.fusion import voxel_keys
from services.mapstore.core.geometry import backproject_grid, grid_intrinsics, sample_cell_colours
from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth
from services.mapstore.core.map import KeyframeMap
from services.mapstore.core.regions import find_regions
from services.mapstore.core.index import ScoringIndex
from services.mapstore.core.scoring import PcaBasis

synth = pytest.importorskip("services.synth")

D, K, NOISE = 64, 16, 0.3


class Scene:
    """Rendered keyframes on the grid: disparity, labels, dynamic mask, oracle codes."""

    def __init__(self, use_static_weights: bool) -> None:
        self.world = synth.SynthWorld(synth.SynthConfig(width=256, height=192, n_frames=48))
        names = self.world.label_names
        self.vectors = synth.label_vectors(len(names), D, seed=0)
        rng = np.random.default_rng(0)
        frames = [self.world.render(i) for i in range(0, 48, 2)]
        centre = slice(3, None, 8)  # nearest pixel to the cell centre (8c + 3.5): pixel 8c + 3
        self.grid = [(f, f.depth[centre, centre], f.labels[centre, centre], f.dynamic[centre, centre]) for f in frames]
        feats = [synth.oracle_features(lab, self.vectors, NOISE, rng) for _, _, lab, _ in self.grid]
        flat = np.concatenate([x.reshape(-1, D) for x in feats])
        mean = flat.mean(0)
        comps = np.linalg.svd(flat - mean, full_matrices=False)[2][:K]
        self.basis = PcaBasis(1, mean.astype(np.float32), comps.astype(np.float32), "oracle")
        params = MapParams(fusion=FusionParams(voxel_size=0.02, voxel_mode="relative"),
                           consistency=ConsistencyParams(neighbours=2, rel_tolerance=0.05))
        self.map = KeyframeMap(params)
        for (f, depth, lab, dyn), feat in zip(self.grid, feats):
            codes = ((feat - mean) @ comps.T).astype(np.float16)
            self.map.add_content(KeyframeContent(f.index, f.t_ns, codes, sample_cell_colours(f.rgb), f.rgb.shape[:2], 1))
            static = np.where(dyn, 0.0, 1.0).astype(np.float32) if use_static_weights else None
            self.map.set_depth(f.index, KeyframeDepth((1.0 / depth).astype(np.float32), f.intrinsics, static))
            self.map.set_pose(f.index, f.world_from_cam)
        self.map.refresh()
        self.fused = self.map.fused()

    def gt_voxel_labels(self) -> dict[int, int]:
        """Majority GT label of the static cells falling in each voxel (GT depth and poses, static parts only)."""
        votes: dict[tuple[int, int], int] = {}
        for f, depth, lab, dyn in self.grid:
            pts = backproject_grid(1.0 / depth, grid_intrinsics(f.intrinsics)).reshape(-1, 3)
            xyz = pts @ f.world_from_cam[:3, :3].T + f.world_from_cam[:3, 3]
            keys = voxel_keys(np.floor(xyz / self.map.voxel_size).astype(np.int64))
            for key, label in zip(keys[~dyn.ravel()].tolist(), lab.ravel()[~dyn.ravel()].tolist()):
                votes[(key, label)] = votes.get((key, label), 0) + 1
        best: dict[int, tuple[int, int]] = {}
        for (key, label), n in votes.items():
            if n > best.get(key, (-1, 0))[1]:
                best[key] = (label, n)
        return {k: v[0] for k, v in best.items()}

    def kept_fraction(self, label: str | None = None) -> float:
        """Fraction of the GT cells of moving objects (or of one label) that the map keeps as points."""
        kept = total = 0
        for f, _, lab, dyn in self.grid:
            cells = np.zeros(lab.size, bool)
            cells[self.map.keyframe_points(f.index).cells] = True
            target = dyn.ravel() if label is None else lab.ravel() == self.world.label_names.index(label)
            kept += int((cells & target).sum())
            total += int(target.sum())
        assert total > 0
        return kept / total


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(use_static_weights=True)


def boxes_overlap(lo_a, hi_a, lo_b, hi_b, margin: float) -> bool:
    return bool(np.all(lo_a <= hi_b + margin) and np.all(lo_b <= hi_a + margin))


def test_oracle_queries_return_regions_on_the_true_objects(scene):
    index = ScoringIndex(scene.fused.codes, scene.basis, device="cpu")
    params = RegionParams(score_threshold=0.7, min_voxels=3)
    last = len(scene.world) - 1
    static_boxes = [b for b in scene.world.instance_boxes(last) if not b.dynamic]
    margin = 2 * scene.map.voxel_size
    checked = 0
    for box in static_boxes:
        scores = index.score(scene.vectors[box.label])[0]
        regions = find_regions(scene.fused.ijk, scene.fused.xyz, scores, params)
        if not regions:  # never seen by the camera: no map points of that label at all
            assert not np.any(scores > 0.9), box.name
            continue
        checked += 1
        same_label = [b for b in static_boxes if b.label == box.label]
        for r in regions:  # every region lies on some object of the queried label
            assert any(boxes_overlap(r.box_min, r.box_max, b.lo, b.hi, margin) for b in same_label), box.name
    assert checked >= 5


def test_per_point_argmax_matches_ground_truth_labels(scene):
    index = ScoringIndex(scene.fused.codes, scene.basis, device="cpu")
    pred, _ = index.argmax(scene.vectors)
    gt = scene.gt_voxel_labels()
    truth = np.array([gt.get(k, -1) for k in scene.fused.keys.tolist()])
    known = truth >= 0
    assert known.mean() > 0.95  # map voxels are where GT static surfaces are
    acc = (pred[known] == truth[known]).mean()
    ious = []
    for lab in np.unique(truth[known]):
        p, t = pred[known] == lab, truth[known] == lab
        ious.append((p & t).sum() / (p | t).sum())
    assert acc > 0.9 and np.mean(ious) > 0.7, (acc, np.mean(ious))


def test_moving_objects_are_absent_with_static_weights(scene):
    assert scene.kept_fraction() == 0.0


def test_depth_consistency_alone_removes_most_of_the_walking_person():
    """Without static weights, only the free-space check of neighbouring keyframes sees the person move."""
    scene = Scene(use_static_weights=False)
    assert scene.kept_fraction("person") < 0.25
    assert scene.kept_fraction("table") > 0.9  # static objects stay
