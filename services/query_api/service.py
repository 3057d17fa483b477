"""Query gateway service: the HTTP server (uvicorn) around a :class:`Gateway` on the bus, until ``stop``."""
from __future__ import annotations

import logging
import threading
import time

import uvicorn

from ..common.bus import Bus
from .app import create_app
from .config import QuerySettings
from .gateway import Gateway

log = logging.getLogger(__name__)
POLL_S = 0.2


class Server(uvicorn.Server):
    """uvicorn without its own signal handlers (the process's stop event rules) and with a ready flag."""

    def install_signal_handlers(self) -> None:  # noqa: D401 - uvicorn hook
        pass


def build_server(cfg: QuerySettings, bus: Bus, gateway: Gateway | None = None) -> Server:
    """The uvicorn server of the gateway's app; declares the bus's liveliness token (the pose subscription is
    in place once the Gateway exists)."""
    app = create_app(cfg, gateway or Gateway(cfg, bus))
    bus.ready()
    return Server(uvicorn.Config(app, host=cfg.host, port=cfg.port, log_level="warning", access_log=False))


def bound_port(server: Server) -> int:
    """The TCP port the started server listens on (useful with port 0)."""
    return server.servers[0].sockets[0].getsockname()[1]


def run(cfg: QuerySettings, bus: Bus, stop: threading.Event, gateway: Gateway | None = None) -> None:
    """Serve HTTP on ``cfg.host:cfg.port`` until ``stop`` is set."""
    server = build_server(cfg, bus, gateway)
    thread = threading.Thread(target=server.run, name="http", daemon=True)
    thread.start()
    while not stop.wait(POLL_S) and thread.is_alive():
        pass
    server.should_exit = True
    thread.join(timeout=10)
    log.info("query gateway stopped")


def start_background(cfg: QuerySettings, bus: Bus, gateway: Gateway | None = None, timeout_s: float = 10.0):
    """Start the server in a daemon thread; returns (server, thread, port) once it accepts connections."""
    server = build_server(cfg, bus, gateway)
    thread = threading.Thread(target=server.run, name="http", daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout_s
    while not server.started and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.02)
    if not server.started:
        server.should_exit = True
        raise RuntimeError(f"query gateway did not start on {cfg.host}:{cfg.port} (port in use?)")
    return server, thread, bound_port(server)
