"""Text side of open-vocabulary queries: CLIP text tower and the Talk2DINO head into DINO space.

Upstream (github.com/lorebianchi98/Talk2DINO) feeds the head OpenAI CLIP's ``encode_text`` output as it is, not
L2-normalised: ``text_features_extraction.py`` stores it for training, ``src/hf_model.py`` ``encode_text`` and
``dinotext.py`` ``build_text_embedding`` project it at inference. The head is affine + tanh, so the input scale
matters; :class:`ClipTextEncoder` therefore returns the raw embeddings.
"""
from __future__ import annotations

import logging
from pathlib import Path

import torch
from torch import nn

from ..errors import ModelError, missing_models_extra

log = logging.getLogger(__name__)

HEAD_PREFIXES = ("", "proj.")
"""Where the projection's tensors sit: at the top of the head-only ``.pth`` (``weights/vitb_mlp_infonce.pth``),
under ``proj.`` in the hub's ``model.safetensors`` (the whole ``DINOText``: ``model.*`` DINOv2, ``clip_model.*``
OpenAI CLIP, ``logit_scale``, ``proj.*``)."""
# linear_layer2: upstream's old name of hidden_layers.0 (ProjectionLayer.load_state_dict renames it)
_HEAD_MODULES = ("linear_layer", "hidden_layers", "linear_layer2")


class ClipTextEncoder:
    """``encode(texts)`` → (N, D) float32 CLIP text embeddings, not normalised (D = 512 for ViT-B/16).

    The embedding is ``text_embeds`` of ``CLIPTextModelWithProjection``: the final-layer-normed end-of-text token
    times the text projection, i.e. OpenAI CLIP's ``encode_text``.
    """

    def __init__(self, model, tokenizer, name: str, output_space: str, device: torch.device):
        self.model = model.to(device).eval()
        self.tokenizer = tokenizer
        self.name, self.output_space, self.device = name, output_space, device
        self.dim = int(model.config.projection_dim)

    @torch.inference_mode()
    def encode(self, texts: list[str]) -> torch.Tensor:
        if not texts:
            raise ValueError("encode() needs at least one text")
        max_len = int(getattr(self.model.config, "max_position_embeddings", 77))  # CLIP's context length
        batch = self.tokenizer(
            list(texts), padding=True, truncation=True, max_length=max_len, return_tensors="pt"
        ).to(self.device)
        out = self.model(input_ids=batch["input_ids"], attention_mask=batch["attention_mask"]).text_embeds
        return out.float()


class Talk2DinoHead(nn.Module):
    """Talk2DINO projection: CLIP text (N, 512) → DINO space (N, 768): linear, then (tanh, linear) per hidden layer.

    Mirrors ``ProjectionLayer.project_clip_txt`` of lorebianchi98/Talk2DINO ``src/model.py`` (config
    ``configs/vitb_mlp_infonce.yaml``: act tanh, ``hidden_layer: True`` = one hidden layer, dino_embed_dim 768,
    clip_embed_dim 512), with the same parameter names so its checkpoints load unchanged. No output
    normalisation here: upstream normalises after the projection (see ``PromptEncoder``).
    """

    def __init__(self, clip_dim: int = 512, dino_dim: int = 768, n_hidden: int = 1):
        super().__init__()
        self.clip_dim, self.dino_dim = clip_dim, dino_dim
        self.linear_layer = nn.Linear(clip_dim, dino_dim)
        self.hidden_layers = nn.ModuleList([nn.Linear(dino_dim, dino_dim) for _ in range(n_hidden)])

    def forward(self, text_embeds: torch.Tensor) -> torch.Tensor:
        x = self.linear_layer(text_embeds.float())
        for layer in self.hidden_layers:
            x = layer(torch.tanh(x))
        return x


def head_state_from_checkpoint(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The projection's tensors (``linear_layer.*``, ``hidden_layers.<i>.*``) from either upstream layout.

    Looks at the top level first (head-only ``.pth``), then under ``proj.`` (hub ``model.safetensors``); other
    sub-models' tensors are never read. Returns {} when neither layout holds ``linear_layer.weight``.
    """
    for prefix in HEAD_PREFIXES:
        out = {}
        for key, value in state.items():
            rest = key[len(prefix):]
            if key.startswith(prefix) and rest.split(".", 1)[0] in _HEAD_MODULES:
                out[rest.replace("linear_layer2.", "hidden_layers.0.")] = value
        if "linear_layer.weight" in out:
            return out
    return {}


def _read_state(path: Path) -> dict[str, torch.Tensor]:
    if path.suffix == ".safetensors":
        try:
            from safetensors.torch import load_file
        except ImportError as exc:
            raise missing_models_extra("safetensors", f"reading {path.name}") from exc

        return load_file(str(path))
    state = torch.load(str(path), map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise TypeError(f"expected a state dict, got {type(state).__name__}")
    return state


def _head_dims(state: dict[str, torch.Tensor]) -> tuple[int, int, int]:
    """(clip_dim, dino_dim, n_hidden) of a projection state; ValueError when it is not a Talk2DINO MLP."""
    first = state["linear_layer.weight"]
    if first.ndim != 2:
        raise ValueError(f"linear_layer.weight has shape {tuple(first.shape)}, expected (dino_dim, clip_dim)")
    dino_dim, clip_dim = first.shape
    n_hidden = len({k.split(".")[1] for k in state if k.startswith("hidden_layers.")})
    return int(clip_dim), int(dino_dim), n_hidden


def load_talk2dino_head(folder: Path, name: str, device: torch.device) -> Talk2DinoHead:
    """Build the head from the first weight file in ``folder`` holding a projection; ModelError otherwise.

    Every error says which file is wrong and which ``kmvipe models pull`` replaces it.
    """
    fix = f"delete it and run 'kmvipe models pull {name}'"
    files = sorted(folder.glob("*.safetensors")) + sorted(folder.glob("*.pth"))
    for path in files:
        try:
            state = head_state_from_checkpoint(_read_state(path))
        except Exception as exc:  # noqa: BLE001 - corrupt file: say which and how to fix it
            raise ModelError(f"model '{name}': cannot read {path} ({type(exc).__name__}: {exc}); {fix}") from exc
        if not state:
            continue
        try:
            head = Talk2DinoHead(*_head_dims(state))
            head.load_state_dict(state, strict=True)
        except (RuntimeError, ValueError) as exc:
            detail = " ".join(str(exc).split())  # torch's multi-line message on one log line
            raise ModelError(f"model '{name}': {path} does not fit the Talk2DINO head ({detail}); {fix}") from exc
        return head.requires_grad_(False).to(device).eval()
    raise ModelError(f"model '{name}': no Talk2DINO projection weights in {folder}; run 'kmvipe models pull {name}'")
