"""The Talk2DINO text path checked against upstream (github.com/lorebianchi98/Talk2DINO) with tiny random models.

The upstream computation is written out here from its sources, independently of services/:

- ``ProjectionLayer.project_clip_txt`` (src/model.py; configs/vitb_mlp_infonce.yaml: act tanh, hidden_layer True):
  ``x = linear_layer(t)``, then ``x = hidden(tanh(x))`` for each hidden layer; no normalisation.
- ``DINOText.build_text_embedding`` (src/open_vocabulary_segmentation/models/dinotext/dinotext.py): OpenAI CLIP
  ``encode_text`` of every template (raw, 77-token zero-padded context), mean over templates, ``project_clip_txt``,
  L2-normalise.
- Templates: ``sub_imagenet_template`` (datasets/templates.py), used by demo.py and the eval configs.
- Checkpoints: weights/vitb_mlp_infonce.pth holds ``linear_layer.*`` and ``hidden_layers.0.*`` (old ones
  ``linear_layer2.*``, renamed by ``ProjectionLayer.load_state_dict``); the hub's model.safetensors is the state of
  src/hf_model.py ``Talk2DINO(DINOText)``: ``proj.*`` beside ``model.*`` (DINOv2), ``clip_model.*`` (OpenAI CLIP)
  and ``logit_scale``.
"""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

pytest.importorskip("transformers")

from services.common.errors import ModelError  # noqa: E402
from services.common.models import ModelStore, get_entry, text_head_for  # noqa: E402
from services.common.models import loaders  # noqa: E402
from services.common.models.tiny import TINY_DIM, TINY_TEXT_DIM, write_tiny_model  # noqa: E402
from services.query_api.config import QuerySettings  # noqa: E402
from services.query_api.core.text import DEFAULT_TEMPLATES  # noqa: E402
from services.query_api.textpath import TextPath, TextUnavailable  # noqa: E402

HEAD = "talk2dino-vitb"
# datasets/templates.py sub_imagenet_template, verbatim
UPSTREAM_TEMPLATES = (
    "itap of a {}.", "a bad photo of a {}.", "a origami {}.", "a photo of the large {}.", "a {} in a video game.",
    "art of the {}.", "a photo of the small {}.",
)  # fmt: skip
CONTEXT = 77  # clip.tokenize's context_length


def upstream_project(t: torch.Tensor, w: dict[str, torch.Tensor]) -> torch.Tensor:
    """project_clip_txt with one hidden layer and tanh."""
    x = t.float() @ w["W1"].T + w["b1"]
    return torch.tanh(x) @ w["W2"].T + w["b2"]


@pytest.fixture(scope="module")
def weights() -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(7)
    c, d = TINY_TEXT_DIM, TINY_DIM
    shapes = {"W1": (d, c), "b1": (d,), "W2": (d, d), "b2": (d,)}
    return {k: 0.3 * torch.randn(s, generator=g) for k, s in shapes.items()}


def write_head(folder, layout: str, w: dict[str, torch.Tensor]) -> None:
    """The projection in one of upstream's layouts, built from raw tensors (not through our head class)."""
    folder.mkdir(parents=True, exist_ok=True)
    hidden = "linear_layer2" if layout == "pth_legacy" else "hidden_layers.0"
    head = {"linear_layer.weight": w["W1"], "linear_layer.bias": w["b1"],
            f"{hidden}.weight": w["W2"], f"{hidden}.bias": w["b2"]}
    if layout in ("pth", "pth_legacy"):
        torch.save(head, folder / "vitb_mlp_infonce.pth")
        return
    from safetensors.torch import save_file

    state = {f"proj.{k}": v.contiguous() for k, v in head.items()}
    state.update({  # a few of the other sub-models' tensors, as they sit in the full model
        "logit_scale": torch.tensor(2.659),
        "model.cls_token": torch.zeros(1, 1, TINY_DIM),
        "model.register_tokens": torch.zeros(1, 4, TINY_DIM),
        "model.blocks.0.attn.qkv.weight": torch.zeros(3 * TINY_DIM, TINY_DIM),
        "model.norm.weight": torch.ones(TINY_DIM),
        "clip_model.positional_embedding": torch.zeros(CONTEXT, TINY_TEXT_DIM),
        "clip_model.text_projection": torch.zeros(TINY_TEXT_DIM, TINY_TEXT_DIM),
        "clip_model.ln_final.weight": torch.ones(TINY_TEXT_DIM),
        "clip_model.transformer.resblocks.0.attn.in_proj_weight": torch.zeros(3 * TINY_TEXT_DIM, TINY_TEXT_DIM),
        "clip_model.visual.proj": torch.zeros(TINY_DIM, TINY_TEXT_DIM),
    })
    save_file(state, str(folder / "model.safetensors"))


@pytest.fixture(scope="module")
def base_models(tmp_path_factory):
    root = tmp_path_factory.mktemp("base")
    write_tiny_model("clip-vitb16-text", root, seed=3)
    write_tiny_model("dinov2-vitb14-reg", root, seed=4)
    return root


@pytest.fixture
def models_dir(tmp_path, base_models):
    """A models folder with the tiny CLIP and backbone; each test writes its own head."""
    root = tmp_path / "models"
    shutil.copytree(base_models, root)
    return root


