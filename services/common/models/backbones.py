"""Dense feature backbones: normalised images in, patch-feature maps out.

Every backbone is called the same way, whatever runs it (onnxruntime, transformers/torch or the synthetic
oracle): ``backbone(images)`` with ``images`` a numpy (B, 3, H, W) float32 array, ImageNet-normalised RGB, H and
W multiples of ``patch_size`` → a numpy (B, C, H/patch, W/patch) float32 array of patch tokens after the final
layer norm (CLS and register tokens dropped). ``device_type`` says where it computes ("cpu" or "cuda").

Arrays, not tensors, at this interface: the features service's CPU path (onnxruntime) then runs without torch,
~280 MB less per process (docs/BENCHMARKS.md, "Features without torch"). The torch backbones
(:mod:`.torch_backbones`) move the image to their device and the tokens back, a few MB per keyframe.
"""
from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def check_backbone_input(images: np.ndarray, patch_size: int) -> None:
    """Raise ValueError unless ``images`` is (B, 3, H, W) with H, W multiples of ``patch_size``."""
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"backbone input must be (B, 3, H, W), got {tuple(images.shape)}")
    if images.shape[2] % patch_size or images.shape[3] % patch_size:
        raise ValueError(f"backbone input sides must be multiples of {patch_size}, got {tuple(images.shape[2:])}")


def tokens_to_map(tokens: np.ndarray, n_prefix: int, h: int, w: int) -> np.ndarray:
    """(B, n_prefix + h·w, C) tokens → (B, C, h, w) float32 map of the patch tokens."""
    b, _, c = tokens.shape
    return np.ascontiguousarray(tokens[:, n_prefix:].reshape(b, h, w, c).transpose(0, 3, 1, 2), dtype=np.float32)


class OnnxDinoBackbone:
    """An onnxruntime session whose single output is (B, 1 + h·w, C) layer-normed tokens."""

    runtime = "onnx"
    device_type = "cpu"

    def __init__(self, session, name: str, output_space: str, dim: int, patch_size: int = 14):
        self.session = session
        self.name, self.output_space = name, output_space
        self.dim, self.patch_size, self.n_prefix = dim, patch_size, 1
        self.input_name = session.get_inputs()[0].name

    def __call__(self, images: np.ndarray) -> np.ndarray:
        check_backbone_input(images, self.patch_size)
        h, w = images.shape[2] // self.patch_size, images.shape[3] // self.patch_size
        x = np.ascontiguousarray(images, dtype=np.float32)
        return tokens_to_map(self.session.run(None, {self.input_name: x})[0], self.n_prefix, h, w)


def normalise_rgb(image_u8: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB → (1, 3, H, W) float32 ImageNet-normalised array."""
    if image_u8.ndim != 3 or image_u8.shape[2] != 3 or image_u8.dtype != np.uint8:
        raise ValueError(f"expected (H, W, 3) uint8 RGB, got {image_u8.shape} {image_u8.dtype}")
    x = image_u8.astype(np.float32) / np.float32(255.0)
    x = (x - np.asarray(IMAGENET_MEAN, np.float32)) / np.asarray(IMAGENET_STD, np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])
