"""The features service's handlers with a tiny random DINOv2 from the registry: keyframes that wait for the
PCA basis leave with their own timestamp and size, and the EOS follows the last keyframe."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("transformers")

from services.common.models.tiny import write_tiny_model  # noqa: E402
from services.common.schema import Eos, Frame, Keyframe, PcaBasis  # noqa: E402
from services.features.config import FeaturesSettings  # noqa: E402
from services.features.service import build_state, handle_eos, handle_frame  # noqa: E402
from services.synth import SynthConfig, SynthWorld  # noqa: E402


def test_held_back_keyframes_keep_their_own_timestamps(tmp_path):
    write_tiny_model("dinov2-vitb14-reg", tmp_path)
    cfg = FeaturesSettings(stream="s", backbone="dinov2-vitb14-reg", models_dir=tmp_path, device="cpu",
                           scales=(1.0,), pca_components=4, pca_fit_keyframes=3)
    state = build_state(cfg)
    world = SynthWorld(SynthConfig(n_frames=12, person=False, moved_chair=False))
    out = []
    for i in range(12):  # the whole orbit in 12 frames: most of them are keyframes
        f = world.render(i)
        out += handle_frame(state, Frame("s", i, int(f.t_ns), 512, 384, image=f.rgb), cfg)
    out += handle_eos(state, Eos("s", 11, 0, stage="ingest", count=12), cfg)
    keyframes = [m for _, m in out if isinstance(m, Keyframe)]
    assert len(keyframes) >= 3 and isinstance(out[-1][1], Eos) and out[-1][1].stage == "features"
    assert [m for _, m in out if isinstance(m, PcaBasis)]
    stamps = {seq: int(world.t_ns(seq)) for seq in range(12)}
    assert [k.t_ns for k in keyframes] == [stamps[k.seq] for k in keyframes]
    assert all((k.orig_width, k.orig_height) == (512, 384) for k in keyframes)
    assert np.all(np.diff([k.seq for k in keyframes]) > 0)


def test_a_restarted_features_process_numbers_its_bases_above_the_last_run():
    """Consumers keep PCA bases by version: a restart must not count from 1 again (its bases would be taken for
    the old ones). The default first version is the start time (unix s × 1000), and the fitter starts there."""
    import time

    import torch

    from services.features.core.pca import PcaFitter

    first = FeaturesSettings().pca_first_version
    time.sleep(1.0)
    again = FeaturesSettings().pca_first_version
    assert again >= first + 1000  # room for 1000 refits per second the earlier process ran
    params = FeaturesSettings(pca_first_version=again, pca_components=2, pca_fit_keyframes=1).params().pca
    basis = PcaFitter(params, "test").add(torch.randn(8, 6, 6, generator=torch.Generator().manual_seed(0)))
    assert basis is not None and basis.version == again


@pytest.mark.parametrize("missing, handled, lost", [
    ((4, 5, 9), -1, 3),
    ((0, 4, 9), -1, 3),  # the first frame too: a worker that starts on a stream answers for it
    ((0, 1, 2, 3, 4, 5, 9), 3, 3),  # a restart: its predecessor handled up to 3, so 4, 5 and 9 are lost
], ids=["middle", "first", "after-a-predecessor"])
def test_frames_lost_on_the_way_are_counted_in_the_end_of_stream(tmp_path, missing, handled, lost):
    """Ingest announces 12 frames; some never arrive (as Zenoh drops them on congestion): features' EOS says how
    many, after waiting ``eos_wait_s`` for them, counting from after the frames a predecessor had handled."""
    import time

    from services.features.service import closing_outputs, overdue_eos

    write_tiny_model("dinov2-vitb14-reg", tmp_path)
    cfg = FeaturesSettings(stream="s", backbone="dinov2-vitb14-reg", models_dir=tmp_path, device="cpu",
                           scales=(1.0,), pca_components=4, pca_fit_keyframes=3, eos_wait_s=0.05)
    state = build_state(cfg)
    world = SynthWorld(SynthConfig(n_frames=12, person=False, moved_chair=False))
    out = []
    for i in [s for s in range(12) if s not in missing]:
        f = world.render(i)
        out += handle_frame(state, Frame("s", i, int(f.t_ns), 512, 384, image=f.rgb, features_handled=handled), cfg)
    out += handle_eos(state, Eos("s", 11, 0, stage="ingest", count=12), cfg)
    assert not [m for _, m in out if isinstance(m, Eos)], "the EOS waits for the missing frames first"
    time.sleep(0.1)
    out += overdue_eos(state)
    for _ in range(200):  # the semantics thread finishes its queue before the EOS goes on
        eos = [m for _, m in out if isinstance(m, Eos)]
        if eos:
            break
        time.sleep(0.05)
        out += closing_outputs(state)
    assert eos and eos[0].lost == lost and eos[0].dropped == 0


def test_lossless_credit_holds_while_ba_is_keyframes_or_frames_behind_and_the_mapstore_keyframes_behind(tmp_path):
    """ba is held to ``ba_keyframes`` keyframes (its work) and ``downstream_frames`` messages behind what features
    published; the mapstore to ``downstream_keyframes`` keyframes; a silent stage no longer holds anyone back."""
    from services.features.service import credit_limit

    write_tiny_model("dinov2-vitb14-reg", tmp_path)
    cfg = FeaturesSettings(stream="s", backbone="dinov2-vitb14-reg", models_dir=tmp_path, device="cpu",
                           ba_keyframes=2, downstream_frames=10, downstream_keyframes=3, credit_window=4)
    state = build_state(cfg)
    state.last_seq, now = 40, 100.0
    state.started = now - 1.0
    state.sent.extend((s, s % 8 == 0) for s in range(41))  # keyframes 0, 8, 16, 24, 32, 40
    open_credit = state.last_seq + cfg.credit_window

    def limit(ba: int, mapstore: int, ba_seen: float = now) -> int:
        state.downstream.update({"ba-1.0": (ba, ba_seen), "mapstore-1.0": (mapstore, now)})
        return credit_limit(state, cfg, now)

    assert limit(ba=39, mapstore=39) == open_credit  # one keyframe (40) behind each
    assert limit(ba=31, mapstore=39) == state.last_seq  # ba: 32 and 40 to do, 9 messages
    assert limit(ba=33, mapstore=39) == open_credit  # ba: one keyframe, 7 messages
    assert limit(ba=33, mapstore=23) == state.last_seq  # the mapstore: 24, 32, 40
    assert limit(ba=33, mapstore=24) == open_credit
    cfg_frames = cfg.model_copy(update={"ba_keyframes": 10})
    state.downstream.update({"ba-1.0": (29, now)})
    assert credit_limit(state, cfg_frames, now) == state.last_seq  # 11 messages behind, two keyframes
    assert limit(ba=0, mapstore=39, ba_seen=now - cfg.downstream_ttl_s - 1) == open_credit  # ba went silent
