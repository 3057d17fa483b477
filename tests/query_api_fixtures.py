"""Shared helpers of the query gateway tests: a loopback bus pair, a synthetic labelled scene served by the
reference map queryable, and a gateway wired to it."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from services.common.bus import Bus
from services.common.config import BusSettings
from services.query_api.config import QuerySettings
from services.query_api.refmap import RefMap, RefMapParams
from services.runner.children import free_tcp_endpoint
from services.synth import LABEL_NAMES, label_vectors

STREAM = "cam0"
LABELS = ("floor", "table", "chair", "monitor", "plant", "fire extinguisher")
DIM = 16
SEED = 3


def free_port() -> int:
    """A free loopback port not handed out before (services.runner.children.free_tcp_endpoint)."""
    return int(free_tcp_endpoint().rsplit(":", 1)[1])


def bus_pair(listener: str = "map", other: str = "query_api") -> tuple[Bus, Bus]:
    """Two peers on loopback TCP, no multicast: the first listens, the second connects."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    a = Bus(BusSettings(mode="peer", listen=[endpoint]), listener)
    b = Bus(BusSettings(mode="peer", connect=[endpoint]), other)
    a.ready()
    b.ready()
    return a, b


def wait_for(condition, timeout_s: float = 10.0, what: str = "condition"):
    """Poll ``condition()`` until it returns a truthy value or raise after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    last_exc = None
    while time.monotonic() < deadline:
        try:
            value = condition()
            if value:
                return value
        except Exception as exc:  # noqa: BLE001 - retried until the deadline
            last_exc = exc
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what} (last error: {last_exc!r})")


@dataclass
class Scene:
    """Points in one axis-aligned box per label; ``label`` is each point's GT label index."""

    xyz: np.ndarray
    rgb: np.ndarray
    label: np.ndarray
    vectors: np.ndarray  # (L, D) oracle label vectors
    boxes: np.ndarray  # (L, 2, 3) min/max corner of each label's box


def make_scene(points_per_label: int = 400, noise: float = 0.3, seed: int = 0) -> Scene:
    rng = np.random.default_rng(seed)
    table = label_vectors(len(LABEL_NAMES), DIM, SEED)  # what the oracle text encoder knows
    vectors = table[[LABEL_NAMES.index(n) for n in LABELS]]
    xyz, label, boxes = [], [], []
    for k in range(len(LABELS)):
        lo = np.array([1.5 * k, 0.5 * (k % 2), 0.0])
        hi = lo + np.array([0.6, 0.5, 0.4 + 0.1 * k])
        xyz.append(rng.uniform(lo, hi, (points_per_label, 3)))
        label.append(np.full(points_per_label, k))
        boxes.append((lo, hi))
    label = np.concatenate(label)
    palette = (np.arange(len(LABELS))[:, None] * np.array([40, 90, 150]) % 255).astype(np.uint8)
    return Scene(np.concatenate(xyz).astype(np.float32), palette[label], label, vectors, np.array(boxes))


def scene_map(scene: Scene, noise: float = 0.3, seed: int = 0, backbone: str = "oracle") -> RefMap:
    """Reference map whose point features are the label vectors plus Gaussian noise (identity PCA basis)."""
    rng = np.random.default_rng(seed)
    feats = scene.vectors[scene.label] + noise * rng.standard_normal((len(scene.label), DIM)) / np.sqrt(DIM)
    return RefMap(scene.xyz, scene.rgb, feats.astype(np.float32), np.zeros(DIM, np.float32),
                  np.eye(DIM, dtype=np.float32), backbone, RefMapParams(voxel_size=0.1))


def oracle_settings(**overrides) -> QuerySettings:
    kw = dict(text_encoder="oracle", oracle_synth_seed=SEED, oracle_synth_dim=DIM, timeout_s=3.0, alive_timeout_s=0.5)
    kw.update(overrides)
    return QuerySettings(_env_file=None, **kw)
