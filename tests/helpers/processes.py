"""The deployed processes in tests: ``kmvipe`` commands started as compose starts them, stopped as docker stop does."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Iterator

import httpx

from services.runner.children import free_tcp_endpoint

KMVIPE = Path(sys.executable).with_name("kmvipe")


def start(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    """``kmvipe ARGS`` with its output appended to ``log``."""
    return subprocess.Popen([str(KMVIPE), *args], env=env, stdout=log.open("ab"), stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL)


def stop(procs: list[subprocess.Popen], grace_s: float = 30.0) -> None:
    """SIGTERM to every process still running, then SIGKILL to any that has not exited after ``grace_s``."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def client_env(endpoint: str, spec: str, maps: Path, **settings: str) -> dict[str, str]:
    """The services' environment in the compose topology on a loopback router: client mode, the synthetic world's
    oracle backbone for ``spec`` in place of DINO, one map database per stream under ``maps``, plus ``settings``
    (``KMVIPE_...`` names); nothing inherited from the caller's own ``KMVIPE_`` variables."""
    base = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    return {**base, "KMVIPE_BUS_MODE": "client", "KMVIPE_BUS_CONNECT": json.dumps([endpoint]),
            "KMVIPE_BUS_LISTEN": "[]", "KMVIPE_FEATURES_BACKBONE": "synth-oracle",
            "KMVIPE_FEATURES_ORACLE_SOURCE": spec, "KMVIPE_MAPSTORE_DB_PATH": str(maps / "{stream}.db"), **settings}


def start_services(names: tuple[str, ...], env: dict[str, str], logs: Path, bus) -> dict[str, subprocess.Popen]:
    """``kmvipe service NAME`` for each name, logging to ``logs/NAME.log``; returns once all are alive on ``bus``."""
    from tests.conftest import wait_until

    procs = {name: start(["service", name], env, logs / f"{name}.log") for name in names}
    try:
        wait_until(lambda: set(names) <= set(bus.alive(timeout=0.5)), 120, "services ready")
    except BaseException:
        stop(list(procs.values()))
        raise
    return procs


@contextlib.contextmanager
def served_run(args: list[str], cwd: Path, env: dict[str, str], timeout_s: float = 300.0) -> Iterator[str]:
    """``kmvipe ARGS --serve --port P --out out`` (a run or the demo) in ``cwd``: yields the gateway's URL once the
    stream's outputs are written and the gateway answers; SIGTERM (then SIGKILL) at the end."""
    from tests.conftest import wait_until

    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    proc = subprocess.Popen([str(KMVIPE), *args, "--serve", "--port", str(port), "--out", "out"], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until(lambda: (cwd / "out" / "summary.json").exists() or proc.poll() is not None, timeout_s,
                   "the run's outputs")
        assert proc.poll() is None, proc.stdout.read()
        wait_until(lambda: _answers(url), 60, "the gateway")
        yield url
    finally:
        stop([proc], 60.0)


def _answers(url: str) -> bool:
    try:
        return httpx.get(f"{url}/v1/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def stop_cleanly(proc: subprocess.Popen, log: Path, grace_s: float = 30.0) -> None:
    """SIGTERM, and the process must exit 0 within ``grace_s`` (its log in the failure); killed if it does not."""
    proc.send_signal(signal.SIGTERM)
    try:
        assert proc.wait(timeout=grace_s) == 0, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
