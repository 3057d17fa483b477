"""``kmvipe``: run the pipeline, one service, an edge publisher, the demo, and the tools of each stage."""
from __future__ import annotations

import argparse
import importlib
import json
import logging
import signal
import sys
from pathlib import Path

from pydantic import ValidationError

from .common.errors import KmVipeError
from .common.keys import DEFAULT_STREAM
from .common.logs import setup_logging
from .runner import children
from .runner.semantics import TEXT_PROFILES

DEFAULT_DEMO_SOURCE = "synth:frames={frames},seed={seed}"


def _add_stream_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--stream", default=DEFAULT_STREAM, help="stream name (the <s> in kmvipe/<s>/...)")
    p.add_argument("--pacing", choices=["lossless", "realtime"], default="lossless")
    p.add_argument("--encoding", choices=["jpeg", "raw"], default="jpeg")
    p.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                   help="optional calibration hint in source pixels (else estimated)")
    p.add_argument("--max-frames", type=int)
    p.add_argument("--skip", action="append", default=[], metavar="SERVICE", help="a built service not to start")
    p.add_argument("--port", type=int, default=8000, help="HTTP port of the query gateway")


def _cmd_run(args: argparse.Namespace) -> int:
    from .runner.pipeline import RunSettings, run_pipeline
    from .runner.rerun_log import load_rerun, target_settings
    from .common.query_support import QuerySupport

    rerun = target_settings(args.rerun, args.rerun_connect, image_every=args.rerun_every,
                            map_every_s=args.rerun_map_every, queries=tuple(args.rerun_query))
    if rerun is not None:
        load_rerun()  # a missing rerun-sdk ends the run before anything starts
    cfg = RunSettings(
        source=args.source, out=Path(args.out), stream=args.stream, pacing=args.pacing, encoding=args.encoding,
        intrinsics=tuple(args.intrinsics) if args.intrinsics else None, max_frames=args.max_frames, serve=args.serve,
        skip=tuple(args.skip), port=args.port, depth=getattr(args, "depth", False),
        depth_scale=getattr(args, "depth_scale", None), text=args.text, topic=getattr(args, "topic", None),
        rerun=rerun,
    )
    report = run_pipeline(cfg, on_outputs=_print_summary,  # the summary is printed as soon as it is written
                          on_start=lambda r: print("kmvipe: semantic queries of this map: "
                                                   f"{QuerySupport(**r.queries).line()}", flush=True))
    if report.stopped_by:  # SIGINT / SIGTERM / SIGHUP before the end of the stream: the shell's 128 + signal
        print(f"kmvipe: stopped by {report.stopped_by} before the end of the stream; "
              f"what was produced so far is in {cfg.out.resolve()}", file=sys.stderr)
        return 128 + signal.Signals[report.stopped_by].value
    return 0 if report.end_reason == "end" else 1


def _print_summary(report) -> None:
    print(f"\nKM-ViPE run of {report.source} (stream {report.stream}): {report.end_reason}")
    print(f"  services ran:      {', '.join(report.services_ran)}")
    if report.services_not_built:
        print(f"  not built yet:     {', '.join(report.services_not_built)}")
    if report.services_skipped:
        print(f"  skipped (--skip):  {', '.join(report.services_skipped)}")
    print(f"  frames:            {report.frames} in {report.duration_s:.1f} s ({report.fps:.1f} fps), "
          f"{report.frames_dropped_or_lost} dropped or lost")
    print(f"  keyframes:         {report.keyframes}")
    print(f"  frames with pose:  {report.posed_frames}")
    if report.queries:
        q = report.queries
        print(f"  text queries:      {'available' if q['text'] else 'unavailable'} — {q['text_why']}")
        print(f"  example queries:   {'available' if q['example'] else 'unavailable'} — {q['example_why']}")
    if report.ate_rmse_sim3 is not None:
        print(f"  ATE (Sim3) vs GT:  {report.ate_rmse_sim3:.4f} RMSE over {report.ate_pairs} poses")
    if report.intrinsics is not None:
        fx, fy, cx, cy = report.intrinsics
        error = "" if report.focal_error_pct is None else f" (fx {report.focal_error_pct:+.2f} % from the true)"
        print(f"  intrinsics:        fx {fx:.1f} fy {fy:.1f} cx {cx:.1f} cy {cy:.1f} source px{error}")
    _print_live(report)
    if report.rerun:
        r = report.rerun
        print(f"  rerun recording:   {r['poses']} poses, {r['images']} images, {r['map_points']} map points"
              + "".join(f"; {text!r}: " + (f"{a['regions']} regions" if "regions" in a else a["error"])
                        for text, a in r["queries"].items()))
    for path in report.outputs:
        print(f"  wrote {path}")
    sys.stdout.flush()


