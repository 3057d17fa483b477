"""The /v1 routes: thin — validate, call the gateway in a worker thread, shape the answer."""
from __future__ import annotations

import base64
import binascii

import cv2
import numpy as np
from fastapi import APIRouter, HTTPException, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import PlainTextResponse, Response, StreamingResponse

from ...common import keys
from ...common.errors import ConfigError
from ...common.query_support import EXAMPLE_WHY
from ..core import ply
from ..core.imagesize import declared_size
from ..core.answers import apply_min_score, label_palette, segment_summary, subsample
from ..core.trajectory import tum_text
from ..gateway import Answer, Gateway
from ..mapclient import QueryOptions
from . import models as m
from .streaming import ply_stream

STREAM = Path(description="Stream name (the <s> in kmvipe/<s>/...).", examples=["cam0"])
SESSION = Query("", pattern=r"^[A-Za-z0-9_\-]{0,64}$", description="An earlier session of the stream (GET "
                ".../sessions lists them): its own map, in its own world frame. Empty: the current session.")
ERRORS = {code: {"model": m.ErrorResponse} for code in (401, 404, 409, 413, 422, 502, 503, 504)}
router = APIRouter(prefix="/v1", responses=ERRORS)
public = APIRouter(prefix="/v1")
"""Routes that answer without the API key: liveness only, so probes and load balancers need no secret."""


def _gateway(request: Request) -> Gateway:
    return request.app.state.gateway


def _stream(name: str) -> str:
    try:
        return keys.check_name(name)
    except ConfigError as exc:
        raise HTTPException(404, f"unknown stream: {exc}") from exc


def _check_texts(request: Request, texts: list[str], what: str) -> list[str]:
    cfg = request.app.state.settings
    if len(texts) > cfg.max_texts:
        raise HTTPException(422, f"too many {what}: {len(texts)} > {cfg.max_texts} (KMVIPE_QUERY_MAX_TEXTS)")
    cleaned = [" ".join(t.split()) for t in texts]
    for i, t in enumerate(cleaned):
        if not t:
            raise HTTPException(422, f"{what}[{i}] is empty: give a word or phrase such as 'chair'")
        if len(t) > cfg.max_text_chars:
            raise HTTPException(422, f"{what}[{i}] has {len(t)} characters; at most {cfg.max_text_chars} allowed")
    return cleaned


def _options(request: Request, top_k: int, threshold, max_regions: int, with_points: bool = False) -> QueryOptions:
    cfg = request.app.state.settings
    if top_k > cfg.max_top_k:
        raise HTTPException(422, f"top_k {top_k} exceeds the limit {cfg.max_top_k} (KMVIPE_QUERY_MAX_TOP_K)")
    return QueryOptions(top_k, -1.0 if threshold is None else float(threshold), max_regions, with_points)


def _answer_out(stream: str, texts: list[str], ans: Answer, encoder: str = "example",
                oracle: bool = False) -> m.QueryResponse:
    results = [m.TextResult(
        text=text,
        regions=[m.RegionOut(score=r.score, centroid=r.centroid.tolist(), box_min=r.box_min.tolist(),
                             box_max=r.box_max.tolist(), count=r.count, samples=r.samples.tolist(),
                             sample_scores=r.sample_scores.tolist()) for r in res.regions],
        top_points=[m.PointOut(xyz=p.tolist(), score=float(s)) for p, s in zip(res.top_xyz, res.top_scores)],
    ) for text, res in zip(texts, ans.results)]
    scores = ans.all_scores.tolist() if ans.all_scores is not None else None
    return m.QueryResponse(stream=stream, n_points=ans.n_points, space=ans.space, encoder=encoder, oracle=oracle,
                           results=results, point_scores=scores)


@router.post("/streams/{stream}/query", response_model=m.QueryResponse, summary="Natural-language query")
async def query(request: Request, body: m.QueryRequest, stream: str = STREAM, session: str = SESSION) -> m.QueryResponse:
    """Texts → CLIP → Talk2DINO → the map's DINO space → ranked 3D regions and top points per text."""
    stream = _stream(stream)
    texts = _check_texts(request, body.texts, "texts")
    opts = _options(request, body.top_k, body.threshold, body.max_regions, body.with_point_scores)
    ans = await run_in_threadpool(_gateway(request).query_text, stream, texts, opts, session)
    limit = request.app.state.settings.max_point_scores
    if ans.all_scores is not None and ans.all_scores.size > limit:
        raise HTTPException(413, f"per-point scores of {ans.all_scores.shape[0]} texts x {ans.all_scores.shape[1]} points "
                                 f"exceed {limit} values (KMVIPE_QUERY_MAX_POINT_SCORES); use /segment with format=ply")
    text = _gateway(request).text
    return _answer_out(stream, texts, ans, text.encoder_name(), text.is_oracle())


