"""Text → backbone-space query vectors: prompt templates, encoder + head, and an LRU cache.

A :class:`TextEmbedder` turns labels such as ``"red chair"`` into unit vectors (Q, D) float32 in the
embedding space of a backbone (``output_space``). Two encoders exist:

- :class:`PromptEncoder`: CLIP text tower → Talk2DINO head (both callables taking/returning tensors), as
  Talk2DINO's ``DINOText.build_text_embedding`` (``src/open_vocabulary_segmentation/models/dinotext/dinotext.py``):
  every label is written into each template, the raw CLIP embeddings of its prompts are averaged, the mean is
  projected once, and the projection is L2-normalised.
- :class:`OracleTextEncoder`: label names mapped to given vectors (the synthetic world's oracle labels), so
  retrieval can be checked exactly without a language model.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Protocol, Sequence

import numpy as np

if TYPE_CHECKING:
    import torch

# Talk2DINO's templates: ``sub_imagenet_template`` of ``src/open_vocabulary_segmentation/datasets/templates.py``
# (from TCL), which its evaluation configs (``configs/*/eval_*.yml``: ``template: sub_imagenet_template``) and
# ``demo.py`` use; upstream writes ``{}`` where we write ``{label}``.
DEFAULT_TEMPLATES: tuple[str, ...] = (
    "itap of a {label}.",
    "a bad photo of a {label}.",
    "a origami {label}.",
    "a photo of the large {label}.",
    "a {label} in a video game.",
    "art of the {label}.",
    "a photo of the small {label}.",
)


class UnknownLabel(ValueError):
    """The oracle encoder was asked for a label it does not know (the message lists the known ones)."""


class TextEncoder(Protocol):
    """Labels → (Q, D) float32 unit vectors in ``output_space``."""

    name: str
    output_space: str

    def encode(self, labels: Sequence[str]) -> np.ndarray: ...


def normalise_label(text: str) -> str:
    """The cache key of a label: stripped, inner whitespace collapsed, lower case."""
    return " ".join(str(text).split()).lower()


def _unit_rows(x: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(x, axis=1, keepdims=True)
    return (x / np.maximum(norms, 1e-12)).astype(np.float32)


class PromptEncoder:
    """CLIP text tower + text head with prompt ensembling.

    ``text_model.encode(prompts) -> (P, C) tensor``: CLIP text embeddings as the head was trained on them (raw,
    not normalised, for Talk2DINO); ``head(tensor (Q, C)) -> (Q, D)`` (backbone space). ``templates`` contain
    ``{label}``.
    """

    def __init__(self, text_model, head: Callable[[torch.Tensor], torch.Tensor], templates: Sequence[str],
                 name: str, output_space: str):
        if not templates or any("{label}" not in t for t in templates):
            raise ValueError(f"every template needs a '{{label}}' placeholder, got {list(templates)!r}")
        self.text_model, self.head, self.templates = text_model, head, tuple(templates)
        self.name, self.output_space = name, output_space

    def encode(self, labels: Sequence[str]) -> np.ndarray:
        """(Q,) labels → (Q, D) float32 unit vectors."""
        import torch  # here, not at the top: the oracle encoder and the gateway around it run without torch

        if not labels:
            raise ValueError("encode() needs at least one label")
        prompts = [t.format(label=label) for label in labels for t in self.templates]
        with torch.inference_mode():
            clip = self.text_model.encode(prompts).float()  # (Q·T, C)
            # upstream averages in CLIP space and projects the mean (the head is non-linear: not the mean of
            # projections)
            mean = clip.reshape(len(labels), len(self.templates), -1).mean(dim=1)  # (Q, C)
            return _unit_rows(self.head(mean).float().cpu().numpy())  # (Q, D)


class OracleTextEncoder:
    """Maps label names to given vectors: ``names`` (L,) and ``vectors`` (L, D) float32."""

    def __init__(self, names: Sequence[str], vectors: np.ndarray, output_space: str = "oracle"):
        vectors = np.asarray(vectors, np.float32)
        if vectors.ndim != 2 or vectors.shape[0] != len(names):
            raise ValueError(f"oracle needs (L, D) vectors for L={len(names)} names, got {vectors.shape}")
        self.table = {normalise_label(n): v for n, v in zip(names, _unit_rows(vectors))}
        self.name, self.output_space = "oracle", output_space
        self.dim = int(vectors.shape[1])

    def encode(self, labels: Sequence[str]) -> np.ndarray:
        missing = [label for label in labels if normalise_label(label) not in self.table]
        if missing:
            raise UnknownLabel(f"oracle text encoder knows no label {missing[0]!r}; known: {', '.join(sorted(self.table))}")
        return np.stack([self.table[normalise_label(label)] for label in labels])


@dataclass(frozen=True)
class CacheInfo:
    """Counters of the embedding cache."""

    hits: int
    misses: int
    size: int


class TextEmbedder:
    """An encoder with an LRU cache of per-label vectors (keys: :func:`normalise_label`).

    ``capacity``: labels kept; the least recently used is evicted first. Not thread-safe: callers serialise.
    """

    def __init__(self, encoder: TextEncoder, capacity: int = 1024):
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.encoder, self.capacity = encoder, capacity
        self._cache: OrderedDict[str, np.ndarray] = OrderedDict()
        self.hits = self.misses = 0

    @property
    def output_space(self) -> str:
        return self.encoder.output_space

    def embed(self, labels: Sequence[str]) -> np.ndarray:
        """(Q,) labels → (Q, D) float32 unit vectors; only labels not in the cache reach the encoder."""
        keys = [normalise_label(label) for label in labels]
        todo = list(dict.fromkeys(k for k in keys if k not in self._cache))
        self.hits += len(keys) - sum(1 for k in keys if k in todo)
        self.misses += len(todo)
        if todo:
            for key, vec in zip(todo, self.encoder.encode(todo)):
                self._cache[key] = np.asarray(vec, np.float32)
        out = np.stack([self._cache[k] for k in keys])
        for key in keys:
            self._cache.move_to_end(key)
        while len(self._cache) > self.capacity:
            self._cache.popitem(last=False)
        return out

    def info(self) -> CacheInfo:
        return CacheInfo(self.hits, self.misses, len(self._cache))
