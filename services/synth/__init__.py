"""Synthetic world with exact ground truth: a textured room, furniture, a walking person, a moved chair.

Pure renderer and helpers are importable from here; the file writers live in :mod:`services.synth.io`.

    from services.synth import SynthConfig, SynthWorld
    world = SynthWorld(SynthConfig(n_frames=50))
    frame = world.render(0)  # rgb, depth, labels, instance, dynamic, world_from_cam, intrinsics, t_ns
"""

from services.synth.config import CAMERA_MODES, SynthConfig
from services.synth.geometry import (
    Correspondence,
    Projection,
    backproject,
    pixel_grid,
    project,
    sample_bilinear,
    static_correspondence,
    visible_in_j,
)
from services.synth.layout import LABEL_NAMES
from services.synth.oracle import label_vectors, oracle_features
from services.synth.render import InstanceBox, SynthFrame, SynthWorld

__all__ = [
    "CAMERA_MODES", "LABEL_NAMES", "Correspondence", "InstanceBox", "Projection", "SynthConfig", "SynthFrame",
    "SynthWorld", "backproject", "label_vectors", "oracle_features", "pixel_grid", "project", "sample_bilinear",
    "static_correspondence", "visible_in_j",
]
