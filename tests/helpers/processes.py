"""The deployed processes in tests: ``kmvipe`` commands started as compose starts them, stopped as docker stop does."""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

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
