"""The /v1 API over real HTTP (TestClient) and a real loopback Zenoh bus with the reference map queryable."""
from __future__ import annotations

import base64
import threading

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.query_api_fixtures import LABELS, STREAM, bus_pair, make_scene, oracle_settings, scene_map, wait_for
from services.common import keys
from services.common.schema import Poses
from services.query_api.app import create_app
from services.query_api.core import ply
from services.query_api.gateway import Gateway
from services.query_api.refmap import RefMap


@pytest.fixture(scope="module")
def world():
    scene = make_scene()
    map_bus, gw_bus = bus_pair()
    scene_map(scene).serve(map_bus, STREAM)
    # a second map in another backbone space: text queries on it must be refused
    other = scene_map(scene, backbone="dinov2_vits14")
    other.serve(map_bus, "vits")
    # a mapstore that never answers in time (replies late from its own thread: Zenoh's stay free)
    late = lambda query: threading.Timer(2.0, lambda: query.reply(query.key_expr, b"late")).start()  # noqa: E731
    slow = map_bus.session.declare_queryable(keys.map_key("slow", "**"), late)
    cfg = oracle_settings(timeout_s=1.0, max_texts=8, max_body_bytes=64 * 1024, cors_origins=["http://viewer.example"],
                          max_point_scores=5000)
    gw = Gateway(cfg, gw_bus)
    wait_for(lambda: gw.maps.stats(STREAM), what="the map queryable")
    with TestClient(create_app(cfg, gw)) as client:
        client.gw_bus = gw_bus
        yield scene, map_bus, client
    slow.undeclare()
    map_bus.close()
    gw_bus.close()


def _inside(xyz, box):
    return np.all((xyz >= box[0] - 1e-6) & (xyz <= box[1] + 1e-6), axis=-1)


def test_every_label_query_returns_its_object_first(world):
    scene, _, client = world
    res = client.post(f"/v1/streams/{STREAM}/query", json={"texts": list(LABELS), "top_k": 5})
    assert res.status_code == 200, res.text
    body = res.json()
    assert body["n_points"] == len(scene.xyz) and body["space"] == "oracle"
    for k, result in enumerate(body["results"]):
        best = result["regions"][0]
        assert result["text"] == LABELS[k]
        assert _inside(np.array(best["centroid"]), scene.boxes[k])
        assert _inside(np.array(result["top_points"][0]["xyz"]), scene.boxes[k])
        assert best["count"] > 0.9 * np.sum(scene.label == k) and best["samples"]


def test_point_scores_are_returned_on_request(world):
    scene, _, client = world
    res = client.post(f"/v1/streams/{STREAM}/query", json={"texts": ["chair", "table"], "with_point_scores": True})
    scores = np.array(res.json()["point_scores"])
    assert scores.shape == (2, len(scene.xyz))
    chair = LABELS.index("chair")
    assert scores[0][scene.label == chair].mean() > scores[0][scene.label != chair].max() - 0.5


def test_segment_json_matches_ground_truth_and_ply_carries_labels(world):
    scene, _, client = world
    res = client.post(f"/v1/streams/{STREAM}/segment", json={"labels": list(LABELS), "include_points": True})
    body = res.json()
    assert res.status_code == 200 and body["n_points"] == len(scene.xyz)
    assert [x["count"] for x in body["labels"]] == [int(np.sum(scene.label == k)) for k in range(len(LABELS))]
    res = client.post(f"/v1/streams/{STREAM}/segment", json={"labels": list(LABELS), "format": "ply"})
    assert res.headers["content-type"] == "application/x-ply"
    data = ply.read(res.content)
    pred = data["label"]
    order = np.lexsort(scene.xyz.T)  # match PLY rows to scene points by position
    got = np.lexsort(np.stack([data["x"], data["y"], data["z"]]))
    np.testing.assert_array_equal(pred[got], scene.label[order])


def test_map_streams_every_point_as_ply_in_chunks(world):
    scene, _, client = world
    client.app.state.settings.export_chunk_points = 700  # force several mapstore chunks
    res = client.get(f"/v1/streams/{STREAM}/map")
    data = ply.read(res.content)
    np.testing.assert_array_equal(np.stack([data["x"], data["y"], data["z"]], 1), scene.xyz)
    np.testing.assert_array_equal(data["red"], scene.rgb[:, 0])
    small = client.get(f"/v1/streams/{STREAM}/map", params={"format": "json", "max_points": 100}).json()
    assert small["returned"] == 100 and small["total_points"] == len(scene.xyz) and len(small["rgb"]) == 300


