"""Bus benchmark: 640×480 RGB frames (raw uint8 and JPEG) between two processes over the KM-ViPE bus.

    .venv/bin/python bench/bus.py    # tcp + unix socket × raw + jpeg × 4 SHM variants × 3 rounds (< 2 min)
    .venv/bin/python bench/bus.py --quick --encoding raw --transport unix --shm on --size 1280x720

Method. The main process publishes, a spawned child process subscribes; both open the project's own
:class:`~services.common.bus.Bus` from :class:`BusSettings` (peer mode, multicast scouting off; the child listens
on ``tcp/127.0.0.1:<free port>`` or ``unixsock-stream//tmp/…sock``, the main process connects to it). Every frame
takes the real path: ``Frame`` → ``schema.encode`` (msgpack) → Zenoh (reliable, congestion control BLOCK:
lossless) → ``schema.decode`` in the child's ``Bus.subscribe`` callback, which echoes a tiny ``Credit`` back.

* warm-up: one frame every 0.1 s until the first echo (routes are up), then ping-pong for ≥ 0.5 s (Zenoh
  allocates its SHM pool lazily: the first large payloads still go over the socket).
* throughput: N frames sent back-to-back; t = first send → N-th echo; frames/s = N / t (median over the rounds,
  which interleave all cases since the load drifts), MB/s = frames/s × encoded payload size (1 MB = 1e6 bytes).
* latency: ping-pong, one frame in flight; RTT = send (including encode) → echo received; p50 / p99 over the
  pings. One-way ≈ RTT / 2 (the frame's own leg lies between RTT / 2 and RTT: the echo is tiny).

SHM variants. ``off``: ``shared_memory=False``. ``on``: ``shared_memory=True`` only: Zenoh's transport
optimization (default in 1.x: lazy 16 MiB pool, payloads ≥ 3072 B) copies each large payload into an SHM pool and
sends a reference; when the pool is full it silently falls back to the socket. ``pool64``: ``on`` plus a
``BusSettings.zenoh_config`` file with a 64 MiB pool made at session start. ``provider`` (not what Bus does): the
publisher copies each encoded payload into a buffer from its own ``zenoh.shm.ShmProvider`` (16 MiB, blocking
until one is free). The child also taps the frame keys with a raw subscriber and counts SHM-backed payloads
(``ZBytes.as_shm()``): the "via SHM" columns show the path each phase took. JPEG frames carry pre-encoded bytes.
Each case is a fresh pair of sessions; other processes' load skews the numbers (load average printed).
``--malloc tuned`` raises glibc's mmap threshold: by default each new ~1 MB buffer comes as fresh mmap pages whose
page faults dominate ``schema.encode`` of a raw frame (the header line shows encode/decode times in-process).
"""
from __future__ import annotations

import argparse
import ctypes
import itertools
import multiprocessing as mp
import os
import queue
import socket
import statistics
import sys
import tempfile
import time
import timeit
import uuid
from collections import Counter
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path

import cv2
import numpy as np
import zenoh

from services.common import keys
from services.common.bus import Bus, Delivery, zenoh_config
from services.common.config import BusSettings
from services.common.schema import Credit, Frame, Message, decode, encode

TRANSPORTS = ("tcp", "unix")
SHM_VARIANTS = ("off", "on", "pool64", "provider")
ENCODINGS = ("raw", "jpeg")
SHM_POOL_BYTES = 16 << 20  # provider variant: the same size as Zenoh's default transport-optimization pool
POOL64_JSON5 = '{transport: {shared_memory: {mode: "init", transport_optimization: {pool_size: %d}}}}' % (64 << 20)
JPEG_QUALITY = 90
READY_TIMEOUT_S = 20.0  # child start (imports, session open) and route set-up
REPLY_TIMEOUT_S = 20.0  # one phase's echoes; a lossless bus never gets near it
WARMUP_MIN_S = 0.5
WARMUP_MIN_FRAMES = 10
CHILD_MAX_S = 300.0  # the echo process exits on its own after this, whatever happens to the parent
CODEC_REPS = 20
MMAP_THRESHOLD_BYTES = 32 << 20  # --malloc tuned: glibc serves frame-sized buffers from the heap, not fresh mmaps
TRIM_THRESHOLD_BYTES = 128 << 20  # --malloc tuned: glibc keeps freed heap memory instead of returning it at once
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameter numbers (malloc.h)


@dataclass(frozen=True)
class Case:
    """One row of the table."""

    transport: str  # one of TRANSPORTS
    shm: str  # one of SHM_VARIANTS
    encoding: str  # one of ENCODINGS


