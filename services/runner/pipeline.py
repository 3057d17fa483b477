"""``kmvipe run``: every built service as its own process on a private loopback router, the source streamed
through, a progress bar, and outputs + a summary at end of stream.

Paths are made absolute before anything uses them, so a run started in any directory reads its source and writes
under its ``--out`` only. SIGINT, SIGTERM and SIGHUP end a run cleanly: the services are stopped and what was
produced so far is written (``RunReport.stopped_by`` names the signal)."""
from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from ..common import keys
from ..common.bus import Bus
from ..common.config import BusSettings
from ..common.errors import KmVipeError
from ..common.schema import Credit
from . import children as kids
from .observer import Observer, fill_report, settle
from .outputs import write_live, write_outputs, write_resources
from .rerun_log import RerunSettings
from .rerun_recorder import open_recorder
from .resources import ResourceMonitor
from .settings_used import SettingsProbe, child_env, run_settings
from .semantics import check_models, semantic_profile

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunSettings:
    source: str
    out: Path
    stream: str = keys.DEFAULT_STREAM
    pacing: str = "lossless"
    encoding: str = "jpeg"
    intrinsics: tuple[float, float, float, float] | None = None
    max_frames: int | None = None
    serve: bool = False
    skip: tuple[str, ...] = ()  # built services not to start (e.g. the gateway on a headless batch run)
    port: int = 8000  # the query gateway's HTTP port on 127.0.0.1
    depth: bool = False  # send the source's sensor depth (opt-in: ``kmvipe run --depth``)
    depth_scale: float | None = None  # depth PNG units per metre (None: per dataset, see ingest's depth_units)
    text: str = "none"  # semantic profile (services/runner/semantics.py): none, talk2dino, oracle (synthetic only)
    topic: str | None = None  # the bag's (ROS) topic ingest reads (KMVIPE_INGEST_TOPIC); None: ingest's default
    rerun: RerunSettings | None = None  # record the run to Rerun (services/runner/rerun_log.py); None: no recording
    credit_window: int = 8  # frames the runner lets ingest run ahead when it is the only consumer
    alive_timeout_s: float = 120.0  # model loading can take a while on a cold CPU
    stall_timeout_s: float = 600.0  # no message at all for this long means something hung
    rss_every_frames: int = 500  # RunReport.rss_mb_at_frames: every service's RSS each time this many frames passed


@dataclass
class RunReport:
    source: str
    stream: str
    services_ran: list[str]
    services_not_built: list[str]
    services_skipped: list[str] = field(default_factory=list)
    frames: int = 0
    keyframes: int = 0
    posed_frames: int = 0
    frames_dropped_or_lost: int = 0
    duration_s: float = 0.0
    fps: float = 0.0
    end_reason: str = ""
    ate_rmse_sim3: float | None = None  # against the source's ground truth, when it has one (final poses)
    ate_pairs: int = 0
    intrinsics: list[float] | None = None  # ba's refined fx, fy, cx, cy in the source's pixels (also camera.txt)
    image_size: list[int] | None = None  # the source's width, height
    focal_error_pct: float | None = None  # fx against the source's true fx, when it has one (groundtruth.py)
    # live operation: what a consumer of the pose stream saw while the stream ran
    frames_read: int = 0  # frames ingest read from the source (its EOS seq + 1), sent or dropped
    posed_fraction: float | None = None  # frames with any pose / frames read (frames ingest dropped: not posed)
    pose_latency_ms: dict[str, float] | None = None  # frame seen on the bus → its first pose: p50, p99, max, n
    ate_first_poses: float | None = None  # Sim(3) ATE of each frame's first pose (tracked or mapped)
    ate_first_poses_pairs: int = 0
    provisional_poses: int = 0  # frames whose first pose was tracking's rotation-only one from before the map
    ate_first_poses_mapped: float | None = None  # the same ATE over the frames posed after the map started
    ate_first_poses_mapped_pairs: int = 0
    drops: dict[str, int | None] = field(default_factory=dict)  # per stage, from its EOS (None: no EOS came)
    codes_skipped: int | None = None  # features, real time: keyframes the backbone skipped as stale
    frames_lost: int | None = None  # frames ingest sent that never reached features (Zenoh drops on congestion)
    views_lost: list[list[int]] = field(default_factory=list)  # ba: [first, last] frame seqs of each run of frames
    # whose view held no evidence (covered, blank, a cut), posed by time between their neighbours
    frames_strayed: int = 0  # ba: frames whose solve strayed off the path of the poses around them (posed by time)
    end_of_stream_s: float | None = None  # ingest's EOS → the last stage's EOS, as the runner saw them
    # per stage: its EOS after ingest's ("after_ingest_s") and the end-of-stream work it reported ("work_s")
    end_of_stream_stages: dict[str, dict[str, float]] = field(default_factory=dict)
    services: dict[str, dict[str, float]] = field(default_factory=dict)  # cpu_s, cpu_stream_s, rss_peak_mb
    rss_total_peak_mb: float = 0.0  # largest sum over the services of their RSS at one sample
    pss_total_peak_mb: float | None = None  # the same for PSS: shared library pages counted once (resources.py)
    rss_mb_at_frames: list[dict] = field(default_factory=list)  # {"frames", "t_s", "rss_mb": {service: MB}}
    queries: dict = field(default_factory=dict)  # which queries the map answers, and why (semantics.QuerySupport)
    rerun: dict = field(default_factory=dict)  # what the Rerun recording holds (rerun_recorder.RerunRecorder.close)
    settings: dict = field(default_factory=dict)  # "run": RunSettings; "services": each one's (settings_used.py)
    stopped_by: str | None = None  # the signal (SIGINT, SIGTERM, SIGHUP) that cut the stream short, if one did
    outputs: list[str] = field(default_factory=list)


