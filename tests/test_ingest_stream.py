"""Ingest → a consumer in a second process over real Zenoh (unix socket, no scouting), for a 300-frame video.

lossless: every frame arrives exactly once, in order, and ingest's memory stays bounded with a slow consumer.
realtime: with a slow consumer frames are dropped (not queued), and the drop count is reported.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import psutil
import pytest

from tests.conftest import REPO, wait_until

N_FRAMES = 300
FRAME_BYTES = 640 * 480 * 3


@pytest.fixture(scope="module")
def video_300(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("video") / "v300.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (640, 480))
    base = np.tile(np.linspace(0, 255, 640, dtype=np.uint8), (480, 1))
    for i in range(N_FRAMES):
        frame = np.dstack([base, np.roll(base, 7 * i, axis=1), np.full_like(base, i % 256)])
        writer.write(frame)
    writer.release()
    return path


class RssSampler:
    """Samples a process's resident memory every 20 ms in a background thread."""

    def __init__(self, pid: int):
        self.samples: list[tuple[float, int]] = []
        self._process = psutil.Process(pid)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.samples.append((time.monotonic(), self._process.memory_info().rss))
            except psutil.Error:
                return
            self._stop.wait(0.02)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def growth_after(self, fraction: float) -> int:
        """Peak RSS minus the RSS at ``fraction`` of the sampled time span."""
        t0, t1 = self.samples[0][0], self.samples[-1][0]
        early = next(rss for t, rss in self.samples if t >= t0 + fraction * (t1 - t0))
        return max(rss for _, rss in self.samples) - early


def _stream(video: Path, endpoint: str, out: Path, pacing: str, delay: float, extra_env: dict | None = None):
    consumer = subprocess.Popen(
        [sys.executable, "-m", "tests.helpers.frame_consumer", endpoint, "t300", str(out), "--listen",
         "--delay", str(delay), "--window", "4"], cwd=REPO,
    )
    wait_until(lambda: Path(str(out) + ".ready").exists() or consumer.poll() is not None, 60, "the consumer to subscribe")
    env = {**os.environ, "KMVIPE_BUS_MODE": "peer", "KMVIPE_BUS_CONNECT": json.dumps([endpoint]),
           "KMVIPE_INGEST_SOURCE": str(video), "KMVIPE_INGEST_STREAM": "t300", "KMVIPE_INGEST_PACING": pacing,
           "KMVIPE_INGEST_ENCODING": "raw", "KMVIPE_LOG_LEVEL": "INFO", **(extra_env or {})}
    ingest = subprocess.Popen([sys.executable, "-m", "services.ingest"], cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    sampler = RssSampler(ingest.pid)
    try:
        _, log = ingest.communicate(timeout=180)
        consumer.wait(timeout=60)
    finally:
        sampler.stop()
        for p in (ingest, consumer):
            if p.poll() is None:
                p.kill()
    assert ingest.returncode == 0, log
    return json.loads(out.read_text()), sampler, log


@pytest.mark.slow
def test_lossless_delivers_every_frame_once_in_order_with_bounded_memory(video_300, unix_endpoint, tmp_path):
    result, sampler, _ = _stream(video_300, unix_endpoint, tmp_path / "out.json", "lossless", delay=0.02)
    assert result["seqs"] == list(range(N_FRAMES))
    assert result["eos"] == {"seq": N_FRAMES - 1, "count": N_FRAMES}
    assert result["inbox_dropped"] == 0 and result["bad_payloads"] == 0
    # the raw stream is 276 MB; a credit window of 4 frames bounds what ingest holds to a few frames
    growth = sampler.growth_after(0.5)  # the second half of a 6 s stream: queueing would add ~140 MB
    assert growth < 16 * FRAME_BYTES, f"ingest RSS grew by {growth / 1e6:.0f} MB while streaming"


@pytest.mark.slow
def test_realtime_drops_instead_of_queueing(video_300, unix_endpoint, tmp_path):
    result, sampler, log = _stream(
        video_300, unix_endpoint, tmp_path / "out.json", "realtime", delay=0.05, extra_env={"KMVIPE_INGEST_FPS": "120"}
    )
    seqs, eos = result["seqs"], result["eos"]
    dropped = eos["seq"] + 1 - eos["count"]
    assert eos["seq"] == N_FRAMES - 1  # every frame was read and numbered
    assert dropped > N_FRAMES // 3, "a consumer at 20 fps behind a 120 fps source must cause drops"
    assert len(seqs) == eos["count"] and seqs == sorted(set(seqs))  # what was sent arrived, in order, once
    assert f"dropped={dropped}" in log  # ingest reports the drop count
    assert sampler.growth_after(0.5) < 16 * FRAME_BYTES
