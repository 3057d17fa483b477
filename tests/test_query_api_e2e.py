"""End to end on the synthetic world with oracle features and the oracle text encoder: every label's query
returns its object first (top-1), and ``segment`` agrees with the ground-truth labels (mIoU).

The map is served by the reference queryable (points back-projected from exact depth and poses), and — when
the mapstore speaks the MapQuery protocol — by the real mapstore service fed keyframes and graphs.
"""
from __future__ import annotations

import threading

import numpy as np
import torch
from fastapi.testclient import TestClient

from services.common import keys
from services.common.schema import Eos, Graph, Keyframe, PcaBasis, Poses
from services.query_api.app import create_app
from services.query_api.gateway import Gateway
from services.query_api.refmap import RefMap, RefMapParams
from services.synth import LABEL_NAMES, SynthConfig, SynthWorld, backproject, label_vectors, oracle_features
from tests.query_api_fixtures import bus_pair, oracle_settings, wait_for

DIM, SEED, STREAM, NOISE = 64, 5, "synth", 0.3
MIN_POINTS = 30  # labels with fewer visible points are not asked for


def synth_frames(n_keyframes: int, step: int = 8):
    """Every 4th frame of a small synthetic sequence, sampled at the centres of ``step``×``step`` cells."""
    world = SynthWorld(SynthConfig(width=160, height=120, n_frames=n_keyframes * 4, seed=1))
    grid = (slice(step // 2 - 1 if step > 1 else 0, None, step),) * 2
    return world, [world.render(i) for i in range(0, n_keyframes * 4, 4)], grid


def synth_points(n_keyframes: int = 6, step: int = 4):
    """Static pixels back-projected with exact depth and poses: xyz, rgb, GT label, oracle features, poses, stamps."""
    _, frames, grid = synth_frames(n_keyframes, step)
    vecs = label_vectors(len(LABEL_NAMES), DIM, SEED)
    rng = np.random.default_rng(0)
    xyz, rgb, lab, feats = [], [], [], []
    for f in frames:
        keep = ~f.dynamic[grid]
        k = f.intrinsics / step
        k[2:] = (f.intrinsics[2:] + 0.5) / step - 0.5  # the grid's intrinsics (docs/CONVENTIONS.md)
        xyz.append(backproject(f.depth[grid], k, f.world_from_cam)[keep])
        rgb.append(f.rgb[grid][keep])
        lab.append(f.labels[grid][keep])
        feats.append(oracle_features(f.labels[grid], vecs, NOISE, rng)[keep])
    return (np.concatenate(xyz).astype(np.float32), np.concatenate(rgb), np.concatenate(lab),
            np.concatenate(feats), np.stack([f.world_from_cam for f in frames]), np.array([f.t_ns for f in frames]))


def nearest_labels(xyz: np.ndarray, gt_xyz: np.ndarray, gt_label: np.ndarray) -> np.ndarray:
    """GT label of the nearest GT point of every map point."""
    a, b = torch.from_numpy(np.asarray(xyz, np.float32)), torch.from_numpy(np.asarray(gt_xyz, np.float32))
    idx = torch.cat([torch.cdist(a[i:i + 4096], b).argmin(1) for i in range(0, len(a), 4096)])
    return gt_label[idx.numpy()]


def retrieval_metrics(client: TestClient, stream: str, gt_xyz: np.ndarray, gt_label: np.ndarray):
    """(top-1 accuracy over the labels present, mIoU of ``segment`` against GT, labels that missed). A query's
    top-1 is right when its best region holds mostly points of its label and its best point is of its label."""
    present = [k for k in range(len(LABEL_NAMES)) if np.sum(gt_label == k) >= MIN_POINTS]
    names = [LABEL_NAMES[k] for k in present]
    seg = client.post(f"/v1/streams/{stream}/segment", json={"labels": names, "include_points": True,
                                                              "max_points": 5_000_000}).json()
    xyz = np.array(seg["xyz"], np.float32)
    truth = nearest_labels(xyz, gt_xyz, gt_label)
    pred = np.array(present)[np.array(seg["point_labels"])]
    ious = [np.sum((pred == k) & (truth == k)) / max(1, np.sum((pred == k) | (truth == k))) for k in present]
    res = client.post(f"/v1/streams/{stream}/query", json={"texts": names, "top_k": 1, "max_regions": 1})
    assert res.status_code == 200, res.text
    missed = []
    for k, result in zip(present, res.json()["results"]):
        if not result["regions"]:
            missed.append(LABEL_NAMES[k])
            continue
        best = result["regions"][0]
        inside = np.all((xyz >= np.array(best["box_min"]) - 1e-4) & (xyz <= np.array(best["box_max"]) + 1e-4), axis=1)
        top_label = nearest_labels(np.array([result["top_points"][0]["xyz"]]), gt_xyz, gt_label)[0]
        if np.bincount(truth[inside], minlength=len(LABEL_NAMES)).argmax() != k or top_label != k:
            missed.append(LABEL_NAMES[k])
    return 1 - len(missed) / len(present), float(np.mean(ious)), missed


def test_every_label_finds_its_object_through_the_gateway():
    xyz, rgb, gt, feats, poses, stamps = synth_points()
    map_bus, gw_bus = bus_pair()
    try:
        RefMap(xyz, rgb, feats, np.zeros(DIM, np.float32), np.eye(DIM, dtype=np.float32), "oracle",
               RefMapParams(voxel_size=0.1)).serve(map_bus, STREAM)
        cfg = oracle_settings(oracle_synth_seed=SEED, oracle_synth_dim=DIM)
        gw = Gateway(cfg, gw_bus)
        wait_for(lambda: gw.maps.stats(STREAM), what="the synthetic map")
        map_bus.publish(keys.topic(STREAM, keys.POSE), Poses(STREAM, 0, 0, frame_seqs=np.arange(len(poses)),
                                                             stamps_ns=stamps, poses=poses))
        with TestClient(create_app(cfg, gw)) as client:
            top1, miou, missed = retrieval_metrics(client, STREAM, xyz, gt)
            print(f"\nsynthetic world (reference map, {len(xyz)} points): top-1 {top1:.3f}, segment mIoU {miou:.3f}")
            assert top1 == 1.0, f"labels whose query did not return their object first: {missed}"
            assert miou > 0.9
            traj = wait_for(lambda: client.get(f"/v1/streams/{STREAM}/trajectory").json().get("frames"), what="poses")
            np.testing.assert_allclose([f["world_from_cam"] for f in traj], poses)
    finally:
        map_bus.close()
        gw_bus.close()


def mapstore_messages(stream: str, n_keyframes: int):
    """pca (identity basis: codes are the oracle features), then per keyframe: keyframe and graph with exact
    poses, disparity and static weights on the 1/8 grid."""
    _, frames, grid = synth_frames(n_keyframes, 8)
    vecs = label_vectors(len(LABEL_NAMES), DIM, SEED)
    rng = np.random.default_rng(0)
    msgs = [PcaBasis(stream, 0, 0, version=1, backbone="oracle", mean=np.zeros(DIM, np.float32),
                     components=np.eye(DIM, dtype=np.float32))]
    for j, f in enumerate(frames):
        codes = oracle_features(f.labels[grid], vecs, NOISE, rng).astype(np.float16)
        msgs.append(Keyframe(stream, j, f.t_ns, image=f.rgb, intrinsics=f.intrinsics, pca_version=1, codes=codes))
        msgs.append(Graph(stream, j, f.t_ns, kf_seqs=np.arange(j + 1), poses=np.stack([g.world_from_cam for g in frames[:j + 1]]),
                          intrinsics=f.intrinsics, width=160, height=120, updated_seqs=np.array([j]),
                          disparities=(1.0 / f.depth[grid])[None].astype(np.float32), metric=True,
                          static_weights=(~f.dynamic[grid])[None].astype(np.float32), final=j == len(frames) - 1))
    return msgs


def test_gateway_against_the_real_mapstore(tmp_path):
    from services.mapstore.config import MapstoreSettings
    from services.mapstore.service import run as run_mapstore

    n_kf = 6
    map_bus, gw_bus = bus_pair("mapstore")
    stop = threading.Event()
    cfg_map = MapstoreSettings(stream=STREAM, db_path=str(tmp_path / "{stream}.db"), device="cpu",
                               voxel_mode="absolute", voxel_size=0.15, synchronous="NORMAL")  # voxels joining neighbouring grid samples
    thread = threading.Thread(target=run_mapstore, args=(cfg_map, map_bus, stop), daemon=True)
    thread.start()
    try:
        cfg = oracle_settings(oracle_synth_seed=SEED, oracle_synth_dim=DIM)
        gw = Gateway(cfg, gw_bus)
        wait_for(lambda: gw.maps.stats(STREAM), what="the mapstore")
        done = threading.Event()
        gw_bus.subscribe(keys.topic(STREAM, keys.EOS), lambda d: d.msg.stage == "mapstore" and done.set(), [Eos])
        for msg in mapstore_messages(STREAM, n_kf):
            gw_bus.publish(keys.topic(STREAM, msg.KIND), msg)
        # the mapstore handles messages in order and forwards the EOS last: the map is complete then
        gw_bus.publish(keys.topic(STREAM, keys.EOS), Eos(STREAM, n_kf, 0, stage=cfg_map.upstream))
        assert done.wait(30), "the mapstore did not forward the end of stream"
        assert gw.maps.stats(STREAM).keyframes == n_kf
        gt_xyz, _, gt_label, *_ = synth_points(n_kf, step=4)
        with TestClient(create_app(cfg, gw)) as client:
            top1, miou, missed = retrieval_metrics(client, STREAM, gt_xyz, gt_label)
            n = gw.maps.stats(STREAM).points
            print(f"\nsynthetic world (real mapstore, {n} points): top-1 {top1:.3f}, segment mIoU {miou:.3f}")
            assert top1 == 1.0, f"labels whose query did not return their object first: {missed}"
            assert miou > 0.8
    finally:
        stop.set()
        thread.join(5)
        map_bus.close()
        gw_bus.close()