@dataclass(frozen=True)
class Result:
    """One round of one case."""

    payload_bytes: int  # encoded Frame message size
    sent: int  # throughput frames sent
    echoed: int  # throughput echoes received (== sent when lossless)
    seconds: float  # throughput wall time
    rtt_s: np.ndarray  # (P,) round-trip times of the pings, seconds
    via_shm: dict[str, tuple[int, int]]  # phase "thr" | "lat" -> (frames received SHM-backed, frames received)


def echo_main(settings: dict, ready, stop, tap_out) -> None:
    """Child process: decode every frame through Bus.subscribe and echo a Credit; count SHM-backed payloads."""
    tap: Counter[tuple[str, bool]] = Counter()

    def echo(delivery: Delivery) -> None:
        m = delivery.msg
        bus.publish(keys.topic(m.stream, keys.CREDIT), Credit(m.stream, m.seq, m.t_ns, consumer="bench-echo"))

    def count(sample: zenoh.Sample) -> None:
        tap[(keys.stream_of(str(sample.key_expr)), sample.payload.as_shm() is not None)] += 1

    with Bus(BusSettings(**settings), "bench-echo") as bus:
        bus.subscribe(keys.topic("*", keys.FRAME), echo, [Frame])
        tap_sub = bus.session.declare_subscriber(keys.topic("*", keys.FRAME), count)
        ready.set()
        stop.wait(CHILD_MAX_S)
        tap_sub.undeclare()
    tap_out.put(dict(tap))


class Sender:
    """Publishes messages through ``Bus.publish``, or (variant ``provider``) from an SHM provider's buffers."""

    def __init__(self, bus: Bus, shm: str):
        self.bus = bus
        self.provider = zenoh.shm.ShmProvider.default_backend(SHM_POOL_BYTES) if shm == "provider" else None
        self._publishers: dict[str, zenoh.Publisher] = {}

    def send(self, key: str, msg: Message) -> None:
        if self.provider is None:
            return self.bus.publish(key, msg)
        payload = encode(msg)
        buf = self.provider.alloc(len(payload), policy=zenoh.shm.BlockOn(zenoh.shm.GarbageCollect()))
        buf[:] = payload
        if key not in self._publishers:  # the same options as Bus.put uses
            self._publishers[key] = self.bus.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
        self._publishers[key].put(buf)


class Echoes:
    """Echoed Credits: arrival times (perf_counter, taken on the Zenoh thread) and counts per stream."""

    def __init__(self, bus: Bus):
        self._queue: queue.Queue[tuple[float, Credit]] = queue.Queue()
        self.counts: Counter[str] = Counter()
        bus.subscribe(keys.topic("*", keys.CREDIT), self._on_echo, [Credit])

    def _on_echo(self, delivery: Delivery) -> None:
        self.counts[delivery.msg.stream] += 1
        self._queue.put((time.perf_counter(), delivery.msg))

    def wait(self, stream: str, seq: int, timeout: float) -> float | None:
        """Arrival time of the echo of (stream, seq); echoes before it are discarded. None on timeout."""
        deadline = time.perf_counter() + timeout
        while True:
            try:
                t, msg = self._queue.get(timeout=max(deadline - time.perf_counter(), 0.0))
            except queue.Empty:
                return None
            if msg.stream == stream and msg.seq == seq:
                return t


@dataclass(frozen=True)
class FrameMaker:
    """Builds a fresh Frame (new seq, new t_ns) around the same pixels or JPEG bytes."""

    width: int
    height: int
    content: dict  # {"image": (H, W, 3) uint8 RGB} or {"jpeg": bytes}

    def __call__(self, stream: str, seq: int) -> Frame:
        return Frame(stream, seq, time.time_ns(), width=self.width, height=self.height, **self.content)


def warm_up(sender: Sender, echoes: Echoes, make: FrameMaker) -> None:
    """Send every 0.1 s until the first echo (routes up), then ping-pong for WARMUP_MIN_S and WARMUP_MIN_FRAMES."""
    deadline = time.perf_counter() + READY_TIMEOUT_S
    seq, up_since = 0, None
    while up_since is None or seq < WARMUP_MIN_FRAMES or time.perf_counter() - up_since < WARMUP_MIN_S:
        sender.send(keys.topic("warmup", keys.FRAME), make("warmup", seq))
        if echoes.wait("warmup", seq, 0.1 if up_since is None else REPLY_TIMEOUT_S) is not None:
            up_since = up_since or time.perf_counter()
        elif up_since is not None or time.perf_counter() > deadline:
            raise TimeoutError(f"no echo from the subscriber process (warm-up frame {seq})")
        seq += 1


