"""``kmvipe``: run the pipeline, one service, an edge publisher, the demo, and the tools of each stage."""
from __future__ import annotations

import argparse
import importlib
import json
import logging
import signal
import sys
from pathlib import Path

from .common.errors import KmVipeError
from .common.keys import DEFAULT_STREAM
from .common.logs import setup_logging
from .runner import children

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

    cfg = RunSettings(
        source=args.source, out=Path(args.out), stream=args.stream, pacing=args.pacing, encoding=args.encoding,
        intrinsics=tuple(args.intrinsics) if args.intrinsics else None, max_frames=args.max_frames, serve=args.serve,
        skip=tuple(args.skip), port=args.port, depth=getattr(args, "depth", False),
        depth_scale=getattr(args, "depth_scale", None),
    )
    report = run_pipeline(cfg, on_outputs=_print_summary)  # the summary is printed as soon as it is written
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
    if report.ate_rmse_sim3 is not None:
        print(f"  ATE (Sim3) vs GT:  {report.ate_rmse_sim3:.4f} RMSE over {report.ate_pairs} poses")
    _print_live(report)
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
        print(f"  dropped:           {drops}{skipped}")
    if report.end_of_stream_s is not None:
        print(f"  end of stream:     {report.end_of_stream_s:.1f} s from ingest's EOS to the last stage's")
    if report.services:
        wall = report.duration_s or 0.0
        parts = []
        for name, use in report.services.items():
            share = f" ({100 * use['cpu_stream_s'] / wall:.0f} %)" if wall else ""
            parts.append(f"{name} {use['cpu_stream_s']:.1f} s{share} {use['rss_peak_mb']:.0f} MB")
        print(f"  CPU, peak RSS:     {'; '.join(parts)}; all services {report.rss_total_peak_mb:.0f} MB at peak")


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
    return importlib.import_module("services.ingest.__main__").main()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="kmvipe", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run the whole pipeline on a source, write outputs")
    p.add_argument("source", help="video file, image folder, camera index, rtsp/http URL, or synth:...")
    p.add_argument("--out", default="out/run", help="output directory")
    p.add_argument("--serve", action="store_true", help="keep the query API up after the stream ends")
    p.add_argument("--depth", action="store_true",
                   help="use the source's sensor depth (a folder's depth.txt, synth:depth=1); off: RGB only")
    p.add_argument("--depth-scale", type=float, default=None, metavar="UNITS_PER_M",
                   help="depth PNG units per metre (default per dataset: ADT 1000, TUM 5000)")
    _add_stream_options(p)
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("demo", help="run the synthetic world through the pipeline")
    p.add_argument("--out", default="out/demo")
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--serve", action="store_true")
    _add_stream_options(p)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("service", help="run one service (what docker-compose runs); settings from the environment")
    p.add_argument("name", help=", ".join(children.PIPELINE))
    p.set_defaults(func=_cmd_service)

    p = sub.add_parser("publish", help="stream a camera or file from an edge device to a remote router")
    p.add_argument("source")
    p.add_argument("--connect", action="append", required=True, metavar="ENDPOINT", help="e.g. tcp/10.0.0.2:7447")
    _add_stream_options(p)
    p.set_defaults(func=_cmd_publish, pacing="realtime")

    for module in _TOOL_MODULES:
        importlib.import_module(module).register(sub)
    return parser


# Tools of later stages; each exposes register(subparsers).
_TOOL_MODULES = [
    "services.evaluation.cli", "services.common.models.cli", "services.mapstore.cli", "services.query_api.cli",
    "services.common.bus_cli",
]


def main(argv: list[str] | None = None) -> int:
    setup_logging("kmvipe")
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
