"""bench/machine_reference.py: the workload runs and times itself, in this process and in a one-thread process."""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import machine_reference  # noqa: E402


def test_the_workload_times_both_parts():
    ref = machine_reference.measure(repeats=1)
    assert set(ref) == {"dis_flow_ms", "matmul_ms"}
    assert all(0 < value < 10_000 for value in ref.values())


def test_the_reference_runs_in_a_process_of_its_own_and_reads_as_a_cell():
    ref = machine_reference.reference()
    assert ref is not None and ref["dis_flow_ms"] > 0 and ref["matmul_ms"] > 0
    cell = machine_reference.describe(ref)
    assert "DIS flow 808×240" in cell and "one thread" in cell
    assert machine_reference.describe(None) == "– (not measured)"
