"""Parameters of the map core (frozen dataclasses) and the service settings.

Algorithm parameters are plain frozen dataclasses so the pure core can take them without
importing pydantic; `MapstoreSettings` (env prefix ``KMVIPE_MAPSTORE_``, or ``[mapstore]`` of the ``KMVIPE_CONFIG``
file) builds them once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from ..common.config_file import KmVipeSettings
from ..common.keys import ALL_STREAMS


@dataclass(frozen=True)
class PointParams:
    """Which keyframe cells become map points and with what weight."""

    min_disparity: float = 1e-6
    """Cells with disparity at or below this are unknown (disparity 0 = unknown)."""
    dynamic_threshold: float = 0.5
    """A cell whose static (ARK) weight is below this is marked dynamic and left out."""
    min_weight: float = 0.1
    """Cells whose weight (confidence × static × consistency) is below this are left out."""
    max_depth_ratio: float = 20.0
    """Cells deeper than this × the keyframe's median depth are left out: near-zero disparities (sky, the
    horizon) are where monocular depth is least certain, and their points would land far outside the map."""


@dataclass(frozen=True)
class ConsistencyParams:
    """Multi-view depth consistency between a keyframe and its temporal neighbours."""

    neighbours: int = 2
    """Keyframes on each side (by id) a keyframe's depth is checked against; 0 disables the check."""
    rel_tolerance: float = 0.05
    """Depths agree when |z_projected − z_neighbour| ≤ rel_tolerance · z_neighbour."""
    unverified: float = 1.0
    """Consistency of a point no neighbour can check (outside their views, or occluded in all)."""


@dataclass(frozen=True)
class CarvingParams:
    """Free-space carving: a keyframe's point that later keyframes see through (a surface clearly behind it) has
    moved away and is left out. Only *later* keyframes vote, so an object that arrived somewhere (contradicting
    earlier views of the empty place) stays: the most recent observations are the current truth."""

    later_keyframes: int = 16
    """Keyframes after a keyframe (by id) whose depths may carve its points; 0 disables carving. Also how far
    back a changed keyframe re-checks earlier ones, so it bounds the work per update."""
    recent_views: int = 3
    """Per point, the most recent later keyframes that see it (agree or see through it) that decide."""
    min_violations: int = 2
    """A point is carved when at least this many of its deciding views see through it, and they outnumber the
    views that agree with it."""
    free_margin: float = 0.1
    """A view sees through a point at depth z when the nearest surface around its projection is beyond
    (1 + free_margin)·z: relative, so it holds for maps with no metric scale."""
    agree_tolerance: float = 0.05
    """A view agrees with a point when |z − z_view| ≤ agree_tolerance · z_view at its projection."""
    footprint: Literal["cell", "corners", "3x3"] = "corners"
    """Cells around a point's projection whose nearest surface must lie behind it: "cell" (the one it rounds to),
    "corners" (the 2×2 whose centres surround it) or "3x3". More than one cell keeps a point at a depth edge from
    being carved by a projection that rounds onto the background."""
    min_reliability: float = 0.1
    """A view's cell carves only if its flow confidence × static weight is at least this (a moving person or a
    badly tracked cell says nothing about free space); the default is the weight a cell needs to be a map point
    (PointParams.min_weight): evidence of free space is trusted as much as evidence of a surface."""
    semantic: bool = True
    """Use the keyframes' codes as evidence too: a later view that sees something else (codes that disagree) at
    about a point's depth votes like one that sees through it. Monocular depth over a vacated place is pulled
    towards the object that stood there, so depth alone rarely sees through it."""
    max_code_cosine: float = 0.2
    """A view's codes disagree with a point's when the cosine of the two (in the newest PCA space, centred) is
    below this in every cell of the footprint. Oracle codes of different labels are near-orthogonal (≈ 0), of the
    same label ≈ 1; real DINO codes of one surface seen from far-apart views can fall well below 1: on KITTI 07,
    0.5 carved 12 % of the map beyond depth-only carving, 0.2 carved 4.9 %, while the synthetic world's moved chair
    is carved the same at 0.2 and 0.5 (docs/BENCHMARKS.md, map quality)."""
    min_code_reliability: float = 0.0
    """A view's disagreeing codes contradict a point only where its flow confidence × static weight is at least
    this. 0 (default): BA's ARK weight is low exactly where an object left (the place changed between views), so
    gating the codes by it would silence the evidence (48-frame synth: old chair place 0.22 present at 0, 0.27 at
    0.05, 0.40 at 0.1); a nearer moving person is kept from carving what is behind it by occluder_margin."""
    occluder_margin: float = 0.3
    """A view whose nearest surface around a point's projection is nearer than (1 − occluder_margin)·z is an
    occluder in front of the point and its codes say nothing about it (a person walking past is much nearer than
    the wall behind); within that, disagreeing codes contradict the point."""


