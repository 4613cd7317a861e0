"""Session control: blank, resume, reset the temporal history (bearer token required).

A runtime in another process waits (bounded) for the session's reply, which must not hold up the
event loop that serves /status: so the handlers wait in worker threads. Resume and reset-history
are plain `def` (the shared thread pool); the blank waits in threads of its own
(`BLANK_THREADS`), so a pool full of settings patches never queues the operator's blank.
"""

from __future__ import annotations

import anyio
from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse

from server.deps import RuntimeDep, require_token
from server.models import ActionResult

router = APIRouter(prefix="/session", tags=["session"], dependencies=[Depends(require_token)],
                   responses={401: {"description": "missing or wrong bearer token"}})


BLANK_THREADS = 4


@router.post("/blank", response_model=ActionResult, summary="Go dark now; stays dark until resume")
async def blank(request: Request, runtime: RuntimeDep) -> ActionResult:
    state = request.app.state
    if getattr(state, "blank_threads", None) is None:  # made inside the server's event loop
        state.blank_threads = anyio.CapacityLimiter(BLANK_THREADS)
    await anyio.to_thread.run_sync(runtime.blank, limiter=state.blank_threads)
    return ActionResult(ok=True, message="blank requested; the next frame is dark", state=runtime.status()["state"])


@router.post("/resume", response_model=ActionResult, summary="Lift an operator blank / manual latch",
             responses={409: {"model": ActionResult, "description": "a fault is still active"}})
def resume(runtime: RuntimeDep):
    ok, message = runtime.resume()
    result = ActionResult(ok=ok, message=message, state=runtime.status()["state"])
    return result if ok else JSONResponse(result.model_dump(), status_code=409)


@router.post("/reset-history", response_model=ActionResult, summary="Forget temporal-reuse and prediction history")
def reset_history(runtime: RuntimeDep) -> ActionResult:
    runtime.reset_history()
    return ActionResult(ok=True, message="history reset on the next frame", state=runtime.status()["state"])
