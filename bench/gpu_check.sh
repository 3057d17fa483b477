#!/usr/bin/env bash
# GPU check on a lent device machine (library entry `device`): the CUDA paths under the tests, then KITTI 07 live
# and lossless with the backbone on the GPU. The machine has no registry access and Python 3.12 with torch, so
# the project's other wheels travel in .whl/ (see docs/BENCHMARKS.md, "GPU"), KITTI in .gpudata/, and the
# backbone is a random-weight DINOv2 ViT-B/14-reg of the hub layout: timings do not depend on the weights.
# Prepare here (both folders git-ignored through .git/info/exclude, then named in the device call's `carry`):
#   echo /.whl/ >> .git/info/exclude; echo /.gpudata/ >> .git/info/exclude
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
#     <each of: fastapi starlette pydantic pydantic_core pydantic-settings python-dotenv annotated-types
#      typing-inspection uvicorn eclipse-zenoh python-json-logger prometheus-fastapi-instrumentator rosbags lz4
#      cryptography cffi typing_extensions, at the versions `.venv/bin/pip list` shows>
#   mkdir -p .gpudata && cp -r ../shared/data/kitti07_160 .gpudata/
# Usage there: bash bench/gpu_check.sh   (writes $OUT/*.log and $OUT/live.json)
set -uo pipefail
OUT=${OUT:-/tmp/gpu-out}; mkdir -p "$OUT"
# into the image's own Python (the one with torch; the machine is thrown away after the lease)
PY=/opt/torch/.venv/bin/python3; [ -x "$PY" ] || PY=$(command -v python3)
$PY -m pip install -q --no-index --no-deps --no-compile .whl/*.whl || exit 1
$PY -m pip install -q --no-index --no-deps --no-build-isolation -e . || exit 1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
nproc
export KMVIPE_MODELS_DIR=/tmp/models KMVIPE_FEATURES_MODELS_DIR=/tmp/models KMVIPE_DATA_DIR=$PWD/.gpudata PYTHONUNBUFFERED=1
$PY - <<'PY'
import torch, transformers
cfg = transformers.Dinov2WithRegistersConfig(hidden_size=768, num_hidden_layers=12, num_attention_heads=12,
                                             num_register_tokens=4, patch_size=14, image_size=518)
transformers.Dinov2WithRegistersModel(cfg).save_pretrained("/tmp/models/dinov2-vitb14-reg")
print("torch", torch.__version__, "cuda", torch.cuda.is_available(), "transformers", transformers.__version__)
PY
echo "== KITTI 07 realtime and lossless, ViT-B/14-reg on the GPU"
export KMVIPE_FEATURES_BACKBONE=dinov2-vitb14-reg KMVIPE_QUERY_BACKBONE=dinov2-vitb14-reg
timeout 130 $PY bench/live.py --kitti --json "$OUT/live.json" --out /tmp/live 2>&1 | tee "$OUT/live_rt.log" | tail -30
timeout 160 $PY bench/live.py --kitti --lossless --json "$OUT/live_lossless.json" --out /tmp/live2 2>&1 \
  | tee "$OUT/live_ll.log" | tail -30
for f in /tmp/live*/*/logs/*.log; do echo "-- $f"; tail -4 "$f"; done 2>/dev/null | tail -40
echo "== tests (not slow) with CUDA present"
timeout 170 $PY -m pytest -v -m "not slow" -n 14 -p no:cacheprovider --maxfail=30 tests > "$OUT/pytest.log" 2>&1; grep -E "FAILED|ERROR|passed|failed" "$OUT/pytest.log" | tail -40
