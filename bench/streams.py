"""Streams per deployment (issue 14): how many synthetic cameras one deployment keeps up with on this machine.

The deployment as docker-compose.yml runs it, without docker: a Zenoh router (here in this process, on loopback),
features, ba and mapstore started once each as ``kmvipe service NAME`` with no stream setting (they serve every
stream a source announces), and N edge cameras as ``kmvipe publish FOLDER --stream camK --connect ...``, all started
together. Each camera plays the same pre-rendered synthetic sequence (no depth, no intrinsics; the real DINO
backbone unless --oracle). This script watches the bus like a consumer: when each frame appeared and when its first
pose came, every stream's final poses (Sim(3) ATE against the sequence's ground truth), each stage's drops and the
keyframes whose codes the backbone skipped (from the EOS messages), and the services' CPU and RSS (psutil).

"Sustained" (docs/DEPLOY.md): lossless — every stream ends with every frame posed and the aggregate throughput is
no lower than one stream's (N streams share the machine); realtime — every frame of every stream posed and the
capture → pose p99 under one second.

Usage:
  python bench/streams.py --streams 1 2 3 --pacing realtime
  python bench/streams.py --streams 1 2 4 --pacing lossless --frames 120
  python bench/streams.py --streams 2 --fps 10 --width 256 --height 192
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from services.common import keys  # noqa: E402
from services.common.bus import Bus  # noqa: E402
from services.common.config import BusSettings  # noqa: E402
from services.common.schema import Eos, Frame, Poses  # noqa: E402
from services.runner.children import free_tcp_endpoint  # noqa: E402
from services.runner.groundtruth import evaluate  # noqa: E402
from services.runner.resources import ResourceMonitor  # noqa: E402
from services.evaluation.trajectory_io import Trajectory  # noqa: E402

KMVIPE = Path(sys.executable).parent / "kmvipe"
SERVICES = ("features", "ba", "mapstore")


@dataclass
class StreamSeen:
    seen_at: dict[int, float] = field(default_factory=dict)
    first_pose_at: dict[int, float] = field(default_factory=dict)
    final: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)
    mapped: set[int] = field(default_factory=set)
    eos: dict[str, Eos] = field(default_factory=dict)
    eos_at: dict[str, float] = field(default_factory=dict)


class Watcher:
    """Frames, poses and ends of stream of every stream, as a consumer on the bus sees them."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.streams: dict[str, StreamSeen] = {}

    def _of(self, stream: str) -> StreamSeen:
        return self.streams.setdefault(stream, StreamSeen())

    def on_message(self, delivery) -> None:
        msg, now = delivery.msg, time.monotonic()
        with self.lock:
            seen = self._of(msg.stream)
            if isinstance(msg, Frame):
                seen.seen_at.setdefault(msg.seq, now)
            elif isinstance(msg, Poses):
                for seq, stamp, pose in zip(msg.frame_seqs, msg.stamps_ns, msg.poses):
                    seq = int(seq)
                    seen.first_pose_at.setdefault(seq, now)
                    if msg.tracked and seq in seen.mapped:
                        continue  # mapping's revision stays
                    seen.final[seq] = (int(stamp), np.asarray(pose, np.float64))
                    if not msg.tracked:
                        seen.mapped.add(seq)
            elif isinstance(msg, Eos):
                seen.eos[msg.stage] = msg
                seen.eos_at[msg.stage] = now


def render(frames: int, fps: float, width: int, height: int, cache: Path) -> Path:
    """The synthetic world as an image folder with ground truth and no depth, rendered once into ``cache``."""
    folder = cache / f"kmvipe-streams-synth-{frames}-{width}x{height}-{fps:g}hz"
    if not (folder / ".complete").is_file():
        from services.synth import SynthConfig, SynthWorld
        from services.synth.io import write_image_folder

        print(f"rendering {frames} frames into {folder} (once) ...", flush=True)
        write_image_folder(SynthWorld(SynthConfig(n_frames=frames, fps=fps, width=width, height=height)), folder)
        (folder / "depth.txt").unlink()
        (folder / ".complete").write_text("")
    return folder


