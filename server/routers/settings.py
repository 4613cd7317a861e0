"""Live settings: read freely; change with the bearer token (applied on the next frame).

A PATCH that changes nothing (every value as accepted, every field already the operator's: pinned
against the quality governor) is answered at once from the accepted settings; any other waits
for the session in the thread pool, for the reason given in `session.py`.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException
from starlette.concurrency import run_in_threadpool

from server.deps import RuntimeDep, require_token
from server.models import SettingsModel, SettingsPatch

router = APIRouter(prefix="/settings", tags=["settings"])


@router.get("", response_model=SettingsModel, summary="The accepted live settings")
async def get_settings(runtime: RuntimeDep) -> SettingsModel:
    return SettingsModel.model_validate(runtime.settings().model_dump())


@router.patch("", response_model=SettingsModel, dependencies=[Depends(require_token)],
              summary="Change some settings; invalid values → 422 with the reason",
              responses={401: {"description": "missing or wrong bearer token"}})
async def patch_settings(patch: SettingsPatch, runtime: RuntimeDep) -> SettingsModel:
    changes = patch.model_dump(exclude_unset=True)
    if any(v is None for v in changes.values()):
        raise HTTPException(422, f"null is not a value for: {', '.join(k for k, v in changes.items() if v is None)}")
    current = runtime.settings()
    pinned = runtime.status().get("governor", {}).get("pinned", ())
    if all(getattr(current, k, _MISSING) == v and k in pinned for k, v in changes.items()):
        new = current  # changes nothing, pins nothing new: answered here, the session is never asked
    else:
        try:
            new = await run_in_threadpool(runtime.update_settings, changes)
        except ValueError as exc:  # SettingsError: what the loop itself refuses
            raise HTTPException(422, str(exc)) from None
    return SettingsModel.model_validate(new.model_dump())


_MISSING = object()
