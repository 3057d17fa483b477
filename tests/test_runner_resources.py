"""The runner's memory count: RSS per service with its children, and PSS, which splits shared pages."""
import subprocess
import sys

import psutil
import pytest

from services.runner.resources import ResourceMonitor

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PSS is read from /proc (Linux)")

# numpy's libraries, mapped by every such process, and 64 MB of the process's own
HOLD = ("import numpy, sys, time; held = numpy.ones(8 * 1024 * 1024); "
        "sys.stdout.write('up\\n'); sys.stdout.flush(); time.sleep(60)")
# the same, after starting a child process that holds the same (as ba starts its tracking process)
WITH_CHILD = ("import subprocess, sys; child = subprocess.Popen([sys.executable, '-c', " + repr(HOLD) + "], "
              "stdout=subprocess.PIPE, text=True); child.stdout.readline(); " + HOLD)


def _start(code: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "up"
    return proc


def test_pss_counts_shared_libraries_once_and_a_child_process_is_counted_with_its_parent():
    procs = [_start(HOLD), _start(WITH_CHILD)]
    try:
        monitor = ResourceMonitor()
        for name, proc in zip(("one", "two"), procs):
            monitor.watch(name, proc.pid)
        monitor.sample()
        one, two = monitor.usage["one"], monitor.usage["two"]
        assert one.rss_mb > 64 and two.rss_mb > 1.5 * one.rss_mb  # the child is counted with its parent
        assert one.pss_mb < one.rss_mb and two.pss_mb < two.rss_mb  # three processes share the libraries
        assert one.pss_mb > 64  # its own array is its own
        assert monitor.pss_total_peak_mb == pytest.approx(one.pss_mb + two.pss_mb)
        assert monitor.pss_total_peak_mb < monitor.rss_total_peak_mb
        assert monitor.report()["two"]["pss_peak_mb"] == round(two.pss_peak_mb, 1)
        monitor.sample()
        assert [name for _, name, *_ in monitor.timeline] == ["one", "two"] * 2  # every sample, for resources.csv
        t_s, _, cpu_s, rss_mb, pss_mb = monitor.timeline[-1]
        assert t_s >= monitor.timeline[0][0] and (rss_mb, pss_mb) == (round(two.rss_mb, 1), round(two.pss_mb, 1))
    finally:
        for proc in procs:
            for child in psutil.Process(proc.pid).children(recursive=True):
                child.kill()
            proc.kill()
            proc.wait()
