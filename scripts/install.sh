#!/usr/bin/env bash
# Creates .venv (if missing) and installs KM-ViPE into it.
# PyTorch goes in first and pinned: an unpinned torch pulls several GB of CUDA packages,
# so on a machine without an NVIDIA GPU we take the CPU build.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${VENV:-.venv}
TORCH_VERSION=${TORCH_VERSION:-2.13.0}
EXTRAS=${EXTRAS:-models,dev}

if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
  echo "KM-ViPE needs Python >= 3.11 (found $("$PY" --version)); set PYTHON=/path/to/python3.11" >&2
  exit 1
fi
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
PIP="$VENV/bin/python -m pip"
stamp="$VENV/.kmvipe-installed"
if [ -f "$stamp" ] && [ "$stamp" -nt pyproject.toml ]; then exit 0; fi

if ! "$VENV/bin/python" -c "import torch" 2>/dev/null; then
  if command -v nvidia-smi >/dev/null 2>&1; then
    $PIP install "torch==$TORCH_VERSION"
  else
    # A local CPU wheel first (offline machines and CI: pip's find-links), else PyTorch's CPU index;
    # its dependencies then come from the ordinary index.
    if $PIP install --no-deps --no-index "torch==$TORCH_VERSION" 2>/dev/null; then
      $PIP install "torch==$TORCH_VERSION"
    else
      $PIP install "torch==$TORCH_VERSION" --index-url https://download.pytorch.org/whl/cpu \
        --extra-index-url https://pypi.org/simple
    fi
  fi
fi
$PIP install -e ".[$EXTRAS]"
touch "$stamp"
