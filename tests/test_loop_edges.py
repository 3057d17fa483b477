"""Loop edges: a keyframe back where an older held keyframe was, beyond the BA window, gets proximity edges to it
(upkeep.add_loop_edges), and only then; the BA over the held keyframes uses them, the window BA does not."""
from __future__ import annotations

import math

import numpy as np
import torch

from services.ba.core import se3
from services.ba.core.params import FlowParams
from services.ba.frontend import upkeep
from services.ba.frontend.graph import KeyframeGraph
from services.ba.frontend.params import GraphParams

H, W, LAP = 24, 32, 40


def _pose(theta: float, pitch: float = 0.0, radius: float = 2.0) -> torch.Tensor:
    """A camera on a circle of ``radius`` at angle ``theta``, looking outward (optical axis z along the radius),
    tilted up by ``pitch``."""
    pose = torch.eye(4, dtype=torch.float64)
    yaw = se3.so3_exp(torch.tensor([0.0, theta, 0.0], dtype=torch.float64))
    tilt = se3.so3_exp(torch.tensor([pitch, 0.0, 0.0], dtype=torch.float64))
    pose[:3, :3] = yaw @ tilt
    pose[:3, 3] = torch.tensor([radius * math.sin(theta), 0.0, radius * math.cos(theta)])
    return pose


def _lap_graph(extra: torch.Tensor) -> KeyframeGraph:
    """A lap of ``LAP`` keyframes around a circle (each seeing a wall 3 m ahead), then one more at ``extra``."""
    graph = KeyframeGraph(torch.tensor([28.0, 28.0, 15.5, 11.5], dtype=torch.float64), (H, W), FlowParams(),
                          torch.device("cpu"))
    wall = torch.full((H, W), 1.0 / 3.0, dtype=torch.float64)
    grey = np.zeros((H * 8, W * 8), np.uint8)
    for k in range(LAP):
        graph.append(k, k, grey, None, None, _pose(2 * math.pi * k / LAP), wall.clone())
    graph.append(LAP, LAP, grey, None, None, extra, wall.clone())
    return graph


def _linked(graph: KeyframeGraph, params: GraphParams) -> set[int]:
    window = list(range(LAP - 9, LAP + 1))
    upkeep.add_loop_edges(graph, LAP, window, params)
    assert {(a, b) for a, b in graph.proximity if b == LAP} == {(b, a) for a, b in graph.proximity if a == LAP}
    return {a for a, b in graph.proximity if b == LAP}


def test_a_keyframe_back_at_the_start_of_its_lap_is_linked_to_the_keyframes_there():
    # back at the first keyframe's place, slightly off (the drift a loop edge is for)
    linked = _linked(_lap_graph(_pose(0.02, radius=2.05)), GraphParams(loop_max_edges=2))
    assert 0 in linked and linked <= {0, 1, 2}


def test_no_loop_edges_where_the_view_shares_nothing_or_they_are_off():
    assert _linked(_lap_graph(_pose(0.0, pitch=math.radians(80))), GraphParams(loop_max_edges=2)) == set()
    assert _linked(_lap_graph(_pose(0.0)), GraphParams(loop_max_edges=0)) == set()


def test_loop_edges_go_only_to_keyframes_older_than_the_window():
    # halfway round the lap the nearest keyframe (20) is older than the window: linked
    assert 20 in _linked(_lap_graph(_pose(math.pi)), GraphParams(loop_max_edges=3))
    # where keyframe 33 of the window is, the window's own keyframes are not linked (the window BA has them)
    assert _linked(_lap_graph(_pose(2 * math.pi * 33 / LAP)), GraphParams(loop_max_edges=3)) == set()


