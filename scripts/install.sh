#!/usr/bin/env bash
# Creates .venv (if missing) and installs KM-ViPE into it.
#   VENV=.venv            where (created if missing)
#   EXTRAS=models,dev     optional dependency groups ("" for none)
#   EDITABLE=1            1: editable install for development (edits to services/ take effect at once);
#                         0: a regular install, as in production (the Dockerfile): the package is copied into
#                         the venv, so it runs from any directory and never imports the checkout
# PyTorch goes in first and pinned: an unpinned torch pulls several GB of CUDA packages,
# so on a machine without an NVIDIA GPU we take the CPU build.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${VENV:-.venv}
TORCH_VERSION=${TORCH_VERSION:-2.13.0}
EXTRAS=${EXTRAS-models,dev}
EDITABLE=${EDITABLE:-1}
case "$EDITABLE" in
  0|1) ;;
  *) echo "EDITABLE must be 0 or 1 (got $EDITABLE)" >&2; exit 1 ;;
esac

if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
  echo "KM-ViPE needs Python >= 3.11 (found $("$PY" --version)); set PYTHON=/path/to/python3.11" >&2
  exit 1
fi
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
PIP="$VENV/bin/python -m pip"
# The stamp records how the venv was installed; it is current when it says the same, is newer than
# pyproject.toml and, for a regular (copied) install, newer than every file of the package.
stamp="$VENV/.kmvipe-installed"
want="editable=$EDITABLE extras=$EXTRAS"
if [ -f "$stamp" ] && [ "$stamp" -nt pyproject.toml ] && [ "$(cat "$stamp")" = "$want" ]; then
  if [ "$EDITABLE" = 1 ] || [ -z "$(find services -newer "$stamp" -print -quit)" ]; then exit 0; fi
fi

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
spec="."
[ -n "$EXTRAS" ] && spec=".[$EXTRAS]"
if [ "$EDITABLE" = 1 ]; then
  $PIP install -e "$spec"
else
  # setuptools builds in ./build; a stale build/lib would put modules deleted since into the wheel.
  # pip always rebuilds and reinstalls a local directory, so the venv gets the checkout as it is now.
  rm -rf build
  $PIP install "$spec"
fi
if [[ ",$EXTRAS," == *",dev,"* ]]; then
  # evo, the reference RPE/ATE implementation tests/test_rpe.py compares with: its core needs only numpy and
  # scipy, and its plotting dependencies (matplotlib, pandas, seaborn...) are not needed for that
  $PIP install --no-deps "evo==1.38.1"
fi
echo "$want" > "$stamp"
