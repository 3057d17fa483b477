"""ROS 2 names as Zenoh key expressions, in the two forms ROS 2 is reached over Zenoh (pure: strings and bytes).

**rmw_zenoh** (``RMW_IMPLEMENTATION=rmw_zenoh_cpp``; ros2/rmw_zenoh ``docs/design.md``, "Topic and Service name
mapping to Zenoh key expressions", "Graph Cache", "Publishers"):

- data: ``<domain_id>/<fully qualified name without the outer '/'>/<DDS type name>/<type hash>``, e.g.
  ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74…``; the hash is the type's RIHS01 hash (REP 2016), or
  ``TypeHashNotSupported`` on Humble;
- every sample carries an attachment: int64 sequence number and int64 source time (ns since the epoch), both
  little endian, then the publisher GID as a one-byte length (16) and 16 bytes — 33 bytes; rmw_zenoh
  subscriptions drop a sample without it;
- the graph (``ros2 node list``, ``ros2 topic info``) is made of liveliness tokens
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/<node>``, and for a
  publisher or subscription ``…/<topic>/<type>/<hash>/<qos>`` after that,
  where a name is "mangled" by writing each ``/`` as ``%`` and an unset enclave or namespace is ``%``.

**zenoh-bridge-ros2dds** (eclipse-zenoh/zenoh-plugin-ros2dds): the key is the topic name without its leading
``/`` (``/chatter`` → ``chatter``; a bridge configured with ``namespace: /bot1`` uses ``bot1/chatter``), the payload
the same CDR bytes, no attachment, no tokens.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Literal

Form = Literal["rmw_zenoh", "bridge"]
FORMS: tuple[Form, ...] = ("rmw_zenoh", "bridge")
LIVELINESS_ROOT = "@ros2_lv"
HASH_NOT_SUPPORTED = "TypeHashNotSupported"
"""What rmw_zenoh on Humble (no type descriptions yet) writes where later releases write the RIHS01 hash."""
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE since Iron; rmw_zenoh hashes the entity's token into it
RMW_DEFAULT_DEPTH = 42  # rmw_zenoh's default KEEP_LAST depth: a token leaves a depth equal to it out
RELIABILITY_BEST_EFFORT = 2  # rmw_qos_reliability_policy_e (rmw/types.h); RELIABLE is rmw_zenoh's default
DURABILITY_TRANSIENT_LOCAL = 1  # rmw_qos_durability_policy_e; VOLATILE is rmw_zenoh's default

_TOPIC = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
_NODE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_FRAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_/\-.]*$")
_MSGTYPE = re.compile(r"^([A-Za-z0-9_]+)/(msg|srv)/([A-Za-z0-9_]+)$")
_ATTACHMENT = struct.Struct("<qqB")


def check_topic(name: str) -> str:
    """``name`` if it is a fully qualified ROS 2 topic name (``/camera/image_raw``), else ValueError."""
    if not isinstance(name, str) or not _TOPIC.match(name):
        raise ValueError(f"ROS 2 topic {name!r} must be fully qualified: '/' then tokens of letters, digits and '_' "
                         "separated by '/', none starting with a digit (e.g. /camera/image_raw)")
    return name


def check_node_name(name: str) -> str:
    if not isinstance(name, str) or not _NODE.match(name):
        raise ValueError(f"ROS 2 node name {name!r} must be letters, digits and '_', not starting with a digit")
    return name


def check_frame(name: str) -> str:
    """``name`` if it can be a tf2 frame id here (no spaces; letters, digits, ``_ - . /``), else ValueError."""
    if not isinstance(name, str) or not _FRAME.match(name):
        raise ValueError(f"frame id {name!r} must be letters, digits, '_', '-', '.' or '/' (e.g. map)")
    return name


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/Image`` → ``sensor_msgs::msg::dds_::Image_``: the type name rmw_zenoh puts in keys."""
    match = _MSGTYPE.match(msgtype)
    if match is None:
        raise ValueError(f"message type {msgtype!r} must read package/msg/Name")
    return f"{match[1]}::{match[2]}::dds_::{match[3]}_"


def msgtype_of_dds(dds: str) -> str:
    """Inverse of :func:`dds_type_name`; ValueError for anything else."""
    match = re.match(r"^([A-Za-z0-9_]+)::(msg|srv)::dds_::([A-Za-z0-9_]+)_$", dds)
    if match is None:
        raise ValueError(f"{dds!r} is not a DDS type name of a ROS 2 message")
    return f"{match[1]}/{match[2]}/{match[3]}"


