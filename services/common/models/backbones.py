"""Dense feature backbones: normalised images in, patch-feature maps out.

Every backbone is called the same way, whatever runs it (transformers/torch or onnxruntime):
``backbone(images)`` with ``images`` (B, 3, H, W) float32, ImageNet-normalised RGB, H and W multiples of
``patch_size`` → (B, C, H/patch, W/patch) float32 patch tokens after the final layer norm (CLS and register
tokens dropped).
"""
from __future__ import annotations

import logging

import numpy as np
import torch

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def check_backbone_input(images: torch.Tensor, patch_size: int) -> None:
    """Raise ValueError unless ``images`` is (B, 3, H, W) with H, W multiples of ``patch_size``."""
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"backbone input must be (B, 3, H, W), got {tuple(images.shape)}")
    if images.shape[2] % patch_size or images.shape[3] % patch_size:
        raise ValueError(f"backbone input sides must be multiples of {patch_size}, got {tuple(images.shape[2:])}")


def tokens_to_map(tokens: torch.Tensor, n_prefix: int, h: int, w: int) -> torch.Tensor:
    """(B, n_prefix + h·w, C) tokens → (B, C, h, w) map of the patch tokens."""
    b, _, c = tokens.shape
    return tokens[:, n_prefix:].reshape(b, h, w, c).permute(0, 3, 1, 2).contiguous()


class TorchDinoBackbone:
    """A transformers ``Dinov2Model`` / ``Dinov2WithRegistersModel`` as a backbone.

    ``dtype`` is the compute precision (float32 on CPU; bf16/fp16 on CUDA); outputs are always float32.
    """

    runtime = "torch"

    def __init__(self, model, name: str, output_space: str, device: torch.device, dtype=torch.float32):
        self.model = model.to(device=device, dtype=dtype).eval()
        self.name, self.output_space = name, output_space
        self.device, self.dtype = device, dtype
        cfg = model.config
        self.patch_size = int(cfg.patch_size)
        self.dim = int(cfg.hidden_size)
        self.n_prefix = 1 + int(getattr(cfg, "num_register_tokens", 0) or 0)

    @torch.inference_mode()
    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        check_backbone_input(images, self.patch_size)
        h, w = images.shape[2] // self.patch_size, images.shape[3] // self.patch_size
        out = self.model(pixel_values=images.to(self.device, self.dtype)).last_hidden_state
        return tokens_to_map(out.float(), self.n_prefix, h, w)


class OnnxDinoBackbone:
    """An onnxruntime session whose single output is (B, 1 + h·w, C) layer-normed tokens."""

    runtime = "onnx"

    def __init__(self, session, name: str, output_space: str, dim: int, patch_size: int = 14):
        self.session = session
        self.name, self.output_space = name, output_space
        self.dim, self.patch_size, self.n_prefix = dim, patch_size, 1
        self.input_name = session.get_inputs()[0].name
        self.device = torch.device("cpu")

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        check_backbone_input(images, self.patch_size)
        h, w = images.shape[2] // self.patch_size, images.shape[3] // self.patch_size
        x = np.ascontiguousarray(images.detach().to("cpu", torch.float32).numpy())
        tokens = torch.from_numpy(self.session.run(None, {self.input_name: x})[0])
        return tokens_to_map(tokens, self.n_prefix, h, w).to(images.device)


def normalise_rgb(image_u8: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """(H, W, 3) uint8 RGB → (1, 3, H, W) float32 ImageNet-normalised tensor on ``device``."""
    if image_u8.ndim != 3 or image_u8.shape[2] != 3 or image_u8.dtype != np.uint8:
        raise ValueError(f"expected (H, W, 3) uint8 RGB, got {image_u8.shape} {image_u8.dtype}")
    x = torch.from_numpy(np.ascontiguousarray(image_u8)).to(device).permute(2, 0, 1)[None].float() / 255.0
    mean = torch.tensor(IMAGENET_MEAN, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=x.device).view(1, 3, 1, 1)
    return (x - mean) / std
