"""Idle runtime threads sleep instead of spinning on the shared CPU (services/__init__.py for torch's OpenMP pool;
the onnxruntime session's own option is checked in test_models_imgfocus.py)."""
from __future__ import annotations

import os
import subprocess
import sys

# ba solves in torch (features on the CPU does not load it)
PROBE = ("import sys, os; import services.ba.service; "
         "print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)")


def _probe(env_policy: str | None) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if env_policy is not None:
        env["OMP_WAIT_POLICY"] = env_policy
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_a_service_process_loads_torch_with_its_openmp_threads_sleeping():
    assert _probe(None) == ["PASSIVE", "True"]


def test_a_wait_policy_the_user_set_is_kept():
    assert _probe("ACTIVE") == ["ACTIVE", "True"]
