"""Semantic map quality of the full pipeline on the synthetic world with oracle features (no model needed).

    .venv/bin/python bench/map_quality.py --frames 120 --max-frames 36 --out out/map_quality
    .venv/bin/python bench/map_quality.py --out out/map_quality --reuse   # evaluate an existing run again

Runs ``kmvipe run synth:frames=F,seed=S --skip query_api`` with the features service's ``synth-oracle``
backbone (exact label vectors + noise instead of DINO), then reopens the run's map database with the
mapstore's own state and queryables (``map/segment``, ``map/query``) and scores them against the synthetic
world's exact depth, labels and poses (services/evaluation/map_quality.py). Writes ``map_quality.json`` in
the run folder and prints a per-label table. The moving objects' presence is also split by place (the places
they left vs where they are at the last keyframe); re-score one run without free-space carving with
``KMVIPE_MAPSTORE_CARVE_KEYFRAMES=0 ... --reuse``.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.common.schema import MapAnswer, MapQuery, MapSegment, decode  # noqa: E402
from services.evaluation import map_quality as mq  # noqa: E402
from services.evaluation.ate import absolute_trajectory_error  # noqa: E402
from services.evaluation.trajectory_io import Trajectory, read_tum  # noqa: E402
from services.mapstore import queries  # noqa: E402
from services.mapstore.config import MapstoreSettings  # noqa: E402
from services.mapstore.core.upsample import UpsampleParams, output_centres, upsample_disparity  # noqa: E402
from services.mapstore.state import MapState  # noqa: E402
from services.synth import LABEL_NAMES, SynthFrame, SynthWorld, label_vectors  # noqa: E402
from services.synth.spec import config_from_spec  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
STREAM = "cam0"
ROOM_LABELS = ("floor", "wall", "ceiling")  # surfaces, not objects: no box to overlap


def oracle_env(source: str, seed: int, dim: int, noise: float) -> dict[str, str]:
    """Environment that makes the features service (and a gateway) use the synthetic oracle."""
    return {"KMVIPE_FEATURES_BACKBONE": "synth-oracle", "KMVIPE_FEATURES_ORACLE_SOURCE": source,
            "KMVIPE_FEATURES_ORACLE_SEED": str(seed), "KMVIPE_FEATURES_ORACLE_DIM": str(dim),
            "KMVIPE_FEATURES_ORACLE_NOISE": str(noise), "KMVIPE_QUERY_TEXT_ENCODER": "oracle",
            "KMVIPE_QUERY_ORACLE_SYNTH_SEED": str(seed), "KMVIPE_QUERY_ORACLE_SYNTH_DIM": str(dim)}


def run_pipeline(source: str, out: Path, max_frames: int, env: dict[str, str], timeout_s: float) -> None:
    cmd = [sys.executable, "-m", "services.cli", "run", source, "--out", str(out), "--skip", "query_api",
           "--max-frames", str(max_frames)]
    result = subprocess.run(cmd, cwd=REPO, env={**os.environ, **env}, capture_output=True, text=True, timeout=timeout_s)
    if result.returncode != 0:
        raise RuntimeError(f"kmvipe run failed ({result.returncode}):\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}")


def ask(state: MapState, verb: str, request: MapQuery):
    return decode(queries.answer(state, STREAM, f"kmvipe/{STREAM}/map/{verb}", {}, request.encode()))


def gt_of_keyframes(frames: dict[int, SynthFrame], stride: int) -> mq.GtPoints:
    """GT points of the rendered keyframes (seq → frame), every ``stride``-th pixel."""
    parts = []
    for f in frames.values():
        parts.append(mq.gt_points_of_frame(f.depth, f.labels, f.dynamic, f.world_from_cam, f.intrinsics, stride))
    return mq.concat_gt(parts)


def region_boxes(world: SynthWorld, answer: MapAnswer, alignment, last_frame: int) -> dict[str, dict]:
    """Per object label: IoU of its best-scoring region's box (GT frame) with the label's static instances."""
    boxes = [b for b in world.instance_boxes(last_frame) if not b.dynamic]
    out = {}
    for qi, name in enumerate(LABEL_NAMES):
        truth = [b for b in boxes if b.label_name == name]
        rows = np.flatnonzero(answer.region_query == qi)
        if not truth or name in ROOM_LABELS:
            continue
        if len(rows) == 0:
            out[name] = {"regions": 0, "top_iou": 0.0, "top_hits": False, "top_centroid_inside": False}
            continue
        top = rows[np.argmax(answer.region_score[rows])]
        ious = [mq.aligned_box_iou(alignment, answer.region_box_min[top], answer.region_box_max[top], b.lo, b.hi)
                for b in truth]
        centroid = mq.apply_sim3(alignment, answer.region_centroid[top][None])[0]
        inside = any(bool(np.all(centroid >= b.lo) and np.all(centroid <= b.hi)) for b in truth)
        out[name] = {"regions": int(len(rows)), "top_iou": max(ious), "top_hits": max(ious) > 0,
                     "top_centroid_inside": inside}
    return out


def evaluate_run(out: Path, source: str, seed: int, dim: int, params: mq.MapQualityParams) -> dict:
    """Every metric of one finished run in ``out`` (trajectory.txt, map.db)."""
    world = SynthWorld(config_from_spec(source))
    estimate = read_tum(out / "trajectory.txt")
    truth = Trajectory(world.timestamps_ns() / 1e9, world.poses)
    ate = absolute_trajectory_error(truth, estimate, align="sim3", max_diff=0.02)
    state = MapState(MapstoreSettings(stream=STREAM, db_path=str(out / "map.db"), device="cpu"))
    try:
        vectors = label_vectors(len(LABEL_NAMES), dim, seed)
        seg: MapSegment = ask(state, "segment", MapQuery(STREAM, 0, 0, vectors=vectors, space="oracle"))
        answer: MapAnswer = ask(state, "query", MapQuery(STREAM, 1, 0, vectors=vectors, space="oracle", max_regions=10))
        kf_seqs = sorted(state.store.keyframe_ids())  # folded ones too: their points are in the map
        voxel = float(state.map.voxel_size or 0.0)
        disparities = {k: np.array(state.map.depths[k].disparity) for k in kf_seqs if k in state.map.depths}
    finally:
        state.close()
    frames = {seq: world.render(seq) for seq in kf_seqs}  # rendered once: GT points and the upsampling check
    gt = gt_of_keyframes(frames, params.gt_stride)
    xyz = mq.apply_sim3(ate.alignment, seg.xyz)
    match = mq.match_to_gt(xyz, gt, params.max_dist)
    scores = mq.label_scores(seg.label[match.matched], gt.label[match.index[match.matched]], len(LABEL_NAMES))
    per_label = {name: {"precision": _f(scores.precision[i]), "recall": _f(scores.recall[i]),
                        "iou": _f(scores.iou[i]), "support": int(scores.support[i]), "predicted": int(scores.predicted[i])}
                 for i, name in enumerate(LABEL_NAMES) if scores.support[i] or scores.predicted[i]}
    return {
        "source": source, "keyframes": kf_seqs, "map_points": int(len(xyz)), "ate_rmse_m": ate.rmse,
        "sim3_scale": ate.alignment.scale, "voxel_m": voxel * ate.alignment.scale, "max_dist_m": params.max_dist,
        "matched_fraction": float(match.matched.mean()) if len(xyz) else 0.0,
        "median_dist_m": float(np.median(match.distance)) if len(xyz) else float("nan"),
        "miou": scores.miou, "per_label": per_label,
        "map_points_on_moving_objects": int((match.matched & gt.dynamic[match.index]).sum()),
        "moving_gt_points": int(gt.dynamic.sum()),
        "moving_fraction_present": mq.moving_presence(gt, match, xyz, params.max_dist),
        "moving_fraction_present_by_label": {
            name: _f(mq.moving_presence(gt, match, xyz, params.max_dist, gt.label == LABEL_NAMES.index(name)))
            for name in ("person", "chair")},
        "moving_fraction_present_by_place": moved_places(world, gt, match, xyz, params.max_dist, max(kf_seqs)),
        "static_coverage": static_coverage(gt, xyz, params.max_dist),
        "boxes": region_boxes(world, answer, ate.alignment, max(kf_seqs)),
        "upsampling": upsample_gain(frames, disparities, ate.alignment.scale),
    }


def static_coverage(gt: mq.GtPoints, xyz: np.ndarray, max_dist: float) -> dict[str, float | None]:
    """Fraction of the static GT points with a map point within ``max_dist`` (all labels, and per label): what
    carving must not take away."""
    static = ~gt.dynamic
    if not len(xyz) or not static.any():
        return {"all": 0.0}
    dist, _ = cKDTree(xyz).query(gt.xyz[static], k=1)
    near, labels = dist <= max_dist, gt.label[static]
    out = {"all": _f(near.mean())}
    out.update({LABEL_NAMES[i]: _f(near[labels == i].mean()) for i in np.unique(labels)})
    return out


PLACE_MARGIN_M = 0.03  # GT surface samples lie on the objects' box faces: grow the boxes by this


def moved_places(world: SynthWorld, gt: mq.GtPoints, match: mq.Matching, xyz: np.ndarray, max_dist: float,
                 last_frame: int) -> dict[str, dict[str, float | None]]:
    """Per moving label: fraction of its GT points present in the map, split into those of the places the object
    has left by the last keyframe ("left") and those where it is then ("now")."""
    out = {}
    for name in ("person", "chair"):
        boxes = [b for b in world.instance_boxes(last_frame) if b.dynamic and b.label_name == name]
        if not boxes:
            continue
        now = mq.inside_any_box(gt.xyz, np.array([b.lo for b in boxes]), np.array([b.hi for b in boxes]),
                                PLACE_MARGIN_M)
        label = gt.label == LABEL_NAMES.index(name)
        out[name] = {"left": _f(mq.moving_presence(gt, match, xyz, max_dist, label & ~now)),
                     "now": _f(mq.moving_presence(gt, match, xyz, max_dist, label & now)),
                     "gt_points_left": int((gt.dynamic & label & ~now).sum()),
                     "gt_points_now": int((gt.dynamic & label & now).sum())}
    return out


EDGE_REL = 0.10  # an output cell is "at a depth edge" when its GT depth differs this much from its 1/8 cell's


def upsample_gain(frames: dict[int, SynthFrame], disparities: dict[int, np.ndarray], scale: float,
                  factors: tuple[int, ...] = (2, 4)) -> dict:
    """Depth error of keyframe points at 1/8 and upsampled by each factor and method, against GT depth.

    Two inputs: the run's BA disparity (map units; metres = scale / d) and the GT depth sampled on the 1/8
    grid (isolates the upsampling error). Error: |z − z_gt| / z_gt at each output cell centre (nearest pixel).
    """
    rows: dict[str, dict] = {}
    working = {seq: _working(frames[seq], disp.shape) for seq, disp in disparities.items()}
    for source in ("ba", "gt"):
        for factor in factors:
            for method in ("nearest", "bilinear", "guided"):
                errs, edge_errs, known, total = [], [], 0, 0
                for seq, disp in disparities.items():
                    rgb, depth = working[seq]
                    coarse = _gt_on_grid(depth, disp.shape, 1)
                    low = 1.0 / coarse if source == "gt" else disp / scale  # metric disparity (1/m): metres = scale / d
                    up = upsample_disparity(low, rgb, UpsampleParams(factor=factor, method=method))
                    z_gt = _gt_on_grid(depth, disp.shape, factor)
                    ok = up > 0
                    rel = np.abs(1.0 / np.where(ok, up, 1.0) - z_gt) / z_gt
                    parent = np.repeat(np.repeat(coarse, factor, 0), factor, 1)
                    edge = np.abs(parent - z_gt) > EDGE_REL * z_gt
                    errs.append(rel[ok]), edge_errs.append(rel[ok & edge])
                    known, total = known + int(ok.sum()), total + ok.size
                e, ee = np.concatenate(errs), np.concatenate(edge_errs)
                rows[f"{source} x{factor} {method}"] = {
                    "points_per_keyframe": known / max(len(disparities), 1), "known_fraction": known / max(total, 1),
                    "median_rel_err": float(np.median(e)), "within_5pct": float(np.mean(e < 0.05)),
                    "edge_cells": int(len(ee)), "edge_median_rel_err": float(np.median(ee)) if len(ee) else None}
    return rows


def _working(frame, grid_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The frame's RGB and GT depth at the working size of a (h, w) grid (8h × 8w)."""
    size = (8 * grid_hw[1], 8 * grid_hw[0])
    if frame.rgb.shape[:2] == size[::-1]:
        return frame.rgb, frame.depth
    return (cv2.resize(frame.rgb, size, interpolation=cv2.INTER_AREA),
            cv2.resize(frame.depth, size, interpolation=cv2.INTER_NEAREST))


