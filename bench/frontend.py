"""A source through the features keyframe selector and the BA frontend, in one process (no bus, no DINO).

The same per-frame path as `kmvipe run` minus transport and codes (so the kernel is the fixed one): resize to the
working size, DIS keyframe test, keyframes into ``Frontend.add_keyframe``, other frames (lite grey) into
``Frontend.add_frame``, ``finish`` at the end. Reports ATE (Sim(3)) over every frame with a pose when the source
has ground truth, how many frames got a pose, keyframes, the focal length, seconds per keyframe, and the drift from
the first pose (rotation and translation: a static camera must stay put). It is the quick loop for tuning the
frontend; the full pipeline is ``kmvipe run SOURCE``.

With ``--track`` every frame is first posed by the frame-rate tracker against the newest mapped keyframe, and
anchored there as the ba service does (mapping then spends no flow on it); with ``--live`` a keyframe's mapping
also starts at its tracked pose, as the service does for a live keyframe only. The report adds the ATE of those
first (tracked) poses.

Usage:
  python bench/frontend.py ../shared/data/kitti07_160 --focal 919.2      # KITTI 07 from a +30 % focal
  python bench/frontend.py ../shared/data/kitti07_160 --track            # the live path's tracking too
  python bench/frontend.py ../shared/data/vtest/vtest.avi --max-frames 300
  python bench/frontend.py synth:frames=10000,width=256,height=192,span=8333 --max-frames 2500 --track \
      --drift-stretch 500                                                     # laps of a room: drift on revisits
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass
from itertools import islice
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from services.ba.frontend import graph as frontend_graph
from services.ba.frontend import motion as frontend_motion
from services.ba.core import se3_numpy
from services.ba.frontend.frontend import FrameInput, Frontend, KeyframeInput
from services.ba.frontend.tracker import Tracker
from services.ba.settings import BaSettings
from services.ba.tracking_process import half_size
from services.common.config import LogSettings
from services.common.lifecycle import tune_malloc_for_tensors
from services.common.logs import setup_logging
from services.evaluation.drift import drift_by_stretch
from services.evaluation.trajectory_io import Trajectory, write_tum
from services.features.core.geometry import Intrinsics, fov_prior, resize_to_working, to_grey, working_size
from services.features.core.keyframes import KeyframeParams, KeyframeSelector
from services.ingest.sources import SourceFrame, open_source
from services.runner.groundtruth import MAX_STAMP_DIFF_S, evaluate, source_groundtruth


@dataclass
class FrontendRun:
    """What :func:`run_frontend` produced."""

    latest: dict[int, tuple[int, np.ndarray]]  # seq -> (t_ns, world_from_cam): the last pose published
    first: dict[int, tuple[int, np.ndarray]]  # seq -> the first pose (tracking's with track=True)
    focal_px: float  # estimated focal length, source pixels
    start_focal_px: float
    principal_px: tuple[float, float]  # estimated principal point (cx, cy), source pixels
    keyframes: int
    graph_keyframes: int
    ba_seconds: float
    finish_seconds: float
    wall_seconds: float
    frontend: Frontend

    def trajectory(self, first: bool = False) -> Trajectory:
        poses = self.first if first else self.latest
        seqs = sorted(poses)
        return Trajectory(np.array([poses[s][0] for s in seqs]) / 1e9, np.stack([poses[s][1] for s in seqs]))


def run_frontend(frames: list[SourceFrame], focal: float | None = None,
                 kf_threshold: float = KeyframeParams.threshold_grid_px, track: bool = False,
                 verbose: bool = False, progress: bool = True, live: bool = False, map_lag: int = 0) -> FrontendRun:
    """``frames`` through the keyframe selector and the frontend as the pipeline does (see the module docstring).
    ``focal``: the start focal in source pixels (default: the 60 deg prior, i.e. no calibration). ``live``: keyframes
    flagged real-time, as a live camera's are (mapping's cheaper settings, FrontendParams.live_*). ``map_lag``:
    mapping runs this many keyframes behind tracking, as on a CPU too slow for it (with ``live``, keyframes mapped
    while later ones wait leave their window BA to a later one, as the ba service does)."""
    frontend = Frontend(BaSettings().frontend_params(), "cpu")
    selector = KeyframeSelector(KeyframeParams(threshold_grid_px=kf_threshold))
    n_kf, ba_seconds, t_start = 0, 0.0, time.perf_counter()
    height, width = frames[0].rgb.shape[:2]
    size = working_size(height, width)
    start = fov_prior(height, width) if focal is None else Intrinsics(focal, focal, (width - 1) / 2, (height - 1) / 2)
    k_work = start.scaled(size.scale_x, size.scale_y).as_array()
    latest: dict[int, tuple[int, np.ndarray]] = {}
    first: dict[int, tuple[int, np.ndarray]] = {}
    settings = BaSettings()
    tracker = settings.tracker() if track else None

    def keep(update) -> None:
        if update.poses is not None:
            for seq, stamp, pose in zip(update.poses.frame_seqs, update.poses.stamps_ns, update.poses.poses):
                latest[int(seq)] = (int(stamp), pose)
                first.setdefault(int(seq), (int(stamp), pose))

    queue: list[tuple] = []  # mapping's inbox: (frame, working grey, tracking's anchor, is keyframe)

    def map_next() -> None:
        nonlocal n_kf, ba_seconds
        frame, work, anchor, is_kf = queue.pop(0)
        if not is_kf:
            lite = cv2.resize(work, (work.shape[1] // 2, work.shape[0] // 2), interpolation=cv2.INTER_AREA)
            tracked = None if anchor is None else anchor[:2]
            world = anchor[2] if anchor is not None and live else None
            flow = None if anchor is None or not live or anchor[3] is None else (anchor[0], *anchor[3])
            keep(frontend.add_frame(FrameInput(frame.index, frame.t_ns, lite, tracked, tracked_world=world,
                                               tracked_flow=flow)))
            return
        guess = None
        if anchor is not None and live:  # as the ba service does for a live keyframe: start where tracking put it
            g = frontend.graph
            guess = g.poses[g.index(anchor[0])] @ anchor[1] if anchor[0] in g.seqs else anchor[2]
        behind = live and any(item[3] for item in queue)
        t0 = time.perf_counter()
        keep(frontend.add_keyframe(KeyframeInput(frame.index, frame.t_ns, work, k_work, pose_guess=guess,
                                                 realtime=live, defer_ba=behind)))
        ba_seconds += time.perf_counter() - t0
        n_kf += 1
        if not live:  # a lossless stream's mapping idles between keyframes (the backbone paces them)
            keep(frontend.refine_globally())
        if tracker is not None and (ref := frontend.reference()) is not None:
            tracker.set_reference(ref)
        if verbose:
            _print_steps(frontend, frame.index, time.perf_counter() - t0)

    for n, frame in enumerate(tqdm(frames, unit="frame", disable=not progress)):
        work = to_grey(resize_to_working(frame.rgb, size))
        anchor = _track(tracker, frame, work, k_work, first)
        is_kf = selector.observe(work).is_keyframe or n == len(frames) - 1
        if is_kf:
            selector.set_reference(work)
            if tracker is not None:
                tracker.keyframe_seen(frame.index)
            if anchor is not None:  # as the tracking thread does: move on to the keyframe
                tracker.promote(frame.index, frame.t_ns, work, anchor[2])
        queue.append((frame, work, anchor, is_kf))
        while queue and sum(item[3] for item in queue) > map_lag:
            map_next()
    while queue:
        map_next()
    t0 = time.perf_counter()
    keep(frontend.finish())
    finish_seconds = time.perf_counter() - t0
    graph_kf = len(frontend.graph) if frontend.graph is not None else 0
    final = (Intrinsics(*(float(v) for v in frontend.intrinsics)).scaled(1 / size.scale_x, 1 / size.scale_y)
             if frontend.graph is not None else start)
    return FrontendRun(latest, first, final.fx, start.fx, (final.cx, final.cy), n_kf, graph_kf, ba_seconds,
                       finish_seconds, time.perf_counter() - t_start, frontend)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="anything `kmvipe run` takes: image folder, video, synth:...")
    parser.add_argument("--first", type=int, default=0, help="skip the frames before this one")
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--kf-threshold", type=float, default=KeyframeParams.threshold_grid_px)
    parser.add_argument("--focal", type=float, default=None, help="start focal (original px); default: FOV prior")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--verbose", action="store_true", help="print every keyframe's last steps")
    parser.add_argument("--log-level", default="WARNING", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                        help="INFO shows the graph's decisions (keyframes removed, edges, BA refusals)")
    parser.add_argument("--out", type=Path, default=None, help="write the TUM trajectory here")
    parser.add_argument("--drift-stretch", type=int, default=None, metavar="N",
                        help="also the error per N frames with the estimate aligned on its first N (drift on revisits)")
    parser.add_argument("--track", action="store_true", help="pose every frame by tracking first (the live path)")
    parser.add_argument("--live", action="store_true", help="keyframes flagged real-time (mapping's live settings)")
    parser.add_argument("--map-lag", type=int, default=0, help="mapping runs this many keyframes behind tracking")
    parser.add_argument("--blank", default=None, metavar="A-B",
                        help="frames A to B (inclusive) go black, as a covered lens (a lost view)")
    parser.add_argument("--jpeg-quality", type=int, default=None, metavar="Q",
                        help="each frame through JPEG at quality Q first, as ingest sends it (KMVIPE_INGEST_JPEG_QUALITY)")
    args = parser.parse_args()
    tune_malloc_for_tensors()  # as the ba service does
    torch.set_num_threads(args.threads)
    spent = _instrument()
    setup_logging("bench-frontend", LogSettings(level=args.log_level))
    stop = None if args.max_frames is None else args.first + args.max_frames
    # read no further than needed: a synthetic source renders every frame it yields
    read = (f for f in open_source(args.source).frames() if isinstance(f, SourceFrame))
    frames = list(islice(read, args.first, stop))
    if args.blank:
        first, last = (int(v) for v in args.blank.split("-"))
        frames = [dataclasses.replace(f, rgb=np.zeros_like(f.rgb)) if first <= f.index <= last else f for f in frames]
    if args.jpeg_quality is not None:
        frames = [dataclasses.replace(f, rgb=jpeg_round_trip(f.rgb, args.jpeg_quality)) for f in frames]
    run = run_frontend(frames, args.focal, args.kf_threshold, args.track, args.verbose, live=args.live,
                       map_lag=args.map_lag)
    est = run.trajectory()
    poses = est.world_from_cam
    print(f"frames {len(frames)}  posed {len(run.latest)}  keyframes {run.keyframes} (graph {run.graph_keyframes})")
    print(f"focal {run.focal_px:.1f} px (start {run.start_focal_px:.1f}), principal point "
          f"({run.principal_px[0]:.1f}, {run.principal_px[1]:.1f}) px")
    print(f"BA {run.ba_seconds:.1f} s ({run.ba_seconds / max(run.keyframes, 1):.2f} s/keyframe), finish "
          f"{run.finish_seconds:.1f} s, wall {run.wall_seconds:.1f} s")
    print("time in: " + ", ".join(f"{name} {sec:.1f} s ({calls} calls)" for name, (sec, calls) in spent.items()))
    rel = np.linalg.inv(poses[0]) @ poses
    angles = np.degrees(np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
    lost = run.frontend.frames.lost_views()
    print(f"view lost: {', '.join(f'{a}-{b}' for a, b in lost) if lost else 'none'}; "
          f"frames whose solve strayed off the poses around them: {run.frontend.frames.strayed()}")
    print(f"drift from the first pose: max rotation {angles.max():.3f} deg, max translation "
          f"{np.linalg.norm(rel[:, :3, 3], axis=1).max():.4f} (map units)")
    ate = evaluate(args.source, est)
    if ate is not None:
        print(f"ATE sim3 rmse {ate.rmse:.3f} m  max {ate.max:.3f} m  pairs {ate.n_pairs}")
    if ate is not None and args.drift_stretch:
        print(f"aligned on the first {args.drift_stretch} frames: mean error (m) / scale against them, per stretch: "
              + ", ".join(f"{s.first}: {s.mean_error:.4f} / {s.scale_ratio:.4f}"
                          for s in drift_by_stretch(source_groundtruth(args.source), est, args.drift_stretch,
                                                    MAX_STAMP_DIFF_S)))
    if args.track:
        at_once = evaluate(args.source, run.trajectory(first=True))
        if at_once is not None:
            print(f"ATE of the first (tracked) poses: sim3 rmse {at_once.rmse:.3f} m  pairs {at_once.n_pairs}")
    if args.out:
        write_tum(args.out, est)
        if args.track:
            write_tum(args.out.with_suffix(".first.txt"), run.trajectory(first=True))


def jpeg_round_trip(rgb: np.ndarray, quality: int) -> np.ndarray:
    """``rgb`` as features sees it after ingest's JPEG at ``quality``."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _track(tracker: Tracker | None, frame: SourceFrame, work: np.ndarray, intrinsics: np.ndarray,
           first: dict[int, tuple[int, np.ndarray]]) -> tuple | None:
    """The tracking thread's work for one frame: its pose at once, and the anchor mapping will use
    (reference keyframe seq, reference_from_cam, world_from_cam, tracking's flow)."""
    if tracker is None:
        return None
    lite, lite_k = half_size(work, intrinsics)
    out = tracker.track(frame.index, frame.t_ns, lite, lite_k)  # before the map: provisional rotation-only poses
    if out is None:
        return None
    first.setdefault(frame.index, (frame.t_ns, out.pose))
    if not out.ok:
        return None
    # tensors, as the ba service takes a step from its tracking process (services/ba/tracking.py)
    flow = None if out.target is None else (torch.from_numpy(out.target), torch.from_numpy(out.confidence))
    return (out.ref_seq, torch.from_numpy(se3_numpy.inverse(tracker.reference.pose) @ out.pose),
            torch.from_numpy(out.pose), flow)  # a relocalised pose carries no flow


