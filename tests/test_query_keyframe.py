"""Query by keyframe region: the pure pooling (known answers), the mapstore's thumbnails and ``map/{keyframes,
keyframe,example}`` verbs against the synthetic world's ground truth (oracle label features: a box over one
label's cells must retrieve that label's object first), and the HTTP routes through a real gateway (uvicorn) and a
real mapstore over loopback Zenoh, errors included."""
from __future__ import annotations

import threading

import cv2
import httpx
import numpy as np
import pytest

from services.common import keys
from services.common.schema import (Eos, Keyframe, KeyframeList, KeyframeQuery, KeyframeRefusal, KeyframeThumbnail,
                                    MapAnswer, MapQuery, PcaBasis as PcaMessage, decode)
from services.mapstore import queries
from services.mapstore.config import MapstoreSettings
from services.mapstore.core.pooling import box_cells, check_box, lift_code, pool_codes, region_vector
from services.mapstore.core.scoring import PcaBasis, decode_codes
from services.mapstore.service import handle
from services.mapstore.state import MapState
from services.synth import LABEL_NAMES
from tests.query_api_fixtures import bus_pair, oracle_settings, wait_for
from tests.test_query_api_e2e import DIM, SEED, STREAM, mapstore_messages, nearest_labels, synth_frames, synth_points

N_KF = 6
BACKGROUND = {"floor", "wall", "ceiling"}  # big surfaces: a box over an object says more
PERSON = LABEL_NAMES.index("person")  # dynamic: left out of the map


# ---------------------------------------------------------------------------------------------- pure pooling
def test_box_cells_take_the_cells_whose_centres_are_inside():
    mask = box_cells((3, 4), np.array([0.0, 0.0, 0.5, 1.0]))  # column centres 0.125, 0.375 | 0.625, 0.875
    np.testing.assert_array_equal(mask, np.repeat([[True, True, False, False]], 3, axis=0))
    mask = box_cells((3, 4), np.array([0.3, 0.4, 0.7, 0.6]))  # only row 1 (centre 0.5), columns 1 and 2
    assert mask.sum() == 2 and mask[1, 1] and mask[1, 2]


def test_a_click_takes_the_one_cell_under_it():
    for (x, y), cell in {(0.6, 0.1): (0, 2), (0.0, 0.0): (0, 0), (1.0, 1.0): (2, 3), (0.2, 0.5): (1, 0)}.items():
        mask = box_cells((3, 4), np.array([x, y, x, y]))
        assert mask.sum() == 1 and mask[cell], (x, y)


@pytest.mark.parametrize("box, error", [([0.1, 0.1, 1.2, 0.5], r"\[0, 1\]"), ([-0.1, 0, 0.5, 0.5], r"\[0, 1\]"),
                                        ([0.6, 0.1, 0.5, 0.5], "inverted"), ([0.1, 0.2, 0.3], "4 finite"),
                                        ([0.1, np.nan, 0.3, 0.4], "4 finite")])
def test_bad_boxes_say_what_is_wrong(box, error):
    with pytest.raises(ValueError, match=error):
        check_box(np.array(box))


def test_pooled_and_lifted_code_is_the_normalised_mean_feature_of_the_cells():
    rng = np.random.default_rng(0)
    d, k = 12, 5
    components = np.linalg.qr(rng.normal(size=(d, k)))[0].T.astype(np.float32)
    basis = PcaBasis(1, rng.normal(size=d).astype(np.float32), components)
    codes = rng.normal(size=(4, 6, k)).astype(np.float16)
    box = np.array([0.0, 0.5, 0.5, 1.0])  # rows 2-3, columns 0-2
    feats = decode_codes(codes[2:, :3].reshape(-1, k), basis)  # the reference decoder, cell by cell
    expect = feats.mean(0) / np.linalg.norm(feats.mean(0))  # decoding is affine: mean of features = decoded mean
    np.testing.assert_allclose(region_vector(codes, box, basis.mean, basis.components), expect, atol=1e-6)
    np.testing.assert_allclose(pool_codes(codes, box_cells((4, 6), box)), codes[2:, :3].astype(np.float64).mean((0, 1)))
    assert np.linalg.norm(lift_code(np.zeros(k), basis.mean, basis.components)) == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError, match="no cell"):
        pool_codes(codes, np.zeros((4, 6), bool))
    with pytest.raises(ValueError, match="share their grid"):
        pool_codes(codes, np.ones((3, 6), bool))


