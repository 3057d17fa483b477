"""Whether a keyframe's aligned pose is a plausible step from the keyframes before it, and the prediction that
replaces one that is not. Speeds over time gaps, not step lengths: keyframes come every frame while a car
drives fast and every dozen while a hand-held camera creeps, and a live stream's keyframes merged into frames
leave gaps of several frames between mapped ones."""
from __future__ import annotations

import torch

from services.ba.core import se3
from services.ba.frontend.graph import STILL_STEP, KeyframeGraph
from services.ba.frontend.tracker import MAX_EXTRAPOLATION


def recent_speed(graph: KeyframeGraph, k: int) -> float:
    """Median speed (length per nanosecond) between consecutive keyframes among the six before ``k``."""
    first = max(0, k - 6)
    centres = torch.stack([graph.poses[i][:3, 3] for i in range(first, k)])
    dt = torch.tensor(graph.stamps[first:k], dtype=torch.float64, device=centres.device).diff().clamp_min(1.0)
    return float(((centres[1:] - centres[:-1]).norm(dim=-1) / dt).median())


def held_path(graph: KeyframeGraph, k: int) -> tuple[float, float]:
    """Path length and nanoseconds from the oldest held keyframe to keyframe ``k - 1``."""
    centres = torch.stack([graph.poses[i][:3, 3] for i in range(k)])
    return float((centres[1:] - centres[:-1]).norm(dim=-1).sum()), float(max(1, graph.stamps[k - 1] - graph.stamps[0]))


def median_depth(graph: KeyframeGraph, k: int) -> float:
    """Keyframe ``k``'s median depth (1 / its median disparity)."""
    return 1.0 / float(graph.disparity[k].median().clamp_min(1e-12))


def still_between(graph: KeyframeGraph, a: int, b: int) -> bool:
    """Keyframes ``a`` and ``b`` lie less than a hundredth of ``b``'s depth apart: their flow has no baseline."""
    return float((graph.poses[a][:3, 3] - graph.poses[b][:3, 3]).norm()) < STILL_STEP * median_depth(graph, b)


def turned_on_the_spot(graph: KeyframeGraph, k: int) -> bool:
    """Keyframe ``k``'s steps to its held neighbours are all still (:func:`still_between`): nothing has measured
    its depth yet."""
    near = [i for i in (k - 1, k + 1) if 0 <= i < len(graph)]
    return bool(near) and all(still_between(graph, i, k) for i in near)


def reference_speed(graph: KeyframeGraph, k: int) -> float:
    """The speed keyframe ``k``'s step is judged by: the recent median (:func:`recent_speed`), or the held keyframes'
    mean speed (path / time) where that is higher. After a turn on the spot the recent steps are all still, their
    median is 0, and every step of the walk that followed was refused (pure_rotation: its last 40 cm missing)."""
    path, span = held_path(graph, k)
    return max(recent_speed(graph, k), path / span)


def never_moved(graph: KeyframeGraph, k: int) -> bool:
    """The held keyframes before ``k`` span less than a hundredth of the scene's depth (a map started on the
    spot, turning): there is no speed to judge a first translation by, and it sets the map's scale."""
    return held_path(graph, k)[0] < STILL_STEP * median_depth(graph, k - 1)


def gap(graph: KeyframeGraph, k: int) -> float:
    """Nanoseconds between keyframe ``k`` and the one before."""
    return float(max(1, graph.stamps[k] - graph.stamps[k - 1]))


def plausible(graph: KeyframeGraph, pose: torch.Tensor, k: int, max_growth: float) -> bool:
    """Motion-only alignment of a keyframe whose flow barely constrains it (near objects lost by DIS, a forward
    motion along the depth ambiguity) can slide far along its free direction; kept, that step would be repeated by
    every later constant-velocity prediction. ``pose`` (world_from_cam of keyframe ``k``) must keep its speed from
    keyframe ``k - 1`` within ``max_growth`` times :func:`reference_speed`; any step is plausible after a map that never
    moved (:func:`never_moved`)."""
    if k < 3 or never_moved(graph, k):
        return True
    step = float((pose[:3, 3] - graph.poses[k - 1][:3, 3]).norm())
    return step <= max_growth * reference_speed(graph, k) * gap(graph, k)


def bounded_prediction(graph: KeyframeGraph, k: int) -> torch.Tensor:
    """The motion from keyframe ``k - 2`` to ``k - 1`` continued over keyframe ``k``'s time gap, its translation no
    longer than the recent median speed allows."""
    span = float(max(1, graph.stamps[k - 1] - graph.stamps[k - 2]))
    twist = se3.log(se3.inverse(graph.poses[k - 2]) @ graph.poses[k - 1])
    rel = se3.exp(min(gap(graph, k) / span, MAX_EXTRAPOLATION) * twist)
    length, allowed = float(rel[:3, 3].norm()), reference_speed(graph, k) * gap(graph, k)
    if length > allowed > 0:
        rel = rel.clone()
        rel[:3, 3] *= allowed / length
    return se3.orthonormalize(graph.poses[k - 1] @ rel)


def early(graph: KeyframeGraph, k: int, factor: float) -> bool:
    """Keyframe ``k`` comes within ``factor`` x the median spacing of the six keyframes before it (time)."""
    if k < 3:
        return False
    stamps = torch.tensor(graph.stamps[max(0, k - 7):k], dtype=torch.float64)
    return gap(graph, k) < factor * float(stamps.diff().median())
