"""Every message on the KM-ViPE bus, versioned, with encode/decode.

A message is a frozen dataclass; on the wire it is a msgpack map ``{"kind", "v", <fields>}`` (see
:mod:`services.common.codec`). :func:`decode` checks kind and version, and :mod:`services.common.wire_check` field
types, array dtypes and shapes; both raise :class:`DecodeError` with a message that names the field — services
count and drop such payloads.
Every message carries ``stream``, ``seq`` and ``t_ns`` so one frame can be followed through the logs, and the
``session`` of the stream it belongs to: a source that starts (or restarts) on a stream opens a new session, and
no stage mixes two sessions' messages into one state (:mod:`services.common.streams`).
Conventions (poses ``world_from_cam``, RGB, the 1/8 grid) are in docs/CONVENTIONS.md.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar, Optional

import numpy as np

from . import codec
from .errors import DecodeError
from .wire_check import arr, from_dict

SCHEMA_VERSION = 1


@dataclass(frozen=True)
class Message:
    """Fields every message has."""

    KIND: ClassVar[str] = ""
    stream: str
    seq: int
    t_ns: int
    session: str = field(default="", kw_only=True)  # "" : sent outside any session (tests, tools)

    def check(self) -> None:
        """Cross-field rules beyond types and shapes; raise DecodeError."""

    def encode(self) -> bytes:
        return encode(self)


@dataclass(frozen=True)
class Frame(Message):
    """ingest → features: one camera frame. Exactly one of ``image`` (raw RGB) and ``jpeg`` is set."""

    KIND: ClassVar[str] = "frame"
    width: int
    height: int
    image: Optional[np.ndarray] = field(default=None, metadata=arr("u1", ("H", "W", 3)))
    jpeg: Optional[bytes] = None
    intrinsics: Optional[np.ndarray] = field(default=None, metadata=arr("f8", (4,)))  # fx fy cx cy (px)
    depth: Optional[np.ndarray] = field(default=None, metadata=arr("f4", ("H", "W")))  # metres, 0 = missing
    realtime: bool = False  # the source is paced in real time: later stages may drop frames (never keyframes)
    # the highest seq a features instance had reported handled when this was sent (-1: none): a features that
    # starts on the stream counts every frame after it as its own, so one lost before its first is still counted
    features_handled: int = -1

    def check(self) -> None:
        if (self.image is None) == (self.jpeg is None):
            raise DecodeError("frame: exactly one of 'image' and 'jpeg' must be set")
        if self.image is not None and self.image.shape[:2] != (self.height, self.width):
            raise DecodeError(f"frame: image shape {self.image.shape} does not match {self.height}x{self.width}")
        if self.depth is not None and self.depth.shape != (self.height, self.width):
            raise DecodeError(f"frame: depth shape {self.depth.shape} does not match {self.height}x{self.width}")


@dataclass(frozen=True)
class Credit(Message):
    """features → ingest (on ``credit``): ``seq`` is the highest frame seq ``consumer`` can take now.

    ba and mapstore → features (on ``progress``): ``seq`` is the highest frame seq ``consumer`` has handled (ba:
    any frame; mapstore: keyframes), so features holds ingest back while the stages behind it are behind. A ba
    that checkpoints (``checkpoints``) also says up to which seq its last checkpoint holds (``durable``): features
    keeps what it sent after that, and sends it again to a ba instance that resumed from the checkpoint."""

    KIND: ClassVar[str] = "credit"
    consumer: str = ""
    checkpoints: bool = False
    durable: int = -1


@dataclass(frozen=True)
class Keyframe(Message):
    """features → ba, mapstore: a keyframe at working resolution with its codes on the 1/8 grid."""

    KIND: ClassVar[str] = "keyframe"
    image: np.ndarray = field(metadata=arr("u1", ("H", "W", 3)))
    intrinsics: np.ndarray = field(metadata=arr("f8", (4,)))  # at working resolution
    orig_width: int = 0
    orig_height: int = 0
    pca_version: int = -1  # -1: no codes (geometry only)
    codes: Optional[np.ndarray] = field(default=None, metadata=arr("f2 f4", ("h", "w", "K")))
    disparity_prior: Optional[np.ndarray] = field(default=None, metadata=arr("f4", ("h", "w")))  # 1/m, 0 = none
    realtime: bool = False  # from the frame: the stream is paced in real time

    def check(self) -> None:
        h, w = self.image.shape[:2]
        if h % 8 or w % 8:
            raise DecodeError(f"keyframe: working size {w}x{h} must be multiples of 8")
        for name in ("codes", "disparity_prior"):
            grid = getattr(self, name)
            if grid is not None and grid.shape[:2] != (h // 8, w // 8):
                raise DecodeError(f"keyframe: {name} grid {grid.shape[:2]} must be {(h // 8, w // 8)}")


@dataclass(frozen=True)
class KeyframeCodes(Message):
    """features → ba, mapstore: the DINO codes of keyframe ``seq``, sent once the backbone is done with it.

    Keyframes leave features with their geometry at once (``Keyframe`` with ``pca_version`` -1); the codes follow
    in this message, so tracking and mapping never wait for the backbone."""

    KIND: ClassVar[str] = "codes"
    pca_version: int
    codes: np.ndarray = field(metadata=arr("f2 f4", ("h", "w", "K")))


@dataclass(frozen=True)
class FrameLite(Message):
    """features → ba: a non-keyframe as a small grey image, for motion-only pose filling."""

    KIND: ClassVar[str] = "frame_lite"
    image: np.ndarray = field(metadata=arr("u1", (None, None)))
    intrinsics: np.ndarray = field(metadata=arr("f8", (4,)))  # for this small image
    ref_seq: int = -1  # the last keyframe before it
    realtime: bool = False  # from the frame: the stream is paced in real time


@dataclass(frozen=True)
class PcaBasis(Message):
    """features → all: the frozen PCA basis. codes z ↦ feature ≈ mean + z @ components."""

    KIND: ClassVar[str] = "pca"
    version: int
    backbone: str
    mean: np.ndarray = field(metadata=arr("f4", ("D",)))
    components: np.ndarray = field(metadata=arr("f4", ("K", "D")))
    explained_variance: Optional[np.ndarray] = field(default=None, metadata=arr("f4", ("K",)))


@dataclass(frozen=True)
class Graph(Message):
    """ba → mapstore: the keyframe graph state. ``poses`` for all of ``kf_seqs``; disparities, static (ARK)
    weights and flow confidences only for the keyframes in ``updated_seqs``."""

    KIND: ClassVar[str] = "graph"
    kf_seqs: np.ndarray = field(metadata=arr("i8", ("N",)))
    poses: np.ndarray = field(metadata=arr("f8", ("N", 4, 4)))  # world_from_cam
    intrinsics: np.ndarray = field(metadata=arr("f8", (4,)))  # at working resolution
    width: int = 0
    height: int = 0
    updated_seqs: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), metadata=arr("i8", ("M",)))
    disparities: Optional[np.ndarray] = field(default=None, metadata=arr("f4", ("M", "h", "w")))
    static_weights: Optional[np.ndarray] = field(default=None, metadata=arr("f4", ("M", "h", "w")))
    confidence: Optional[np.ndarray] = field(default=None, metadata=arr("f4", ("M", "h", "w")))
    metric: bool = False  # True when a depth prior fixed the scale
    final: bool = False


@dataclass(frozen=True)
class Poses(Message):
    """ba → anyone: camera poses of frames (the trajectory stream); re-sent when BA revises them."""

    KIND: ClassVar[str] = "pose"
    frame_seqs: np.ndarray = field(metadata=arr("i8", ("N",)))
    stamps_ns: np.ndarray = field(metadata=arr("i8", ("N",)))
    poses: np.ndarray = field(metadata=arr("f8", ("N", 4, 4)))  # world_from_cam
    final: bool = False
    tracked: bool = False  # frame-rate tracking poses: kept until mapping publishes a revision of the frame
    provisional: bool = False  # tracked before the map started: rotation only, no translation (nor scale) yet


@dataclass(frozen=True)
class Intrinsics(Message):
    """ba → features: refined intrinsics at working resolution."""

    KIND: ClassVar[str] = "intrinsics"
    intrinsics: np.ndarray = field(metadata=arr("f8", (4,)))
    width: int
    height: int


@dataclass(frozen=True)
class Eos(Message):
    """each stage → next: end of stream. ``stage`` says who sent it; ``seq`` is the last frame seq."""

    KIND: ClassVar[str] = "eos"
    stage: str
    count: int = 0  # messages of its main kind that stage published
    reason: str = "end"  # "end" | "error" | "stopped"
    dropped: int = 0  # messages this stage dropped by its real-time policy (never keyframes, codes, bases, EOS)
    codes_skipped: int = 0  # features, real-time: keyframes the backbone skipped as stale (no codes sent)
    lost: int = 0  # frames the stage before announced that never arrived (lost on the way: Zenoh drops on congestion)
    # ba: (first, last) frame seqs of each run of frames whose view held no evidence (covered, blank, a cut),
    # posed by time between their neighbours
    views_lost: Optional[np.ndarray] = field(default=None, metadata=arr("i8", (None, 2)))
    # ba: frames whose solved pose lay farther off the path of the poses around them than the camera can have gone
    # (something moving filled the view), posed by time between their neighbours instead
    frames_strayed: int = 0
    # seconds the stage spent on work the end of stream started (ba: the final BA and frames; the mapstore: the
    # export), apart from the backlog it finished first
    work_s: float = 0.0


# --- mapstore queries (``kmvipe/<s>/map/<verb>``: the request is the query payload, the answer the reply) ---


@dataclass(frozen=True)
class MapQuery(Message):
    """query_api → mapstore: score query vectors given in the backbone space ``space``.
    Verbs: ``map/query`` (regions + top-k points per vector), ``map/segment`` (argmax over the vectors as a
    label set, per point). ``seq`` is a request id, echoed in the answer."""

    KIND: ClassVar[str] = "map_query"
    vectors: np.ndarray = field(metadata=arr("f4", ("Q", "D")))
    space: str = ""  # backbone id the vectors live in; must equal the map's PCA backbone
    top_k: int = 20  # points returned per query vector
    threshold: float = -1.0  # region score threshold; < 0: chosen by the mapstore relative to the best score
    max_regions: int = 10
    with_points: bool = False  # per-point scores of every map point (large)


@dataclass(frozen=True)
class MapAnswer(Message):
    """mapstore → query_api: regions and top points, flattened over queries (``*_query`` says which)."""

    KIND: ClassVar[str] = "map_answer"
    region_query: np.ndarray = field(metadata=arr("i4", ("R",)))
    region_score: np.ndarray = field(metadata=arr("f4", ("R",)))
    region_centroid: np.ndarray = field(metadata=arr("f4", ("R", 3)))
    region_box_min: np.ndarray = field(metadata=arr("f4", ("R", 3)))
    region_box_max: np.ndarray = field(metadata=arr("f4", ("R", 3)))
    region_count: np.ndarray = field(metadata=arr("i4", ("R",)))
    point_query: np.ndarray = field(metadata=arr("i4", ("P",)))
    point_xyz: np.ndarray = field(metadata=arr("f4", ("P", 3)))
    point_score: np.ndarray = field(metadata=arr("f4", ("P",)))
    all_scores: Optional[np.ndarray] = field(default=None, metadata=arr("f4", ("Q", "N")))
    n_points: int = 0


@dataclass(frozen=True)
class MapSegment(Message):
    """mapstore → query_api: per-point argmax label (index into the query vectors) and its score."""

    KIND: ClassVar[str] = "map_segment"
    xyz: np.ndarray = field(metadata=arr("f4", ("N", 3)))
    label: np.ndarray = field(metadata=arr("i4", ("N",)))
    score: np.ndarray = field(metadata=arr("f4", ("N",)))


@dataclass(frozen=True)
class MapChunk(Message):
    """mapstore → anyone (``map/export?chunk=i``): one chunk of the fused map; ``seq`` = chunk index."""

    KIND: ClassVar[str] = "map_chunk"
    xyz: np.ndarray = field(metadata=arr("f4", ("N", 3)))
    rgb: np.ndarray = field(metadata=arr("u1", ("N", 3)))
    codes: Optional[np.ndarray] = field(default=None, metadata=arr("f2", ("N", "K")))
    n_chunks: int = 1
    total_points: int = 0


@dataclass(frozen=True)
class MapStats(Message):
    """mapstore → anyone (``map/stats``)."""

    KIND: ClassVar[str] = "map_stats"
    keyframes: int = 0
    points: int = 0
    voxels: int = 0
    backbone: str = ""
    pca_version: int = -1
    metric: bool = False
    keyframes_without_codes: int = 0  # keyframes fused for geometry whose codes have not arrived (or never will)


MESSAGES: dict[str, type[Message]] = {
    cls.KIND: cls
    for cls in (
        Frame, Credit, Keyframe, KeyframeCodes, FrameLite, PcaBasis, Graph, Poses, Intrinsics, Eos,
        MapQuery, MapAnswer, MapSegment, MapChunk, MapStats,
    )
}


def encode(msg: Message) -> bytes:
    """Message → payload bytes."""
    body = {"kind": msg.KIND, "v": SCHEMA_VERSION}
    for f in dataclasses.fields(msg):
        value = getattr(msg, f.name)
        if value is not None:
            body[f.name] = value
    return codec.pack(body)


def decode(payload: bytes | bytearray | memoryview, expect: type[Message] | None = None) -> Message:
    """Payload bytes → validated message; ``expect`` restricts the kind. Raises DecodeError."""
    body = codec.unpack(payload)
    if not isinstance(body, dict):
        raise DecodeError(f"payload is a {type(body).__name__}, not a message map")
    kind, version = body.get("kind"), body.get("v")
    if version != SCHEMA_VERSION:
        raise DecodeError(f"schema version {version!r} not supported (this build speaks v{SCHEMA_VERSION})")
    cls = MESSAGES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise DecodeError(f"unknown message kind {kind!r}")
    if expect is not None and cls is not expect:
        raise DecodeError(f"expected a {expect.KIND!r} message, got {kind!r}")
    return from_dict(cls, body)


# --- query by keyframe region (``kmvipe/<s>/map/{keyframes,keyframe,example}``; services/mapstore/keyframe_queries.py)


@dataclass(frozen=True)
class KeyframeList(Message):
    """mapstore → anyone (``map/keyframes``): every keyframe the map has stored, ascending ``seqs``."""

    KIND: ClassVar[str] = "keyframe_list"
    seqs: np.ndarray = field(metadata=arr("i8", ("N",)))
    stamps_ns: np.ndarray = field(metadata=arr("i8", ("N",)))
    widths: np.ndarray = field(metadata=arr("i4", ("N",)))  # the keyframe's working image, pixels
    heights: np.ndarray = field(metadata=arr("i4", ("N",)))
    has_codes: np.ndarray = field(metadata=arr("u1", ("N",)))  # 1: codes and their basis are in (queryable)
    has_thumbnail: np.ndarray = field(metadata=arr("u1", ("N",)))


@dataclass(frozen=True)
class KeyframeThumbnail(Message):
    """mapstore → anyone (``map/keyframe?seq=n``): the small JPEG of keyframe ``seq`` (RGB, longest side
    the mapstore's ``thumbnail_side``)."""

    KIND: ClassVar[str] = "keyframe_thumbnail"
    jpeg: bytes
    width: int  # of the thumbnail, pixels
    height: int


@dataclass(frozen=True)
class KeyframeQuery(Message):
    """query_api → mapstore (``map/example``): the region ``box`` of keyframe ``keyframe`` as the query; its codes
    pooled over the 1/8-grid cells inside are the query vector. ``box`` is [x0, y0, x1, y1] normalised to the
    image (0 = left/top edge, 1 = right/bottom edge); a box that holds no cell centre (x0 = x1, y0 = y1: a click)
    takes the cell under its centre. ``seq`` is a request id, echoed in the answer (a ``MapAnswer``)."""

    KIND: ClassVar[str] = "keyframe_query"
    keyframe: int
    box: np.ndarray = field(metadata=arr("f4 f8", (4,)))
    top_k: int = 20
    threshold: float = -1.0  # as MapQuery
    max_regions: int = 10
    with_points: bool = False


@dataclass(frozen=True)
class KeyframeRefusal(Message):
    """mapstore → query_api: why a ``map/keyframe`` or ``map/example`` request was not answered. ``status``:
    ``not_found`` (no such keyframe or thumbnail), ``no_codes`` (its codes or their basis are not in yet, or never
    will be) or ``bad_request`` (a box outside [0, 1] or inverted)."""

    KIND: ClassVar[str] = "keyframe_refusal"
    status: str
    reason: str

    def check(self) -> None:
        if self.status not in ("not_found", "no_codes", "bad_request"):
            raise DecodeError(f"keyframe_refusal: status {self.status!r} must be not_found, no_codes or bad_request")


MESSAGES.update({cls.KIND: cls for cls in (KeyframeList, KeyframeThumbnail, KeyframeQuery, KeyframeRefusal)})


@dataclass(frozen=True)
class MapSessions(Message):
    """mapstore → anyone (``map/sessions``): the stream's sessions with a map: the current one (``current``) and
    every earlier one kept aside (services/mapstore/sessions.py), each queryable with ``?session=<id>``."""

    KIND: ClassVar[str] = "map_sessions"
    current: str
    names: str  # session ids, newline-separated, in the order of the arrays (ids are [A-Za-z0-9_-], no newline)
    keyframes: np.ndarray = field(metadata=arr("i8", ("N",)))
    finished: np.ndarray = field(metadata=arr("u1", ("N",)))  # 1: the session's stream ended (its map is complete)

    def sessions(self) -> list[str]:
        return self.names.split("\n") if self.names else []

    def check(self) -> None:
        if len(self.sessions()) != len(self.keyframes):
            raise DecodeError(f"map_sessions: {len(self.sessions())} names for {len(self.keyframes)} sessions")


MESSAGES.update({MapSessions.KIND: MapSessions})