@pytest.mark.parametrize("layout", ["pth", "pth_legacy", "hub"])
def test_head_reads_each_upstream_layout_and_computes_project_clip_txt(models_dir, weights, layout):
    write_head(models_dir / HEAD, layout, weights)
    head = loaders.load_text_head(HEAD, ModelStore(models_dir, use_hf_cache=False), "cpu")
    assert (head.clip_dim, head.dino_dim) == (TINY_TEXT_DIM, TINY_DIM)
    t = 8.0 * torch.randn(5, TINY_TEXT_DIM, generator=torch.Generator().manual_seed(1))  # CLIP-sized norms
    torch.testing.assert_close(head(t), upstream_project(t, weights), atol=1e-5, rtol=1e-5)


def test_default_templates_are_talk2dinos():
    assert [t.format(label="sofa") for t in DEFAULT_TEMPLATES] == [t.format("sofa") for t in UPSTREAM_TEMPLATES]
    assert QuerySettings(_env_file=None).templates == list(DEFAULT_TEMPLATES)


def upstream_text_embedding(folder, labels, w) -> np.ndarray:
    """build_text_embedding with the same CLIP weights, straight from transformers (no services/ code)."""
    from transformers import CLIPTextModelWithProjection, CLIPTokenizer

    tok = CLIPTokenizer.from_pretrained(str(folder))
    clip = CLIPTextModelWithProjection.from_pretrained(str(folder)).eval()
    rows = []
    with torch.no_grad():
        for label in labels:
            ids = tok([t.format(label) for t in UPSTREAM_TEMPLATES], padding="max_length", max_length=CONTEXT,
                      return_tensors="pt")["input_ids"]
            raw = clip(input_ids=ids).text_embeds  # encode_text: no attention mask, causal only
            rows.append(torch.nn.functional.normalize(upstream_project(raw.mean(0, keepdim=True), w), dim=-1)[0])
    return torch.stack(rows).numpy()


def test_gateway_text_vectors_follow_build_text_embedding(models_dir, weights):
    write_head(models_dir / HEAD, "hub", weights)
    backbone_entry = get_entry("dinov2-vitb14-reg")
    cfg = QuerySettings(_env_file=None, text_encoder="clip", models_dir=models_dir, device="cpu")
    path = TextPath(cfg)
    labels = ["fire extinguisher", "chair", "potted plant"]
    got = path.embed(labels, backbone_entry.output_space)

    want = upstream_text_embedding(models_dir / "clip-vitb16-text", labels, weights)
    np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)

    # the vectors live where the registry says: the space and width of the backbone the head was trained on
    store = ModelStore(models_dir, use_hf_cache=False)
    backbone = loaders.load_backbone(backbone_entry.name, store, "cpu")
    assert path.loaded().output_space == backbone.output_space == get_entry(HEAD).output_space
    assert text_head_for(backbone.output_space).name == HEAD
    assert got.shape == (len(labels), backbone.dim)

    # the order matters and the test sees it: normalising CLIP first, or averaging after the head, differ
    enc, head = loaders.load_text_encoder("clip-vitb16-text", store, "cpu"), loaders.load_text_head(HEAD, store, "cpu")
    prompts = [t.format(labels[0]) for t in UPSTREAM_TEMPLATES]
    unit_first = torch.nn.functional.normalize(enc.encode(prompts), dim=-1).mean(0, keepdim=True)
    mean_after = torch.nn.functional.normalize(head(enc.encode(prompts)), dim=-1).mean(0, keepdim=True)
    for other in (head(unit_first), mean_after):
        assert not np.allclose(torch.nn.functional.normalize(other, dim=-1)[0].numpy(), got[0], atol=1e-3)


def _garbage(folder, w):
    folder.mkdir(parents=True)
    (folder / "model.safetensors").write_bytes(b"\x00garbage" * 10)


def _wrong_width(folder, w):
    write_head(folder, "pth", {**w, "W2": torch.zeros(TINY_DIM, TINY_DIM + 1)})


def _no_projection(folder, w):
    from safetensors.torch import save_file

    folder.mkdir(parents=True)
    save_file({"model.norm.weight": torch.ones(TINY_DIM), "clip_model.text_projection": torch.zeros(4, 4)},
              str(folder / "model.safetensors"))


def _not_a_state_dict(folder, w):
    folder.mkdir(parents=True)
    torch.save(torch.zeros(3), folder / "vitb_mlp_infonce.pth")


@pytest.mark.parametrize("spoil, says", [
    (_garbage, "cannot read"), (_wrong_width, "does not fit the Talk2DINO head"),
    (_no_projection, "no Talk2DINO projection weights"), (_not_a_state_dict, "cannot read"),
])  # fmt: skip
def test_bad_head_checkpoint_says_which_pull_to_run(models_dir, weights, spoil, says):
    spoil(models_dir / HEAD, weights)
    with pytest.raises(ModelError, match=f"'{HEAD}'.*{says}.*kmvipe models pull {HEAD}"):
        loaders.load_text_head(HEAD, ModelStore(models_dir, use_hf_cache=False), "cpu")


def test_gateway_reports_a_bad_head_with_the_pull_to_run(models_dir, weights):
    _wrong_width(models_dir / HEAD, weights)
    cfg = QuerySettings(_env_file=None, text_encoder="clip", models_dir=models_dir, device="cpu")
    with pytest.raises(TextUnavailable, match=f"kmvipe models pull {HEAD}"):
        TextPath(cfg).embed(["chair"], "dinov2_vitb14_reg")
