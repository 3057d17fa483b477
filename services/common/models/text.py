"""Text side of open-vocabulary queries: CLIP text tower and the Talk2DINO head into DINO space."""
from __future__ import annotations

import logging
from pathlib import Path

import torch
from torch import nn

from ..errors import ModelError, missing_models_extra

log = logging.getLogger(__name__)

# Talk2DINO's template for scene queries (architecture brief)
PROMPT = "There is {label} in the scene"


class ClipTextEncoder:
    """``encode(texts)`` → (N, D) float32 L2-normalised CLIP text embeddings (D = 512 for ViT-B/16)."""

    def __init__(self, model, tokenizer, name: str, output_space: str, device: torch.device):
        self.model = model.to(device).eval()
        self.tokenizer = tokenizer
        self.name, self.output_space, self.device = name, output_space, device
        self.dim = int(model.config.projection_dim)

    @torch.inference_mode()
    def encode(self, texts: list[str]) -> torch.Tensor:
        if not texts:
            raise ValueError("encode() needs at least one text")
        max_len = int(getattr(self.model.config, "max_position_embeddings", 77))
        batch = self.tokenizer(
            list(texts), padding=True, truncation=True, max_length=max_len, return_tensors="pt"
        ).to(self.device)
        out = self.model(input_ids=batch["input_ids"], attention_mask=batch["attention_mask"]).text_embeds
        return nn.functional.normalize(out.float(), dim=-1)


class Talk2DinoHead(nn.Module):
    """Talk2DINO projection: CLIP text (N, 512) → DINO space (N, 768): linear, tanh, linear.

    Mirrors ``ProjectionLayer.project_clip_txt`` of lorebianchi98/Talk2DINO (config ``vitb_mlp_infonce``:
    act=tanh, one hidden layer), with the same parameter names so its checkpoints load unchanged.
    """

    def __init__(self, clip_dim: int = 512, dino_dim: int = 768, n_hidden: int = 1):
        super().__init__()
        self.linear_layer = nn.Linear(clip_dim, dino_dim)
        self.hidden_layers = nn.ModuleList([nn.Linear(dino_dim, dino_dim) for _ in range(n_hidden)])

    def forward(self, text_embeds: torch.Tensor) -> torch.Tensor:
        x = self.linear_layer(text_embeds.float())
        for layer in self.hidden_layers:
            x = layer(torch.tanh(x))
        return x


def head_state_from_checkpoint(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The projection's tensors from a head-only ``.pth`` or the full hub ``model.safetensors``.

    Keys may carry a prefix (``proj.`` in the full model); the old name ``linear_layer2`` means
    ``hidden_layers.0``.
    """
    out = {}
    for key, value in state.items():
        for anchor in ("linear_layer.", "hidden_layers.", "linear_layer2."):
            idx = key.find(anchor)
            if idx >= 0 and (idx == 0 or key[idx - 1] == "."):
                if "clip" in key[:idx] or "model." == key[:idx]:  # belongs to another sub-model
                    continue
                out[key[idx:].replace("linear_layer2.", "hidden_layers.0.")] = value
                break
    return out


def _read_state(path: Path) -> dict[str, torch.Tensor]:
    if path.suffix == ".safetensors":
        try:
            from safetensors.torch import load_file
        except ImportError as exc:
            raise missing_models_extra("safetensors", f"reading {path.name}") from exc

        return load_file(str(path))
    return torch.load(str(path), map_location="cpu", weights_only=True)


def load_talk2dino_head(folder: Path, name: str, device: torch.device) -> Talk2DinoHead:
    """Build the head from the first weight file in ``folder`` holding a projection; ModelError otherwise."""
    files = sorted(folder.glob("*.safetensors")) + sorted(folder.glob("*.pth"))
    for path in files:
        try:
            state = head_state_from_checkpoint(_read_state(path))
        except Exception as exc:  # noqa: BLE001 - corrupt file: say which and how to fix it
            raise ModelError(
                f"model '{name}': cannot read {path} ({type(exc).__name__}: {exc}); "
                f"delete it and run 'kmvipe models pull {name}'"
            ) from exc
        if "linear_layer.weight" not in state:
            continue
        dino_dim, clip_dim = state["linear_layer.weight"].shape
        n_hidden = len({k.split(".")[1] for k in state if k.startswith("hidden_layers.")})
        head = Talk2DinoHead(clip_dim, dino_dim, n_hidden)
        try:
            head.load_state_dict(state, strict=True)
        except RuntimeError as exc:
            raise ModelError(f"model '{name}': {path} does not fit the Talk2DINO head: {exc}") from exc
        return head.requires_grad_(False).to(device).eval()
    raise ModelError(
        f"model '{name}': no Talk2DINO projection weights in {folder}; run 'kmvipe models pull {name}'"
    )
