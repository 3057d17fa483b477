"""The metric code of bench/query_example.py and its core, bench/query_metrics.py, on cases with a known answer
(no model, no data files).

The end-to-end case uses the synthetic world's oracle features (services/synth: one unit vector per label plus
noise): two "chair" instances share a vector (same category, indistinguishable), a "table" has its own, so the
precision of each query at the mapstore's default threshold is known exactly.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from services.mapstore.config import RegionParams
from services.query_api.core.example import pooled_feature
from services.synth import label_vectors, oracle_features

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def qe():
    spec = importlib.util.spec_from_file_location("bench_query_example", REPO / "bench" / "query_example.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclass/NamedTuple introspection looks the module up by name
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def qm(qe):
    """Its metric core (bench/query_metrics.py), as the bench imported it."""
    return sys.modules["query_metrics"]


def test_cell_majority_known_answer(qe):
    labels = np.zeros((6, 9), np.int64)
    labels[:3, :3] = 7  # a whole cell
    labels[3:, 3:5] = 5  # 6 of the 9 pixels of cell (1, 1): majority
    labels[:2, 6:] = 2**40  # big ids (ADT instance ids) survive
    labels[2, 6:] = 3
    expected = np.array([[7, 0, 2**40], [0, 5, 0]])
    np.testing.assert_array_equal(qe.cell_majority(labels, (2, 3)), expected)
    # a grid that does not divide the image: pixel centres decide (columns 0-2 | 3-6 | 7-9 for 10 → 3 cells),
    # and with every label once per cell the tie goes to the smallest
    ramp = np.repeat(np.arange(10)[None], 4, axis=0)
    np.testing.assert_array_equal(qe.cell_majority(ramp, (1, 3)), [[0, 3, 7]])


def test_prf_and_oracle_threshold(qm):
    rel = np.array([True, False, True, False])
    p = qm.prf(np.array([True, True, True, False]), rel)
    assert (p.precision, p.recall, p.retrieved) == (pytest.approx(2 / 3), 1.0, 3)
    assert qm.prf(np.zeros(4, bool), rel).precision == 0.0  # nothing retrieved: precision 0, not NaN
    t, f1 = qm.best_f1_threshold(np.array([0.9, 0.8, 0.7, 0.6]), rel)
    assert (t, f1) == (0.7, pytest.approx(0.8))
    # equal scores cannot be split: the best is t = 0.9 (both retrieved), not the 1.0 of retrieving one
    t, f1 = qm.best_f1_threshold(np.array([0.9, 0.9, 0.5]), np.array([True, False, False]))
    assert (t, f1) == (0.9, pytest.approx(2 / 3))


def test_product_threshold_is_the_mapstores(qm):
    """The bench's threshold is the one the mapstore applies to a query that names none (``threshold=-1``)."""
    from services.mapstore.queries import _threshold

    s = np.array([0.2, np.nan, 0.9, 0.5])
    assert qm.product_threshold(s) == pytest.approx(RegionParams().relative_threshold * 0.9)
    for params in (RegionParams(), RegionParams(relative_threshold=0.0, score_threshold=0.3)):
        for scores in (s, np.array([np.nan, np.nan]), np.array([-0.4, 0.1])):
            assert qm.product_threshold(scores, params) == pytest.approx(_threshold(scores, -1.0, params))


def test_paint_labels_order_and_regions(qe):
    regions = [{"class": "car", "box": [2, 1, 4, 3]}, {"class": "road", "polygon": [[0, 0], [3, 0], [3, 2], [0, 2]]}]
    labels = qe.paint_labels(regions, (4, 6), ["road", "car"])  # car painted last: on top of the road
    expected = np.array([[0, 0, 0, 0, -1, -1],
                         [0, 0, 1, 1, -1, -1],
                         [0, 0, 1, 1, -1, -1],
                         [-1, -1, -1, -1, -1, -1]])
    np.testing.assert_array_equal(labels, expected)


def _synthetic_map(qe, noise: float = 0.05):
    """Two 12×16 frames; ids 1, 2 = chairs (same vector), 3 = table, 4 = a table-like decoy in frame 0 only."""
    vecs = label_vectors(3, 64, seed=0)  # 0 floor, 1 chair, 2 table
    vec_of = {0: 0, 1: 1, 2: 1, 3: 2, 4: 2}
    rng = np.random.default_rng(0)
    ids = []
    for shift in (0, 1):
        m = np.zeros((12, 16), np.int64)
        m[2:5, 1 + shift:5 + shift] = 1
        m[7:10, 1:4] = 2
        m[2:8, 8 + shift:13 + shift] = 3
        if shift == 0:
            m[9:11, 10:14] = 4
        ids.append(m)
    frames = []
    for i, m in enumerate(ids):
        f = oracle_features(np.vectorize(vec_of.get)(m), vecs, noise, rng)  # (h, w, D)
        feats = np.ascontiguousarray(f.transpose(2, 0, 1))
        frames.append(qe.Frame(f"f{i}", feats, m, np.ones(m.shape, bool), np.ones(m.shape, bool)))
    groups = {0: "floor", 1: "chair", 2: "chair", 3: "table", 4: "table"}
    queries = [qe.Query(0, t, groups[t], "mask", pooled_feature(frames[0].features, ids[0] == t), str(t))
               for t in (1, 3, 4)]  # 4 is absent from frame 1: no ground truth there, so not evaluated
    return frames, queries, groups, ids


@pytest.mark.parametrize("mode", ["pca", "raw", "centred"])
def test_evaluate_known_answer_on_oracle_features(qe, mode):
    frames, queries, groups, ids = _synthetic_map(qe)
    rows = {r["region"]: r for r in qe.evaluate(frames, queries, groups, mode)}
    assert set(rows) == {"1", "3"}
    other = ids[1]
    chair, table = rows["1"], rows["3"]
    # chairs are indistinguishable: the chair query finds both, its own instance is a share of them
    n1, n2 = (other == 1).sum(), (other == 2).sum()
    assert chair["product"]["precision"] == pytest.approx(n1 / (n1 + n2))
    assert chair["product"]["recall"] == 1.0
    assert chair["product_group"]["precision"] == 1.0 and chair["product_group"]["recall"] == 1.0
    assert chair["base_rate"] == pytest.approx(n1 / other.size)
    # the table is unique in frame 1; the decoy of frame 0 (same vector) must not count: other frames only
    assert table["product"] == {"precision": 1.0, "recall": 1.0, "f1": 1.0, "retrieved": int((other == 3).sum())}
    assert table["oracle_query"]["f1"] == 1.0
    t, res = qe.global_oracle([table])
    assert res[0].f1 == 1.0 and 0.0 < t < 0.95


def test_evaluate_noise_lowers_precision_at_fixed_threshold(qe):
    """With heavy noise the fixed 0.5 threshold misses cells: the metric must see it (it can fail)."""
    frames, queries, groups, _ = _synthetic_map(qe, noise=3.0)
    table = next(r for r in qe.evaluate(frames, queries, groups, "raw") if r["region"] == "3")
    assert table["fixed"]["recall"] < 0.5
    tables = qe.group_table(qe.evaluate(frames, queries, groups, "raw"), with_group=True)
    assert [r["group"] for r in tables] == ["chair", "table", "all"]
    assert tables[-1]["queries"] == 2 and np.isnan(tables[-1]["box_P"])  # no box queries in this case