def _print_live(report) -> None:
    """What a live consumer saw: posed fraction and pose latency, the first poses' ATE, drops, and each
    service's CPU and memory."""
    if report.posed_fraction is not None:
        line = (f"  posed (any pose):  {round(report.posed_fraction * report.frames_read)}/{report.frames_read} "
                f"frames read ({100 * report.posed_fraction:.1f} %)")
        if report.pose_latency_ms:
            lat = report.pose_latency_ms
            line += f"; frame → first pose p50 {lat['p50']:.0f} ms, p99 {lat['p99']:.0f} ms, max {lat['max']:.0f} ms"
        print(line)
    if report.ate_first_poses is not None:
        print(f"  ATE first poses:   {report.ate_first_poses:.4f} RMSE over {report.ate_first_poses_pairs} poses "
              "(each frame's first pose, as published live)")
    if report.provisional_poses:
        after = ("" if report.ate_first_poses_mapped is None else
                 f"; after the map: {report.ate_first_poses_mapped:.4f} RMSE over {report.ate_first_poses_mapped_pairs}")
        print(f"  before the map:    {report.provisional_poses} frames got a provisional (rotation-only) first "
              f"pose{after}")
    if report.drops:
        drops = ", ".join(f"{stage} {'?' if n is None else n}" for stage, n in report.drops.items())
        skipped = f"; codes skipped {report.codes_skipped}" if report.codes_skipped is not None else ""
        skipped += f"; lost on the way to features {report.frames_lost}" if report.frames_lost else ""
        print(f"  dropped:           {drops}{skipped}")
    if report.views_lost:
        runs = ", ".join(f"{a}–{b}" if b > a else f"{a}" for a, b in report.views_lost)
        frames = sum(b - a + 1 for a, b in report.views_lost)
        print(f"  view lost:         frames {runs} ({frames} frame{'s' * (frames != 1)} whose view held no evidence, "
              "posed by time between their neighbours)")
    if report.frames_strayed:
        print(f"  strayed:           {report.frames_strayed} frame{'s' * (report.frames_strayed != 1)} whose solve "
              "lay farther off the poses around it than the camera can go (something moving filled the view), posed "
              "by time between their neighbours")
    if report.end_of_stream_s is not None:
        work = ", ".join(f"{stage} {use['work_s']:.1f} s" for stage, use in report.end_of_stream_stages.items()
                         if use.get("work_s"))
        print(f"  end of stream:     {report.end_of_stream_s:.1f} s from ingest's EOS to the last stage's"
              + (f" (its own work: {work})" if work else ""))
    if report.services:
        wall = report.duration_s or 0.0
        parts = []
        for name, use in report.services.items():
            share = f" ({100 * use['cpu_stream_s'] / wall:.0f} %)" if wall else ""
            parts.append(f"{name} {use['cpu_stream_s']:.1f} s{share} {use['rss_peak_mb']:.0f} MB")
        pss = f" (PSS {report.pss_total_peak_mb:.0f} MB)" if report.pss_total_peak_mb else ""
        print(f"  CPU, peak RSS:     {'; '.join(parts)}; all services {report.rss_total_peak_mb:.0f} MB at peak{pss}")


def _cmd_demo(args: argparse.Namespace) -> int:
    args.source = DEFAULT_DEMO_SOURCE.format(frames=args.frames, seed=args.seed)
    return _cmd_run(args)


def _cmd_service(args: argparse.Namespace) -> int:
    if args.name not in children.PIPELINE:
        raise KmVipeError(f"unknown service {args.name!r}; services: {', '.join(children.PIPELINE)}")
    if not children.is_built(args.name):
        raise KmVipeError(f"service {args.name!r} is not built in this version of KM-ViPE")
    return importlib.import_module(f"services.{args.name}.__main__").main()


def _cmd_publish(args: argparse.Namespace) -> int:
    """The ingest service on an edge device: client mode against a remote router."""
    import os

    os.environ.update({
        "KMVIPE_BUS_MODE": "client", "KMVIPE_BUS_CONNECT": json.dumps(args.connect), "KMVIPE_BUS_LISTEN": "[]",
        "KMVIPE_INGEST_SOURCE": args.source, "KMVIPE_INGEST_STREAM": args.stream,
        "KMVIPE_INGEST_PACING": args.pacing, "KMVIPE_INGEST_ENCODING": args.encoding,
    })
    if args.intrinsics:
        os.environ["KMVIPE_INGEST_INTRINSICS"] = json.dumps(args.intrinsics)
    if args.max_frames:
        os.environ["KMVIPE_INGEST_MAX_FRAMES"] = str(args.max_frames)
    if args.topic:
        os.environ["KMVIPE_INGEST_TOPIC"] = args.topic
    return importlib.import_module("services.ingest.__main__").main()


