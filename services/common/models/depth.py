"""Metric monocular depth (Depth Anything V2 metric through transformers)."""
from __future__ import annotations

import torch
from torch import nn

from .backbones import check_backbone_input


class MetricDepthModel:
    """``model(images)``: (B, 3, H, W) float32 ImageNet-normalised, sides multiples of 14 → (B, H, W) metres.

    Depth is resized back to the input size (bilinear); values are metric z-depth as the model predicts it.
    """

    def __init__(self, model, name: str, device: torch.device, dtype=torch.float32):
        self.model = model.to(device=device, dtype=dtype).eval()
        self.name, self.device, self.dtype = name, device, dtype
        self.patch_size = int(getattr(model.config.backbone_config, "patch_size", 14))

    @torch.inference_mode()
    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        check_backbone_input(images, self.patch_size)
        depth = self.model(pixel_values=images.to(self.device, self.dtype)).predicted_depth.float()
        if depth.shape[-2:] != images.shape[-2:]:
            depth = nn.functional.interpolate(depth[:, None], size=images.shape[-2:], mode="bilinear")[:, 0]
        return depth
