"""How a synthetic run's map grows against what the true depth would add (issue 12: the mapstore's memory follows
its voxels): distinct voxels of the run's exported keyframe depth maps under its final poses (Sim(3)-aligned to the
ground truth) against the same grid cells of the synthetic world's exact depth under its exact poses, keyframe by
keyframe, people and moved objects left out of both.

A camera circling one room sees every surface within a lap, yet the true depth keeps adding voxels after that: each
keyframe samples the surfaces on its 1/8 grid, about every other voxel, so later views fill the gaps in. What the
estimate adds beyond that is its depth and pose noise landing points in voxels next to the surface. The counts are of
raw points (no consistency check, carving or snapping, which the mapstore applies), so they bound the map's growth
from above; the table says how much of it the truth itself has.

Usage (the run's folder keeps ``depth/``, ``trajectory.txt``, ``camera.txt`` and ``summary.json``):
  python bench/live.py --frames 10000 --oracle --timeout 1500    # /tmp/kmvipe-live/synth10000-memory-lossless
  python bench/map_growth.py /tmp/kmvipe-live/synth10000-memory-lossless [--markdown]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.common.camera import scale_intrinsics  # noqa: E402
from services.evaluation.ate import align_poses, matched_poses  # noqa: E402
from services.evaluation.map_quality import apply_sim3, backproject_frame  # noqa: E402
from services.evaluation.trajectory_io import Trajectory, read_tum  # noqa: E402
from services.mapstore.config import FusionParams  # noqa: E402
from services.mapstore.core.fusion import voxel_keys as pack_voxel_keys  # noqa: E402
from services.mapstore.export import read_depth_map  # noqa: E402
from services.runner.groundtruth import MAX_STAMP_DIFF_S  # noqa: E402
from services.synth import SynthWorld  # noqa: E402
from services.synth.spec import config_from_spec  # noqa: E402

GRID = 8  # working pixels per map point (the mapstore's 1/8 grid)


class Growth(NamedTuple):
    """Cumulative distinct voxels after each keyframe (K keyframes, in id order)."""

    seqs: np.ndarray  # (K,) keyframe ids (frame indices)
    estimated: np.ndarray  # (K,) voxels of the run's depth under its aligned poses
    true: np.ndarray  # (K,) voxels of the exact depth of the same cells under the exact poses
    voxel: float  # edge, metres


# The synthetic room's floor and walls are planes of the world's axes, some on a voxel boundary: exact points there
# fall into two layers by their rounding. The grid is turned and moved off them, as the mapstore's (set in its own
# first keyframe's frame) is.
_GRID_ROTATION = cv2.Rodrigues(np.array([0.3, -0.5, 0.7]))[0]
_GRID_OFFSET = np.array([0.37, 0.61, 0.23])  # voxels


def voxel_keys(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """(N,) int64 keys of the voxels of (N, 3) points, packed as the mapstore packs its own, in a grid off the
    world's axes."""
    return pack_voxel_keys(np.floor(xyz @ _GRID_ROTATION.T / voxel + _GRID_OFFSET))


def estimated_alignment(world: SynthWorld, trajectory: Path):
    """The run's final poses by frame index, and the Sim(3) that takes them onto the world's."""
    truth = Trajectory(world.timestamps_ns() / 1e9, world.poses)
    try:  # associated by timestamp as the run's own ATE is (services/runner/groundtruth.py)
        reference, estimate, pairs = matched_poses(truth, read_tum(trajectory), MAX_STAMP_DIFF_S)
    except ValueError as exc:
        raise SystemExit(f"{trajectory}: {exc}; is it this source's run?") from exc
    align = align_poses(estimate[:, :3, 3], reference[:, :3, 3], "sim3")
    return dict(zip(pairs.reference_index.tolist(), estimate)), align