def absolute_source(source: str) -> str:
    """``source`` as an absolute path when it names an existing local file or folder (``~`` expanded); camera
    indices, ``/dev/video*``, URLs, ``synth:`` specs and anything else unchanged (the same reading as
    ingest's ``open_source``)."""
    if source.startswith("synth:") or source.isdigit() or source.startswith("/dev/video") or "://" in source:
        return source
    path = Path(source).expanduser()
    return os.path.abspath(path) if path.exists() else source


def absolute_paths(cfg: RunSettings) -> RunSettings:
    """The same settings with ``out``, a local ``source`` and the Rerun file absolute, against the current directory:
    the services are separate processes, so no relative path may travel to them."""
    rerun = cfg.rerun
    if rerun is not None and rerun.path is not None:
        rerun = replace(rerun, path=rerun.path.expanduser().resolve())
    return replace(cfg, out=cfg.out.expanduser().resolve(), source=absolute_source(cfg.source), rerun=rerun)


class StopSignals:
    """While active (main thread only), SIGINT, SIGTERM and SIGHUP set :attr:`event` instead of killing or
    raising: every wait of the runner polls it, so a signal ends the run through the same clean path as the end of
    the stream, and a second signal cannot interrupt the services' shutdown or the writing of the outputs.
    A signal the caller ignores stays ignored (``nohup kmvipe run ...`` survives the terminal's SIGHUP)."""

    SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    @property
    def name(self) -> str | None:
        return signal.Signals(self.signum).name if self.signum is not None else None

    def is_set(self) -> bool:
        return self.event.is_set()

    def _handler(self, signum: int, _frame) -> None:
        if self.signum is None:
            self.signum = signum
        self.event.set()

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                if signal.getsignal(sig) is not signal.SIG_IGN:
                    self._previous[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous.clear()


def run_pipeline(cfg: RunSettings, on_outputs: Callable[[RunReport], None] | None = None,
                 on_start: Callable[[RunReport], None] | None = None) -> RunReport:
    """Run the pipeline on ``cfg.source``; the outputs are written at end of stream (before ``--serve`` keeps the
    gateway up), or, when a signal stops the run, after the services stopped. ``on_start(report)`` is called once
    the run is checked (its models present, ``report.queries`` known), before any process starts;
    ``on_outputs(report)`` once the outputs are on disk."""
    cfg = absolute_paths(cfg)
    keys.check_name(cfg.stream)
    unknown = set(cfg.skip) - set(kids.PIPELINE)
    if unknown:
        raise KmVipeError(f"cannot skip unknown service(s) {sorted(unknown)}; services: {', '.join(kids.PIPELINE)}")
    built = [name for name in kids.PIPELINE if kids.is_built(name) and name not in cfg.skip]
    if "ingest" not in built:
        raise KmVipeError("the ingest service is missing from this installation (or skipped)")
    profile = semantic_profile(cfg.text, cfg.source)
    check_models(profile)  # before any process starts: a missing model ends the run in seconds, saying what to pull
    report = RunReport(cfg.source, cfg.stream, built, [n for n in kids.PIPELINE if not kids.is_built(n)],
                       services_skipped=list(cfg.skip), queries=profile.support.as_dict())
    if on_start is not None:
        on_start(report)
    cfg.out.mkdir(parents=True, exist_ok=True)
    endpoint = kids.free_tcp_endpoint()
    observer = Observer(last_stage=kids.last_connected_stage(built))
    monitor = ResourceMonitor()
    started: list[kids.Child] = []

    def finish() -> None:
        with observer.lock:  # late messages may still arrive (a --serve run, a signal)
            fill_report(report, observer, monitor)
            poses, first_poses = dict(observer.poses), dict(observer.first_pose)
            seen_at, first_tracked = dict(observer.seen_at), set(observer.first_tracked)
            provisional = set(observer.first_provisional)
        report.provisional_poses = len(provisional)
        report.rerun = recorder.close(services_up=not report.stopped_by)  # the map and answers need the services
        report.settings = {"run": run_settings(cfg), "services": probe.result()}
        live = write_live(cfg.out, first_poses, seen_at, first_tracked, provisional)
        live += write_resources(cfg.out, list(monitor.timeline))
        live += [report.rerun["path"]] if report.rerun.get("path") else []
        report.outputs = write_outputs(cfg.out, cfg.source, report, poses, first_poses, provisional, live)
        if on_outputs is not None:
            on_outputs(report)

    envs = {name: _service_env(name, cfg, built, profile.env.get(name, {})) for name in built}  # in chain order
    overrides = {name: child_env(endpoint, env) for name, env in envs.items()}
    gateway = f"http://127.0.0.1:{cfg.port}" if "query_api" in built else None
    with StopSignals() as stop, Bus(BusSettings(mode="router", listen=[endpoint]), "runner") as bus, \
            SettingsProbe(overrides) as probe, open_recorder(cfg.rerun, bus, cfg.stream, gateway) as recorder:
        for topic in (keys.FRAME, keys.KEYFRAME, keys.POSE, keys.INTRINSICS, keys.EOS):
            bus.subscribe(keys.topic(cfg.stream, topic), observer.on_message)
        bus.ready()
        try:
            if not _stream(bus, cfg, envs, endpoint, observer, monitor, started, stop, report):
                report.stopped_by = stop.name
                report.end_reason = f"stopped by {stop.name}"
            else:  # the stream ended: outputs now, so they are on disk while the gateway serves
                finish()
                if cfg.serve and "query_api" in built:
                    _serve_until_stopped(started, cfg.port, stop)
        finally:
            kids.stop(started)
        if report.stopped_by:  # what was produced before the signal, once the services have stopped
            finish()
    return report


def _stream(bus: Bus, cfg: RunSettings, envs: dict[str, dict[str, str]], endpoint: str, observer: Observer,
            monitor: ResourceMonitor, started: list[kids.Child], stop: StopSignals, report: RunReport) -> bool:
    """Start the services (``envs``: each built one's environment), then ingest, and follow the stream to its end
    (True; ``report.end_reason`` says how it ended) or until a stop signal cuts it short (False)."""
    for name in [n for n in envs if n != "ingest"]:
        if stop.is_set():
            return False
        started.append(kids.start(name, endpoint, cfg.out / "logs", envs[name]))
        monitor.watch(name, started[-1].process.pid)
    if not _wait_alive(bus, started, cfg.alive_timeout_s, stop):
        return False
    sink = None if "features" in envs else _CreditSink(bus, cfg, observer)
    monitor.mark_stream_start()  # CPU spent loading models is not the stream's
    begin = time.monotonic()
    try:
        ingest = kids.start("ingest", endpoint, cfg.out / "logs", envs["ingest"])
        started.append(ingest)
        monitor.watch("ingest", ingest.process.pid)
        reason = _follow(observer, monitor, started, ingest, cfg, stop)
        report.duration_s = time.monotonic() - begin
    finally:
        if sink:
            sink.close()
    if reason is None:
        return False
    report.end_reason = reason
    return True


def _service_env(name: str, cfg: RunSettings, built: list[str] = (), semantic: dict[str, str] | None = None
                 ) -> dict[str, str]:
    """``name``'s environment for this run; ``semantic``: its settings of the run's semantic profile."""
    prefix = f"KMVIPE_{name.upper()}_"
    env = {prefix + "STREAM": cfg.stream, **(semantic or {})}
    if name == "features":  # its first credit waits for the downstream stages this run starts, no other
        env[prefix + "AWAIT_DOWNSTREAM"] = json.dumps([n for n in ("ba", "mapstore") if n in built])
    if name == "mapstore":
        env.update({prefix + "DB_PATH": str(cfg.out / "map.db"), prefix + "EXPORT_DIR": str(cfg.out)})
    if name == "query_api":
        env.update({"KMVIPE_QUERY_PORT": str(cfg.port), "KMVIPE_QUERY_HOST": "127.0.0.1"})
    if name == "ingest":
        env.update({prefix + "SOURCE": cfg.source, prefix + "PACING": cfg.pacing, prefix + "ENCODING": cfg.encoding})
        if cfg.intrinsics:
            env[prefix + "INTRINSICS"] = json.dumps(list(cfg.intrinsics))
        if cfg.max_frames:
            env[prefix + "MAX_FRAMES"] = str(cfg.max_frames)
        env[prefix + "USE_DEPTH"] = "true" if cfg.depth else "false"
        if cfg.depth_scale is not None:
            env[prefix + "DEPTH_SCALE"] = str(cfg.depth_scale)
        if cfg.topic:
            env[prefix + "TOPIC"] = cfg.topic
    return env


def _wait_alive(bus: Bus, started: list[kids.Child], timeout_s: float, stop: StopSignals) -> bool:
    """Block until every started service has announced itself on the bus (True), or a stop signal (False)."""
    deadline = time.monotonic() + timeout_s
    waiting = {child.name for child in started}
    while waiting:
        if stop.is_set():
            return False
        waiting -= set(bus.alive(timeout=0.5))
        for child in started:
            if not child.running():
                raise KmVipeError(f"service '{child.name}' exited during start-up; its log ends:\n{child.tail()}")
        if waiting and time.monotonic() > deadline:
            raise KmVipeError(f"services {sorted(waiting)} did not come up within {timeout_s:.0f} s (logs in {started[0].log_path.parent})")
    return not stop.is_set()


class _CreditSink:
    """When no features service runs, the runner itself consumes frames and grants credit, so a lossless
    stream still flows (and is counted) without anything being faked downstream."""

    def __init__(self, bus: Bus, cfg: RunSettings, observer: Observer):
        self._bus, self._cfg, self._observer = bus, cfg, observer
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="credit-sink", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        key = keys.topic(self._cfg.stream, keys.CREDIT)
        while not self._stop.is_set():
            with self._observer.lock:
                limit = self._observer.last_frame_seq + self._cfg.credit_window
            self._bus.publish(key, Credit(self._cfg.stream, limit, time.time_ns(), consumer="runner"))
            self._stop.wait(0.02)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


def _follow(observer: Observer, monitor: ResourceMonitor, started: list[kids.Child], ingest: kids.Child,
            cfg: RunSettings, stop: StopSignals) -> str | None:
    """Show progress until the last stage's end of stream, a dead service or a stall (the reason), or a stop
    signal (None). The services' CPU and memory are sampled on the way (every ``monitor.interval_s``, and once
    more when a service exited, before it is reaped), and every service's RSS is recorded each time another
    ``cfg.rss_every_frames`` frames passed."""
    interactive = sys.stderr.isatty()
    bar = tqdm(desc=f"kmvipe {cfg.stream}", unit="frame", mininterval=0.5 if interactive else 10.0,
               dynamic_ncols=True)
    begin = time.monotonic()
    recorded = 0  # frames at the last RSS record
    try:
        while not observer.done.wait(0.25):
            if stop.is_set():
                return None
            with observer.lock:
                frames = observer.frames
                fps = frames / max(time.monotonic() - begin, 1e-6)
                bar.set_postfix(keyframes=observer.keyframes, fps=f"{fps:.1f}", refresh=False)
                bar.update(frames - bar.n)
                idle = time.monotonic() - observer.last_activity
            if monitor.due() or any(c.exited_unreaped() for c in started):
                monitor.sample()
                if cfg.rss_every_frames and frames >= recorded + cfg.rss_every_frames:
                    recorded = frames - frames % cfg.rss_every_frames
                    monitor.record(frames)
            dead = [c for c in started if not c.running() and not (c is ingest and c.process.returncode == 0)]
            if dead:  # say why, and still write what was produced so far
                log.error("service died", extra={"service": dead[0].name, "log_tail": dead[0].tail()})
                return f"error: service '{dead[0].name}' died (exit {dead[0].process.returncode}); see {dead[0].log_path}"
            if idle > cfg.stall_timeout_s:
                return f"stalled: nothing on the bus for {idle:.0f} s"
        settle(observer)
        return observer.eos[observer.last_stage].reason
    finally:
        monitor.sample()  # CPU up to the end of the stream, before anything is stopped
        monitor.record(observer.frames)
        bar.update(observer.frames - bar.n)
        bar.close()


def _serve_until_stopped(started: list[kids.Child], port: int, stop: StopSignals) -> None:
    """Keep the gateway up until a stop signal (Ctrl-C, SIGTERM, SIGHUP) or until it exits."""
    print(f"serving queries at http://127.0.0.1:{port}/ (viewer) and /docs (API); Ctrl-C to stop", flush=True)
    while all(c.running() for c in started if c.name == "query_api") and not stop.event.wait(0.5):
        pass