def test_a_keyframe_right_after_one_with_a_loop_edge_gets_none():
    wall = torch.full((H, W), 1.0 / 3.0, dtype=torch.float64)
    grey = np.zeros((H * 8, W * 8), np.uint8)
    for every, expected in ((4, set()), (1, {1})):
        graph = _lap_graph(_pose(0.0))
        _linked(graph, GraphParams(loop_max_edges=1, loop_every=every))
        graph.append(LAP + 1, LAP + 1, grey, None, None, _pose(2 * math.pi / LAP), wall.clone())
        window = list(range(LAP - 8, LAP + 2))
        upkeep.add_loop_edges(graph, LAP + 1, window, GraphParams(loop_max_edges=1, loop_every=every))
        assert {a for a, b in graph.proximity if b == LAP + 1} == expected, every


def test_loop_edges_are_set_from_the_environment(monkeypatch):
    from services.ba.settings import BaSettings

    assert BaSettings().frontend_params().graph.loop_max_edges == GraphParams().loop_max_edges > 0
    monkeypatch.setenv("KMVIPE_BA_LOOP_MAX_EDGES", "0")
    monkeypatch.setenv("KMVIPE_BA_LOOP_EVERY", "2")
    graph = BaSettings().frontend_params().graph
    assert (graph.loop_max_edges, graph.loop_every) == (0, 2)


def test_a_keyframe_back_at_a_landmark_is_linked_to_it_and_to_the_lap_before():
    # keyframes 0-9 are landmarks (the first lap, kept past keep_keyframes); 10-39 the recent lap: each kind of
    # target gets its own loop edge, so the lap before (whose drift it shares) does not hide the first visit
    graph = _lap_graph(_pose(0.02, radius=2.05))
    graph.landmarks = set(range(0, 40, 4))
    linked = _linked(graph, GraphParams(loop_max_edges=1))
    assert len(linked) == 2 and len(linked & graph.landmarks) == 1 and 0 in linked
    # the next keyframe gets neither kind: both were linked lately
    window = list(range(LAP - 8, LAP + 2))
    graph.append(LAP + 1, LAP + 1, np.zeros((H * 8, W * 8), np.uint8), None, None, _pose(2 * math.pi / LAP),
                 torch.full((H, W), 1.0 / 3.0, dtype=torch.float64))
    upkeep.add_loop_edges(graph, LAP + 1, window, GraphParams(loop_max_edges=1))
    assert {a for a, b in graph.proximity if b == LAP + 1} == set()


def test_temporal_edges_skip_landmarks_and_linked_landmarks_are_found():
    graph = _lap_graph(_pose(0.0))
    graph.landmarks = {0, 4}
    pairs = graph.pairs(list(range(LAP + 1)), radius=2)
    assert not any({a, b} & {0, 4} for a, b in pairs)  # list neighbours of a landmark are laps apart
    assert (1, 2) in pairs and (3, 5) in pairs  # the recent keyframes' neighbours close over the landmark's gap
    assert graph.recent() == [k for k in range(LAP + 1) if k not in (0, 4)]
    graph.proximity |= {(LAP, 4), (4, LAP)}
    assert graph.linked_landmarks(list(range(30, LAP + 1))) == [4]
    assert graph.linked_landmarks(list(range(30, LAP))) == []
    assert 4 in {b for a, b in graph.pairs([4] + list(range(30, LAP + 1)), radius=2) if a == LAP}
    graph.remove(4)
    assert graph.landmarks == {0}


def test_a_keyframe_leaving_is_a_new_place_unless_a_landmark_shows_it():
    graph = _lap_graph(_pose(0.0))
    gp = GraphParams()
    assert upkeep.new_place(graph, 3, gp)  # no landmark yet
    graph.landmarks = {graph.seqs[2]}
    assert not upkeep.new_place(graph, 3, gp)  # 9 degrees on, most of landmark 2's wall is in view
    assert upkeep.new_place(graph, 20, gp)  # the other side of the circle


def test_a_graph_pickled_before_landmarks_existed_loads_with_none():
    import pickle

    graph = _lap_graph(_pose(0.0))
    state = dict(graph.__dict__)
    del state["landmarks"]
    old = KeyframeGraph.__new__(KeyframeGraph)
    old.__dict__.update(state)
    loaded = pickle.loads(pickle.dumps(old))
    assert loaded.landmarks == set() and loaded.recent() == list(range(LAP + 1))
