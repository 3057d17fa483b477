"""Metric monocular depth (Depth Anything V2 metric through transformers)."""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .backbones import check_backbone_input


class MetricDepthModel:
    """``model(images)``: (B, 3, H, W) float32 ImageNet-normalised array, sides multiples of 14 → (B, H, W)
    float32 array of metres.

    Depth is resized back to the input size (bilinear); values are metric z-depth as the model predicts it.
    """

    def __init__(self, model, name: str, device: torch.device, dtype=torch.float32):
        self.model = model.to(device=device, dtype=dtype).eval()
        self.name, self.device, self.dtype = name, device, dtype
        self.patch_size = int(getattr(model.config.backbone_config, "patch_size", 14))

    @torch.inference_mode()
    def __call__(self, images: np.ndarray) -> np.ndarray:
        check_backbone_input(images, self.patch_size)
        x = torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)).to(self.device, self.dtype)
        depth = self.model(pixel_values=x).predicted_depth.float()
        if depth.shape[-2:] != x.shape[-2:]:
            depth = nn.functional.interpolate(depth[:, None], size=x.shape[-2:], mode="bilinear")[:, 0]
        return depth.cpu().numpy()
