"""The ROS 2 side of the Zenoh network: one session that publishes and subscribes ROS 2 topics in either form
(:mod:`services.ros2.core.names`). In the rmw_zenoh form it also holds the liveliness tokens that put this process
in the ROS graph as a node with its publishers and subscriptions, and attaches rmw_zenoh's sequence number, source
time and GID to every sample.
"""
from __future__ import annotations

import hashlib
import itertools
import logging
import threading
import time
from typing import Callable

import zenoh

from ..common.bus import open_session
from .config import Ros2Settings, RosZenohSettings
from .core import messages
from .core.names import Qos, endpoint_token, msgtype_of_key, node_token, pack_attachment, topic_key, topic_selector

log = logging.getLogger(__name__)

OnSample = Callable[[str, str | None, bytes], None]
"""``(key, message type the key names or None, CDR payload)``, called on a Zenoh thread."""


class RosPublisher:
    """Publishes one topic's CDR payloads (thread-safe)."""

    def __init__(self, node: "RosNode", topic: str, msgtype: str, entity_id: int):
        cfg = node.cfg
        self.topic, self.msgtype = topic, msgtype
        digest = messages.type_hash(msgtype, cfg.distro)
        self.key = topic_key(cfg.form, topic, msgtype, digest, cfg.domain_id)
        self._rmw = cfg.form == "rmw_zenoh"
        self._sequence = itertools.count(1)  # rmw_zenoh numbers a publisher's samples from 1
        self._lock = threading.Lock()
        self._token = None
        token_key = endpoint_token("MP", cfg.domain_id, node.zid, node.node_id, entity_id, cfg.node_name, topic,
                                   msgtype, digest, Qos(depth=cfg.depth))
        # the GID only has to tell publishers apart; rmw_zenoh also derives it from the token's key
        self.gid = hashlib.blake2b(token_key.encode(), digest_size=16).digest()
        self._publisher = node.session.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.DROP,
                                                         reliability=zenoh.Reliability.RELIABLE)
        if self._rmw:
            self._token = node.session.liveliness().declare_token(token_key)

    def put(self, payload: bytes) -> None:
        """Send one serialised message (``messages.serialize``)."""
        with self._lock:
            attachment = (pack_attachment(next(self._sequence), time.time_ns(), self.gid) if self._rmw else None)
            self._publisher.put(payload, attachment=attachment)

    def close(self) -> None:
        if self._token is not None:
            self._token.undeclare()
        self._publisher.undeclare()


class RosNode:
    """A Zenoh session on the ROS 2 graph (:class:`RosZenohSettings`) acting as node ``cfg.node_name``."""

    def __init__(self, cfg: Ros2Settings, zenoh_settings: RosZenohSettings):
        self.cfg = cfg
        self.session = open_session(zenoh_settings)
        self.zid = str(self.session.info.zid())
        self.node_id = 0
        self._entities = itertools.count(1)
        self._handles: list = []
        self._publishers: list[RosPublisher] = []
        if cfg.form == "rmw_zenoh":
            self._handles.append(self.session.liveliness().declare_token(
                node_token(cfg.domain_id, self.zid, self.node_id, cfg.node_name)))

    def publisher(self, topic: str, msgtype: str) -> RosPublisher:
        pub = RosPublisher(self, topic, msgtype, next(self._entities))
        self._publishers.append(pub)
        log.info("publishing ROS 2 topic", extra={"topic": topic, "type": msgtype, "key": pub.key})
        return pub

    def subscribe(self, topic: str, msgtypes: tuple[str, ...], on_sample: OnSample) -> str:
        """Call ``on_sample`` for every sample published on ``topic`` under any type and hash (the rmw_zenoh
        form announces a subscription of each of ``msgtypes``); returns the selector."""
        cfg = self.cfg
        selector = topic_selector(cfg.form, topic, cfg.domain_id)

        def _callback(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            try:
                on_sample(key, msgtype_of_key(key) if cfg.form == "rmw_zenoh" else None, sample.payload.to_bytes())
            except Exception:  # the error boundary of a Zenoh callback: log, keep the session
                log.exception("ROS 2 sample handler failed", extra={"key": key})

        self._handles.append(self.session.declare_subscriber(selector, _callback))
        if cfg.form == "rmw_zenoh":
            for msgtype in msgtypes:
                self._handles.append(self.session.liveliness().declare_token(endpoint_token(
                    "MS", cfg.domain_id, self.zid, self.node_id, next(self._entities), cfg.node_name, topic,
                    msgtype, messages.type_hash(msgtype, cfg.distro), Qos(depth=cfg.depth))))
        log.info("subscribed to ROS 2 topic", extra={"topic": topic, "selector": selector})
        return selector

    def close(self) -> None:
        for pub in self._publishers:
            pub.close()
        for handle in reversed(self._handles):
            handle.undeclare()
        self._publishers.clear()
        self._handles.clear()
        self.session.close()

    def __enter__(self) -> "RosNode":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
