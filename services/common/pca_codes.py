"""Translate PCA codes between two versions of a stream's basis (pure numpy / torch, no I/O; torch is never
imported here: a tensor can only exist where its caller already has it, and the mapstore works without it).

A basis (μ: (D,), V: (K, D) with orthonormal rows) codes a backbone feature f as z = V(f − μ) and decodes
it as f̂ = μ + Vᵀz (``services/features/core/pca.py``; the same layout travels in the ``PcaBasis`` message).
A code of basis A is moved into basis B by coding A's reconstruction with B:

    z_B = V_B (μ_A + V_Aᵀ z_A − μ_B) = M z_A + c,   M = V_B V_Aᵀ (K_B, K_A),   c = V_B (μ_A − μ_B) (K_B,)

so B's reconstruction of z_B is the orthogonal projection of A's reconstruction onto B's affine subspace
(exact when A's subspace lies in B's). The map is affine, so a weighted mean of codes maps to the weighted
mean of the mapped codes, and a weighted sum Σw·z maps to M Σw·z + c Σw.

Maps do not compose exactly (A → B → C projects twice; A → C once): consumers convert each keyframe's codes
from the version it was coded with straight to the latest one.
"""
from __future__ import annotations

import sys
from typing import NamedTuple, Protocol, TypeVar

import numpy as np


class HasBasis(Protocol):
    """Any basis record: the features core's, mapstore's or the ``PcaBasis`` wire message."""

    mean: np.ndarray
    components: np.ndarray


class CodeMap(NamedTuple):
    """The affine map z_B = matrix @ z_A + offset from the codes of basis A to those of basis B."""

    matrix: np.ndarray
    """(K_B, K_A) float64 V_B V_Aᵀ."""
    offset: np.ndarray
    """(K_B,) float64 V_B (μ_A − μ_B)."""

    @property
    def is_identity(self) -> bool:
        m = self.matrix
        return m.shape[0] == m.shape[1] and np.array_equal(m, np.eye(m.shape[0])) and not self.offset.any()


def identity_map(k: int) -> CodeMap:
    """The exact identity on K-d codes (no rounding: a basis mapped to itself by :func:`code_map` is I ± ε)."""
    return CodeMap(np.eye(k), np.zeros(k))


def code_map(source: HasBasis, target: HasBasis) -> CodeMap:
    """The map from ``source``'s codes to ``target``'s (both with mean (D,) and components (K, D)).

    Raises:
        ValueError: when the shapes are not (D,) / (K, D) or the two feature sizes D differ.
    """
    mu_a, v_a = _checked(source, "source")
    mu_b, v_b = _checked(target, "target")
    if mu_a.shape != mu_b.shape:
        raise ValueError(f"bases of different feature sizes: {mu_a.shape[0]} vs {mu_b.shape[0]}")
    return CodeMap(v_b @ v_a.T, v_b @ (mu_a - mu_b))


def _checked(basis: HasBasis, name: str) -> tuple[np.ndarray, np.ndarray]:
    mu = np.asarray(basis.mean, np.float64)
    v = np.asarray(basis.components, np.float64)
    if mu.ndim != 1 or v.ndim != 2 or v.shape[1] != mu.shape[0]:
        raise ValueError(f"{name} basis needs mean (D,) and components (K, D), got {mu.shape} and {v.shape}")
    return mu, v


Codes = TypeVar("Codes")  # np.ndarray or torch.Tensor


def convert_codes(codes: Codes, cmap: CodeMap) -> Codes:
    """Apply ``cmap`` to (..., K_A) codes → (..., K_B).

    numpy input: float32 result (float16 codes are widened first); torch input: same dtype (float16 → float32)
    and device as the input, computed in float64 on that device.
    """
    k_a = cmap.matrix.shape[1]
    if codes.shape[-1] != k_a:
        raise ValueError(f"codes must be (..., {k_a}), got {tuple(codes.shape)}")
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(codes, torch.Tensor):
        out_dtype = torch.float32 if codes.dtype in (torch.float16, torch.bfloat16) else codes.dtype
        m = torch.from_numpy(cmap.matrix).to(codes.device)
        c = torch.from_numpy(cmap.offset).to(codes.device)
        return (codes.double() @ m.T + c).to(out_dtype)
    return (np.asarray(codes, np.float64) @ cmap.matrix.T + cmap.offset).astype(np.float32)


def convert_sums(code_sums: np.ndarray, weight_sums: np.ndarray, cmap: CodeMap,
                 columns: slice = slice(None)) -> np.ndarray:
    """Apply ``cmap`` to weighted sums: (N, K_A) Σw·z and (N,) Σw → (N, K_B) float64 Σw·z_B = M Σw·z + c Σw;
    ``columns`` of K_B only, if given."""
    if code_sums.ndim != 2 or weight_sums.shape != code_sums.shape[:1]:
        raise ValueError(f"code sums (N, K) and weight sums (N,) expected, got {code_sums.shape}, {weight_sums.shape}")
    return (np.asarray(code_sums, np.float64) @ cmap.matrix[columns].T
            + np.asarray(weight_sums, np.float64)[:, None] * cmap.offset[columns])