def throughput(sender: Sender, echoes: Echoes, make: FrameMaker, n: int) -> tuple[int, float]:
    """(echoes received, seconds from the first send to the last echo) for n frames sent back-to-back."""
    t0 = time.perf_counter()
    for seq in range(n):
        sender.send(keys.topic("thr", keys.FRAME), make("thr", seq))
    t_last = echoes.wait("thr", n - 1, REPLY_TIMEOUT_S)  # one reliable publisher: echoes arrive in order
    if t_last is None:
        raise TimeoutError(f"only {echoes.counts['thr']}/{n} throughput frames echoed")
    return echoes.counts["thr"], t_last - t0


def latency(sender: Sender, echoes: Echoes, make: FrameMaker, n: int) -> np.ndarray:
    """(n,) round-trip times in seconds, one frame in flight at a time."""
    rtts = []
    for seq in range(n):
        t0 = time.perf_counter()
        sender.send(keys.topic("lat", keys.FRAME), make("lat", seq))
        t1 = echoes.wait("lat", seq, REPLY_TIMEOUT_S)
        if t1 is None:
            raise TimeoutError(f"ping {seq} got no echo within {REPLY_TIMEOUT_S:.0f} s")
        rtts.append(t1 - t0)
    return np.asarray(rtts)


def free_endpoint(transport: str) -> str:
    if transport == "unix":
        return f"unixsock-stream//tmp/kmv-bench-{uuid.uuid4().hex[:10]}.sock"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def run_case(case: Case, make: FrameMaker, frames: int, pings: int, tmp: Path) -> Result:
    """Warm-up, throughput and latency of one case with a fresh publisher/subscriber process pair."""
    endpoint = free_endpoint(case.transport)
    common = dict(shared_memory=case.shm != "off", multicast_scouting=False, mode="peer")
    if case.shm == "pool64":
        common["zenoh_config"] = tmp / "pool64.json5"
        common["zenoh_config"].write_text(POOL64_JSON5)
    ctx = mp.get_context("spawn")
    ready, stop, tap_out = ctx.Event(), ctx.Event(), ctx.Queue()
    child = ctx.Process(target=echo_main, args=(dict(common, listen=[endpoint]), ready, stop, tap_out), daemon=True)
    child.start()
    try:
        if not ready.wait(READY_TIMEOUT_S):
            raise TimeoutError(f"subscriber process not ready within {READY_TIMEOUT_S:.0f} s")
        with Bus(BusSettings(**common, connect=[endpoint]), "bench-pub") as bus:
            sender, echoes = Sender(bus, case.shm), Echoes(bus)
            warm_up(sender, echoes, make)
            echoed, seconds = throughput(sender, echoes, make, frames)
            rtts = latency(sender, echoes, make, pings)
        stop.set()
        tap = tap_out.get(timeout=READY_TIMEOUT_S)
    finally:
        stop.set()
        child.join(READY_TIMEOUT_S)
        child.terminate()  # a no-op once it has exited
        if case.transport == "unix":
            Path(endpoint.split("/", 1)[1]).unlink(missing_ok=True)
    via_shm = {ph: (tap.get((ph, True), 0), tap.get((ph, True), 0) + tap.get((ph, False), 0)) for ph in ("thr", "lat")}
    return Result(len(encode(make("thr", 0))), frames, echoed, seconds, rtts, via_shm)


