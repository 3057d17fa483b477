"""Service processes started by the runner: each is ``services.<name>`` (through :mod:`services.runner.child`) in
client mode against the runner's private router, with its log in ``<out>/logs/<name>.log``.

Children run in the caller's working directory and import the very package the runner runs: ``python -P``
keeps the working directory off ``sys.path`` (a ``services/`` folder there must not shadow the package), and
where the package is not installed in a site directory (a checkout or an editable install) its parent goes on
``PYTHONPATH``. The runner hands them absolute paths only (:func:`services.runner.pipeline.absolute_paths`)."""
from __future__ import annotations

import importlib.util
import json
import logging
import os
import signal
import site
import subprocess
import sys
import sysconfig
import time
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

# Chain order: each stage consumes what the one before publishes.
PIPELINE = ("ingest", "features", "ba", "mapstore", "query_api")


def is_built(name: str) -> bool:
    """A service exists once its package has a ``service`` module (later issues fill them in)."""
    return importlib.util.find_spec(f"services.{name}.service") is not None


def last_connected_stage(built: list[str]) -> str:
    """The last streaming stage reachable from ingest without a gap: its end of stream ends the run."""
    last = "ingest"
    for name in PIPELINE[1:-1]:  # query_api answers queries; it forwards no stream
        if name not in built:
            break
        last = name
    return last


_HANDED_OUT: set[int] = set()  # ports free_tcp_endpoint returned: a port is only taken once its process binds it


def free_tcp_endpoint() -> str:
    """A loopback TCP endpoint on a port free now and not handed out before by this process. The kernel can give
    the same free port to two bind-and-release probes in a row, and two children told one port collide (a
    deployment test's gateway and its metrics endpoint were both given 60363)."""
    import socket

    while True:
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        if port not in _HANDED_OUT:
            _HANDED_OUT.add(port)
            return f"tcp/127.0.0.1:{port}"


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    log_path: Path
    started: float = field(default_factory=time.monotonic)

    def running(self) -> bool:
        return self.process.poll() is None

    def exited_unreaped(self) -> bool:
        """Exited but not yet reaped (``running()`` would reap it): its CPU times can still be read. False where
        the platform cannot tell without reaping."""
        if self.process.returncode is not None or not hasattr(os, "waitid"):
            return False
        try:
            return os.waitid(os.P_PID, self.process.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None
        except ChildProcessError:
            return False

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


PACKAGE_PARENT = Path(__file__).resolve().parents[2]
"""The folder that holds the ``services`` package the runner runs (site-packages, or a checkout)."""


def _site_dirs() -> set[Path]:
    dirs = [*site.getsitepackages(), site.getusersitepackages(), sysconfig.get_paths()["purelib"],
            sysconfig.get_paths()["platlib"]]
    return {Path(d).resolve() for d in dirs if d}


def child_pythonpath(environ: dict[str, str]) -> str | None:
    """``PYTHONPATH`` for a child, so that it imports the runner's own package from any working directory:
    unchanged (None) for a regular install, else the package's parent in front of the inherited one."""
    if PACKAGE_PARENT in _site_dirs():
        return None
    inherited = environ.get("PYTHONPATH", "")
    return os.pathsep.join([str(PACKAGE_PARENT), *([inherited] if inherited else [])])


def command(name: str) -> list[str]:
    """The command line of service ``name`` as a child of this process."""
    return [sys.executable, "-P", "-m", "services.runner.child", name, str(os.getpid())]


def start(name: str, endpoint: str, log_dir: Path, env: dict[str, str]) -> Child:
    """Start service ``name`` as a child process connected to ``endpoint``, in the caller's working directory.

    ``log_dir`` and every path in ``env`` must be absolute (the child resolves relative ones against the same
    working directory as the runner, but the runner does not rely on that)."""
    log_dir.mkdir(parents=True, exist_ok=True)
    log_path = log_dir / f"{name}.log"
    child_env = {
        **os.environ,
        "KMVIPE_BUS_MODE": "client",
        "KMVIPE_BUS_CONNECT": json.dumps([endpoint]),
        "KMVIPE_BUS_LISTEN": "[]",
        "KMVIPE_METRICS_PORT": "0",  # a run's services on one host: no metrics server, so their ports never clash
        "PYTHONUNBUFFERED": "1",
        **env,
    }
    pythonpath = child_pythonpath(child_env)
    if pythonpath is not None:
        child_env["PYTHONPATH"] = pythonpath
    with open(log_path, "wb") as out:
        process = subprocess.Popen(command(name), env=child_env, stdout=out, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL)
    return Child(name, process, log_path)


def stop(children: list[Child], grace_s: float = 10.0) -> None:
    """SIGTERM every child, wait up to ``grace_s``, then SIGKILL what is left."""
    for child in children:
        if child.running():
            child.process.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for child in children:
        try:
            child.process.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("service did not stop in time; killed", extra={"service": child.name})
            child.process.kill()
            child.process.wait()