def _decode_image(b64: str, what: str, flags: int, max_side: int) -> np.ndarray:
    try:
        raw = base64.b64decode(b64, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise HTTPException(422, f"{what} is not valid base64: {exc}") from exc
    size = declared_size(raw)
    if size is None:
        raise HTTPException(422, f"{what} is not a PNG or JPEG image")
    if max(size) > max_side:
        raise HTTPException(413, f"{what} is {size[0]}x{size[1]}; the longest side may be {max_side} px")
    img = cv2.imdecode(np.frombuffer(raw, np.uint8), flags)
    if img is None:
        raise HTTPException(422, f"{what} is a corrupt PNG or JPEG image")
    return img


@router.post("/streams/{stream}/query/example", response_model=m.QueryResponse, summary="Query by example")
async def query_example(request: Request, body: m.ExampleRequest, stream: str = STREAM) -> m.QueryResponse:
    """An image and a box or mask → the region's DINO feature (registry backbone) → the same answer as a query."""
    stream = _stream(stream)
    cfg = request.app.state.settings
    image = cv2.cvtColor(_decode_image(body.image_b64, "image_b64", cv2.IMREAD_COLOR, cfg.max_image_side),
                         cv2.COLOR_BGR2RGB)
    mask = None
    if body.mask_b64 is not None:
        mask = _decode_image(body.mask_b64, "mask_b64", cv2.IMREAD_GRAYSCALE, cfg.max_image_side) > 0
        if mask.shape != image.shape[:2] or not mask.any():
            raise HTTPException(422, f"mask_b64 must be a non-empty mask of the image's size {image.shape[1]}x{image.shape[0]}")
    elif body.box is None:
        raise HTTPException(422, "give the region as 'box' [x0, y0, x1, y1] or as 'mask_b64'")
    opts = _options(request, body.top_k, body.threshold, body.max_regions)
    try:
        ans = await run_in_threadpool(_gateway(request).query_example, stream, image, body.box, mask, opts)
    except ValueError as exc:  # a box that covers no pixel
        raise HTTPException(422, str(exc)) from exc
    return _answer_out(stream, ["example"], ans)


@router.post("/streams/{stream}/segment", response_model=m.SegmentResponse, summary="Label every map point",
             responses={200: {"content": {"application/x-ply": {}}}})
async def segment(request: Request, body: m.SegmentRequest, stream: str = STREAM, session: str = SESSION):
    """A label set → each point's best label (argmax of cosine scores); JSON summary or a labelled PLY."""
    stream = _stream(stream)
    labels = _check_texts(request, body.labels, "labels")
    seg = await run_in_threadpool(_gateway(request).segment, stream, labels, session)
    point_label = apply_min_score(seg.label, seg.score, body.min_score)
    if body.format == "ply":
        palette = np.vstack([label_palette(len(labels)), [[128, 128, 128]]])
        rgb = palette[np.where(point_label < 0, len(labels), point_label)]
        data = ply.header(len(seg.xyz), labelled=True, comment="labels: " + " | ".join(labels))
        data += ply.vertices(seg.xyz, rgb, point_label, seg.score)
        return Response(data, media_type="application/x-ply",
                        headers={"Content-Disposition": f'attachment; filename="{stream}-segment.ply"'})
    n = len(seg.xyz)
    summary = segment_summary(point_label, seg.score, seg.xyz, len(labels))
    out = m.SegmentResponse(stream=stream, n_points=n, unlabelled=int((point_label < 0).sum()), labels=[
        m.LabelOut(label=name, count=s.count, fraction=s.count / n if n else 0.0,
                   mean_score=s.mean_score if s.count else None, centroid=s.centroid.tolist() if s.count else None)
        for name, s in zip(labels, summary)])
    if body.include_points:
        keep = subsample(n, body.max_points)
        out.xyz, out.point_labels = seg.xyz[keep].tolist(), point_label[keep].tolist()
    return out


@router.get("/streams/{stream}/trajectory", summary="Camera trajectory",
            responses={200: {"content": {"application/json": {"schema": m.TrajectoryResponse.model_json_schema()},
                                         "text/plain": {"example": "0.000000000 0 0 0 0 0 0 1\n"}}}})
async def trajectory(request: Request, stream: str = STREAM,
                     format: str = Query("json", pattern="^(json|tum)$", description="json or tum (text)"),
                     session: str = SESSION):
    """Latest pose of every frame the BA published for the stream (world_from_cam)."""
    stream = _stream(stream)
    gw = _gateway(request)
    traj = await run_in_threadpool(gw.session_trajectory, stream, session) if session else \
        await run_in_threadpool(gw.trajectory, stream)
    if traj is None:
        raise HTTPException(404, f"unknown stream '{stream}': no poses received on {keys.topic(stream, keys.POSE)}")
    if format == "tum":
        return PlainTextResponse(tum_text(traj), headers={"Content-Disposition": f'inline; filename="{stream}.tum"'})
    frames = [m.FramePose(seq=s, t_ns=t, world_from_cam=p.tolist())
              for s, t, p in zip(traj.seqs.tolist(), traj.stamps_ns.tolist(), traj.poses)]
    return m.TrajectoryResponse(stream=stream, frames=frames)


@router.get("/streams/{stream}/map", summary="The fused map",
            responses={200: {"content": {"application/x-ply": {}, "application/json": {
                "schema": m.MapPoints.model_json_schema()}}}})
async def map_points(request: Request, stream: str = STREAM,
                     format: str = Query("ply", pattern="^(ply|json)$", description="ply (streamed) or json"),
                     max_points: int = Query(0, ge=0, le=5_000_000, description="json: subsample to this many (0: setting)"),
                     session: str = SESSION):
    """PLY of every point (x y z, rgb), streamed chunk by chunk; or JSON of a subsample (what the viewer draws)."""
    stream = _stream(stream)
    gw, cfg = _gateway(request), request.app.state.settings
    first = await run_in_threadpool(gw.maps.export_chunk, stream, 0, cfg.export_chunk_points, session)
    if format == "ply":
        return StreamingResponse(ply_stream(gw, stream, first, cfg.export_chunk_points, session),
                                 media_type="application/x-ply",
                                 headers={"Content-Disposition": f'attachment; filename="{stream}.ply"'})
    chunks = [first] + [await run_in_threadpool(gw.maps.export_chunk, stream, i, cfg.export_chunk_points, session)
                        for i in range(1, first.n_chunks)]
    xyz = np.concatenate([c.xyz for c in chunks]) if chunks else np.zeros((0, 3), np.float32)
    rgb = np.concatenate([c.rgb for c in chunks]) if chunks else np.zeros((0, 3), np.uint8)
    keep = subsample(len(xyz), max_points or cfg.viewer_points)
    return m.MapPoints(stream=stream, total_points=len(xyz), returned=len(keep),
                       xyz=np.round(xyz[keep], 4).ravel().tolist(), rgb=rgb[keep].ravel().tolist())


@router.get("/streams/{stream}/sessions", response_model=m.SessionsResponse, summary="The stream's sessions")
async def sessions(request: Request, stream: str = STREAM) -> m.SessionsResponse:
    """Every session of the stream with a map: the current one and the earlier ones kept aside, each queryable
    with ``?session=<id>`` on /query, /segment, /map and /trajectory (each session is its own world frame)."""
    stream = _stream(stream)
    found = await run_in_threadpool(_gateway(request).maps.sessions, stream)
    return m.SessionsResponse(stream=stream, current=found.current, sessions=[
        m.SessionInfo(session=name, keyframes=int(k), finished=bool(f), current=name == found.current)
        for name, k, f in zip(found.sessions(), found.keyframes.tolist(), found.finished.tolist())])


@router.get("/streams", response_model=m.StreamsResponse, summary="Known streams")
async def streams(request: Request) -> m.StreamsResponse:
    gw = _gateway(request)
    found = await run_in_threadpool(gw.streams)
    support = {name: await run_in_threadpool(_support, gw, v["map"]) for name, v in found.items()}
    return m.StreamsResponse(streams=[m.StreamInfo(name=k, map=v["map"], poses=v["poses"], session=v.get("session", ""),
                                                   queries=support[k]) for k, v in sorted(found.items())])


def _support(gw: Gateway, stats: dict | None) -> m.QuerySupport:
    """Text: the gateway's encoder against the map's space; example: a keyframe region pools the map's own codes."""
    space = (stats or {}).get("backbone", "")
    text, why = gw.text.availability(space)
    example = bool(space)
    return m.QuerySupport(text=text, text_why=why, example=example, oracle=gw.text.is_oracle() and text,
                          example_why=EXAMPLE_WHY if example else "the map has no features yet")


@public.get("/health", response_model=m.HealthResponse, summary="Liveliness of every service (no API key needed)")
async def health(request: Request) -> m.HealthResponse:
    alive = await run_in_threadpool(_gateway(request).health)
    services = {k: m.ServiceHealth(alive=bool(v), instances=v) for k, v in alive.items()}
    return m.HealthResponse(status="ok" if services["mapstore"].alive else "degraded", services=services)

