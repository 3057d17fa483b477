"""Model registry: entries, lookup, tiny random models through the real loaders, clear errors."""
from __future__ import annotations

import argparse

import pytest
import numpy as np
import torch

pytest.importorskip("transformers")

from services.common.errors import ModelError  # noqa: E402
from services.common.models import HubSource, ModelKind, ModelStore, all_entries, get_entry, text_head_for  # noqa: E402
from services.common.models import cli, loaders  # noqa: E402
from services.common.models.tiny import TINY_DIM, TINY_TEXT_DIM, write_tiny_model  # noqa: E402


@pytest.fixture(scope="module")
def tiny_store(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    for name in ("dinov2-vitb14-reg", "clip-vitb16-text", "talk2dino-vitb", "depth-anything-v2-metric-indoor-small"):
        write_tiny_model(name, root, seed=0)
    return ModelStore(root, use_hf_cache=False)


def test_every_entry_is_complete_and_unique():
    entries = all_entries()
    assert len({e.name for e in entries}) == len(entries)
    for e in entries:
        assert e.licence and e.output_space and e.output_dim > 0 and e.description
        if e.kind is ModelKind.BACKBONE:
            assert e.patch_size == 14
    kinds = {e.kind for e in entries}
    assert kinds == set(ModelKind)


def test_lookup_by_name_and_repo_id_and_unknown():
    assert get_entry("facebook/dinov2-with-registers-base").name == "dinov2-vitb14-reg"
    assert get_entry("dinov2-vitb14-reg").output_dim == 768
    with pytest.raises(ModelError, match="unknown model 'nope'.*dinov2-vits14-imgfocus"):
        get_entry("nope")


def test_text_head_pairs_only_with_its_backbone():
    assert text_head_for("dinov2_vitb14_reg").name == "talk2dino-vitb"
    assert text_head_for("dinov2_vits14") is None


def test_missing_model_is_one_clear_error(tmp_path):
    store = ModelStore(tmp_path, use_hf_cache=False)
    with pytest.raises(ModelError) as err:
        loaders.load_backbone("dinov2-vitb14-reg", store, "cpu")
    msg = str(err.value)
    assert "dinov2-vitb14-reg" in msg and "kmvipe models pull dinov2-vitb14-reg" in msg
    assert "facebook/dinov2-with-registers-base" in msg


def test_wrong_kind_is_refused(tiny_store):
    with pytest.raises(ModelError, match="is a text model, not a backbone"):
        loaders.load_backbone("clip-vitb16-text", tiny_store, "cpu")


def test_tiny_backbone_with_registers_drops_prefix_tokens(tiny_store):
    bb = loaders.load_backbone("dinov2-vitb14-reg", tiny_store, "cpu")
    assert bb.n_prefix == 5  # CLS + 4 registers
    x = torch.randn(2, 3, 28, 42)
    out = bb(x.numpy())
    assert out.shape == (2, TINY_DIM, 2, 3) and isinstance(out, np.ndarray)
    # the map is the model's own patch tokens, in row-major order
    with torch.inference_mode():
        ref = bb.model(pixel_values=x).last_hidden_state[:, 5:].numpy()
    np.testing.assert_allclose(out.transpose(0, 2, 3, 1).reshape(2, 6, TINY_DIM), ref, atol=1e-6)
    with pytest.raises(ValueError, match="multiples of 14"):
        bb(np.zeros((1, 3, 30, 42), np.float32))


def test_tiny_text_encoder_and_head(tiny_store):
    enc = loaders.load_text_encoder("clip-vitb16-text", tiny_store, "cpu")
    texts = ["There is a chair in the scene", "There is a car in the scene"]
    emb = enc.encode(texts)
    assert emb.shape == (2, TINY_TEXT_DIM)
    # CLIP's text_embeds as they are (Talk2DINO's head reads them unnormalised), one prompt at a time = batched
    single = torch.cat([enc.encode([t]) for t in texts])
    assert torch.allclose(emb, single, atol=1e-5)
    assert not torch.allclose(emb.norm(dim=1), torch.ones(2), atol=1e-3)
    assert not torch.allclose(emb[0], emb[1])
    head = loaders.load_text_head("talk2dino-vitb", tiny_store, "cpu")
    out = head(emb)
    assert out.shape == (2, TINY_DIM)
    # linear → tanh → linear, read from the "proj."-prefixed checkpoint
    manual = head.hidden_layers[0](torch.tanh(head.linear_layer(emb)))
    assert torch.allclose(out, manual)


def test_tiny_depth_model_outputs_positive_metric_depth(tiny_store):
    model = loaders.load_depth_model("depth-anything-v2-metric-indoor-small", tiny_store, "cpu")
    depth = model(np.random.default_rng(0).standard_normal((1, 3, 56, 70), np.float32))
    assert depth.shape == (1, 56, 70) and depth.dtype == np.float32
    assert np.all(depth >= 0) and np.all(depth <= 20.0 + 1e-4)  # sigmoid · max_depth head


def test_corrupt_weights_are_one_clear_error(tmp_path):
    for name in ("dinov2-vitb14-reg", "talk2dino-vitb"):
        folder = write_tiny_model(name, tmp_path, seed=1)
        (folder / "model.safetensors").write_bytes(b"\x00garbage" * 10)
    store = ModelStore(tmp_path, use_hf_cache=False)
    with pytest.raises(ModelError, match="dinov2-vitb14-reg.*missing or corrupt.*kmvipe models pull"):
        loaders.load_backbone("dinov2-vitb14-reg", store, "cpu")
    with pytest.raises(ModelError, match="talk2dino-vitb.*cannot read"):
        loaders.load_text_head("talk2dino-vitb", store, "cpu")


def _run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_list_shows_installed_and_missing(tiny_store, capsys):
    assert _run_cli(["models", "--models-dir", str(tiny_store.models_dir), "list"]) == 0
    out = capsys.readouterr().out
    for e in all_entries():
        assert e.name in out
    assert "installed (models_dir" in out
    assert "depth-anything-v2-metric-outdoor-small" in out and "missing" in out


def test_cli_pull_says_why_it_cannot_download(tmp_path, monkeypatch, capsys):
    # an endpoint nobody listens on: the pull must fail fast with the reason, never hang or crash
    monkeypatch.setenv("HF_ENDPOINT", "http://127.0.0.1:9")
    monkeypatch.setenv("HF_HUB_ETAG_TIMEOUT", "2")
    rc = _run_cli(["models", "--models-dir", str(tmp_path), "pull", "clip-vitb16-text"])
    out = capsys.readouterr().out
    assert rc == 1
    assert "cannot download 'clip-vitb16-text'" in out and "Copy the files by hand" in out


def test_hub_entries_pin_a_revision():
    for e in all_entries():
        if isinstance(e.source, HubSource):
            assert e.source.revision


def test_both_model_services_search_the_shared_models_folder(tmp_path, monkeypatch):
    # KMVIPE_MODELS_DIR is the air-gapped folder the README names; a GPU run found features ignoring it
    from services.features.config import FeaturesSettings
    from services.query_api.config import QuerySettings

    monkeypatch.setenv("KMVIPE_MODELS_DIR", str(tmp_path / "shared"))
    assert FeaturesSettings().models_dir == QuerySettings().models_dir == tmp_path / "shared"
    monkeypatch.setenv("KMVIPE_FEATURES_MODELS_DIR", str(tmp_path / "own"))
    assert FeaturesSettings().models_dir == tmp_path / "own"
    monkeypatch.delenv("KMVIPE_MODELS_DIR")
    assert QuerySettings().models_dir is None
