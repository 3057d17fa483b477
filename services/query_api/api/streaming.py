"""Streaming the fused map as PLY: the header from the first chunk, then every chunk as it arrives (plyfile writes
only whole arrays: services/common/ply.py)."""
from __future__ import annotations

import logging
from typing import AsyncIterator

import numpy as np
from fastapi.concurrency import run_in_threadpool

from ...common.schema import MapChunk
from ..core import ply

log = logging.getLogger(__name__)


async def ply_stream(gw, stream: str, first: MapChunk, chunk_points: int, session: str = "") -> AsyncIterator[bytes]:
    """PLY bytes of the map of ``stream``. The vertex count is the first chunk's ``total_points``; should the
    map grow or shrink while it streams, the body is cut or padded (with the last point) to match the header."""
    total = int(first.total_points)
    yield ply.header(total, comment=f"KM-ViPE map of stream {stream}")
    sent, chunk, index = 0, first, 0
    last = (np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8))
    while sent < total:
        take = min(len(chunk.xyz), total - sent)
        if take:
            yield ply.vertices(chunk.xyz[:take], chunk.rgb[:take])
            sent += take
            last = (chunk.xyz[take - 1:take], chunk.rgb[take - 1:take])
        index += 1
        if sent >= total or index >= first.n_chunks:
            break
        chunk = await run_in_threadpool(gw.maps.export_chunk, stream, index, chunk_points, session)
    if sent < total:
        log.warning("map shrank while streaming; padding", extra={"stream": stream, "missing": total - sent})
        yield ply.vertices(np.repeat(last[0], total - sent, 0), np.repeat(last[1], total - sent, 0))