def synthetic_image(width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB: smooth colour blobs plus sensor noise; JPEG q90 ≈ 52 KB at 640×480 (a real ADT frame
    resized to 640×480: ≈ 60 KB)."""
    rng = np.random.default_rng(0)
    coarse = rng.integers(0, 256, (height // 40 + 2, width // 40 + 2, 3), dtype=np.uint8)
    blobs = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    return cv2.add(blobs, rng.integers(0, 8, blobs.shape, dtype=np.uint8))


def codec_costs(image: np.ndarray) -> tuple[bytes, str]:
    """The JPEG bytes of ``image`` and a line with the median in-process costs (ms) of the codecs involved."""
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
    jpeg = cv2.imencode(".jpg", image, params)[1]
    frame = Frame("cost", 0, 0, width=image.shape[1], height=image.shape[0], image=image)
    payload = encode(frame)
    median_ms = lambda fn: 1e3 * statistics.median(timeit.repeat(fn, repeat=CODEC_REPS, number=1))  # noqa: E731
    costs = {"cv2 JPEG encode": median_ms(lambda: cv2.imencode(".jpg", image, params)),
             "cv2 JPEG decode": median_ms(lambda: cv2.imdecode(jpeg, cv2.IMREAD_COLOR)),
             "schema.encode raw Frame": median_ms(lambda: encode(frame)),
             "schema.decode raw Frame": median_ms(lambda: decode(payload))}
    line = ", ".join(f"{name} {ms:.2f}" for name, ms in costs.items())
    return jpeg.tobytes(), f"JPEG q{JPEG_QUALITY} {jpeg.size / 1e3:.1f} KB; in-process ms: {line}"


def table(results: dict[Case, list[Result]]) -> str:
    """One row per case over its rounds: median (min–max) frames/s, RTT percentiles of all pings pooled."""
    head = ("| transport | SHM | encoding | payload KB | frames echoed | frames/s median | frames/s min–max | MB/s "
            "| RTT p50 ms | RTT p99 ms | one-way p50 ms | one-way p99 ms | via SHM thr | via SHM lat |")
    rows = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for case, runs in results.items():
        fps = np.array([r.echoed / r.seconds for r in runs])
        p50, p99 = np.percentile(1e3 * np.concatenate([r.rtt_s for r in runs]), [50, 99])
        shm = {ph: "/".join(str(sum(r.via_shm[ph][i] for r in runs)) for i in (0, 1)) for ph in ("thr", "lat")}
        size = runs[0].payload_bytes
        rows.append(
            f"| {case.transport} | {case.shm} | {case.encoding} | {size / 1e3:.1f} "
            f"| {sum(r.echoed for r in runs)}/{sum(r.sent for r in runs)} | {np.median(fps):.0f} "
            f"| {fps.min():.0f}–{fps.max():.0f} | {np.median(fps) * size / 1e6:.0f} | {p50:.2f} | {p99:.2f} "
            f"| {p50 / 2:.2f} | {p99 / 2:.2f} | {shm['thr']} | {shm['lat']} |")
    return "\n".join(rows)


def tune_malloc() -> None:
    """glibc: frame-sized buffers from the heap; here via mallopt, in the subscriber via the environment."""
    os.environ.update(MALLOC_MMAP_THRESHOLD_=str(MMAP_THRESHOLD_BYTES),
                      MALLOC_TRIM_THRESHOLD_=str(TRIM_THRESHOLD_BYTES))
    libc = ctypes.CDLL(None)  # this process's symbols: glibc's mallopt
    libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=200, help="frames per throughput run")
    p.add_argument("--pings", type=int, default=100, help="round trips per latency run")
    p.add_argument("--size", default="640x480", help="frame size WxH")
    p.add_argument("--encoding", choices=(*ENCODINGS, "all"), default="all")
    p.add_argument("--transport", choices=(*TRANSPORTS, "all"), default="all")
    p.add_argument("--shm", choices=(*SHM_VARIANTS, "all"), default="all")
    p.add_argument("--rounds", type=int, default=3, help="passes over all cases, interleaved (the load drifts)")
    p.add_argument("--malloc", choices=("glibc", "tuned"), default="glibc",
                   help="glibc: defaults, as the services run today; tuned: see the docstring")
    p.add_argument("--quick", action="store_true", help="1 round, 30 frames and 30 pings per case")
    args = p.parse_args(argv)
    if args.quick:
        args.frames, args.pings, args.rounds = min(args.frames, 30), min(args.pings, 30), 1
    args.width, args.height = (int(v) for v in args.size.lower().split("x"))
    for name, every in (("encoding", ENCODINGS), ("transport", TRANSPORTS), ("shm", SHM_VARIANTS)):
        setattr(args, name, every if getattr(args, name) == "all" else (getattr(args, name),))
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.malloc == "tuned":
        tune_malloc()
    load_before = os.getloadavg()
    image = synthetic_image(args.width, args.height)
    jpeg, costs = codec_costs(image)
    contents = {"raw": {"image": image}, "jpeg": {"jpeg": jpeg}}
    cases = [Case(t, s, e) for t, e, s in itertools.product(args.transport, args.encoding, args.shm)]
    results: dict[Case, list[Result]] = {case: [] for case in cases}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for _, case in itertools.product(range(args.rounds), cases):
            make = FrameMaker(args.width, args.height, contents[case.encoding])
            results[case].append(run_case(case, make, args.frames, args.pings, Path(tmp)))
    load = [" ".join(f"{v:.2f}" for v in la) for la in (load_before, os.getloadavg())]
    malloc_env = {k: v for k, v in os.environ.items() if k.startswith("MALLOC_")}
    shm_conf = zenoh_config(BusSettings(shared_memory=True)).get_json("transport/shared_memory")
    print(f"command: {os.path.relpath(sys.executable)} {' '.join(sys.argv)}")
    print(f"eclipse-zenoh {version('eclipse-zenoh')}, {os.cpu_count()} CPUs, load average (1/5/15 min) before "
          f"{load[0]}, after {load[1]}; {args.rounds} round(s), wall {time.perf_counter() - t0:.0f} s")
    print(f"frames {args.width}x{args.height}; {costs}; malloc {args.malloc}, environment {malloc_env or '-'}")
    print(f"SHM 'on' = Bus(shared_memory=True): transport/shared_memory = {shm_conf}\n")
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