def _instrument() -> dict[str, list]:
    """Wrap the frontend's flow, BA and alignment calls to report where the time goes (bench only)."""
    spent: dict[str, list] = {}

    def timed(module, attr: str, name: str) -> None:
        inner = getattr(module, attr)
        spent[name] = [0.0, 0]

        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                spent[name][0] += time.perf_counter() - t0
                spent[name][1] += 1
        setattr(module, attr, wrapper)

    timed(frontend_graph.core_flow, "pair_targets", "keyframe edge flows (pairs)")
    timed(frontend_graph.core_flow, "flow_targets", "non-keyframe flows")
    timed(frontend_graph, "run_ba", "run_ba")
    timed(frontend_motion, "align", "motion-only alignment")
    return spent


def _print_steps(frontend: Frontend, seq: int, seconds: float) -> None:
    g = frontend.graph
    if not frontend.initialised or len(g) < 2:
        tqdm.write(f"kf {seq}: not initialised ({len(g)} keyframes)")
        return
    steps = [float((g.poses[k][:3, 3] - g.poses[k - 1][:3, 3]).norm()) for k in range(max(1, len(g) - 4), len(g))]
    tqdm.write(f"kf {seq}: last steps {' '.join(f'{s:.3f}' for s in steps)}  "
               f"focal {float(g.intrinsics[0]) * 8:.1f} (working)  {seconds:.1f} s")


if __name__ == "__main__":
    main()