@dataclass(frozen=True)
class FusionParams:
    """Voxel fusion of keyframe points."""

    voxel_size: float = 0.02
    """Voxel edge: metres when `voxel_mode` is "absolute", else a fraction of the median depth."""
    voxel_mode: Literal["absolute", "relative"] = "relative"
    """"relative" (scale-free maps): edge = voxel_size × median depth of the first fused keyframe."""
    fold_snap_voxels: float = 2.0
    """A folding keyframe's voxel that no folded voxel holds joins the nearest folded voxel within this many voxels
    along its line of sight (core/snapping.py): revisits stop thickening surfaces (the 10,000-frame orbit's map
    93,035 → 51,519 voxels at keyframe 1,088; docs/BENCHMARKS.md). 0: every voxel stays where its points fell, and
    the folded map equals the map without folding."""


@dataclass(frozen=True)
class RegionParams:
    """Clustering of high-scoring voxels into regions."""

    score_threshold: float = 0.5
    """Voxels whose cosine score is at least this take part in regions (when the query gives no threshold
    and ``relative_threshold`` is 0)."""
    relative_threshold: float = 0.8
    """With no threshold in the query, voxels scoring at least this fraction of the best score take part:
    cosine scores of text-derived vectors vary a lot between labels, so a fixed cut suits few of them."""
    connectivity: Literal[6, 26] = 26
    """Voxel neighbourhood for connected components (faces only, or faces+edges+corners)."""
    min_voxels: int = 3
    """Regions with fewer voxels are dropped as noise."""
    max_regions: int = 20
    """At most this many regions are returned, best score first."""


@dataclass(frozen=True)
class ScoreParams:
    """Scoring of query vectors against the map."""

    chunk_points: int = 262_144
    """Points scored per block when many queries are reduced (top-k, argmax) without a Q×N matrix."""
    device: str = "auto"
    """torch device for scoring: "auto" (CUDA when present), "cpu", "cuda", "cuda:1", ..."""


@dataclass(frozen=True)
class MapParams:
    """Everything the map core needs, in one value."""

    points: PointParams = field(default_factory=PointParams)
    consistency: ConsistencyParams = field(default_factory=ConsistencyParams)
    carving: CarvingParams = field(default_factory=CarvingParams)
    fusion: FusionParams = field(default_factory=FusionParams)
    regions: RegionParams = field(default_factory=RegionParams)
    scoring: ScoreParams = field(default_factory=ScoreParams)


