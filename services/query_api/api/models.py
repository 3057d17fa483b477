"""Public request and response models of the /v1 API (what OpenAPI documents, with examples).

Static bounds here are hard ceilings; the configured limits (QuerySettings.max_*) are checked in the routes.
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import BaseModel, ConfigDict, Field

Vec3 = list[float]
MAX_TEXTS = 256
MAX_TEXT_CHARS = 1000
TEXT = Field(min_length=1, max_length=MAX_TEXT_CHARS)


class QueryRequest(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"texts": ["chair"], "top_k": 20},
        {"texts": ["chair", "table", "fire extinguisher"], "top_k": 10, "max_regions": 3, "with_point_scores": False},
    ]})
    texts: list[str] = Field(min_length=1, max_length=MAX_TEXTS, description="One or many texts (labels or phrases).")
    top_k: int = Field(20, ge=1, le=10_000, description="Top-scoring points returned per text.")
    threshold: Optional[float] = Field(None, ge=-1.0, le=1.0, description="Region score threshold (cosine); "
                                       "null: the mapstore chooses one relative to the best score.")
    max_regions: int = Field(10, ge=1, le=1000, description="Most regions returned per text.")
    with_point_scores: bool = Field(False, description="Also return every map point's score per text (large).")


class ExampleRequest(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"image_b64": "<base64 PNG or JPEG>", "box": [120, 80, 260, 240], "top_k": 20},
    ]})
    image_b64: str = Field(min_length=1, description="The example image, PNG or JPEG, base64-encoded.")
    box: Optional[list[float]] = Field(None, min_length=4, max_length=4,
                                       description="Region as pixel box [x0, y0, x1, y1] (x1, y1 exclusive).")
    mask_b64: Optional[str] = Field(None, min_length=1, description="Region as a PNG mask of the image's size "
                                    "(non-zero = inside), base64-encoded; used instead of box.")
    top_k: int = Field(20, ge=1, le=10_000)
    threshold: Optional[float] = Field(None, ge=-1.0, le=1.0)
    max_regions: int = Field(10, ge=1, le=1000)


class RegionOut(BaseModel):
    score: float = Field(description="Region score (cosine similarity).")
    centroid: Vec3 = Field(description="World-frame centroid [x, y, z] (map units; metres when metric).")
    box_min: Vec3
    box_max: Vec3
    count: int = Field(description="Map points in the region.")
    samples: list[Vec3] = Field(description="Best-scoring points inside the region.")
    sample_scores: list[float]


class PointOut(BaseModel):
    xyz: Vec3
    score: float


class TextResult(BaseModel):
    text: str
    regions: list[RegionOut]
    top_points: list[PointOut]


class QueryResponse(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "stream": "cam0", "n_points": 125000, "space": "dinov2_vitb14_reg", "results": [{
            "text": "chair", "regions": [{"score": 0.62, "centroid": [2.1, 3.0, 0.5], "box_min": [1.8, 2.7, 0.0],
                                          "box_max": [2.4, 3.3, 1.0], "count": 812, "samples": [[2.1, 3.0, 0.5]],
                                          "sample_scores": [0.71]}],
            "top_points": [{"xyz": [2.1, 3.0, 0.5], "score": 0.71}]}], "point_scores": None}]})
    stream: str
    n_points: int = Field(description="Points in the map when it was scored.")
    space: str = Field(description="Embedding space the query vectors were scored in (the map's backbone).")
    encoder: str = Field("", description="What made the query vectors: the text encoder (e.g. "
                         "clip-vitb16-text+talk2dino-vitb, oracle) or 'example'.")
    oracle: bool = Field(False, description="The text vectors are the synthetic world's ground-truth label "
                         "vectors (a test double), not a language model's.")
    results: list[TextResult]
    point_scores: Optional[list[list[float]]] = Field(None, description="(texts × points) scores, map order.")


class SegmentRequest(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"labels": ["floor", "wall", "table", "chair"], "format": "json"},
        {"labels": ["chair", "table"], "format": "ply", "min_score": 0.2},
    ]})
    labels: list[str] = Field(min_length=1, max_length=MAX_TEXTS, description="The label set.")
    format: Literal["json", "ply"] = Field("json", description="json: summary (and points when asked); "
                                           "ply: every point with label colour, label index and score.")
    min_score: float = Field(-1.0, ge=-1.0, le=1.0, description="Points whose best score is lower are unlabelled (-1).")
    include_points: bool = Field(False, description="json only: per-point xyz and label, at most max_points.")
    max_points: int = Field(100_000, ge=1, le=5_000_000)


class LabelOut(BaseModel):
    label: str
    count: int
    fraction: float
    mean_score: Optional[float]
    centroid: Optional[Vec3]


class SegmentResponse(BaseModel):
    stream: str
    n_points: int
    unlabelled: int
    labels: list[LabelOut]
    xyz: Optional[list[Vec3]] = None
    point_labels: Optional[list[int]] = None


class FramePose(BaseModel):
    seq: int
    t_ns: int
    world_from_cam: list[list[float]] = Field(description="4x4 camera-to-world matrix (row-major).")


class TrajectoryResponse(BaseModel):
    stream: str
    final: bool = False
    frames: list[FramePose]


class MapPoints(BaseModel):
    stream: str
    total_points: int
    returned: int
    xyz: list[float] = Field(description="Flat [x0, y0, z0, x1, ...] of the returned points.")
    rgb: list[int] = Field(description="Flat [r0, g0, b0, ...] uint8 colours.")


class MapInfo(BaseModel):
    keyframes: int
    points: int
    voxels: int
    backbone: str
    pca_version: int
    metric: bool
    session: str = ""  # the session this map is of


class QuerySupport(BaseModel):
    """Which queries this stream's map answers now, each with the reason (or what to do about it)."""

    text: bool
    text_why: str
    example: bool
    example_why: str
    oracle: bool = Field(False, description="Text vectors come from the synthetic world's ground truth (a test "
                         "double), not from a language model.")


class StreamInfo(BaseModel):
    name: str
    map: Optional[MapInfo]
    poses: int
    queries: Optional[QuerySupport] = None
    session: str = ""  # the stream's current session (a restarted publisher opens a new one): poses and map are its


class SessionInfo(BaseModel):
    session: str
    keyframes: int
    finished: bool = Field(description="The session's stream ended: its map is complete.")
    current: bool


class SessionsResponse(BaseModel):
    stream: str
    current: str
    sessions: list[SessionInfo]


class StreamsResponse(BaseModel):
    streams: list[StreamInfo]


class ServiceHealth(BaseModel):
    alive: bool
    instances: list[str]


class HealthResponse(BaseModel):
    status: Literal["ok", "degraded"]
    services: dict[str, ServiceHealth]


class ErrorResponse(BaseModel):
    detail: str = Field(description="What is wrong and, where possible, how to fix it.")
