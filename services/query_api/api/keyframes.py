"""Routes of query by keyframe region: the keyframes a map holds, their thumbnails, and a region of one of them
as the query (``kmvipe/<s>/map/{keyframes,keyframe,example}``, services/mapstore/keyframe_queries.py).

Unlike ``/query/example`` this needs no backbone in the gateway: the mapstore pools the codes the map was built
from, so it answers wherever the map does, in the map's own feature space.
"""
from __future__ import annotations

import time
from typing import Annotated, Optional

import numpy as np
from fastapi import APIRouter, HTTPException, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ...common.schema import KeyframeList, KeyframeQuery, KeyframeRefusal, KeyframeThumbnail, MapAnswer, Message
from ..core.answers import RegionParams, group_answer
from ..gateway import Answer, Gateway
from ..mapclient import MapClient, MapServiceError, QueryOptions
from . import models as m
from .routes import ERRORS, STREAM, _answer_out, _options, _stream

router = APIRouter(prefix="/v1", responses=ERRORS)
REFUSAL_STATUS = {"not_found": 404, "no_codes": 409, "bad_request": 422}  # KeyframeRefusal.status → HTTP
Unit = Annotated[float, Field(ge=0.0, le=1.0)]
SEQ_MAX = 2**63 - 1  # a frame seq travels to the mapstore as a msgpack int64: a larger one is a 422, not a 500
Seq = Annotated[int, Field(ge=0, le=SEQ_MAX)]
UNKNOWN_VERB = "unknown map verb"  # how a map service without these verbs refuses them (mapstore/queries.py, refmap.py)


class KeyframeOut(BaseModel):
    seq: int = Field(description="The keyframe's frame seq.")
    t_ns: int
    width: int = Field(description="Working image width (px) the keyframe was mapped at.")
    height: int
    has_codes: bool = Field(description="Its DINO codes (and their PCA basis) are in: it can be queried by region.")
    has_thumbnail: bool


class KeyframesResponse(BaseModel):
    stream: str
    total: int = Field(description="Keyframes the map holds (the list may be the newest of them only).")
    keyframes: list[KeyframeOut] = Field(description="Ascending seq.")


class KeyframeQueryRequest(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"seq": 12, "box": [0.25, 0.4, 0.5, 0.8]}, {"seq": 12, "box": [0.3, 0.6, 0.3, 0.6], "top_k": 10}]})
    seq: Seq = Field(description="The keyframe (a seq from GET /keyframes).")
    box: list[Unit] = Field(min_length=4, max_length=4, description="Region [x0, y0, x1, y1] normalised to the "
                            "image (0 = left/top edge, 1 = right/bottom edge); x0 = x1, y0 = y1: the 1/8-grid cell "
                            "under that point (a click).")
    top_k: int = Field(20, ge=1, le=10_000)
    threshold: Optional[float] = Field(None, ge=-1.0, le=1.0)
    max_regions: int = Field(10, ge=1, le=1000)

    @model_validator(mode="after")
    def _ordered(self) -> "KeyframeQueryRequest":
        if self.box[0] > self.box[2] or self.box[1] > self.box[3]:
            raise ValueError(f"box {self.box} is inverted: need x0 <= x1 and y0 <= y1")
        return self


