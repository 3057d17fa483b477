"""``synth:frames=200,seed=0,...`` source specs → :class:`SynthConfig`, so every process that needs the world a
stream was rendered from (the features oracle, map-quality evaluation) rebuilds exactly the same one.

Options (all integers): frames, seed, width, height, person (0/1), chair (0/1: the moved chair), static (0/1:
static camera instead of the orbit), span (degrees the orbit sweeps over the whole stream, default 100: a long
stream with ordinary per-frame motion circles the room many times, e.g. frames=10000,span=8000), depth (0/1:
ingest also sends exact depth; no effect on the world).
"""

from __future__ import annotations

from services.common.errors import ConfigError
from services.synth.config import SynthConfig

# option in the spec → (SynthConfig field, converter); ingest's synth: source uses the same table
OPTIONS = {
    "frames": ("n_frames", int),
    "seed": ("seed", int),
    "width": ("width", int),
    "height": ("height", int),
    "person": ("person", bool),
    "chair": ("moved_chair", bool),
    "static": ("camera", lambda v: "static" if v else "orbit"),
    "span": ("orbit_span_deg", float),
}
_IGNORED = ("depth",)  # source options that do not change the world


def spec_options(spec: str) -> dict[str, int]:
    """The integer options of a ``synth:`` source spec (``synth:frames=200,seed=0`` → ``{"frames": 200, ...}``)."""
    if not spec.startswith("synth:"):
        raise ConfigError(f"not a synthetic source spec: {spec!r} (expected synth:frames=...,seed=...)")
    options = {}
    for item in filter(None, spec.split(":", 1)[1].lstrip("/").split(",")):
        key, _, value = item.partition("=")
        if not value.lstrip("-").isdigit():
            raise ConfigError(f"bad synthetic source option {item!r}: use e.g. synth:frames=200,seed=0")
        options[key.strip()] = int(value)
    return options


def config_from_options(**options: int) -> SynthConfig:
    """The :class:`SynthConfig` of integer options (``frames=200, seed=0``); source-only options (depth) are
    ignored, unknown ones raise ConfigError naming the known ones."""
    unknown = sorted(set(options) - set(OPTIONS) - set(_IGNORED))
    if unknown:
        raise ConfigError(f"unknown synthetic source option(s) {unknown}; known: {', '.join([*OPTIONS, *_IGNORED])}")
    return SynthConfig(**{OPTIONS[k][0]: OPTIONS[k][1](v) for k, v in options.items() if k in OPTIONS})


def config_from_spec(spec: str) -> SynthConfig:
    """The :class:`SynthConfig` a ``synth:`` source spec renders; ConfigError on anything else."""
    return config_from_options(**spec_options(spec))