def _add_topic_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--topic", metavar="TOPIC",
                   help="the image topic (sensor_msgs/Image or CompressedImage) to read from a ROS 2 bag source "
                        "(.mcap, .db3, a rosbag2 folder), e.g. /camera/image_raw (KMVIPE_INGEST_TOPIC; default: the "
                        "bag's only image topic)")


def _add_rerun_options(p: argparse.ArgumentParser) -> None:
    from .runner.rerun_log import DEFAULT_VIEWER, RERUN_INSTALL, RerunSettings

    g = p.add_argument_group("Rerun recording", "frames, camera frustums, trajectory, map points and query answers, "
                                                f"logged to Rerun (needs rerun-sdk: {RERUN_INSTALL})")
    g.add_argument("--rerun", metavar="FILE.rrd|URL",
                   help="write the recording to FILE.rrd (open it with `rerun FILE.rrd`), or stream it to a viewer "
                        "at a rerun+http://... address")
    g.add_argument("--rerun-connect", nargs="?", const=DEFAULT_VIEWER, metavar="URL",
                   help=f"stream to a live viewer (start `rerun` first); default address {DEFAULT_VIEWER}")
    g.add_argument("--rerun-every", type=int, default=RerunSettings.image_every, metavar="N",
                   help="log every Nth frame's image (every pose is logged; images are most of the file)")
    g.add_argument("--rerun-map-every", type=float, default=RerunSettings.map_every_s, metavar="S",
                   help="refresh the map points every S seconds while streaming (a full export by the mapstore "
                        "each time); 0: at end of stream only")
    g.add_argument("--rerun-query", action="append", default=[], metavar="TEXT",
                   help="at end of stream, ask the gateway TEXT and log its answer's regions (repeatable)")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("kmvipe")
    except PackageNotFoundError:  # a checkout on sys.path, never installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="kmvipe", description=__doc__)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run the whole pipeline on a source, write outputs")
    p.add_argument("source", help="video file, image folder, camera index, rtsp/http URL, or synth:...")
    p.add_argument("--out", default="out/run", help="output directory")
    p.add_argument("--serve", action="store_true", help="keep the query API up after the stream ends")
    p.add_argument("--depth", action="store_true",
                   help="use the source's sensor depth (a folder's depth.txt, synth:depth=1); off: RGB only")
    p.add_argument("--depth-scale", type=float, default=None, metavar="UNITS_PER_M",
                   help="depth PNG units per metre (default per dataset: ADT 1000, TUM 5000)")
    p.add_argument("--text", choices=TEXT_PROFILES, default="none",
                   help="semantic profile: talk2dino = the backbone the Talk2DINO text head targets, with the "
                        "CLIP text tower at the gateway (models checked before the stream starts); oracle = "
                        "synthetic sources' ground-truth labels; none = the configured backbone (default)")
    _add_topic_option(p)
    _add_stream_options(p)
    _add_rerun_options(p)
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("demo", help="run the synthetic world through the pipeline")
    p.add_argument("--out", default="out/demo")
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--serve", action="store_true")
    p.add_argument("--text", choices=TEXT_PROFILES, default="oracle",
                   help="oracle (default): the world's ground-truth label features and vectors, so text queries "
                        "work offline (labelled oracle everywhere); none: the real DINO backbone, no text; "
                        "talk2dino: the real text path (needs its models)")
    _add_stream_options(p)
    _add_rerun_options(p)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("service", help="run one service (what docker-compose runs); settings from the environment")
    p.add_argument("name", help=", ".join(children.PIPELINE))
    p.set_defaults(func=_cmd_service)

    p = sub.add_parser("publish", help="stream a camera or file from an edge device to a remote router")
    p.add_argument("source")
    p.add_argument("--connect", action="append", required=True, metavar="ENDPOINT", help="e.g. tcp/10.0.0.2:7447")
    _add_topic_option(p)
    _add_stream_options(p)
    p.set_defaults(func=_cmd_publish, pacing="realtime")

    for module in _TOOL_MODULES:
        importlib.import_module(module).register(sub)
    return parser


# Tools of later stages; each exposes register(subparsers).
_TOOL_MODULES = [
    "services.evaluation.cli", "services.common.models.cli", "services.mapstore.cli", "services.query_api.cli",
    "services.common.bus_cli", "services.ros2.cli",
]


def main(argv: list[str] | None = None) -> int:
    try:
        setup_logging("kmvipe")
    except (ValidationError, KmVipeError) as exc:  # a bad [log] table or KMVIPE_CONFIG file: one line, no traceback
        print(f"kmvipe: error: invalid settings: {exc}", file=sys.stderr)
        return 2
    logging.getLogger().setLevel(logging.WARNING)
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KmVipeError as exc:
        print(f"kmvipe: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