class MapstoreSettings(KmVipeSettings):
    """Settings of the mapstore service (env prefix ``KMVIPE_MAPSTORE_``)."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_MAPSTORE_", env_file=".env", extra="ignore")

    stream: str = ALL_STREAMS
    """The stream served (``kmvipe/<stream>/...``); ``*``: every stream a source announces, each with its own state
    (services/common/streams.py; replicas split them by ``KMVIPE_SHARD_*``)."""
    db_path: str = "out/map/{stream}.db"
    """SQLite map database; ``{stream}`` is replaced by the stream name."""
    synchronous: Literal["NORMAL", "FULL"] = "FULL"
    """FULL: an acknowledged keyframe also survives power loss; NORMAL: survives a killed process."""
    fusion_nice: int = 10
    """Niceness of the thread that commits and fuses a stream's map (Linux; per thread): behind ba's tracking (0)
    and mapping (5), ahead of the semantics backbone (19). Re-fusing after each graph update took about half a
    core on a KITTI 07 live run, and at niceness 0 it took that from tracking (docs/BENCHMARKS.md)."""
    refresh_batch: int = 32
    """Messages already queued are committed one by one (each acknowledged as it commits) but re-fused together,
    at most this many at a time: ba revises 25 keyframes per update and features may send several PCA bases in a
    row, and re-fusing after each made the mapstore the busiest process of a KITTI run. 1 = after every message."""
    refresh_period_s: float = Field(2.0, ge=0)
    """What the messages change is committed at once but re-fused at most once per this many seconds (0: after
    every batch): each graph update moves the keyframes of ba's window again, so re-fusing fewer times does the
    same work fewer times. A query re-fuses what waits before it answers, and so does the export at the end
    of stream. KITTI 07 lossless: docs/BENCHMARKS.md, "Threads that sleep, a map re-fused every 2 s"."""
    refresh_max_share: float = Field(0.34, gt=0, le=1)
    """At most this share of the mapstore's time goes to the periodic re-fusion: one that took t seconds is
    followed by at least t·(1/share − 1) seconds without one (and refresh_period_s). Where re-fusing is slow (a
    loaded CPU, a large window) each re-fusion then covers more graph updates, so a keyframe ba revises again and
    again is re-fused fewer times; queries and the export still re-fuse what waits first. 1: refresh_period_s
    alone. docs/BENCHMARKS.md, "Re-fusion at most a third of the time"."""
    voxel_size: float = 0.02
    """Voxel edge: metres when voxel_mode is absolute, else a fraction of the median depth."""
    voxel_mode: Literal["absolute", "relative"] = "relative"
    """relative suits scale-free maps; absolute needs a metric map."""
    fold_snap_voxels: float = Field(2.0, ge=0)
    """A folding keyframe's voxels join the folded surface along their lines of sight within this many voxels
    (FusionParams.fold_snap_voxels); 0: off."""
    consistency_neighbours: int = 2
    """Keyframes on each side a keyframe's depth is checked against (0 disables)."""
    min_weight: float = 0.1
    """Points with confidence × static × consistency below this are left out."""
    carve_keyframes: int = 16
    """Later keyframes whose depths may carve a keyframe's points as free space (moved objects); 0 disables."""
    carve_views: int = 3
    """Most recent later views of a point that decide whether it is carved."""
    carve_min_violations: int = 2
    """Of those, how many must see through the point (and outnumber the agreeing ones) to carve it."""
    carve_semantic: bool = True
    """A later view whose codes disagree with a point's at about its depth counts as seeing through it."""
    carve_max_code_cosine: float = 0.2
    """Codes disagree when their cosine is below this (CarvingParams.max_code_cosine)."""
    carve_occluder_margin: float = 0.3
    """Surfaces nearer than (1 − this)·z are occluders, not contradictions (CarvingParams.occluder_margin)."""
    carve_min_code_reliability: float = 0.0
    """Reliability a view's cell needs for its codes to contradict a point (CarvingParams.min_code_reliability)."""
    device: str = "auto"
    """torch device for scoring."""
    store_images: bool = True
    """Keep each keyframe's working image (JPEG) for exports."""
    thumbnail_side: int = Field(160, ge=0, le=1024)
    """Longest side (px) of the small JPEG kept per keyframe for the viewer's keyframe strip and query by region
    (``map/keyframe``); a few kB each at 160 (5.3 kB for a 128×96 synthetic keyframe). 0: none kept."""
    thumbnail_quality: int = Field(80, ge=1, le=100)
    """JPEG quality of the thumbnails."""
    answer_cache: int = Field(256, ge=0)
    """Query vectors whose findings are kept for the current map revision (a few kB each): a vector asked again
    before the map changes is answered without scoring. 0: every query scored."""
    release_memory_period_s: float = Field(10.0, ge=0)
    """At most once per this many seconds, between two batches, freed heap goes back to the kernel
    (``lifecycle.release_free_memory``); 0: never. Re-fusion and exports free large arrays whose heap the allocator
    would otherwise keep, fragmented, for the rest of the process."""
    export_dir: str = ""
    """When set, write map.ply, depth maps, keyframe images and the COLMAP model here: the depth maps and images of
    keyframes as they fold (they are final then), the rest at end of stream."""
    colmap_points_per_image: int = Field(2048, ge=1)  # ColmapParams.max_points_per_image (not imported: numpy)
    """At most this many observations per image in the exported COLMAP model (ColmapParams.max_points_per_image)."""
    upstream: str = "ba"
    """The stage whose end of stream ends the map: it is exported and the EOS forwarded as ``mapstore``."""
    eos_wait_s: float = 10.0
    """How long ba's EOS waits for ba's final graph (they travel on different keys) before the map is exported."""
    fold_keyframes: bool = True
    """Flat memory: keyframes that have left ba's graph, have their codes (or come from a real-time stream) and
    are older than the carving window are folded into frozen voxel sums and leave memory (they stay in SQLite).
    False keeps every keyframe in memory (and carving of old points by later views)."""
    frozen_sums: Literal["files", "memory"] = "files"
    """Where folded keyframes' voxel sums are kept (core/frozen.py): ``files`` in a folder beside the database
    (``<db>.frozen-<pid>``, derived state, removed at close; services/mapstore/frozen_files.py), read back a chunk
    at a time by a PCA refit; ``memory`` in the process. They were the mapstore's largest growing part on a
    10,000-frame stream (docs/BENCHMARKS.md)."""
    max_live_keyframes: int = 256
    """Safety bound on the keyframes held in memory: beyond it, the oldest keyframes that have left ba's graph
    are folded even while their codes are still to come (those codes are committed but stay out of the map)."""

    def map_params(self) -> MapParams:
        return MapParams(points=PointParams(min_weight=self.min_weight),
                         consistency=ConsistencyParams(neighbours=self.consistency_neighbours),
                         carving=CarvingParams(later_keyframes=self.carve_keyframes, recent_views=self.carve_views,
                                               min_violations=self.carve_min_violations,
                                               semantic=self.carve_semantic,
                                               max_code_cosine=self.carve_max_code_cosine,
                                               occluder_margin=self.carve_occluder_margin,
                                               min_code_reliability=self.carve_min_code_reliability),
                         fusion=FusionParams(voxel_size=self.voxel_size, voxel_mode=self.voxel_mode,
                                             fold_snap_voxels=self.fold_snap_voxels),
                         scoring=ScoreParams(device=self.device))

