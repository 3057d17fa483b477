"""Settings of the query gateway (env prefix ``KMVIPE_QUERY_``, or ``[query]`` of the ``KMVIPE_CONFIG`` file), built
once at start."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from ..common.config_file import KmVipeSettings
from ..common.models.store import default_models_dir
from .core.text import DEFAULT_TEMPLATES


class QuerySettings(KmVipeSettings):
    model_config = SettingsConfigDict(env_prefix="KMVIPE_QUERY_", env_file=".env", extra="ignore")

    host: str = "127.0.0.1"
    """Interface the HTTP server binds to (0.0.0.0 to serve the LAN)."""
    port: int = Field(8000, ge=0, le=65535)
    """HTTP port (0: any free port)."""
    api_key: str = ""
    """When set, every /v1 and /metrics request needs the header ``X-API-Key: <api_key>``, except the liveness
    probe ``/v1/health``."""
    cors_origins: list[str] = []
    """Origins allowed to call the API from a browser (JSON list; ``["*"]`` for any)."""
    max_body_bytes: int = Field(8 << 20, ge=1024)
    """Requests with a larger body are refused with 413 (images for query-by-example count here)."""
    max_texts: int = Field(64, ge=1)
    """Most texts (labels) in one query or segmentation."""
    max_text_chars: int = Field(200, ge=1)
    """Longest accepted text."""
    max_top_k: int = Field(1000, ge=1)
    """Largest ``top_k`` a client may ask for."""
    max_point_scores: int = Field(2_000_000, ge=1)
    """Most per-point scores (texts × points) a query may return as JSON."""
    max_image_side: int = Field(4096, ge=14)
    """Query-by-example images with a larger side are refused."""
    example_max_side: int = Field(518, ge=14)
    """Query-by-example images are resized so their long side is at most this before the backbone."""
    timeout_s: float = Field(5.0, gt=0)
    """How long to wait for the mapstore; past it the request answers 504 naming the service."""
    space_cache_s: float = Field(2.0, ge=0)
    """How long a map's backbone space (asked from its stats) is remembered; 0 asks before every query."""
    alive_timeout_s: float = Field(1.0, gt=0)
    """How long /v1/health waits for liveliness replies."""
    text_encoder: Literal["clip", "oracle", "none"] = "clip"
    """clip: CLIP text tower + Talk2DINO head from the model registry; oracle: label names → given vectors
    (tests, the synthetic demo); none: text queries are refused (query by example still works)."""
    text_model: str = "clip-vitb16-text"
    """Registry name of the CLIP text tower."""
    text_head: str = "talk2dino-vitb"
    """Registry name of the text head (decides the backbone space text queries land in)."""
    templates: list[str] = list(DEFAULT_TEMPLATES)
    """Prompt templates (each with ``{label}``). Default: the seven Talk2DINO evaluates with (its
    ``sub_imagenet_template``); a label's CLIP embeddings over all templates are averaged before the head, as
    upstream. A single prompt is a one-item list, e.g. ``'["There is {label} in the scene"]'``."""
    embedding_cache: int = Field(4096, ge=1)
    """Labels whose embeddings are kept (LRU)."""
    oracle_vectors: Path | None = None
    """Oracle encoder: an ``.npz`` with ``names`` (L,) str and ``vectors`` (L, D) float32."""
    oracle_synth_seed: int | None = None
    """Oracle encoder without a file: the synthetic world's label names and ``label_vectors(L, dim, seed)``."""
    oracle_synth_dim: int = Field(64, ge=1)
    """Dimension of the synthetic oracle vectors (must match the features service's oracle)."""
    oracle_space: str = "oracle"
    """Backbone id the oracle vectors live in (the map's PCA backbone must equal it)."""
    backbone: str = "dinov2-vits14-imgfocus"
    """Registry backbone for query by example (its space must equal the map's)."""
    models_dir: Path | None = Field(default_factory=default_models_dir)
    """Air-gapped model folder (``<models_dir>/<name>/``; defaults to ``$KMVIPE_MODELS_DIR``); also searched: the
    Hugging Face cache."""
    device: str = "auto"
    """torch device for the text and example models: auto (CUDA when present), cpu, cuda, cuda:1."""
    trajectory_capacity: int = Field(200_000, ge=1)
    """Frames whose poses are kept per stream."""
    export_chunk_points: int = Field(200_000, ge=1)
    """Points per mapstore export chunk fetched while streaming a PLY."""
    viewer_points: int = Field(60_000, ge=100)
    """Default most points the viewer fetches."""