def map_growth(world: SynthWorld, depth_files: dict[int, Path], poses: dict[int, np.ndarray], align,
               intrinsics: np.ndarray, voxel: float | None = None, progress: bool = False) -> Growth:
    """Cumulative voxels of the keyframes in ``depth_files`` ({seq: exported depth map}, each at the working size),
    estimated (under ``poses`` and ``align``, with the run's source-pixel ``intrinsics``) and true (the world's depth
    at the same cells). ``voxel`` None: the mapstore's default, a fraction of the first keyframe's median depth."""
    seen_est: set[int] = set()
    seen_true: set[int] = set()
    seqs, est, true = [], [], []
    for seq in tqdm(sorted(depth_files), desc="keyframes", unit="kf", disable=not progress):
        if seq not in poses:
            continue
        depth = read_depth_map(depth_files[seq])
        frame = world.render(seq)
        h, w = frame.depth.shape
        stride = GRID * w // depth.shape[1]  # the same cells in source pixels
        if stride < 1 or depth.shape[1] * stride != GRID * w or depth.shape[0] * stride != GRID * h:
            raise ValueError(f"keyframe {seq}: its depth map {depth.shape} is not the source's "
                             f"{frame.depth.shape} scaled by {GRID}/n (the cells of one would not be the other's)")
        working = scale_intrinsics(np.asarray(intrinsics, np.float64), depth.shape[1] / w, depth.shape[0] / h)
        static = ~frame.dynamic[::stride, ::stride].reshape(-1)
        z_est = depth[::GRID, ::GRID].reshape(-1)
        keep = static & (z_est > 0) & np.isfinite(z_est)
        if voxel is None:
            voxel = FusionParams().voxel_size * float(np.median(frame.depth[::stride, ::stride].reshape(-1)[keep]))
        xyz_est = apply_sim3(align, backproject_frame(depth, poses[seq], working, GRID)[keep])
        xyz_true = backproject_frame(frame.depth, frame.world_from_cam, np.asarray(frame.intrinsics), stride)[keep]
        seen_est.update(voxel_keys(xyz_est, voxel).tolist())
        seen_true.update(voxel_keys(xyz_true, voxel).tolist())
        seqs.append(seq)
        est.append(len(seen_est))
        true.append(len(seen_true))
    return Growth(np.array(seqs), np.array(est), np.array(true), float(voxel or 0.0))


def table(growth: Growth, after: int, rows: int) -> list[tuple[str, ...]]:
    """Rows at ``rows`` keyframes spread over the run, each with the growth since the last keyframe at or before
    frame ``after``."""
    base = max(int(np.searchsorted(growth.seqs, after, side="right")) - 1, 0)
    picks = sorted(set(np.linspace(0, len(growth.seqs) - 1, rows).round().astype(int).tolist()) | {base})
    out = []
    for k in picks:
        e, t = growth.estimated[k], growth.true[k]
        since = (f"{100 * (e / growth.estimated[base] - 1):+.1f} %", f"{100 * (t / growth.true[base] - 1):+.1f} %") \
            if k >= base else ("–", "–")
        out.append((str(growth.seqs[k]), f"{e:,}", f"{t:,}", f"{e / t:.2f}", *since))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a `kmvipe run` folder of a synthetic source (bench/live.py's)")
    parser.add_argument("--after", type=int, default=1000, help="frame the growth is counted from (default 1000)")
    parser.add_argument("--voxel", type=float, help="voxel edge in metres (default: the mapstore's)")
    parser.add_argument("--rows", type=int, default=12, help="rows of the table")
    parser.add_argument("--markdown", action="store_true", help="print the table as markdown")
    args = parser.parse_args(argv)
    run = args.run.expanduser().resolve()
    try:
        source = json.loads((run / "summary.json").read_text())["source"]
        intrinsics = np.array((run / "camera.txt").read_text().split()[:4], np.float64)
    except (OSError, KeyError, ValueError) as exc:
        raise SystemExit(f"{run}: not a finished `kmvipe run` folder ({exc}); run bench/live.py first") from exc
    if not str(source).startswith("synth:"):
        raise SystemExit(f"{run}: source {source!r} has no exact depth; this bench needs a synthetic run")
    depth_files = {int(p.stem): p for p in sorted((run / "depth").glob("*.*")) if p.suffix in (".npz", ".png")}
    if not depth_files:
        raise SystemExit(f"{run}/depth holds no keyframe depth maps (the mapstore exports them as keyframes fold)")
    world = SynthWorld(config_from_spec(source))
    poses, align = estimated_alignment(world, run / "trajectory.txt")
    try:
        growth = map_growth(world, depth_files, poses, align, intrinsics, args.voxel, progress=True)
    except ValueError as exc:
        raise SystemExit(f"{run}: {exc}") from exc
    header = ("keyframe (frame)", "voxels, estimated", "voxels, true depth", "ratio",
              f"estimated since frame {args.after}", f"true since frame {args.after}")
    rows = table(growth, args.after, args.rows)
    if args.markdown:
        print("| " + " | ".join(header) + " |\n|" + " --- |" * len(header))
        print("\n".join("| " + " | ".join(r) + " |" for r in rows))
    else:
        widths = [max(len(c) for c in col) for col in zip(header, *rows)]
        for r in (header, *rows):
            print("  ".join(c.rjust(n) for c, n in zip(r, widths)))
    last = rows[-1]
    print(f"\n{run.name}: {len(growth.seqs)} keyframes, voxel {growth.voxel * 100:.1f} cm, Sim(3) scale "
          f"{align.scale:.4f}; from frame {args.after} to {growth.seqs[-1]}: estimated {last[4]}, true depth {last[5]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
