"""Typed settings shared by every service: the Zenoh bus, logging, and the metrics and health endpoints.

Each is built once from the environment (``KMVIPE_BUS_*``, ``KMVIPE_LOG_*``, ``KMVIPE_METRICS_*``), an optional
``.env`` file, or the ``[bus]``, ``[log]`` and ``[metrics]`` tables of the ``KMVIPE_CONFIG`` file
(:mod:`services.common.config_file`); defaults work on one machine. Lists are JSON in the environment:
``KMVIPE_BUS_CONNECT='["tcp/10.0.0.2:7447"]'``, TOML arrays in the file.
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import SettingsConfigDict

from .config_file import KmVipeSettings

ENDPOINT_PREFIXES = ("tcp/", "udp/", "tls/", "quic/", "ws/", "unixsock-stream/")


class BusSettings(KmVipeSettings):
    """How a process joins the Zenoh bus."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_BUS_", env_file=".env", extra="ignore")

    mode: Literal["peer", "client", "router"] = "peer"
    """peer on one machine or a LAN; client on edge devices and in containers (they connect to a router)."""
    listen: list[str] = []
    """Endpoints to listen on, e.g. ``tcp/127.0.0.1:7447`` or ``unixsock-stream//tmp/kmvipe.sock``."""
    connect: list[str] = []
    """Endpoints to connect to (a router, or a peer)."""
    multicast_scouting: bool = False
    """Off by default: discovery by multicast floods shared networks and makes tests leak into each other."""
    shared_memory: bool = False
    """Let Zenoh move large payloads through shared memory between processes on one host (raw frames: RTT
    3.5 → 1.5 ms, docs/BENCHMARKS.md). Off by default because the pool needs room in /dev/shm, which small
    containers lack; docker-compose.yml turns it on with a big enough shm_size."""
    shm_pool_mib: int = 64
    """Zenoh's SHM pool per session when shared_memory is on. It must hold every large payload in flight
    (credit window × frame bytes); when full, payloads silently go over the socket instead."""
    zenoh_config: Path | None = None
    """A Zenoh JSON5 config file to start from; the fields above override it."""
    user: str = ""
    """User name to give a router that asks for credentials (the secured router of docs/SECURITY.md)."""
    password: SecretStr | None = None
    """That user's password; prefer ``password_file`` outside tests (the environment shows in ``ps e``)."""
    password_file: Path | None = None
    """A file holding the password (a docker secret, ``kmvipe bus users``); a trailing newline is ignored."""
    tls_root_ca: Path | None = None
    """The CA that signed the router's certificate (``ca.pem`` of ``kmvipe bus certs``); needed to connect to a
    ``tls/`` endpoint: without it Zenoh checks the router against the public web CAs and refuses ours."""

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        for ep in value:
            if not ep.startswith(ENDPOINT_PREFIXES):
                raise ValueError(
                    f"endpoint {ep!r} must start with one of {', '.join(ENDPOINT_PREFIXES)} (e.g. tcp/127.0.0.1:7447)"
                )
        return value

    @model_validator(mode="after")
    def _credentials(self) -> "BusSettings":
        secrets = (self.password is not None) + (self.password_file is not None)
        if secrets > 1:
            raise ValueError("set one of KMVIPE_BUS_PASSWORD and KMVIPE_BUS_PASSWORD_FILE, not both")
        if bool(self.user) != bool(secrets):
            raise ValueError("a bus credential needs both KMVIPE_BUS_USER and KMVIPE_BUS_PASSWORD(_FILE)")
        return self


class LogSettings(KmVipeSettings):
    """Logging of one process."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_LOG_", env_file=".env", extra="ignore")

    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    format: Literal["text", "json"] = "text"
    """text: ``time level logger message key=value…``; json: one object per line for log shippers."""


Allocator = Literal["auto", "glibc", "tcmalloc"]


class MallocSettings(KmVipeSettings):
    """The C allocator of one service process."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_MALLOC_", env_file=".env", extra="ignore")

    allocator: Allocator = "auto"
    """auto (the default): TCMalloc for ba where it is installed (:mod:`services.common.allocator`), else glibc;
    tcmalloc: required (the service exits with how to install it); glibc: never preload anything."""


class MetricsSettings(KmVipeSettings):
    """The metrics and health endpoints of a service process (``/metrics``, ``/livez``, ``/readyz``;
    :mod:`services.common.metrics`)."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_METRICS_", env_file=".env", extra="ignore")

    port: int = Field(0, ge=0, le=65535)
    """TCP port of the endpoints; 0 (the default) serves none, so the child processes of ``kmvipe run`` and several
    runs on one host never compete for a port. docker-compose.yml and deploy/k8s set 9464 (one process per
    container)."""
    host: str = "127.0.0.1"
    """Interface to bind; 0.0.0.0 where a scraper or the kubelet reaches the process from outside (containers)."""
