"""Read-only endpoints: status (and its live stream), health probes, metrics, the latest frame.

All of them only read the session's published snapshots, so they answer even while the loop
is stuck (the watchdog's verdict is part of the status).
"""

from __future__ import annotations

import asyncio
import json
import math
import threading
import time

import anyio
import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.responses import JSONResponse, PlainTextResponse, StreamingResponse

from server.deps import RuntimeDep
from server.prometheus import render_metrics

router = APIRouter(tags=["status"])


def public_status(status: dict) -> dict:
    """The status as /status answers it (the histograms are /metrics's)."""
    out = dict(status)
    out.pop("histograms", None)
    return out


@router.get("/status", summary="Session state with its reason, fps, latency, stage timings, devices, settings")
async def get_status(runtime: RuntimeDep) -> JSONResponse:
    return JSONResponse(public_status(runtime.status()))


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
            yield f"event: status\ndata: {json.dumps(public_status(runtime.status()))}\n\n"
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
    """The latest frame as PNG, encoded at most once per frame and at most once per
    `min_interval_s` however fast frames come (a 1024×768 frame takes tens of ms of the API
    process's CPU): clients in between, and while an encode is under way, get the newest encoded
    frame. A frame that turns dark or lit is encoded at once, so the page shows a blank as soon
    as the session reports it."""

    def __init__(self, min_interval_s: float = 0.25, clock=time.monotonic) -> None:
        self.min_interval_s, self.clock = min_interval_s, clock
        self._lock = threading.Lock()  # the cached PNG and its key
        self._encode_lock = threading.Lock()
        self._key = None
        self._t = -math.inf
        self._png: tuple[bytes, int, bool] = (b"", 0, False)
        self.encoded = 0
        self._encoding = False
        self.threads: anyio.CapacityLimiter | None = None  # made inside the server's event loop

    def _servable(self, frame) -> bool:
        return self._key is not None and (
            self._key == (frame.number, frame.t_present_ns, frame.blank)
            or bool(frame.blank) == self._png[2] and self.clock() - self._t < self.min_interval_s)

    def take(self, frame) -> tuple[bytes, int, bool] | None:
        """(PNG, frame number, blank) to serve for `frame` without waiting, or None: then the
        caller calls `get`. Only one caller at a time is sent to encode; while it does, the others
        get the last PNG (there is none only before the first frame is encoded)."""
        with self._lock:
            if self._servable(frame) or self._encoding and self._key is not None:
                return self._png
            self._encoding = True
            return None

    def get(self, frame) -> tuple[bytes, int, bool]:
        """(PNG, frame number, blank): `frame` encoded, unless what is cached may be served."""
        with self._encode_lock:  # one encode at a time
            try:
                with self._lock:
                    if self._servable(frame):  # encoded by the caller before this one
                        return self._png
                import cv2

                ok, buf = cv2.imencode(".png", np.ascontiguousarray(frame.image[..., ::-1]))
                if not ok:
                    raise HTTPException(500, "PNG encoding failed")
                with self._lock:
                    self._key, self._t = (frame.number, frame.t_present_ns, frame.blank), self.clock()
                    self._png = (buf.tobytes(), frame.number, bool(frame.blank))
                    self.encoded += 1
                    return self._png
            finally:
                self.release()

    def release(self) -> None:
        """End the claim `take` gave (`get` does; so does a request cancelled before its `get`)."""
        with self._lock:
            self._encoding = False


@router.get("/frame.png", summary="The latest frame sent to the projector (what the audience sees)",
            responses={200: {"content": {"image/png": {}}}, 404: {"description": "no frame presented yet"}})
async def frame_png(request: Request, runtime: RuntimeDep) -> Response:
    frame = runtime.latest_frame()
    if frame is None:
        raise HTTPException(404, "no frame has been sent to the projector yet")
    cache = request.app.state.png_cache
    got = cache.take(frame)
    if got is None:  # encode in a worker thread (OpenCV releases the GIL): the event loop goes on serving
        if cache.threads is None:
            cache.threads = anyio.CapacityLimiter(1)
        try:
            got = await anyio.to_thread.run_sync(cache.get, frame, limiter=cache.threads)
        finally:
            cache.release()
    png, number, blank = got
    return Response(png, media_type="image/png",
                    headers={"X-Frame-Number": str(number), "X-Frame-Blank": str(blank).lower(),
                             "Cache-Control": "no-store"})
