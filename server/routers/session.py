"""Session control: blank, resume, reset the temporal history (bearer token required).

Plain `def` handlers: they run in the thread pool, because a runtime in another process waits
(bounded) for the session's reply and must not hold up the event loop that serves /status.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse

from server.deps import RuntimeDep, require_token
from server.models import ActionResult

router = APIRouter(prefix="/session", tags=["session"], dependencies=[Depends(require_token)],
                   responses={401: {"description": "missing or wrong bearer token"}})


@router.post("/blank", response_model=ActionResult, summary="Go dark now; stays dark until resume")
def blank(runtime: RuntimeDep) -> ActionResult:
    runtime.blank()
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
