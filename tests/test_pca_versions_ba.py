"""BA service with several PCA basis versions: every code in the frontend graph is in the newest version.

Keyframes of the synthetic orbit (oracle codes) go through ``services.ba.service.handle``, the real frontend;
the expected codes are the ground-truth conversion of what each keyframe carried (services/common/pca_codes.py).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from services.ba import service
from services.ba.settings import BaSettings
from services.common.pca_codes import code_map, convert_codes
from services.common.schema import Keyframe, PcaBasis
from tests.test_ba_pipeline_synth import K, synth_stream

STREAM, D = "t0", 48


def _bases() -> dict[int, PcaBasis]:
    rng = np.random.default_rng(11)
    return {v: PcaBasis(STREAM, 0, 0, version=v, backbone="oracle", mean=(0.1 * rng.normal(size=D)).astype(np.float32),
                        components=np.linalg.qr(rng.normal(size=(D, K)))[0].T.astype(np.float32)) for v in (1, 2, 3)}


BASES = _bases()


@pytest.fixture(scope="module")
def keyframes() -> list[Keyframe]:
    _, msgs = synth_stream(n_frames=40, rendered=21, every=4, stream=STREAM, width=128)
    return [m for m in msgs if isinstance(m, Keyframe)]  # seqs 0, 4, 8, 12, 16, 20


def _recoded(kf: Keyframe, version: int) -> Keyframe:
    """The keyframe as features would send it had it coded the same features with basis ``version``."""
    codes = kf.codes if version == 1 else convert_codes(kf.codes, code_map(BASES[1], BASES[version]))
    return dataclasses.replace(kf, pca_version=version, codes=np.asarray(codes, np.float16))


def _state():
    cfg = BaSettings(stream=STREAM, device="cpu", threads=1, init_min_flow=0.5, focal_after=3, iterations=2,
                     global_iterations=3)
    return cfg, service.build_state(cfg)


def _assert_all_in(state, version: int) -> None:
    g = state.frontend.graph
    assert state.pca_version == version and len(g) > 0
    for seq, codes, native in zip(g.seqs, g.codes, g.native_codes):
        assert codes is not None, seq
        expect = convert_codes(native.codes, code_map(BASES[native.version], BASES[version]))
        torch.testing.assert_close(codes, torch.from_numpy(expect), atol=1e-5, rtol=0)


def test_a_new_basis_converts_every_graph_code_and_later_keyframes_on_arrival(keyframes):
    cfg, state = _state()
    service.handle(state, BASES[1], cfg)
    for kf in keyframes[:3]:
        service.handle(state, kf, cfg)
    _assert_all_in(state, 1)
    service.handle(state, BASES[2], cfg)
    _assert_all_in(state, 2)
    assert [n.version for n in state.frontend.graph.native_codes] == [1, 1, 1]  # kept as received
    service.handle(state, _recoded(keyframes[3], 2), cfg)
    service.handle(state, keyframes[4], cfg)  # a straggler coded with basis 1: converted on arrival
    _assert_all_in(state, 2)


def test_codes_of_an_unknown_basis_are_left_out_until_it_arrives(keyframes):
    cfg, state = _state()
    service.handle(state, BASES[1], cfg)
    for kf in keyframes[:3]:
        service.handle(state, kf, cfg)
    service.handle(state, _recoded(keyframes[3], 3), cfg)  # basis 3 is still on the way (another key)
    g = state.frontend.graph
    assert g.seqs[-1] == keyframes[3].seq and g.codes[-1] is None  # BA windows holding it run without codes
    assert all(c is not None for c in g.codes[:-1]) and state.pca_version == 1
    service.handle(state, BASES[3], cfg)
    _assert_all_in(state, 3)


def test_first_codes_set_the_version_before_any_basis(keyframes):
    cfg, state = _state()
    service.handle(state, _recoded(keyframes[0], 2), cfg)
    service.handle(state, _recoded(keyframes[1], 2), cfg)
    np.testing.assert_array_equal(state.frontend.graph.codes[1].numpy(), _recoded(keyframes[1], 2).codes)
    service.handle(state, keyframes[2], cfg)  # version 1, neither basis known yet
    assert state.pca_version == 2 and state.frontend.graph.codes[-1] is None
    service.handle(state, BASES[2], cfg)
    assert state.frontend.graph.codes[-1] is None  # basis 1 still unknown
    service.handle(state, BASES[1], cfg)  # an older basis: the version stays, the left-out codes come back
    _assert_all_in(state, 2)
