"""The C allocator of a service process (services/common/allocator.py): chosen per service, preloaded by executing
the process again, kept from the process's own children, and released by the allocator that holds the memory."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from services.common import allocator
from services.common.config import MallocSettings
from services.common.errors import KmVipeError
from services.common.lifecycle import MemoryRelease
from tests.conftest import REPO

TCMALLOC = allocator.library("tcmalloc")
needs_tcmalloc = pytest.mark.skipif(TCMALLOC is None, reason="TCMalloc not installed (Debian: libtcmalloc-minimal4)")

# a process that takes ba's (or the named service's) allocator, then reports what it runs on, what its children
# inherit and what a release does after a burst of mid-size buffers like a BA slice's
_PROBE = textwrap.dedent("""
    import json, os, subprocess, sys
    from services.common import allocator
    allocator.ensure(sys.argv[1])
    import numpy as np
    from services.common.lifecycle import release_free_memory

    def rss_mb():
        return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20

    child = subprocess.run([sys.executable, "-c", "from services.common import allocator; print(allocator.in_use())"],
                           capture_output=True, text=True, check=True).stdout.strip()
    buffers = [np.ones(150_000, np.float32) for _ in range(400)]  # 0.6 MB each, 240 MB
    del buffers
    before = rss_mb()
    released = release_free_memory()
    print(json.dumps({"in_use": allocator.in_use(), "pid": os.getpid(), "child": child,
                      "ld_preload": os.environ.get("LD_PRELOAD", ""), "argv": sys.argv[1:],
                      "released": released, "freed_mb": before - rss_mb()}))
""")


def _probe(service: str, **env: str) -> dict:
    environ = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_MALLOC")}
    environ.pop("LD_PRELOAD", None)
    proc = subprocess.Popen([sys.executable, "-c", _PROBE, service], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**environ, "PYTHONPATH": str(REPO), **env})
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    report = json.loads(out.strip().splitlines()[-1])
    assert report["pid"] == proc.pid  # executed again in place: whoever started it still holds the process
    return report


def test_auto_picks_tcmalloc_for_ba_only_and_glibc_where_it_is_not_installed(monkeypatch):
    assert allocator.chosen("features", "auto") == "glibc"
    assert allocator.chosen("mapstore", "auto") == "glibc"
    assert allocator.chosen("ba", "auto") == ("tcmalloc" if TCMALLOC else None)
    assert allocator.chosen("ba", "glibc") == "glibc"
    monkeypatch.setitem(allocator._LIBRARIES, "tcmalloc", ("kmvipe_no_such_allocator",))
    assert allocator.chosen("ba", "auto") is None  # auto without the library: glibc, no error
    with pytest.raises(KmVipeError, match="apt-get install libtcmalloc-minimal4.*KMVIPE_MALLOC_ALLOCATOR=glibc"):
        allocator.chosen("ba", "tcmalloc")


def test_the_setting_reads_the_environment(monkeypatch):
    assert MallocSettings().allocator == "auto"
    monkeypatch.setenv("KMVIPE_MALLOC_ALLOCATOR", "glibc")
    assert MallocSettings().allocator == "glibc"


def test_a_bad_setting_stops_the_service_with_the_setting_named_and_no_traceback():
    environ = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    result = subprocess.run([sys.executable, "-P", "-m", "services.runner.child", "ba", str(os.getpid())],
                            cwd=REPO, capture_output=True, text=True, timeout=120,
                            env={**environ, "PYTHONPATH": str(REPO), "KMVIPE_MALLOC_ALLOCATOR": "jemalloc"})
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert "KMVIPE_MALLOC_" in result.stderr and "'auto', 'glibc' or 'tcmalloc'" in result.stderr


@pytest.mark.parametrize("service", ["ba", "mapstore"])
def test_python_m_services_takes_its_allocator_before_its_work_and_ba_before_torch(service):
    """`python -m services.NAME` goes through `service_main`, which runs `ensure` first: a bad setting stops any
    service (exit code 2, no traceback; the mapstore used to ignore it), and ba before torch is imported, so an exec
    onto TCMalloc would not pay for torch's import twice."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    result = subprocess.run([sys.executable, "-X", "importtime", "-m", f"services.{service}"], cwd=REPO,
                            capture_output=True, text=True, timeout=120,
                            env={**environ, "PYTHONPATH": str(REPO), "KMVIPE_MALLOC_ALLOCATOR": "jemalloc"})
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert "KMVIPE_MALLOC_" in result.stderr
    imported = {line.split("|")[-1].strip() for line in result.stderr.splitlines() if line.startswith("import time:")}
    assert "services.common.allocator" in imported and "torch" not in imported


def test_a_process_on_glibc_stays_on_it_and_is_not_executed_again():
    report = _probe("features")
    assert report["in_use"] == "glibc" and report["child"] == "glibc" and report["ld_preload"] == ""
    report = _probe("ba", KMVIPE_MALLOC_ALLOCATOR="glibc")
    assert report["in_use"] == "glibc" and report["ld_preload"] == ""


@needs_tcmalloc
def test_ba_runs_on_tcmalloc_its_children_on_glibc_and_a_release_gives_back_what_a_burst_freed():
    report = _probe("ba")
    assert report["in_use"] == "tcmalloc" and report["argv"] == ["ba"]  # the same command line, executed again
    assert report["ld_preload"] == "" and report["child"] == "glibc"  # its own children choose for themselves
    assert report["released"] is True
    assert report["freed_mb"] > 100, report  # of the 240 MB of 0.6 MB buffers TCMalloc kept for reuse


@needs_tcmalloc
def test_a_user_preload_is_kept_beside_tcmalloc_and_given_back_to_children():
    preload = subprocess.run(["sh", "-c", "ldconfig -p | grep -o '/[^ ]*libm\\.so\\.6' | head -1"],
                             capture_output=True, text=True).stdout.strip()
    if not preload:
        pytest.skip("no libm.so.6 path from ldconfig")
    report = _probe("ba", LD_PRELOAD=preload)
    assert report["in_use"] == "tcmalloc" and report["ld_preload"] == preload


def test_periodic_releases_run_on_glibc_only(monkeypatch):
    now = [0.0]
    release = MemoryRelease(10.0, clock=lambda: now[0])
    assert release.periodic  # this test process runs on glibc
    now[0] = 11.0
    assert release.maybe() and release.count == 1
    monkeypatch.setattr(release, "periodic", False)  # as in a process on TCMalloc (the probe above: it reuses)
    now[0] = 30.0
    assert not release.maybe() and release.count == 1
    release.now()  # an explicit release after a known burst still runs
    assert release.count == 2
