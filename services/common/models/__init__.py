"""Model registry shared by features and query_api: entries, on-disk store, loaders, tiny test models."""
from .registry import (
    DEFAULT_BACKBONE,
    DEFAULT_TEXT,
    DEFAULT_TEXT_HEAD,
    HubSource,
    ModelEntry,
    ModelKind,
    PypiSource,
    all_entries,
    get_entry,
    text_head_for,
)
from .store import ModelLocation, ModelStatus, ModelStore, install_hint

__all__ = [
    "DEFAULT_BACKBONE", "DEFAULT_TEXT", "DEFAULT_TEXT_HEAD", "HubSource", "ModelEntry", "ModelKind", "PypiSource",
    "all_entries", "get_entry", "text_head_for", "ModelLocation", "ModelStatus", "ModelStore", "install_hint",
]  # fmt: skip