def test_trajectory_follows_the_pose_stream(world):
    _, map_bus, client = world
    assert client.get(f"/v1/streams/{STREAM}/trajectory").status_code == 404
    poses = np.repeat(np.eye(4)[None], 3, 0)
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    map_bus.publish(keys.topic(STREAM, keys.POSE), Poses(STREAM, 2, 0, frame_seqs=np.arange(3), stamps_ns=np.arange(3) * 10**8, poses=poses))
    wait_for(lambda: client.get(f"/v1/streams/{STREAM}/trajectory").status_code == 200, what="poses")
    revised = poses[1:2].copy()
    revised[0, 0, 3] = 5.0  # BA revises frame 1
    map_bus.publish(keys.topic(STREAM, keys.POSE), Poses(STREAM, 2, 0, frame_seqs=np.array([1]), stamps_ns=np.array([10**8]), poses=revised))
    frames = wait_for(lambda: [f for f in client.get(f"/v1/streams/{STREAM}/trajectory").json()["frames"]
                               if f["world_from_cam"][0][3] == 5.0], what="revised pose")
    assert frames[0]["seq"] == 1
    tum = client.get(f"/v1/streams/{STREAM}/trajectory", params={"format": "tum"}).text.splitlines()
    assert tum == ["0.000000000 0 0 0 0 0 0 1", "0.100000000 5 0 0 0 0 0 1", "0.200000000 2 0 0 0 0 0 1"]


def test_streams_health_and_metrics(world):
    _, _, client = world
    streams = {s["name"]: s for s in client.get("/v1/streams").json()["streams"]}
    assert streams[STREAM]["map"]["points"] > 0 and streams["vits"]["map"]["backbone"] == "dinov2_vits14"
    health = client.get("/v1/health").json()
    assert health["services"]["query_api"]["alive"] and health["services"]["map"]["alive"]
    assert not health["services"]["mapstore"]["alive"] and health["status"] == "degraded"
    client.post(f"/v1/streams/{STREAM}/query", json={"texts": ["chair"]})
    text = client.get("/metrics").text
    assert 'kmvipe_http_requests_total{method="POST",route="/v1/streams/{stream}/query",status="200"}' in text
    assert 'kmvipe_text_embedding_cache{what="hit"}' in text


@pytest.mark.parametrize("path, body, status, needle", [
    ("/v1/streams/nowhere/query", {"texts": ["chair"]}, 404, "unknown stream 'nowhere'"),
    ("/v1/streams/bad.name/query", {"texts": ["chair"]}, 404, "invalid stream name"),
    (f"/v1/streams/{STREAM}/query", {"texts": []}, 422, "texts"),
    (f"/v1/streams/{STREAM}/query", {"texts": ["  "]}, 422, "texts[0] is empty"),
    (f"/v1/streams/{STREAM}/query", {"texts": ["chair"] * 9}, 422, "too many texts: 9 > 8"),
    (f"/v1/streams/{STREAM}/query", {"texts": ["x" * 300]}, 422, "at most 200"),
    (f"/v1/streams/{STREAM}/query", {"texts": ["unicorn"]}, 422, "knows no label 'unicorn'"),
    (f"/v1/streams/{STREAM}/query", {"texts": ["chair"], "colour": 1}, 422, "colour"),
    (f"/v1/streams/{STREAM}/query", {"texts": ["chair"], "top_k": 5000}, 422, "top_k 5000 exceeds"),
    (f"/v1/streams/{STREAM}/query", {"texts": ["chair"] * 1, "pad": "x" * 70_000}, 413, "exceeds the limit"),
    (f"/v1/streams/{STREAM}/query", {"texts": ["chair", "table", "plant"], "with_point_scores": True}, 413,
     "per-point scores of 3 texts x 2400 points exceed 5000 values"),
    ("/v1/streams/vits/query", {"texts": ["chair"]}, 409, "'dinov2_vits14' but the text encoder writes into 'oracle'"),
    ("/v1/streams/slow/query", {"texts": ["chair"]}, 504, "service 'mapstore (stream 'slow', stats)' did not answer within 1.0 s"),
    (f"/v1/streams/{STREAM}/segment", {"labels": ["chair", ""]}, 422, "labels[1] is empty"),
    (f"/v1/streams/{STREAM}/query/example", {"image_b64": "!!!", "box": [0, 0, 1, 1]}, 422, "not valid base64"),
    (f"/v1/streams/{STREAM}/query/example", {"image_b64": base64.b64encode(b"nope").decode(), "box": [0, 0, 1, 1]},
     422, "not a PNG or JPEG"),
])
def test_bad_requests_get_a_4xx_that_says_what_is_wrong(world, path, body, status, needle):
    _, _, client = world
    res = client.post(path, json=body)
    assert res.status_code == status, res.text
    assert needle in res.text


def test_malformed_json_and_missing_region(world):
    _, _, client = world
    res = client.post(f"/v1/streams/{STREAM}/query", content=b"{texts:", headers={"Content-Type": "application/json"})
    assert res.status_code == 422 and "json" in res.text.lower()
    png = base64.b64encode(cv2.imencode(".png", np.zeros((20, 20, 3), np.uint8))[1].tobytes()).decode()
    res = client.post(f"/v1/streams/{STREAM}/query/example", json={"image_b64": png})
    assert res.status_code == 422 and "give the region" in res.text


