"""CPU time and memory of the runner's service processes, sampled while the stream runs (for the summary).

Each service is one child process of the runner, with its own children counted in (ba's tracking process). The
runner calls
:meth:`ResourceMonitor.sample` from its follow loop about every half second, and always before it polls the
children (``Popen.poll`` reaps an exited child, after which its CPU time is gone; before that a zombie still
reports it). Every sample is kept for ``resources.csv``. Peak RSS is the largest sample; CPU is user + system
seconds at the last sample, and ``cpu_stream_s`` the part of it spent after :meth:`mark_stream_start` (while the
stream ran, model loading excluded).

RSS counts a shared page in every process that maps it: the services' Python, torch and OpenCV libraries are mapped
by five or six processes, so a sum of RSS counts them five or six times. PSS (Linux ``smaps_rollup``) splits each
shared page among the processes that map it: the sum of PSS is the memory the services hold together. Both are
reported; PSS is None where the platform has no such count."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import psutil

MB = 1024 * 1024


@dataclass
class ServiceUsage:
    cpu_s: float = 0.0  # user + system seconds since the process started
    cpu_at_stream_start: float | None = None
    rss_mb: float = 0.0  # last sample
    rss_peak_mb: float = 0.0
    pss_mb: float | None = None  # last sample (None: not readable here)
    pss_peak_mb: float | None = None

    @property
    def cpu_stream_s(self) -> float:
        return self.cpu_s - (self.cpu_at_stream_start or 0.0)


@dataclass
class ResourceMonitor:
    interval_s: float = 0.5
    usage: dict[str, ServiceUsage] = field(default_factory=dict)
    rss_total_peak_mb: float = 0.0
    pss_total_peak_mb: float | None = None  # largest sum of the services' PSS at one sample
    series: list[dict] = field(default_factory=list)  # {"frames", "t_s", "rss_mb": {service: MB}}
    # every sample: (t_s, service, cpu_s, rss_mb, pss_mb or None), for resources.csv (where a peak came from)
    timeline: list[tuple[float, str, float, float, float | None]] = field(default_factory=list)
    _procs: dict[str, psutil.Process] = field(default_factory=dict)
    _last: float = float("-inf")
    _t0: float = field(default_factory=time.monotonic)

    def watch(self, name: str, pid: int) -> None:
        try:
            self._procs[name] = psutil.Process(pid)
        except psutil.NoSuchProcess:
            return
        self.usage.setdefault(name, ServiceUsage())

    def due(self) -> bool:
        return time.monotonic() - self._last >= self.interval_s

    def sample(self) -> None:
        """One sample of every watched service (exited ones keep their last values)."""
        self._last = time.monotonic()
        total, total_pss = 0.0, None
        for name, proc in self._procs.items():
            cpu, rss, pss = _process_usage(proc)
            use = self.usage[name]
            if cpu is not None:
                use.cpu_s = max(use.cpu_s, cpu)
            if rss is not None and rss > 0:  # a zombie reports 0
                use.rss_mb = rss / MB
                use.rss_peak_mb = max(use.rss_peak_mb, use.rss_mb)
                total += use.rss_mb
            if pss is not None and pss > 0:
                use.pss_mb = pss / MB
                use.pss_peak_mb = max(use.pss_peak_mb or 0.0, use.pss_mb)
                total_pss = (total_pss or 0.0) + use.pss_mb
            self.timeline.append((round(self._last - self._t0, 2), name, round(use.cpu_s, 2), round(use.rss_mb, 1),
                                  None if use.pss_mb is None else round(use.pss_mb, 1)))
        self.rss_total_peak_mb = max(self.rss_total_peak_mb, total)
        if total_pss is not None:
            self.pss_total_peak_mb = max(self.pss_total_peak_mb or 0.0, total_pss)

    def mark_stream_start(self) -> None:
        self.sample()
        for use in self.usage.values():
            use.cpu_at_stream_start = use.cpu_s

    def record(self, frames: int) -> None:
        """Append the current RSS of every service to :attr:`series` (call right after :meth:`sample`)."""
        self.series.append({"frames": int(frames), "t_s": round(time.monotonic() - self._t0, 2),
                            "rss_mb": {n: round(u.rss_mb, 1) for n, u in self.usage.items()},
                            "pss_mb": {n: round(u.pss_mb, 1) for n, u in self.usage.items() if u.pss_mb is not None}})

    def report(self) -> dict[str, dict[str, float]]:
        return {n: {"cpu_s": round(u.cpu_s, 2), "cpu_stream_s": round(u.cpu_stream_s, 2),
                    "rss_peak_mb": round(u.rss_peak_mb, 1),
                    "pss_peak_mb": None if u.pss_peak_mb is None else round(u.pss_peak_mb, 1)}
                for n, u in self.usage.items()}


def _process_usage(proc: psutil.Process) -> tuple[float | None, float | None, float | None]:
    """CPU seconds, RSS and PSS bytes of ``proc`` and the processes it started (ba's tracking process: live ones
    sampled, ended ones in the parent's children times); None for what can no longer be read (a zombie still has
    its CPU times, its RSS reads 0)."""
    cpu, rss, pss = _own_usage(proc, with_reaped=True)
    try:
        children = proc.children(recursive=True)
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        children = []
    for child in children:
        child_cpu, child_rss, child_pss = _own_usage(child, with_reaped=False)
        if cpu is not None and child_cpu is not None:
            cpu += child_cpu
        if rss is not None and child_rss is not None:
            rss += child_rss
        if pss is not None and child_pss is not None:
            pss += child_pss
    return cpu, rss, pss


def _own_usage(proc: psutil.Process, with_reaped: bool) -> tuple[float | None, float | None, float | None]:
    cpu = rss = pss = None
    with proc.oneshot():
        try:
            times = proc.cpu_times()
            cpu = times.user + times.system
            if with_reaped:
                cpu += times.children_user + times.children_system
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    try:  # RSS and PSS in one call (Linux: PSS from smaps_rollup); platforms without PSS give RSS alone
        memory = proc.memory_full_info()
        rss, pss = float(memory.rss), getattr(memory, "pss", None)
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        pass
    return cpu, rss, (None if pss is None else float(pss))