# ------------------------------------------------------------------------------ ground truth from the world
def pure_box(labels: np.ndarray) -> tuple[int, np.ndarray]:
    """(label, normalised box) of the largest rectangle of 1/8-grid cells that are all one object's label
    (background surfaces only when no object has 2×2 cells; never the person)."""
    h, w = labels.shape
    best: dict[int, tuple[int, tuple]] = {}
    for r0 in range(h):
        for c0 in range(w):
            lab = labels[r0, c0]
            for r1 in range(r0, h):
                for c1 in range(c0, w):
                    if np.all(labels[r0:r1 + 1, c0:c1 + 1] == lab):
                        area = (r1 - r0 + 1) * (c1 - c0 + 1)
                        if area > best.get(lab, (0, None))[0]:
                            best[lab] = (area, (r0, c0, r1, c1))
    best.pop(PERSON, None)
    objects = {k: v for k, v in best.items() if LABEL_NAMES[k] not in BACKGROUND and v[0] >= 4}
    label, (_, (r0, c0, r1, c1)) = max((objects or best).items(), key=lambda kv: kv[1][0])
    inset = 0.25  # a quarter cell inside the outer cells' edges: their centres are inside, no other cell's
    return int(label), np.array([(c0 + inset) / w, (r0 + inset) / h, (c1 + 1 - inset) / w, (r1 + 1 - inset) / h])


def keyframe_boxes() -> list[tuple[int, int, np.ndarray]]:
    """(keyframe seq, label, box) per keyframe of `mapstore_messages`: what the codes under the box show."""
    _, frames, grid = synth_frames(N_KF, 8)
    return [(j, *pure_box(f.labels[grid])) for j, f in enumerate(frames)]


def answer_labels(ans: MapAnswer, map_xyz: np.ndarray, gt_xyz: np.ndarray, gt_label: np.ndarray) -> tuple[int, int]:
    """(majority GT label of the map points inside the best region's box, GT label of the best point)."""
    lo, hi = ans.region_box_min[0], ans.region_box_max[0]
    inside = np.all((map_xyz >= lo - 1e-4) & (map_xyz <= hi + 1e-4), axis=1)
    truth = nearest_labels(map_xyz[inside], gt_xyz, gt_label)
    top = nearest_labels(ans.point_xyz[:1], gt_xyz, gt_label)[0]
    return int(np.bincount(truth, minlength=len(LABEL_NAMES)).argmax()), int(top)


def map_settings(tmp_path, **kw) -> MapstoreSettings:
    return MapstoreSettings(stream=STREAM, db_path=str(tmp_path / "{stream}.db"), device="cpu", voxel_mode="absolute",
                            voxel_size=0.15, synchronous="NORMAL", **kw)


def ask(state: MapState, verb: str, params: dict | None = None, payload: bytes | None = None):
    return decode(queries.answer(state, STREAM, f"kmvipe/{STREAM}/map/{verb}", params or {}, payload))


@pytest.fixture(scope="module")
def fed_state(tmp_path_factory):
    cfg = map_settings(tmp_path_factory.mktemp("kfmap"))
    state = MapState(cfg)
    msgs = mapstore_messages(STREAM, N_KF)
    for msg in msgs:
        handle(state, msg, cfg)
    yield state, msgs
    state.close()


def test_a_box_over_one_labels_cells_retrieves_that_label_first(fed_state):
    state, _ = fed_state
    gt_xyz, _, gt_label, *_ = synth_points(N_KF, step=4)
    map_xyz = state.map.fused().xyz
    hits = []
    for seq, label, box in keyframe_boxes():
        centre = np.repeat(box.reshape(2, 2).mean(0)[None], 2, 0).ravel()  # a click: the one cell under it
        for what, b in (("box", box), ("click", centre)):
            ans = ask(state, "example", payload=KeyframeQuery(STREAM, 1, 0, keyframe=seq, box=b, top_k=5).encode())
            assert isinstance(ans, MapAnswer) and len(ans.region_score) > 0
            hits.append(answer_labels(ans, map_xyz, gt_xyz, gt_label) == (label, label))
            print(f"keyframe {seq}: {what} over '{LABEL_NAMES[label]}' -> best region score "
                  f"{ans.region_score[0]:.3f}, right: {hits[-1]}")
    assert all(hits)


