"""Shared fixtures: the real-data folder, private Zenoh endpoints, and waiting on a condition with a deadline."""
from __future__ import annotations

import os
import time
import uuid
from pathlib import Path
from typing import Callable

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("KMVIPE_DATA_DIR", REPO.parent / "shared" / "data"))


def wait_until(condition: Callable[[], bool], timeout: float, what: str, poll: float = 0.02) -> None:
    """Poll ``condition`` until true; fail the test naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(poll)


@pytest.fixture
def data_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.skip(f"real test data not found at {DATA_DIR} (set KMVIPE_DATA_DIR)")
    return DATA_DIR


@pytest.fixture
def unix_endpoint(tmp_path_factory) -> str:
    """A private unix-socket endpoint (short path: unix socket paths are limited to ~100 bytes)."""
    path = Path("/tmp") / f"kmv-{uuid.uuid4().hex[:10]}.sock"
    yield f"unixsock-stream/{path}"
    path.unlink(missing_ok=True)


@pytest.fixture
def tcp_endpoint() -> str:
    from services.runner.children import free_tcp_endpoint

    return free_tcp_endpoint()
