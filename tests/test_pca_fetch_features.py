"""The features ``pca`` queryable serves every basis version published in the run (``?version=<n>``), the latest
without a selector, and an error reply (never a crash) for a version it never published.

The bases come from the real features handlers: the synthetic world through the synth-oracle backbone with a
retention threshold so high that almost every keyframe refits (a new version). Other tests import
:func:`features_run` to get the same stream and a features state to serve it.
"""
from __future__ import annotations

import threading
from typing import NamedTuple

import numpy as np
import pytest

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.schema import Eos, Frame, Keyframe, KeyframeCodes, Message, PcaBasis, decode
from services.features import service as features
from services.features.config import FeaturesSettings
from services.synth import SynthWorld
from services.synth.spec import config_from_spec
from tests.conftest import wait_until

STREAM = "pf0"
WIDTH, HEIGHT = 128, 96
SOURCE = f"synth:frames=12,seed=3,width={WIDTH},height={HEIGHT}"


class FeaturesRun(NamedTuple):
    cfg: FeaturesSettings
    state: features.FeaturesState
    outputs: list[Message]  # what features published, in order
    world: SynthWorld


def features_run(stream: str = STREAM) -> FeaturesRun:
    """Every frame of SOURCE through the features handlers (oracle features, 2 PCA components, refit below
    99.9 % retention, working size = the frame size, a low keyframe threshold for that size); the outputs in publish order."""
    cfg = FeaturesSettings(stream=stream, backbone="synth-oracle", oracle_source=SOURCE, oracle_dim=16,
                           device="cpu", threads=1, scales=(1.0,), target_area=WIDTH * HEIGHT, pca_components=2,
                           pca_fit_keyframes=1, pca_refit_below=0.999, pca_first_version=1,
                           keyframe_threshold_grid_px=0.5)
    state = features.build_state(cfg)
    world = SynthWorld(config_from_spec(SOURCE))
    outputs: list[Message] = []
    for i in range(world.config.n_frames):
        f = world.render(i)
        frame = Frame(stream, i, int(f.t_ns), WIDTH, HEIGHT, image=f.rgb, intrinsics=f.intrinsics)
        outputs += [m for _, m in features.handle_frame(state, frame, cfg)]
    outputs += [m for _, m in features.handle_eos(state, Eos(stream, i, 0, stage="ingest", count=i + 1), cfg)]
    return FeaturesRun(cfg, state, outputs, world)


def serve(run: FeaturesRun, bus: Bus) -> tuple[threading.Thread, threading.Event]:
    """The real features loop on ``bus`` with ``run``'s state (no frames come: it only serves ``pca``)."""
    stop = threading.Event()
    worker = threading.Thread(target=features.run, args=(run.cfg, bus, stop, run.state), daemon=True)
    worker.start()
    return worker, stop


@pytest.fixture(scope="module")
def stream_run() -> FeaturesRun:
    return features_run()


def test_the_stream_refits_and_every_keyframe_names_a_published_version(stream_run):
    bases = [m for m in stream_run.outputs if isinstance(m, PcaBasis)]
    kfs = [m for m in stream_run.outputs if isinstance(m, Keyframe)]
    codes = [m for m in stream_run.outputs if isinstance(m, KeyframeCodes)]
    assert [b.version for b in bases] == list(range(1, len(bases) + 1)) and len(bases) >= 4
    assert all(k.codes is None and k.pca_version == -1 for k in kfs)  # geometry first
    assert [c.seq for c in codes] == [k.seq for k in kfs]  # then every keyframe's codes, in order
    for c in codes:  # each names a version whose basis went out before it
        before = stream_run.outputs[:stream_run.outputs.index(c)]
        assert c.pca_version in {b.version for b in before if isinstance(b, PcaBasis)}
    assert sorted(stream_run.state.bases) == [b.version for b in bases]
    assert codes[0].codes.shape == (HEIGHT // 8, WIDTH // 8, 2)


def test_answer_pca_refuses_before_any_basis_and_bad_selectors(stream_run):
    empty = features.FeaturesState(stream_run.state.core, stream_run.state.semantics, STREAM)
    with pytest.raises(LookupError, match="no PCA basis"):
        features.answer_pca(empty, {})
    with pytest.raises(LookupError, match="no basis yet"):
        features.answer_pca(empty, {"version": "1"})
    with pytest.raises(ValueError, match="integer"):
        features.answer_pca(stream_run.state, {"version": "two"})


def test_queryable_serves_every_version_and_refuses_an_unknown_one(stream_run, unix_endpoint):
    published = {m.version: m for m in stream_run.outputs if isinstance(m, PcaBasis)}
    with Bus(BusSettings(listen=[unix_endpoint]), "features") as fbus, \
            Bus(BusSettings(connect=[unix_endpoint]), "tester") as bus:
        worker, stop = serve(stream_run, fbus)
        wait_until(lambda: "features" in bus.alive(timeout=0.2), 10, "the features service to be alive")
        key = keys.topic(STREAM, keys.PCA)
        for version, sent in published.items():
            got = decode(bus.request(f"{key}?version={version}", timeout=5.0), PcaBasis)
            assert got.version == version and got.backbone == sent.backbone
            for name in ("mean", "components", "explained_variance"):
                np.testing.assert_array_equal(getattr(got, name), getattr(sent, name))
        assert decode(bus.request(key, timeout=5.0), PcaBasis).version == max(published)  # no selector: latest
        unknown = max(published) + 1
        with pytest.raises(RuntimeError, match=rf"version {unknown} was not published .*versions 1\.\.{unknown - 1}"):
            bus.request(f"{key}?version={unknown}", timeout=5.0)
        with pytest.raises(RuntimeError, match="integer"):
            bus.request(f"{key}?version=latest", timeout=5.0)
        assert decode(bus.request(f"{key}?version=1", timeout=5.0), PcaBasis).version == 1  # still serving
        stop.set()
        worker.join(10)
    assert not worker.is_alive()
    assert fbus.stats.counts[(key, "query")] == 2  # the two refusals, counted