def test_cors_allows_only_configured_origins(world):
    _, _, client = world
    ok = client.options(f"/v1/streams/{STREAM}/query", headers={
        "Origin": "http://viewer.example", "Access-Control-Request-Method": "POST"})
    assert ok.headers.get("access-control-allow-origin") == "http://viewer.example"
    bad = client.options(f"/v1/streams/{STREAM}/query", headers={
        "Origin": "http://evil.example", "Access-Control-Request-Method": "POST"})
    assert "access-control-allow-origin" not in bad.headers


def test_api_key_guards_the_api_but_not_the_viewer(world):
    _, _, shared = world
    cfg = oracle_settings(api_key="s3cret")
    with TestClient(create_app(cfg, Gateway(cfg, shared.gw_bus))) as client:
        assert client.post(f"/v1/streams/{STREAM}/query", json={"texts": ["chair"]}).status_code == 401
        assert client.get("/metrics").status_code == 401
        wrong = client.get("/v1/streams", headers={"X-API-Key": "nope"})
        assert wrong.status_code == 401 and "X-API-Key" in wrong.text
        assert client.post(f"/v1/streams/{STREAM}/query", json={"texts": ["chair"]},
                           headers={"X-API-Key": "s3cret"}).status_code == 200
        page = client.get("/")
        assert page.status_code == 200 and "viewer.js" in page.text
        assert client.get("/static/viewer.js").status_code == 200


def test_query_by_example_with_a_real_backbone_finds_the_region_it_shows(world, tmp_path):
    """Tiny random DINOv2-with-registers (real loading code): a map whose two clusters carry the features of
    the two halves of an image; a box on the left half must find the left cluster first."""
    from services.common.models import ModelStore
    from services.common.models.backbones import normalise_rgb
    from services.common.models.loaders import load_backbone
    from services.common.models.tiny import write_tiny_model
    from services.query_api.core.example import pooled_feature

    _, map_bus, shared = world
    write_tiny_model("dinov2-vitb14-reg", tmp_path, seed=0)
    backbone = load_backbone("dinov2-vitb14-reg", ModelStore(tmp_path, use_hf_cache=False), "cpu")
    rng = np.random.default_rng(0)
    image = np.zeros((56, 112, 3), np.uint8)
    image[:, :56] = rng.integers(0, 255, (56, 56, 3))  # textured left half, flat black right half
    feats = backbone(normalise_rgb(image))[0]
    left, right = np.zeros((56, 112), bool), np.zeros((56, 112), bool)
    left[:, :56], right[:, 56:] = True, True
    codes = np.stack([pooled_feature(feats, left)] * 50 + [pooled_feature(feats, right)] * 50)
    xyz = np.concatenate([rng.uniform(0, 0.3, (50, 3)), rng.uniform(2, 2.3, (50, 3))]).astype(np.float32)
    RefMap(xyz, np.zeros((100, 3), np.uint8), codes, np.zeros(32, np.float32), np.eye(32, dtype=np.float32),
           backbone.output_space).serve(map_bus, "example")
    cfg = oracle_settings(backbone="dinov2-vitb14-reg", models_dir=tmp_path, device="cpu")
    gw = Gateway(cfg, shared.gw_bus)
    wait_for(lambda: gw.maps.stats("example"), what="example map")
    png = base64.b64encode(cv2.imencode(".png", image[..., ::-1])[1].tobytes()).decode()
    with TestClient(create_app(cfg, gw)) as client:
        res = client.post("/v1/streams/example/query/example", json={"image_b64": png, "box": [0, 0, 56, 56]})
        assert res.status_code == 200, res.text
        best = res.json()["results"][0]["regions"][0]
        assert max(best["centroid"]) < 0.3 and best["score"] == pytest.approx(1.0, abs=1e-3)
        wrong_space = client.post(f"/v1/streams/{STREAM}/query/example", json={"image_b64": png, "box": [0, 0, 56, 56]})
        assert wrong_space.status_code == 409 and "'oracle'" in wrong_space.text


def test_chunked_upload_over_the_limit_is_refused_while_it_streams(world):
    _, _, client = world

    def body():
        yield b'{"texts": ["chair"], "pad": "'
        for _ in range(100):
            yield b"x" * 1024
        yield b'"}'

    res = client.post(f"/v1/streams/{STREAM}/query", content=body(), headers={"Content-Type": "application/json"})
    assert res.status_code == 413 and "exceeds the limit of 65536 bytes" in res.text


def test_huge_declared_image_is_refused_before_decoding(world):
    _, _, client = world
    png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))[1].tobytes()
    huge = png[:16] + (100_000).to_bytes(4, "big") + (100_000).to_bytes(4, "big") + png[24:]  # header lies
    res = client.post(f"/v1/streams/{STREAM}/query/example", json={"image_b64": base64.b64encode(huge).decode(), "box": [0, 0, 4, 4]})
    assert res.status_code == 413 and "100000x100000" in res.text