def _start(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    return subprocess.Popen([str(KMVIPE), *args], env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, cwd=REPO)


def _stop(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_deployment(n: int, folder: Path, pacing: str, oracle: str | None, out: Path, timeout_s: float) -> dict:
    """One deployment serving ``n`` cameras from start to every stream's end (or ``timeout_s``)."""
    shutil.rmtree(out, ignore_errors=True)  # a map left by an earlier run would be resumed
    out.mkdir(parents=True)
    endpoint = free_tcp_endpoint()
    base = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    env = {**base, "KMVIPE_BUS_MODE": "client", "KMVIPE_BUS_CONNECT": json.dumps([endpoint]),
           "KMVIPE_BUS_LISTEN": "[]", "KMVIPE_MAPSTORE_DB_PATH": str(out / "maps" / "{stream}.db")}
    if oracle:
        env |= {"KMVIPE_FEATURES_BACKBONE": "synth-oracle", "KMVIPE_FEATURES_ORACLE_SOURCE": oracle}
    streams = [f"cam{i + 1}" for i in range(n)]
    watcher, monitor = Watcher(), ResourceMonitor()
    procs: list[subprocess.Popen] = []
    with Bus(BusSettings(mode="router", listen=[endpoint]), "bench") as bus:
        for topic, kinds in ((keys.FRAME, [Frame]), (keys.POSE, [Poses]), (keys.EOS, [Eos])):
            bus.subscribe(keys.topic("*", topic), watcher.on_message, kinds)
        try:
            for name in SERVICES:
                procs.append(_start(["service", name], env, out / f"{name}.log"))
                monitor.watch(name, procs[-1].pid)
            deadline = time.monotonic() + 300
            while not set(SERVICES) <= set(bus.alive(timeout=0.5)):
                if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                    raise SystemExit(f"services did not start; see {out}/*.log")
            monitor.mark_stream_start()
            began = time.monotonic()
            for stream in streams:
                procs.append(_start(["publish", str(folder), "--stream", stream, "--pacing", pacing,
                                     "--connect", endpoint], env, out / f"publish-{stream}.log"))
            ended = lambda: all("mapstore" in watcher.streams.get(s, StreamSeen()).eos for s in streams)  # noqa: E731
            while not ended() and time.monotonic() - began < timeout_s:
                monitor.sample()
                time.sleep(0.5)
            wall = time.monotonic() - began
        finally:
            _stop(procs)
    return summarize(watcher, monitor, streams, folder, wall, timed_out=not ended())


def summarize(watcher: Watcher, monitor: ResourceMonitor, streams: list[str], folder: Path, wall: float,
              timed_out: bool) -> dict:
    latencies, per_stream = [], {}
    for stream in streams:
        seen = watcher.streams.get(stream, StreamSeen())
        read = seen.eos["ingest"].seq + 1 if "ingest" in seen.eos else len(seen.seen_at)
        latencies += [max(0.0, seen.first_pose_at[s] - t) * 1e3 for s, t in seen.seen_at.items()
                      if s in seen.first_pose_at]
        seqs = sorted(seen.final)
        ate = evaluate(str(folder), Trajectory(np.array([seen.final[s][0] for s in seqs]) / 1e9,
                                               np.stack([seen.final[s][1] for s in seqs]))) if seqs else None
        per_stream[stream] = {
            "frames_read": read, "posed": len([s for s in seen.first_pose_at if 0 <= s < read]),
            "unposed": sorted(set(seen.seen_at) - set(seen.first_pose_at))[:20],
            "ended": "mapstore" in seen.eos, "ate_m": None if ate is None else round(ate.rmse, 4),
            "drops": {k: e.dropped for k, e in seen.eos.items()},
            "codes_skipped": seen.eos["features"].codes_skipped if "features" in seen.eos else None}
    read = sum(s["frames_read"] for s in per_stream.values())
    posed = sum(s["posed"] for s in per_stream.values())
    lat = {"p50": float(np.percentile(latencies, 50)), "p99": float(np.percentile(latencies, 99))} if latencies \
        else None
    return {"streams": len(streams), "timed_out": timed_out, "wall_s": round(wall, 1),
            "frames_read": read, "posed": posed, "aggregate_fps": round(posed / wall, 2) if wall else None,
            "latency_ms": lat, "per_stream": per_stream, "services": monitor.report(),
            "rss_total_peak_mb": round(monitor.rss_total_peak_mb)}


def sustained(result: dict, pacing: str, one_stream_fps: float | None) -> bool:
    every_posed = all(s["ended"] and s["posed"] == s["frames_read"] for s in result["per_stream"].values())
    if pacing == "lossless":
        return every_posed and (one_stream_fps is None or result["aggregate_fps"] >= 0.95 * one_stream_fps)
    return every_posed and result["latency_ms"] is not None and result["latency_ms"]["p99"] < 1000.0


def row(result: dict, pacing: str, ok: bool) -> str:
    lat = result["latency_ms"]
    ates = [s["ate_m"] for s in result["per_stream"].values() if s["ate_m"] is not None]
    skipped = [s["codes_skipped"] or 0 for s in result["per_stream"].values()]
    drops = sum(sum(s["drops"].values()) for s in result["per_stream"].values())
    cpu = sum(u["cpu_stream_s"] for u in result["services"].values())
    return (f"| {result['streams']} | {pacing} | {'yes' if ok else 'no'} | {result['posed']} / {result['frames_read']}"
            f" | {result['aggregate_fps']:.1f} | {lat['p50']:.0f} / {lat['p99']:.0f} ms | "
            f"{(max(ates) if ates else float('nan')):.3f} m | {drops} | {sum(skipped)} | "
            f"{100 * cpu / result['wall_s']:.0f} % | {result['rss_total_peak_mb']} MB | {result['wall_s']:.0f} s |"
            if lat else f"| {result['streams']} | {pacing} | no | {result['posed']} / {result['frames_read']} | – |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--streams", type=int, nargs="+", default=[1, 2, 3], help="camera counts, one run each")
    parser.add_argument("--pacing", choices=("realtime", "lossless"), default="realtime")
    parser.add_argument("--frames", type=int, default=240, help="frames per camera")
    parser.add_argument("--fps", type=float, default=30.0, help="camera rate")
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=384)
    parser.add_argument("--oracle", action="store_true", help="the synth-oracle backbone instead of DINO")
    parser.add_argument("--timeout", type=float, default=900.0, help="give up on a deployment after S seconds")
    parser.add_argument("--out", type=Path, default=Path("/tmp/kmvipe-streams"))
    parser.add_argument("--cache", type=Path, default=Path("/tmp"))
    parser.add_argument("--json", type=Path, help="also write every run's measurements here")
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # a stopped bench stops its deployment (finally)
    if not KMVIPE.is_file():
        raise SystemExit(f"the kmvipe command is not installed beside {sys.executable} (make install)")
    folder = render(args.frames, args.fps, args.width, args.height, args.cache)
    oracle = (f"synth:frames={args.frames},width={args.width},height={args.height}" if args.oracle else None)
    header = ("| cameras | pacing | sustained | frames posed / read | aggregate fps | frame → first pose p50 / p99 | "
              "worst stream ATE (Sim3) | frames dropped | codes skipped | CPU (of one core) | peak RSS (sum) | "
              "wall |\n|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows, results, one_fps = [], [], None
    for n in args.streams:
        print(f"\n{n} camera(s), {args.pacing}: {args.frames} frames each at {args.fps:g} Hz, "
              f"{args.width}x{args.height} ...", flush=True)
        result = run_deployment(n, folder, args.pacing, oracle, args.out / f"{args.pacing}-{n}", args.timeout)
        if n == 1:
            one_fps = result["aggregate_fps"]
        ok = sustained(result, args.pacing, one_fps)
        rows.append(row(result, args.pacing, ok))
        results.append(result)
        print(header + "\n" + rows[-1], flush=True)
    cmd = "python bench/streams.py " + " ".join(sys.argv[1:])
    print(f"\n`{cmd}` ({os.cpu_count()} CPUs, load before the last run: {os.getloadavg()[0]:.2f})\n\n{header}\n"
          + "\n".join(rows))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
