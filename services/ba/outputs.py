"""The messages mapping publishes for a frontend update: its graph (keyframe poses and maps), frame poses, and the
intrinsics when they changed (or at the end of a stream)."""
from __future__ import annotations

from services.ba.frontend.frontend import Frontend
from services.ba.frontend.updates import PoseUpdate, Update
from services.common import keys
from services.common.schema import Graph, Intrinsics, Message, Poses

Outputs = list[tuple[str, Message]]


def outputs_of(fe: Frontend, msg: Message, update: Update, final: bool) -> Outputs:
    """What ``update`` (from handling ``msg``) publishes."""
    return outputs_at(fe, msg.stream, msg.seq, msg.t_ns, update, final)


def outputs_at(fe: Frontend, stream: str, seq: int, t_ns: int, update: Update, final: bool) -> Outputs:
    """The ``graph``, ``pose`` and ``intrinsics`` messages of a frontend ``update``, stamped ``seq`` / ``t_ns``."""
    out: Outputs = []
    width, height = fe.size
    if update.graph is not None:
        g = update.graph
        out.append((keys.topic(stream, keys.GRAPH), Graph(
            stream, seq, t_ns, kf_seqs=g.kf_seqs, poses=g.poses, intrinsics=g.intrinsics, width=width,
            height=height, updated_seqs=g.updated_seqs, disparities=g.disparities, static_weights=g.static_weights,
            confidence=g.confidence, metric=g.metric, final=final)))
    if update.poses is not None:
        out.append(poses_out(stream, seq, t_ns, update.poses, final))
    if update.intrinsics_changed or (final and fe.intrinsics is not None):
        out.append((keys.topic(stream, keys.INTRINSICS), Intrinsics(
            stream, seq, t_ns, intrinsics=fe.intrinsics, width=width, height=height)))
    return out


def poses_out(stream: str, seq: int, t_ns: int, poses: PoseUpdate, final: bool) -> tuple[str, Poses]:
    return keys.topic(stream, keys.POSE), Poses(stream, seq, t_ns, frame_seqs=poses.frame_seqs,
                                                stamps_ns=poses.stamps_ns, poses=poses.poses, final=final)
