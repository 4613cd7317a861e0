"""Read-only endpoints: status (and its live stream), health probes, metrics, the latest frame.

All of them only read the session's published snapshots, so they answer even while the loop
is stuck (the watchdog's verdict is part of the status).
"""

from __future__ import annotations

import asyncio
import json
import threading

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.responses import JSONResponse, PlainTextResponse, StreamingResponse

from server.deps import RuntimeDep
from server.prometheus import render_metrics

router = APIRouter(tags=["status"])


def _jsonable(status: dict) -> dict:
    out = dict(status)
    out.pop("histograms", None)  # /metrics has them
    return out


@router.get("/status", summary="Session state with its reason, fps, latency, stage timings, devices, settings")
async def get_status(runtime: RuntimeDep) -> JSONResponse:
    return JSONResponse(_jsonable(runtime.status()))


@router.get("/status/stream", summary="Server-Sent Events: one status object per `interval`",
            response_class=StreamingResponse)
async def stream_status(request: Request, runtime: RuntimeDep,
                        interval: float = Query(0.5, ge=0.05, le=10.0, description="seconds between events"),
                        count: int | None = Query(None, ge=1, le=100_000, description="stop after this many events")):
    async def events():
        sent = 0
        while count is None or sent < count:
            if await request.is_disconnected():
                return
            yield f"event: status\ndata: {json.dumps(_jsonable(runtime.status()))}\n\n"
            sent += 1
            if count is not None and sent >= count:
                return
            await asyncio.sleep(interval)

    return StreamingResponse(events(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})


@router.get("/livez", summary="The service process answers")
async def livez() -> dict:
    return {"live": True}


@router.get("/readyz", summary="200 when the loop runs (projecting or deliberately dark), else 503")
async def readyz(runtime: RuntimeDep) -> JSONResponse:
    ok = runtime.ready()
    st = runtime.status()
    return JSONResponse({"ready": ok, "state": st.get("state"), "reason": st.get("reason", "")}, status_code=200 if ok else 503)


@router.get("/metrics", summary="Prometheus text format", response_class=PlainTextResponse)
async def metrics(runtime: RuntimeDep) -> Response:
    return Response(render_metrics(runtime.status()), media_type="text/plain; version=0.0.4; charset=utf-8")


class PngCache:
    """Encodes each presented frame at most once, however many clients ask for it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._key = None
        self._png = b""

    def get(self, frame) -> bytes:
        key = (frame.number, frame.t_present_ns, frame.blank)
        with self._lock:
            if key != self._key:
                import cv2

                ok, buf = cv2.imencode(".png", np.ascontiguousarray(frame.image[..., ::-1]))
                if not ok:
                    raise HTTPException(500, "PNG encoding failed")
                self._key, self._png = key, buf.tobytes()
            return self._png


@router.get("/frame.png", summary="The latest frame sent to the projector (what the audience sees)",
            responses={200: {"content": {"image/png": {}}}, 404: {"description": "no frame presented yet"}})
async def frame_png(request: Request, runtime: RuntimeDep) -> Response:
    frame = runtime.latest_frame()
    if frame is None:
        raise HTTPException(404, "no frame has been sent to the projector yet")
    return Response(request.app.state.png_cache.get(frame), media_type="image/png",
                    headers={"X-Frame-Number": str(frame.number), "X-Frame-Blank": str(bool(frame.blank)).lower(),
                             "Cache-Control": "no-store"})