def test_the_region_is_scored_exactly_as_a_text_vector(fed_state):
    """The answer equals map/query's for the vector made from the stored codes and their basis by hand."""
    state, msgs = fed_state
    seq, _, box = keyframe_boxes()[2]
    kf = next(m for m in msgs if isinstance(m, Keyframe) and m.seq == seq)
    basis = state.bases[kf.pca_version]
    vector = region_vector(kf.codes, box, basis.mean, basis.components)
    a = ask(state, "example", payload=KeyframeQuery(STREAM, 9, 0, keyframe=seq, box=box, with_points=True).encode())
    b = ask(state, "query", payload=MapQuery(STREAM, 9, 0, vectors=vector[None], space=basis.backbone,
                                               with_points=True).encode())
    assert a.seq == 9
    np.testing.assert_allclose(a.all_scores, b.all_scores, atol=1e-6)
    np.testing.assert_allclose(a.region_score, b.region_score, atol=1e-6)


def test_keyframes_list_and_thumbnails_survive_a_restart(tmp_path):
    cfg = map_settings(tmp_path)
    state = MapState(cfg)
    msgs = mapstore_messages(STREAM, 3)
    for msg in msgs:
        handle(state, msg, cfg)
    state.close()
    state = MapState(cfg)  # everything below is read back from the database
    kl = ask(state, "keyframes")
    assert isinstance(kl, KeyframeList)
    np.testing.assert_array_equal(kl.seqs, [0, 1, 2])
    assert kl.has_codes.all() and kl.has_thumbnail.all() and set(kl.widths) == {160} and set(kl.heights) == {120}
    images = {m.seq: m.image for m in msgs if isinstance(m, Keyframe)}
    for seq in images:
        thumb = ask(state, "keyframe", {"seq": str(seq)})
        assert isinstance(thumb, KeyframeThumbnail) and (thumb.width, thumb.height) == (160, 120)
        assert_is_image_of(thumb.jpeg, seq, images)
    state.close()


