"""Where torch work runs: ``auto`` means CUDA when present, else the CPU."""
from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

# what a GPU driver puts on the machine: NVIDIA's (CUDA) and AMD's (ROCm, which torch exposes as torch.cuda)
_GPU_DRIVER_PATHS = ("/proc/driver/nvidia/version", "/dev/nvidia0", "/dev/kfd")


def resolve_device(name: str = "auto") -> "torch.device":
    """``auto`` → CUDA when available, else CPU; anything else is passed to ``torch.device``."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def device_type(name: str = "auto") -> str:
    """``resolve_device(name).type``, without importing torch where the answer is the CPU anyway: a process whose
    models run on onnxruntime then never loads torch (features: ~280 MB). ``auto`` asks torch only where a GPU driver is
    installed (torch.cuda needs one) or torch is loaded already."""
    if name == "cpu":
        return "cpu"
    if name == "auto" and "torch" not in sys.modules and not any(os.path.exists(p) for p in _GPU_DRIVER_PATHS):
        return "cpu"
    return resolve_device(name).type