class KeyframeClient(MapClient):
    """The keyframe verbs of the mapstore; a refusal becomes an HTTPException with its status."""

    def _reply(self, stream: str, verb: str, payload: bytes | None, expect: type[Message], params: str = ""):
        try:
            reply = self._ask(stream, verb, payload, None, params)  # type: ignore[arg-type]  # any kind: refusals too
        except MapServiceError as exc:
            if UNKNOWN_VERB not in str(exc):
                raise
            why = (f"the map of stream '{stream}' keeps no keyframes: its map service does not serve '{verb}' "
                   "(a reference map, or a mapstore older than this gateway)")
            raise HTTPException(404, why) from exc
        if isinstance(reply, KeyframeRefusal):
            raise HTTPException(REFUSAL_STATUS[reply.status], reply.reason)
        if not isinstance(reply, expect):
            raise HTTPException(502, f"mapstore of stream '{stream}' answered {verb} with a '{reply.KIND}' message")
        return reply

    def keyframes(self, stream: str) -> KeyframeList:
        return self._reply(stream, "keyframes", None, KeyframeList)

    def thumbnail(self, stream: str, seq: int) -> KeyframeThumbnail:
        return self._reply(stream, "keyframe", None, KeyframeThumbnail, f"seq={seq}")

    def region(self, stream: str, seq: int, box: list[float], opts: QueryOptions) -> MapAnswer:
        q = KeyframeQuery(stream, next(self._request_ids), time.time_ns(), keyframe=seq,
                          box=np.asarray(box, np.float64), top_k=opts.top_k, threshold=opts.threshold,
                          max_regions=opts.max_regions, with_points=opts.with_points)
        return self._reply(stream, "example", q.encode(), MapAnswer)


def _client(request: Request) -> KeyframeClient:
    state = request.app.state
    if getattr(state, "keyframe_client", None) is None:
        gw: Gateway = state.gateway
        state.keyframe_client = KeyframeClient(gw.bus, gw.cfg.timeout_s)
    return state.keyframe_client


@router.get("/streams/{stream}/keyframes", response_model=KeyframesResponse, summary="Keyframes of the map")
async def list_keyframes(request: Request, stream: str = STREAM,
                         limit: int = Query(0, ge=0, le=100_000, description="Only the newest this many (0: all).")):
    stream = _stream(stream)
    kl = await run_in_threadpool(_client(request).keyframes, stream)
    rows = list(zip(kl.seqs.tolist(), kl.stamps_ns.tolist(), kl.widths.tolist(), kl.heights.tolist(),
                    kl.has_codes.tolist(), kl.has_thumbnail.tolist()))
    rows = rows[-limit:] if limit else rows
    return KeyframesResponse(stream=stream, total=len(kl.seqs), keyframes=[
        KeyframeOut(seq=s, t_ns=t, width=w, height=h, has_codes=bool(c), has_thumbnail=bool(th))
        for s, t, w, h, c, th in rows])


@router.get("/streams/{stream}/keyframes/{seq}/thumbnail", summary="A keyframe's thumbnail (JPEG)",
            response_class=Response, responses={200: {"content": {"image/jpeg": {}}}})
async def keyframe_thumbnail(request: Request, seq: Annotated[int, Path(ge=0, le=SEQ_MAX)],
                             stream: str = STREAM) -> Response:
    """The small JPEG the mapstore kept of the keyframe (longest side KMVIPE_MAPSTORE_THUMBNAIL_SIDE)."""
    stream = _stream(stream)
    thumb = await run_in_threadpool(_client(request).thumbnail, stream, seq)
    return Response(thumb.jpeg, media_type="image/jpeg", headers={
        "X-Image-Size": f"{thumb.width}x{thumb.height}", "Cache-Control": "private, max-age=60"})


@router.post("/streams/{stream}/query/keyframe", response_model=m.QueryResponse, summary="Query by keyframe region")
async def query_keyframe(request: Request, body: KeyframeQueryRequest, stream: str = STREAM) -> m.QueryResponse:
    """A box on one of the map's keyframes → the mean of its codes under the box, in the map's feature space →
    the same answer as a text query (regions and top points). 404: no such keyframe; 409: its codes are not in."""
    stream = _stream(stream)
    opts = _options(request, body.top_k, body.threshold, body.max_regions)
    gw: Gateway = request.app.state.gateway
    ans = await run_in_threadpool(_client(request).region, stream, body.seq, body.box, opts)
    results = group_answer(1, ans.region_query, ans.region_score, ans.region_centroid, ans.region_box_min,
                           ans.region_box_max, ans.region_count, ans.point_query, ans.point_xyz, ans.point_score,
                           RegionParams())
    space = await run_in_threadpool(gw.map_space, stream)
    return _answer_out(stream, [f"keyframe {body.seq}"], Answer(results, space, int(ans.n_points), ans.all_scores))