def _gt_on_grid(depth: np.ndarray, grid_hw: tuple[int, int], factor: int) -> np.ndarray:
    """GT depth (m) at the centres of the (h·f, w·f) output cells (nearest working pixel)."""
    r, c = output_centres(*grid_hw, factor)
    to_pix = lambda g: np.clip(np.floor(g * 8 + 3.5 + 0.5).astype(int), 0, None)  # noqa: E731
    return depth[np.ix_(np.minimum(to_pix(r), depth.shape[0] - 1), np.minimum(to_pix(c), depth.shape[1] - 1))]


def _f(value: float) -> float | None:
    return None if not np.isfinite(value) else round(float(value), 4)


def print_report(report: dict) -> None:
    print(f"map quality of {report['source']}: {report['map_points']} points from {len(report['keyframes'])} keyframes, "
          f"ATE {report['ate_rmse_m']:.4f} m, voxel {report['voxel_m']:.3f} m")
    print(f"  within {report['max_dist_m']} m of a GT surface: {report['matched_fraction']:.3f} "
          f"(median distance {report['median_dist_m']:.3f} m); mIoU {report['miou']:.3f}")
    print(f"  moving objects: {report['moving_fraction_present']:.3f} of their {report['moving_gt_points']} GT points "
          f"present ({report['map_points_on_moving_objects']} map points on them); by label "
          f"{report['moving_fraction_present_by_label']}")
    cover = report["static_coverage"]
    print(f"  static GT points with a map point within {report['max_dist_m']} m: {cover['all']} "
          f"(floor {cover.get('floor')}, wall {cover.get('wall')})")
    for name, row in report["moving_fraction_present_by_place"].items():
        print(f"    {name}: {row['left']} of the {row['gt_points_left']} GT points of places it left present, "
              f"{row['now']} of the {row['gt_points_now']} where it is at the end")
    print(f"  {'label':<18}{'prec':>7}{'recall':>8}{'IoU':>7}{'support':>9}  top-region box IoU")
    for name, row in report["per_label"].items():
        box = report["boxes"].get(name)
        box_s = "" if box is None else f"{box['top_iou']:.3f}" + (" (centroid inside)" if box.get("top_centroid_inside") else "")
        fmt = lambda v: "   -" if v is None else f"{v:.3f}"  # noqa: E731
        print(f"  {name:<18}{fmt(row['precision']):>7}{fmt(row['recall']):>8}{fmt(row['iou']):>7}{row['support']:>9}  {box_s}")
    print(f"  {'upsampling':<20}{'pts/kf':>8}{'med rel err':>13}{'<5%':>7}{'edge cells':>12}{'edge med err':>14}")
    for name, row in report["upsampling"].items():
        edge = "-" if row["edge_median_rel_err"] is None else f"{row['edge_median_rel_err']:.4f}"
        print(f"  {name:<20}{row['points_per_keyframe']:>8.0f}{row['median_rel_err']:>13.4f}{row['within_5pct']:>7.3f}"
              f"{row['edge_cells']:>12}{edge:>14}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=120, help="frames of the synthetic sequence (sets its motion speed)")
    p.add_argument("--max-frames", type=int, default=36, help="frames actually streamed")
    p.add_argument("--source", default="", help="a whole synth: spec instead of --frames and --seed's, e.g. "
                   "synth:frames=3000,width=256,height=192,span=2500 (a stream long enough for keyframes to fold)")
    p.add_argument("--seed", type=int, default=0, help="synthetic world and oracle label-vector seed")
    p.add_argument("--dim", type=int, default=64, help="oracle feature dimension")
    p.add_argument("--noise", type=float, default=0.1, help="oracle feature noise (relative norm)")
    p.add_argument("--max-dist", type=float, default=mq.MapQualityParams.max_dist, help="metres")
    p.add_argument("--out", type=Path, default=REPO / "out" / "map_quality")
    p.add_argument("--target-area", type=int, default=0, help="features working-image area (0: the service default)")
    p.add_argument("--reuse", action="store_true", help="evaluate the run already in --out")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds the pipeline run may take")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    source = args.source or f"synth:frames={args.frames},seed={args.seed}"
    if not args.reuse:
        env = oracle_env(source, args.seed, args.dim, args.noise)
        if args.target_area:
            env["KMVIPE_FEATURES_TARGET_AREA"] = str(args.target_area)
        run_pipeline(source, args.out, args.max_frames, env, args.timeout)
    report = evaluate_run(args.out, source, args.seed, args.dim, mq.MapQualityParams(max_dist=args.max_dist))
    (args.out / "map_quality.json").write_text(json.dumps(report, indent=2))
    print_report(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
