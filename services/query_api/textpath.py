"""The language path of the gateway: builds the configured text encoder lazily and checks that text
vectors land in the map's backbone space (else refuses, saying what to install)."""
from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from ..common.errors import KmVipeError, ModelError
from ..common.models import ModelStore, get_entry, text_head_for
from ..common.query_support import ORACLE_WHY
from .config import QuerySettings
from .core.text import OracleTextEncoder, PromptEncoder, TextEmbedder

log = logging.getLogger(__name__)


class TextUnavailable(KmVipeError):
    """Text queries cannot be answered by this gateway (no encoder configured or its models are missing)."""


class SpaceMismatch(KmVipeError):
    """Text vectors live in another embedding space than the map's features."""


def oracle_encoder(cfg: QuerySettings) -> OracleTextEncoder:
    """Oracle encoder from ``cfg.oracle_vectors`` (.npz: names, vectors) or the synthetic world's labels."""
    if cfg.oracle_vectors is not None:
        with np.load(Path(cfg.oracle_vectors)) as data:
            return OracleTextEncoder([str(n) for n in data["names"]], data["vectors"], cfg.oracle_space)
    if cfg.oracle_synth_seed is not None:
        from ..synth import LABEL_NAMES, label_vectors  # only for the synthetic demo

        vectors = label_vectors(len(LABEL_NAMES), cfg.oracle_synth_dim, cfg.oracle_synth_seed)
        return OracleTextEncoder(LABEL_NAMES, vectors, cfg.oracle_space)
    raise TextUnavailable("text_encoder=oracle needs KMVIPE_QUERY_ORACLE_VECTORS or KMVIPE_QUERY_ORACLE_SYNTH_SEED")


def clip_encoder(cfg: QuerySettings) -> PromptEncoder:
    """CLIP text tower + text head from the model registry (local files only; never downloads)."""
    from ..common.models.loaders import load_text_encoder, load_text_head

    store = ModelStore(cfg.models_dir)
    try:
        text_model = load_text_encoder(cfg.text_model, store, cfg.device)
        head = load_text_head(cfg.text_head, store, cfg.device)
    except ModelError as exc:
        raise TextUnavailable(f"text queries need the language models: {exc}") from exc
    if text_model.dim != head.clip_dim:  # caught here, not as a matrix-size error on the first query
        raise TextUnavailable(f"the text head '{cfg.text_head}' reads {head.clip_dim}-d CLIP embeddings but "
                              f"'{cfg.text_model}' writes {text_model.dim}-d ones; install the pair the registry "
                              f"names: 'kmvipe models pull {cfg.text_model}' and 'kmvipe models pull {cfg.text_head}'")
    entry = get_entry(cfg.text_head)
    return PromptEncoder(text_model, head, cfg.templates, f"{cfg.text_model}+{cfg.text_head}", entry.output_space)


class TextPath:
    """Thread-safe lazy :class:`TextEmbedder`; a load failure is remembered and reported on every request."""

    def __init__(self, cfg: QuerySettings, embedder: TextEmbedder | None = None):
        self.cfg = cfg
        self._embedder = embedder
        self._error: TextUnavailable | None = None
        self._lock = threading.Lock()

    def loaded(self) -> TextEmbedder | None:
        """The embedder if it is built already (never triggers loading)."""
        return self._embedder

    def embedder(self) -> TextEmbedder:
        with self._lock:
            if self._embedder is None and self._error is None:
                try:
                    self._embedder = TextEmbedder(self._build(), self.cfg.embedding_cache)
                    log.info("text encoder ready", extra={"encoder": self._embedder.encoder.name,
                                                          "space": self._embedder.output_space})
                except TextUnavailable as exc:
                    self._error = exc
            if self._error is not None:
                raise self._error
            return self._embedder  # type: ignore[return-value]

    def _build(self):
        if self.cfg.text_encoder == "none":
            raise TextUnavailable("text queries are switched off (KMVIPE_QUERY_TEXT_ENCODER=none); use query by example")
        if self.cfg.text_encoder == "oracle":
            return oracle_encoder(self.cfg)
        return clip_encoder(self.cfg)

    def availability(self, map_space: str) -> tuple[bool, str]:
        """Whether text queries can score a map in ``map_space``, and why (or why not). Builds the encoder, so the
        first call pays for loading it; a load failure is remembered, as for queries."""
        try:
            emb = self.embedder()
        except TextUnavailable as exc:
            return False, str(exc)
        name = emb.encoder.name
        if not map_space:
            return False, f"the map has no features yet ({name} is ready)"
        if emb.output_space != map_space:
            return False, mismatch_message(emb.output_space, map_space, self.cfg.models_dir)
        if self.is_oracle():
            return True, ORACLE_WHY
        return True, f"{name} maps text into '{map_space}'"

    def encoder_name(self) -> str:
        """The loaded encoder's name ("" before it is loaded)."""
        return self._embedder.encoder.name if self._embedder is not None else ""

    def is_oracle(self) -> bool:
        return self.cfg.text_encoder == "oracle"

    def embed(self, texts: list[str], map_space: str) -> np.ndarray:
        """(Q,) texts → (Q, D) float32 vectors in ``map_space``; SpaceMismatch / TextUnavailable otherwise."""
        emb = self.embedder()
        if map_space and emb.output_space != map_space:
            raise SpaceMismatch(mismatch_message(emb.output_space, map_space, self.cfg.models_dir))
        with self._lock:
            return emb.embed(texts)


def mismatch_message(text_space: str, map_space: str, models_dir: Path | None) -> str:
    """Why text vectors in ``text_space`` cannot score a map in ``map_space``, and what to install."""
    msg = f"this map's features are in '{map_space}' but the text encoder writes into '{text_space}'. "
    head = text_head_for(map_space)
    if head is not None:
        store = ModelStore(models_dir)
        where = "installed" if store.find(head) else f"install it: {store.status(head).needs}"
        return msg + f"Use the text head '{head.name}' for this map (KMVIPE_QUERY_TEXT_HEAD={head.name}; {where})."
    return msg + (f"No registered text head maps text into '{map_space}'. Rebuild the map with the backbone "
                  f"the head targets ('{text_space}': set the features service's backbone to dinov2-vitb14-reg after "
                  "'kmvipe models pull dinov2-vitb14-reg'), or query by example (POST .../query/example).")
