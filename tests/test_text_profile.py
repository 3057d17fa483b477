"""``kmvipe run --text talk2dino``: the backbone the text head targets, every model checked before the stream
starts (a missing one ends the run in seconds with the exact pull commands), and, with tiny random stand-ins of
the registered models in an air-gapped folder, a full run whose map answers a text query over HTTP."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from services.common.models.tiny import write_tiny_model
from services.features.oracle import ORACLE_BACKBONE
from services.runner import semantics
from tests.helpers.processes import served_run

KMVIPE = Path(sys.executable).parent / "kmvipe"
SOURCE = "synth:frames=24,width=256,height=192"
PROFILE_MODELS = ("dinov2-vitb14-reg", "clip-vitb16-text", "talk2dino-vitb")


def _user_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    env["HF_HUB_OFFLINE"] = "1"
    return env | extra


def test_the_oracle_name_is_the_features_services():
    assert semantics.ORACLE_BACKBONE == ORACLE_BACKBONE


def test_profiles_pick_the_backbone_the_text_head_targets():
    t2d = semantics.semantic_profile("talk2dino", SOURCE, {})
    assert t2d.backbone == "dinov2-vitb14-reg" and set(t2d.models) == set(PROFILE_MODELS)
    assert t2d.env["features"]["KMVIPE_FEATURES_BACKBONE"] == t2d.env["query_api"]["KMVIPE_QUERY_BACKBONE"]
    plain = semantics.semantic_profile("none", SOURCE, {})
    assert not plain.support.text and "--text talk2dino" in plain.support.text_why and plain.support.example
    oracle = semantics.semantic_profile("oracle", SOURCE, {})
    assert oracle.support.oracle and oracle.env["features"]["KMVIPE_FEATURES_ORACLE_SOURCE"] == SOURCE
    with pytest.raises(semantics.KmVipeError, match="synthetic source"):
        semantics.semantic_profile("oracle", "video.mp4", {})


def test_missing_models_end_the_run_in_seconds_with_the_pull_commands(tmp_path):
    models = tmp_path / "models"
    write_tiny_model("clip-vitb16-text", models)  # one of three present: only the two others are named
    start = time.monotonic()
    done = subprocess.run([str(KMVIPE), "run", SOURCE, "--text", "talk2dino", "--out", "out"], cwd=tmp_path,
                          env=_user_env(KMVIPE_MODELS_DIR=str(models)), capture_output=True, text=True, timeout=60)
    took = time.monotonic() - start
    assert done.returncode == 2, done.stdout + done.stderr
    assert took < 5.0, f"took {took:.1f} s"
    for name in ("dinov2-vitb14-reg", "talk2dino-vitb"):
        assert f"kmvipe models --models-dir {models.resolve()} pull {name}" in done.stderr
    assert "pull clip-vitb16-text" not in done.stderr
    assert not (tmp_path / "out").exists(), "nothing may start before the models are there"


# A plain run (no --text) saying which queries its map supports: tests/test_first_contact.py checks it on its run.


@pytest.mark.slow
def test_tiny_stand_ins_answer_a_text_query_end_to_end(tmp_path):
    models = tmp_path / "models"
    for name in PROFILE_MODELS:
        write_tiny_model(name, models)
    with served_run(["run", SOURCE, "--text", "talk2dino"], tmp_path, _user_env(KMVIPE_MODELS_DIR=str(models))) as url:
        streams = httpx.get(f"{url}/v1/streams", timeout=60).json()["streams"]
        assert streams[0]["map"]["backbone"] == "dinov2_vitb14_reg"
        assert streams[0]["queries"]["text"], streams[0]["queries"]
        r = httpx.post(f"{url}/v1/streams/cam0/query", json={"texts": ["chair"], "top_k": 5}, timeout=60)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["space"] == "dinov2_vitb14_reg" and not body["oracle"]
        assert body["encoder"] == "clip-vitb16-text+talk2dino-vitb"
        assert body["results"][0]["top_points"], "a map with points returns its best-scoring ones"
