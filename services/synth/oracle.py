"""Oracle semantic features: one unit vector per label plus per-pixel noise.

Semantic tests use these in place of DINO features, so retrieval can be checked exactly without a model.
"""

from __future__ import annotations

import numpy as np


def label_vectors(n_labels: int, dim: int, seed: int) -> np.ndarray:
    """Unit vectors (L, D) float32, one per label, deterministic in ``seed``.

    Orthonormal when ``n_labels <= dim`` (QR of a Gaussian matrix), else independent random unit vectors.
    """
    if n_labels < 1 or dim < 1:
        raise ValueError(f"n_labels and dim must be >= 1, got {n_labels}, {dim}")
    rng = np.random.default_rng([seed, n_labels, dim])
    gauss = rng.standard_normal((max(n_labels, dim), dim))
    if n_labels <= dim:
        q, _ = np.linalg.qr(gauss[:dim].T)  # (D, D) orthonormal columns
        vecs = q[:, :n_labels].T
    else:
        vecs = gauss[:n_labels]
    return (vecs / np.linalg.norm(vecs, axis=1, keepdims=True)).astype(np.float32)


def oracle_features(labels: np.ndarray, vectors: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Per-pixel unit features (H, W, D) float32: normalise(vectors[label] + noise · g).

    labels: (H, W) int indices into ``vectors`` (L, D); g ~ N(0, I / D), so ``noise`` is the ratio of the
    noise norm to the (unit) signal norm; rng: the generator that draws g.
    """
    labels = np.asarray(labels)
    vectors = np.asarray(vectors, np.float32)
    if labels.ndim != 2 or vectors.ndim != 2:
        raise ValueError(f"labels must be (H, W) and vectors (L, D), got {labels.shape}, {vectors.shape}")
    if labels.size and (labels.min() < 0 or labels.max() >= vectors.shape[0]):
        raise ValueError(f"labels must lie in [0, {vectors.shape[0]}), got [{labels.min()}, {labels.max()}]")
    if noise < 0:
        raise ValueError(f"noise must be >= 0, got {noise}")
    dim = vectors.shape[1]
    feats = vectors[labels] + noise * rng.standard_normal((*labels.shape, dim)).astype(np.float32) / np.sqrt(dim)
    return (feats / np.linalg.norm(feats, axis=-1, keepdims=True)).astype(np.float32)
