"""A test double of the DINO backbone for the synthetic world: exact per-label features instead of a model.

For the frame being processed it renders the synthetic world's label map (the same world ingest's ``synth:``
source plays) and returns ``services.synth.oracle_features`` of the labels under each patch: unit vectors,
one per label (``label_vectors(L, dim, seed)``), plus a little per-pixel noise. The query gateway's oracle
text encoder (``KMVIPE_QUERY_TEXT_ENCODER=oracle``, ``KMVIPE_QUERY_ORACLE_SYNTH_SEED`` / ``_DIM``) maps each
label name to the same vector, so the whole pipeline can be scored against exact semantic ground truth without
a model. It is *not* a feature extractor: it only knows the frames of the synthetic world it was built for.

A backbone sees only the image, not which frame it came from, so the service announces the frame's ``seq``
with :meth:`SynthOracleBackbone.set_frame` before handing the frame to the pipeline.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from ..synth import LABEL_NAMES, SynthWorld, label_vectors, oracle_features
from ..synth.spec import config_from_spec

log = logging.getLogger(__name__)

ORACLE_BACKBONE = "synth-oracle"
"""The features service's ``backbone`` setting that selects this double."""


@dataclass(frozen=True)
class OracleParams:
    """How the oracle features are made (must match the gateway's oracle text encoder)."""

    source: str
    """``synth:...`` spec of the stream ingest plays (same string as ``KMVIPE_INGEST_SOURCE``)."""
    seed: int = 0
    """Seed of ``label_vectors`` (the gateway's ``KMVIPE_QUERY_ORACLE_SYNTH_SEED``)."""
    dim: int = 64
    """Feature dimension (the gateway's ``KMVIPE_QUERY_ORACLE_SYNTH_DIM``)."""
    noise: float = 0.1
    """Per-pixel noise norm relative to the unit label vector (0 = exact label vectors)."""
    patch_size: int = 8
    """Pixels per output cell of the working image: 8 makes the patch grid the 1/8 grid itself."""
    seconds: float = 0.0
    """Time each call takes at least, like a real backbone on a slow CPU (tests of semantics falling behind)."""
    output_space: str = "oracle"
    """Embedding-space id written into the PCA basis (the gateway's ``KMVIPE_QUERY_ORACLE_SPACE``)."""


class SynthOracleBackbone:
    """Callable like a backbone: (B, 3, H, W) normalised images → (B, dim, H/p, W/p) float32 oracle features.

    Every image in the batch is taken to show the frame announced by :meth:`set_frame` (the features pipeline
    calls the backbone once per keyframe and scale, with B = 1).
    """

    runtime = "oracle"
    device_type = "cpu"

    def __init__(self, params: OracleParams):
        self.params = params
        self.world = SynthWorld(config_from_spec(params.source))
        self.vectors = label_vectors(len(LABEL_NAMES), params.dim, params.seed)  # (L, dim) unit rows
        self.name, self.output_space = ORACLE_BACKBONE, params.output_space
        self.patch_size, self.dim, self.n_prefix = params.patch_size, params.dim, 0
        self._seq: int | None = None
        self._labels: tuple[int, np.ndarray] | None = None  # (seq, (H0, W0) int32 label map) of the last render

    def set_frame(self, seq: int) -> None:
        """The frame (0-based index into the synthetic sequence) the next calls show."""
        if not 0 <= seq < len(self.world):
            raise ValueError(f"frame seq {seq} is outside the synthetic sequence [0, {len(self.world)})")
        self._seq = int(seq)

    def labels(self, seq: int) -> np.ndarray:
        """(H0, W0) int32 label map of frame ``seq`` at the source resolution (rendered once per frame)."""
        if self._labels is None or self._labels[0] != seq:
            self._labels = (seq, self.world.render(seq).labels)
        return self._labels[1]

    def __call__(self, images: np.ndarray) -> np.ndarray:
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"backbone input must be (B, 3, H, W), got {tuple(images.shape)}")
        if self._seq is None:
            raise RuntimeError("the synthetic oracle was not told which frame it is looking at (set_frame)")
        if self.params.seconds > 0:
            time.sleep(self.params.seconds)
        h, w = images.shape[2] // self.patch_size, images.shape[3] // self.patch_size
        cell_labels = sample_patch_labels(self.labels(self._seq), h, w)
        rng = np.random.default_rng([self.params.seed, self._seq, h, w])
        feats = oracle_features(cell_labels, self.vectors, self.params.noise, rng)  # (h, w, dim)
        out = np.ascontiguousarray(feats.transpose(2, 0, 1), dtype=np.float32)[None]
        return np.repeat(out, images.shape[0], axis=0)


def sample_patch_labels(labels: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest label at the centre of each cell of an (h, w) grid laid over the whole (H0, W0) label map.

    Cell (r, c) spans the fraction [c/w, (c+1)/w) of the image width, so its centre is at source pixel
    ``(c + 0.5)·W0/w − 0.5`` (pixel centres at integers); same along rows. Returns (h, w) int32.
    """
    if labels.ndim != 2 or h < 1 or w < 1:
        raise ValueError(f"labels must be (H0, W0) and the grid at least 1x1, got {labels.shape}, {h}x{w}")
    rows = np.clip(np.rint((np.arange(h) + 0.5) * labels.shape[0] / h - 0.5), 0, labels.shape[0] - 1).astype(int)
    cols = np.clip(np.rint((np.arange(w) + 0.5) * labels.shape[1] / w - 0.5), 0, labels.shape[1] - 1).astype(int)
    return labels[np.ix_(rows, cols)].astype(np.int32)
