"""Pure parts of the query gateway: text path (tiny real models), answer shaping, PLY, TUM, pooling, regions."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from services.query_api.config import QuerySettings
from services.query_api.core import ply
from services.query_api.core.answers import apply_min_score, group_answer, label_palette, segment_summary, subsample
from services.query_api.core.example import box_mask, fit_to_patches, pooled_feature
from services.query_api.core.text import OracleTextEncoder, TextEmbedder, UnknownLabel
from services.common.rotations import rotation_to_quaternion as quaternion_xyzw
from services.query_api.core.trajectory import PoseBook, tum_text
from services.query_api.refmap import connected_voxels
from services.query_api.textpath import SpaceMismatch, TextPath, TextUnavailable

# the text models and the example backbone run on CUDA where there is one (device auto): their outputs must reach
# numpy through the host
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device here (bench/gpu_check.sh runs it on a lent GPU)"))]


# -- text path -------------------------------------------------------------------------------------------
class CountingEncoder:
    name, output_space = "counting", "space"

    def __init__(self):
        self.calls: list[list[str]] = []

    def encode(self, labels):
        self.calls.append(list(labels))
        return np.stack([np.eye(8, dtype=np.float32)[len(label) % 8] for label in labels])


def test_embedder_caches_normalised_labels_and_evicts_least_recent():
    enc = CountingEncoder()
    emb = TextEmbedder(enc, capacity=2)
    first = emb.embed(["Chair", "table"])
    again = emb.embed(["  chair ", "TABLE"])
    np.testing.assert_array_equal(first, again)
    assert enc.calls == [["chair", "table"]]
    emb.embed(["sofa"])  # evicts "chair" (least recently used)
    emb.embed(["table"])
    emb.embed(["chair"])
    assert enc.calls[-1] == ["chair"] and ["table"] not in enc.calls
    assert emb.info().size == 2


def test_oracle_encoder_returns_unit_vectors_and_names_unknown_labels():
    vecs = np.array([[3.0, 0, 0], [0, 2.0, 0]], np.float32)
    enc = OracleTextEncoder(["Chair", "fire extinguisher"], vecs)
    out = enc.encode(["fire  Extinguisher", "chair"])
    np.testing.assert_allclose(out, [[0, 1, 0], [1, 0, 0]])
    with pytest.raises(UnknownLabel, match="'sofa'.*known: chair, fire extinguisher"):
        enc.encode(["sofa"])


@pytest.fixture(scope="module")
def tiny_models(tmp_path_factory):
    from services.common.models.tiny import write_tiny_model

    folder = tmp_path_factory.mktemp("models")
    write_tiny_model("clip-vitb16-text", folder, seed=1)
    write_tiny_model("talk2dino-vitb", folder, seed=2)
    return folder


@pytest.mark.parametrize("device", DEVICES)
def test_clip_path_projects_the_template_mean(tiny_models, device):
    from services.common.models import ModelStore
    from services.common.models.loaders import load_text_encoder, load_text_head

    templates = ["There is {label} in the scene", "a photo of a {label}"]
    cfg = QuerySettings(_env_file=None, text_encoder="clip", models_dir=tiny_models, device=device, templates=templates)
    path = TextPath(cfg)
    got = path.embed(["red chair", "table"], "dinov2_vitb14_reg")
    store = ModelStore(tiny_models, use_hf_cache=False)
    clip, head = load_text_encoder("clip-vitb16-text", store, "cpu"), load_text_head("talk2dino-vitb", store, "cpu")
    for row, label in zip(got, ["red chair", "table"]):
        # Talk2DINO's build_text_embedding: mean of the raw CLIP embeddings, projected, then normalised
        mean = clip.encode([t.format(label=label) for t in templates]).mean(0, keepdim=True)
        want = torch.nn.functional.normalize(head(mean), dim=-1)[0].numpy()
        np.testing.assert_allclose(row, want, atol=1e-5 if device == "cpu" else 1e-4)
    assert got.shape == (2, 32) and not np.allclose(got[0], got[1])
    np.testing.assert_allclose(path.embed(["Red  chair"], "dinov2_vitb14_reg")[0], got[0])
    assert path.loaded().info().hits == 1


def test_text_query_on_another_backbone_is_refused_with_what_to_do(tiny_models):
    cfg = QuerySettings(_env_file=None, text_encoder="clip", models_dir=tiny_models, device="cpu")
    with pytest.raises(SpaceMismatch, match="dinov2_vits14.*dinov2_vitb14_reg.*kmvipe models pull dinov2-vitb14-reg"):
        TextPath(cfg).embed(["chair"], "dinov2_vits14")


def test_missing_language_models_say_how_to_install(tmp_path):
    cfg = QuerySettings(_env_file=None, text_encoder="clip", models_dir=tmp_path, device="cpu")
    with pytest.raises(TextUnavailable, match="kmvipe models pull clip-vitb16-text"):
        TextPath(cfg).embed(["chair"], "dinov2_vitb14_reg")


# -- answers -----------------------------------------------------------------------------------------------
def test_group_answer_ranks_regions_and_gives_each_its_top_points():
    region_query = np.array([1, 0, 0], np.int32)
    score = np.array([0.9, 0.5, 0.7], np.float32)
    lo = np.array([[0, 0, 0], [0, 0, 0], [5, 5, 5]], np.float32)
    hi = lo + 1
    point_query = np.array([0, 0, 0, 1], np.int32)
    pts = np.array([[0.5, 0.5, 0.5], [5.5, 5.5, 5.5], [9, 9, 9], [0.2, 0.2, 0.2]], np.float32)
    pscore = np.array([0.6, 0.8, 0.1, 0.95], np.float32)
    res = group_answer(2, region_query, score, (lo + hi) / 2, lo, hi, np.array([10, 20, 30], np.int32),
                       point_query, pts, pscore)
    assert [r.score for r in res[0].regions] == pytest.approx([0.7, 0.5])
    np.testing.assert_allclose(res[0].regions[0].samples, [[5.5, 5.5, 5.5]])
    np.testing.assert_allclose(res[0].regions[1].samples, [[0.5, 0.5, 0.5]])
    np.testing.assert_allclose(res[0].top_scores, [0.8, 0.6, 0.1])
    assert res[1].regions[0].count == 10 and len(res[1].regions[0].samples) == 1
    with pytest.raises(ValueError, match="region_centroid"):
        group_answer(1, region_query, score, lo[:2], lo, hi, np.zeros(3, np.int32), point_query, pts, pscore)


def test_segment_summary_and_min_score():
    label = np.array([0, 0, 1, 1, 1])
    score = np.array([0.9, 0.1, 0.5, 0.7, 0.6], np.float32)
    xyz = np.arange(15, dtype=np.float32).reshape(5, 3)
    kept = apply_min_score(label, score, 0.3)
    np.testing.assert_array_equal(kept, [0, -1, 1, 1, 1])
    summary = segment_summary(kept, score, xyz, 3)
    assert [s.count for s in summary] == [1, 3, 0]
    assert summary[1].mean_score == pytest.approx(0.6)
    np.testing.assert_allclose(summary[1].centroid, xyz[2:].mean(0))
    assert np.isnan(summary[2].mean_score)
    assert label_palette(5).shape == (5, 3) and len({tuple(c) for c in label_palette(5)}) == 5
    np.testing.assert_array_equal(subsample(10, 3), [0, 4, 9])


# -- files -------------------------------------------------------------------------------------------------
def test_ply_round_trip_plain_and_labelled():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(7, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (7, 3)).astype(np.uint8)
    body = ply.read(ply.header(7) + ply.vertices(xyz, rgb))
    np.testing.assert_array_equal(np.stack([body["x"], body["y"], body["z"]], 1), xyz)
    np.testing.assert_array_equal(body["green"], rgb[:, 1])
    lab = ply.read(ply.header(7, labelled=True) + ply.vertices(xyz, rgb, np.arange(7), np.full(7, 0.5)))
    np.testing.assert_array_equal(lab["label"], np.arange(7))
    with pytest.raises(ValueError, match="announces 8"):
        ply.read(ply.header(8) + ply.vertices(xyz, rgb))


def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _matrix(q):
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_quaternions_known_answers_and_round_trip():
    q = quaternion_xyzw(np.stack([np.eye(3), _rotation([0, 0, 1], np.pi / 2), _rotation([1, 0, 0], np.pi)]))
    np.testing.assert_allclose(q[0], [0, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(q[1], [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(np.abs(q[2]), [1, 0, 0, 0], atol=1e-12)
    rng = np.random.default_rng(1)
    rots = [_rotation(rng.normal(size=3), a) for a in rng.uniform(0, np.pi, 50)]
    for r, qi in zip(rots, quaternion_xyzw(np.stack(rots))):
        np.testing.assert_allclose(_matrix(qi), r, atol=1e-9)


def test_posebook_newer_poses_win_and_tum_lines():
    book = PoseBook(capacity=3)
    pose = np.eye(4)
    pose[:3, 3] = [1, 2, 3]
    book.update(np.array([0, 1]), np.array([0, 1_500_000_000]), np.stack([np.eye(4), np.eye(4)]))
    book.update(np.array([1, 2, 3]), np.array([1_500_000_000, 2_000_000_000, 2_500_000_000]), np.stack([pose] * 3))
    traj = book.trajectory()
    np.testing.assert_array_equal(traj.seqs, [1, 2, 3])  # capacity 3: seq 0 dropped
    lines = tum_text(traj).splitlines()
    assert lines[0] == "1.500000000 1 2 3 0 0 0 1"
    with pytest.raises(ValueError, match="poses"):
        book.update(np.array([5]), np.array([0]), np.eye(4))


# -- query by example --------------------------------------------------------------------------------------
def test_pooled_feature_averages_the_masked_patches():
    fmap = np.zeros((2, 4, 4), np.float32)  # backbones give numpy maps, wherever they ran
    fmap[0, :, :2] = 1.0  # left half: (1, 0)
    fmap[1, :, 2:] = 1.0  # right half: (0, 1)
    left = np.zeros((56, 56), bool)
    left[:, :28] = True
    np.testing.assert_allclose(pooled_feature(fmap, left), [1, 0], atol=1e-6)
    middle = box_mask(56, 56, (14, 0, 42, 56))  # half on each side
    np.testing.assert_allclose(pooled_feature(fmap, middle), [np.sqrt(0.5)] * 2, atol=1e-6)
    with pytest.raises(ValueError, match="covers no pixel"):
        box_mask(56, 56, (60, 60, 70, 70))


def test_pooled_weights_are_torch_adaptive_average_pooling():
    """The mask's area fractions per patch, for a mask whose size is no multiple of the grid's."""
    rng = np.random.default_rng(0)
    fmap, mask = rng.standard_normal((6, 5, 7)).astype(np.float32), rng.random((37, 45)) > 0.6
    weights = torch.nn.functional.adaptive_avg_pool2d(torch.from_numpy(mask.astype(np.float32))[None, None], (5, 7))[0, 0]
    expected = torch.nn.functional.normalize((torch.from_numpy(fmap) * weights).sum(dim=(1, 2)), dim=0).numpy()
    np.testing.assert_allclose(pooled_feature(fmap, mask), expected, atol=1e-5)


def test_fit_to_patches_keeps_thin_regions():
    img = np.zeros((300, 500, 3), np.uint8)
    mask = np.zeros((300, 500), bool)
    mask[150, 250] = True
    out, m = fit_to_patches(img, mask, 14, 140)
    assert out.shape[0] % 14 == 0 and out.shape[1] % 14 == 0 and max(out.shape[:2]) <= 140 and m.any()


def test_connected_voxels_uses_26_connectivity():
    ijk = np.array([[0, 0, 0], [1, 1, 1], [5, 5, 5], [5, 5, 6], [9, 0, 0]])
    lab = connected_voxels(ijk)
    assert lab[0] == lab[1] and lab[2] == lab[3] and len(set(lab.tolist())) == 3


def test_declared_size_reads_png_and_jpeg_headers_without_decoding():
    import cv2

    from services.query_api.core.imagesize import declared_size

    img = np.zeros((37, 53, 3), np.uint8)
    for ext in (".png", ".jpg"):
        assert declared_size(cv2.imencode(ext, img)[1].tobytes()) == (53, 37)
    assert declared_size(b"GIF89a....") is None and declared_size(b"\xff\xd8\xff") is None