def mangle(name: str) -> str:
    """A ROS name as one key chunk: every ``/`` written as ``%`` (``/`` → ``%``, ``/a/b`` → ``%a%b``)."""
    return name.replace("/", "%")


def topic_key(form: Form, topic: str, msgtype: str, type_hash: str, domain_id: int = 0) -> str:
    """The key expression samples of ``topic`` (type ``msgtype``, hash ``type_hash``) travel on."""
    bare = check_topic(topic).strip("/")
    if form == "bridge":
        return bare
    if form != "rmw_zenoh":
        raise ValueError(f"unknown form {form!r}; forms: {', '.join(FORMS)}")
    return f"{domain_id}/{bare}/{dds_type_name(msgtype)}/{type_hash}"


def topic_selector(form: Form, topic: str, domain_id: int = 0) -> str:
    """A selector for every type and hash published on ``topic`` (a subscription that takes Humble's
    ``TypeHashNotSupported`` keys and later releases' RIHS01 keys alike)."""
    bare = check_topic(topic).strip("/")
    return bare if form == "bridge" else f"{domain_id}/{bare}/*/*"


def msgtype_of_key(key: str) -> str | None:
    """The message type an rmw_zenoh data key names (``…/sensor_msgs::msg::dds_::Image_/<hash>``), or None."""
    parts = str(key).split("/")
    if len(parts) < 4:
        return None
    try:
        return msgtype_of_dds(parts[-2])
    except ValueError:
        return None


@dataclass(frozen=True)
class Qos:
    """The QoS a token announces (rmw_zenoh maps RELIABLE to reliable Zenoh, TRANSIENT_LOCAL to a cache)."""

    depth: int = 10
    reliable: bool = True
    transient_local: bool = False

    def chunk(self) -> str:
        """rmw_zenoh's compact form ``reliability:durability:history,depth:deadline:lifespan:liveliness``, each
        value left empty where it is rmw_zenoh's default (``::,10:,:,:,,`` = RELIABLE, VOLATILE, KEEP_LAST 10)."""
        reliability = "" if self.reliable else str(RELIABILITY_BEST_EFFORT)
        durability = str(DURABILITY_TRANSIENT_LOCAL) if self.transient_local else ""
        depth = "" if self.depth == RMW_DEFAULT_DEPTH else str(self.depth)
        return f"{reliability}:{durability}:,{depth}:,:,:,,"


def node_token(domain_id: int, zid: str, node_id: int, node_name: str, namespace: str = "/") -> str:
    """Liveliness token of a node (``NN``); its entity id is its node id, as rmw_zenoh writes it."""
    return "/".join((LIVELINESS_ROOT, str(domain_id), zid, str(node_id), str(node_id), "NN", mangle("/"),
                     mangle(namespace), check_node_name(node_name)))


def endpoint_token(kind: Literal["MP", "MS"], domain_id: int, zid: str, node_id: int, entity_id: int,
                   node_name: str, topic: str, msgtype: str, type_hash: str, qos: Qos,
                   namespace: str = "/") -> str:
    """Liveliness token of a publisher (``MP``) or subscription (``MS``) of node ``node_name``."""
    if kind not in ("MP", "MS"):
        raise ValueError(f"endpoint kind {kind!r} must be MP (publisher) or MS (subscription)")
    return "/".join((LIVELINESS_ROOT, str(domain_id), zid, str(node_id), str(entity_id), kind, mangle("/"),
                     mangle(namespace), check_node_name(node_name), mangle(check_topic(topic)),
                     dds_type_name(msgtype), type_hash, qos.chunk()))


def pack_attachment(sequence: int, source_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's sample attachment: ``<q`` sequence, ``<q`` source time (ns), ``B`` GID length, GID."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, got {len(gid)}")
    return _ATTACHMENT.pack(sequence, source_ns, GID_SIZE) + bytes(gid)


def unpack_attachment(data: bytes) -> tuple[int, int, bytes]:
    """Inverse of :func:`pack_attachment`: ``(sequence, source_ns, gid)``; ValueError when malformed."""
    data = bytes(data)
    if len(data) != _ATTACHMENT.size + GID_SIZE:
        raise ValueError(f"an rmw_zenoh attachment has {_ATTACHMENT.size + GID_SIZE} bytes, got {len(data)}")
    sequence, source_ns, n = _ATTACHMENT.unpack_from(data)
    if n != GID_SIZE:
        raise ValueError(f"attachment GID length {n}, expected {GID_SIZE}")
    return sequence, source_ns, data[_ATTACHMENT.size:]
