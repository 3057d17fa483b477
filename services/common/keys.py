"""Key expressions of the KM-ViPE bus. Every key is built here; no service spells one by hand.

Layout: ``kmvipe/<stream>/<topic>``; liveliness tokens under ``kmvipe/@alive/<service>/<instance>``
(``@alive`` is a verbatim chunk, so stream wildcards like ``kmvipe/*/frame`` never match it), and a source's token
``kmvipe/<stream>/@source/<session>`` while it streams: services that serve every stream start on it.
"""
from __future__ import annotations

import re
import secrets
import time

from .errors import ConfigError

ROOT = "kmvipe"
ALIVE = f"{ROOT}/@alive"

SOURCE = "@source"
ALL_STREAMS = "*"
"""A service's ``stream`` setting that serves every stream a source announces (:func:`source`)."""

DEFAULT_STREAM = "cam0"
"""The stream every command and service uses unless told otherwise (``--stream``, ``KMVIPE_<SERVICE>_STREAM``):
one default everywhere, so a publisher and the services started without settings meet on the same keys."""

FRAME = "frame"
CREDIT = "credit"
KEYFRAME = "keyframe"
FRAME_LITE = "frame_lite"
PCA = "pca"
GRAPH = "graph"
POSE = "pose"
INTRINSICS = "intrinsics"
EOS = "eos"
CODES = "codes"
PROGRESS = "progress"
MAP = "map"

TOPICS = (FRAME, CREDIT, KEYFRAME, FRAME_LITE, PCA, GRAPH, POSE, INTRINSICS, EOS, CODES, PROGRESS)

_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def check_name(name: str, what: str = "stream") -> str:
    """Return ``name`` if it is a valid key chunk (letters, digits, '_' and '-', ≤ 64), else raise ConfigError."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ConfigError(
            f"invalid {what} name {name!r}: use 1-64 letters, digits, '_' or '-' (it becomes a Zenoh key chunk)"
        )
    return name


def topic(stream: str, name: str) -> str:
    """``kmvipe/<stream>/<name>`` for one of :data:`TOPICS`; ``stream`` may be ``*`` to match every stream."""
    if stream != "*":
        check_name(stream)
    if name not in TOPICS:
        raise ValueError(f"unknown topic {name!r}; known: {', '.join(TOPICS)}")
    return f"{ROOT}/{stream}/{name}"


def map_key(stream: str, *parts: str) -> str:
    """``kmvipe/<stream>/map/<parts...>``: the mapstore's queryables (``**`` for all)."""
    if stream != "*":
        check_name(stream)
    return "/".join((ROOT, stream, MAP, *parts))


def alive(service: str = "*", instance: str = "*") -> str:
    """Liveliness token key of one service instance (or a wildcard selector)."""
    if service not in ("*", "**"):
        check_name(service, "service")
    if instance not in ("*", "**"):
        check_name(instance, "instance")
    return f"{ALIVE}/{service}/{instance}"


def parse_alive(key: str) -> tuple[str, str]:
    """Inverse of :func:`alive`: ``(service, instance)``."""
    parts = str(key).split("/")
    if len(parts) != 4 or "/".join(parts[:2]) != ALIVE:
        raise ValueError(f"not a liveliness key: {key!r}")
    return parts[2], parts[3]


def stream_of(key: str) -> str:
    """The stream chunk of a ``kmvipe/<stream>/...`` key."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise ValueError(f"not a KM-ViPE stream key: {key!r}")
    return parts[1]


def source(stream: str = "*", instance: str = "*") -> str:
    """Liveliness token of a source streaming ``stream`` (a wildcard selector with the defaults)."""
    if stream != "*":
        check_name(stream)
    if instance not in ("*", "**"):
        check_name(instance, "instance")
    return f"{ROOT}/{stream}/{SOURCE}/{instance}"


def parse_source(key: str) -> str:
    """The stream of a :func:`source` token key."""
    return parse_source_session(key)[0]


def parse_source_session(key: str) -> tuple[str, str]:
    """The stream and the session of a :func:`source` token key (a source announces its session as its instance)."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != ROOT or parts[2] != SOURCE:
        raise ValueError(f"not a source token key: {key!r}")
    return check_name(parts[1]), check_name(parts[3], "session")


def new_session() -> str:
    """A session id for a source starting a stream: its UTC start time, readable and in order, and 4 random hex
    digits so two sources started in the same second differ (``20261125T121530-3fa2``)."""
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime()) + "-" + secrets.token_hex(2)
