"""Backbones that run in torch (transformers' DINOv2 models), behind the array interface of :mod:`.backbones`."""
from __future__ import annotations

import numpy as np
import torch

from .backbones import check_backbone_input, tokens_to_map


class TorchDinoBackbone:
    """A transformers ``Dinov2Model`` / ``Dinov2WithRegistersModel`` as a backbone.

    ``dtype`` is the compute precision (float32 on CPU; bf16/fp16 on CUDA); outputs are always float32 arrays.
    """

    runtime = "torch"

    def __init__(self, model, name: str, output_space: str, device: torch.device, dtype=torch.float32):
        self.model = model.to(device=device, dtype=dtype).eval()
        self.name, self.output_space = name, output_space
        self.device, self.dtype = device, dtype
        self.device_type = device.type
        cfg = model.config
        self.patch_size = int(cfg.patch_size)
        self.dim = int(cfg.hidden_size)
        self.n_prefix = 1 + int(getattr(cfg, "num_register_tokens", 0) or 0)

    @torch.inference_mode()
    def __call__(self, images: np.ndarray) -> np.ndarray:
        check_backbone_input(images, self.patch_size)
        h, w = images.shape[2] // self.patch_size, images.shape[3] // self.patch_size
        x = torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)).to(self.device, self.dtype)
        out = self.model(pixel_values=x).last_hidden_state
        return tokens_to_map(out.float().cpu().numpy(), self.n_prefix, h, w)
