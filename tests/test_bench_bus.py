"""Smoke run of bench/bus.py: two real processes over a unix socket, every SHM variant, a few raw frames.

Checks the benchmark's own bookkeeping (every frame echoed, lossless) and what it proves about the bus: with
``shared_memory=False`` no payload arrives SHM-backed, with SHM on (Bus setting, bigger pool, provider) the
ping-pong frames after warm-up all do. No timing is asserted.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FRAMES = 5
COLUMNS = ("transport", "shm", "encoding", "payload_kb", "frames", "fps", "fps_range", "mbps", "rtt50", "rtt99",
           "ow50", "ow99", "shm_thr", "shm_lat")


def table_rows(stdout: str) -> dict[str, dict[str, str]]:
    """Markdown table rows of the benchmark's output, keyed by the SHM variant."""
    rows = {}
    for line in stdout.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == len(COLUMNS) and cells[0] in ("tcp", "unix"):
            row = dict(zip(COLUMNS, cells))
            rows[row["shm"]] = row
    return rows


@pytest.mark.timeout(240)
@pytest.mark.skipif(not Path("/dev/shm").is_dir(), reason="POSIX shared memory (/dev/shm) not available")
def test_bus_bench_smoke_every_shm_variant():
    cmd = [sys.executable, "bench/bus.py", "--transport", "unix", "--encoding", "raw", "--shm", "all",
           "--frames", str(FRAMES), "--pings", str(FRAMES), "--size", "320x240", "--rounds", "1"]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=200)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "command: " in done.stdout and "load average" in done.stdout
    rows = table_rows(done.stdout)
    assert set(rows) == {"off", "on", "pool64", "provider"}, done.stdout
    payload = 320 * 240 * 3 / 1e3
    for variant, row in rows.items():
        assert row["frames"] == f"{FRAMES}/{FRAMES}", f"{variant}: frames lost"
        assert payload < float(row["payload_kb"]) < payload + 1.0, f"{variant}: payload is not one raw frame"
        assert float(row["rtt50"]) <= float(row["rtt99"])
    assert rows["off"]["shm_thr"] == f"0/{FRAMES}" and rows["off"]["shm_lat"] == f"0/{FRAMES}"
    for variant in ("on", "pool64", "provider"):
        assert rows[variant]["shm_lat"] == f"{FRAMES}/{FRAMES}", f"{variant}: pings did not go through SHM"