def assert_is_image_of(jpeg: bytes, seq: int, images: dict[int, np.ndarray]) -> None:
    """The JPEG shows keyframe ``seq``: far closer to its image than to any other keyframe's (JPEG loss only)."""
    img = cv2.cvtColor(cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(float)
    error = {k: np.abs(img - im).mean() for k, im in images.items() if im.shape == img.shape}
    others = min(v for k, v in error.items() if k != seq)
    assert error[seq] < 12 and error[seq] < 0.5 * others, error


def test_thumbnails_are_downscaled_to_the_longest_side_and_can_be_off(tmp_path):
    msgs = mapstore_messages(STREAM, 1)
    for side, want in ((80, (80, 60)), (0, None)):
        cfg = map_settings(tmp_path / str(side), thumbnail_side=side)
        state = MapState(cfg)
        for msg in msgs:
            handle(state, msg, cfg)
        got = ask(state, "keyframe", {"seq": "0"})
        if want is None:
            assert isinstance(got, KeyframeRefusal) and got.status == "not_found" and "THUMBNAIL_SIDE" in got.reason
        else:
            assert (got.width, got.height) == want
            assert cv2.imdecode(np.frombuffer(got.jpeg, np.uint8), cv2.IMREAD_COLOR).shape == (60, 80, 3)
        state.close()


def test_refusals_name_the_reason(tmp_path):
    cfg = map_settings(tmp_path)
    state = MapState(cfg)
    msgs = mapstore_messages(STREAM, 2)
    for msg in msgs:
        handle(state, msg, cfg)
    kf = next(m for m in msgs if isinstance(m, Keyframe))
    geometry_only = Keyframe(STREAM, 7, 0, image=kf.image, intrinsics=kf.intrinsics)  # its codes follow later
    handle(state, geometry_only, cfg)
    other_basis = Keyframe(STREAM, 8, 0, image=kf.image, intrinsics=kf.intrinsics, pca_version=5, codes=kf.codes)
    handle(state, other_basis, cfg)  # coded with a basis the map has not got
    box = np.array([0.2, 0.2, 0.6, 0.6])

    def example(seq, b=box):
        return ask(state, "example", payload=KeyframeQuery(STREAM, 1, 0, keyframe=seq, box=b).encode())

    kl = ask(state, "keyframes")
    assert dict(zip(kl.seqs.tolist(), kl.has_codes.tolist())) == {0: 1, 1: 1, 7: 0, 8: 0}
    assert (example(7).status, example(8).status, example(99).status) == ("no_codes", "no_codes", "not_found")
    assert "after the keyframe's geometry" in example(7).reason and "version 5" in example(8).reason
    bad = example(0, np.array([0.5, 0.5, 0.4, 0.6]))
    assert (bad.status, bad.seq) == ("bad_request", 0) and "inverted" in bad.reason
    assert ask(state, "keyframe", {"seq": "x"}).status == "bad_request"
    assert ask(state, "keyframe", {"seq": "99"}).reason == "no keyframe 99 in this map"
    handle(state, PcaMessage(STREAM, 0, 0, version=5, backbone="oracle", mean=np.zeros(DIM, np.float32),
                             components=np.eye(DIM, dtype=np.float32)), cfg)
    assert isinstance(example(8), MapAnswer)  # the basis came: the keyframe is queryable
    state.close()


# ------------------------------------------------------------------------ HTTP: gateway + mapstore on Zenoh
API_KEY = "k3y"


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A real mapstore (service loop) fed the synthetic stream over loopback Zenoh, and the gateway on uvicorn."""
    from services.mapstore.service import run as run_mapstore
    from services.query_api.service import start_background

    map_bus, gw_bus = bus_pair("mapstore")
    stop = threading.Event()
    cfg_map = map_settings(tmp_path_factory.mktemp("served"))
    thread = threading.Thread(target=run_mapstore, args=(cfg_map, map_bus, stop), daemon=True)
    thread.start()
    server = http_thread = None
    try:
        cfg = oracle_settings(oracle_synth_seed=SEED, oracle_synth_dim=DIM, port=0, api_key=API_KEY)
        from services.query_api.gateway import Gateway

        gw = Gateway(cfg, gw_bus)
        wait_for(lambda: gw.maps.stats(STREAM), what="the mapstore")
        done = threading.Event()
        gw_bus.subscribe(keys.topic(STREAM, keys.EOS), lambda d: d.msg.stage == "mapstore" and done.set(), [Eos])
        msgs = mapstore_messages(STREAM, N_KF)
        kf = next(m for m in msgs if isinstance(m, Keyframe))
        msgs.append(Keyframe(STREAM, 100, 0, image=kf.image, intrinsics=kf.intrinsics))  # geometry only: no codes
        for msg in msgs:
            gw_bus.publish(keys.topic(STREAM, msg.KIND), msg)
        gw_bus.publish(keys.topic(STREAM, keys.EOS), Eos(STREAM, N_KF, 0, stage=cfg_map.upstream))
        assert done.wait(30), "the mapstore did not forward the end of stream"
        server, http_thread, port = start_background(cfg, gw_bus, gw)
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"X-API-Key": API_KEY}, timeout=10) as client:
            wait_for(lambda: len(client.get(f"/v1/streams/{STREAM}/keyframes").json()["keyframes"]) == N_KF + 1,
                     what="every keyframe listed")
            yield client, msgs
    finally:
        if server is not None:
            server.should_exit = True
            http_thread.join(10)
        stop.set()
        thread.join(5)
        map_bus.close()
        gw_bus.close()


def test_http_lists_keyframes_and_serves_thumbnails(served):
    client, msgs = served
    body = client.get(f"/v1/streams/{STREAM}/keyframes").json()
    assert body["total"] == N_KF + 1 and [k["seq"] for k in body["keyframes"]] == [*range(N_KF), 100]
    assert [k["has_codes"] for k in body["keyframes"]] == [True] * N_KF + [False]
    assert [k["seq"] for k in client.get(f"/v1/streams/{STREAM}/keyframes?limit=2").json()["keyframes"]] == [5, 100]
    res = client.get(f"/v1/streams/{STREAM}/keyframes/3/thumbnail")
    assert res.status_code == 200 and res.headers["content-type"] == "image/jpeg"
    assert_is_image_of(res.content, 3, {m.seq: m.image for m in msgs if isinstance(m, Keyframe) and m.seq < N_KF})


def test_http_box_query_retrieves_the_label_under_the_box(served):
    client, _ = served
    gt_xyz, _, gt_label, *_ = synth_points(N_KF, step=4)
    seq, label, box = keyframe_boxes()[1]
    res = client.post(f"/v1/streams/{STREAM}/query/keyframe", json={"seq": seq, "box": box.tolist(), "top_k": 5})
    assert res.status_code == 200, res.text
    body = res.json()
    result = body["results"][0]
    assert body["space"] == "oracle" and result["text"] == f"keyframe {seq}" and result["regions"]
    best = result["regions"][0]
    pts = np.array(result["top_points"][0]["xyz"], np.float32)[None]
    assert int(nearest_labels(pts, gt_xyz, gt_label)[0]) == label
    assert int(nearest_labels(np.array([best["centroid"]], np.float32), gt_xyz, gt_label)[0]) == label
    print(f"keyframe {seq}, box over '{LABEL_NAMES[label]}': best region score {best['score']:.3f}, "
          f"{best['count']} points")


@pytest.mark.parametrize("method, path, body, status, words", [
    ("get", "/v1/streams/nowhere/keyframes", None, 404, "unknown stream"),
    ("get", f"/v1/streams/{STREAM}/keyframes/999/thumbnail", None, 404, "no keyframe 999"),
    ("post", f"/v1/streams/{STREAM}/query/keyframe", {"seq": 999, "box": [0, 0, 1, 1]}, 404, "no keyframe 999"),
    ("post", f"/v1/streams/{STREAM}/query/keyframe", {"seq": 100, "box": [0, 0, 1, 1]}, 409, "no DINO codes"),
    ("post", f"/v1/streams/{STREAM}/query/keyframe", {"seq": 1, "box": [0.5, 0, 0.4, 1]}, 422, "inverted"),
    ("post", f"/v1/streams/{STREAM}/query/keyframe", {"seq": 1, "box": [0, 0, 1.5, 1]}, 422, "less than or equal"),
    ("post", f"/v1/streams/{STREAM}/query/keyframe", {"seq": 1, "box": [0, 0, 1]}, 422, "at least 4"),
    # beyond the wire's int64 (schemathesis found a 500 there): refused before anything is encoded
    ("post", f"/v1/streams/{STREAM}/query/keyframe", {"seq": 2**64, "box": [0, 0, 1, 1]}, 422, "less than or equal"),
    ("get", f"/v1/streams/{STREAM}/keyframes/{2**64}/thumbnail", None, 422, "less than or equal"),
])
def test_http_errors_say_why(served, method, path, body, status, words):
    client, _ = served
    res = client.request(method.upper(), path, json=body)
    assert res.status_code == status, res.text
    assert words in str(res.json()["detail"])


def test_http_keyframe_routes_need_the_api_key(served):
    client, _ = served
    for path in (f"/v1/streams/{STREAM}/keyframes", f"/v1/streams/{STREAM}/keyframes/0/thumbnail"):
        assert client.get(path, headers={"X-API-Key": ""}).status_code == 401
    res = client.post(f"/v1/streams/{STREAM}/query/keyframe", json={"seq": 0, "box": [0, 0, 1, 1]},
                      headers={"X-API-Key": "wrong"})
    assert res.status_code == 401


def test_a_map_without_keyframes_answers_404_not_a_server_error():
    """A reference map (or an older mapstore) does not serve the keyframe verbs: the routes say so with a 404."""
    from fastapi.testclient import TestClient

    from services.query_api.app import create_app
    from services.query_api.gateway import Gateway
    from tests.query_api_fixtures import make_scene, scene_map

    map_bus, gw_bus = bus_pair()
    try:
        scene_map(make_scene(points_per_label=20)).serve(map_bus, "ref")
        cfg = oracle_settings()
        gw = Gateway(cfg, gw_bus)
        wait_for(lambda: gw.maps.stats("ref"), what="the reference map")
        with TestClient(create_app(cfg, gw)) as client:
            for res in (client.get("/v1/streams/ref/keyframes"),
                        client.post("/v1/streams/ref/query/keyframe", json={"seq": 0, "box": [0, 0, 1, 1]})):
                assert res.status_code == 404 and "keeps no keyframes" in res.json()["detail"]
    finally:
        map_bus.close()
        gw_bus.close()
