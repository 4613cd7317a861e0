"""Request and response bodies (the OpenAPI schema is generated from these)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["ActionResult", "SettingsModel", "SettingsPatch"]


class SettingsModel(BaseModel):
    """Live settings; the same bounds as `dpmhw.session.config.LiveSettings`."""

    alpha: float = Field(gt=0.0, le=1.0, description="temporal reuse weight of the new frame, in (0, 1]; 1 = no reuse")
    reuse_mode: Literal["off", "same-pixel", "motion"]
    spp: int = Field(ge=1, le=64, description="samples per pixel per frame")
    split_screen: bool = Field(description="left half without reuse, for comparison")
    prediction: bool = Field(description="extrapolate tracked poses to the display time")


class SettingsPatch(BaseModel):
    """Any subset of the live settings; unknown fields are refused (422). Strict: no string or
    boolean coercion (`"0.5"`, `true` for a number, `"yes"` for a flag are refused), and no NaN
    or infinity."""

    model_config = ConfigDict(extra="forbid", strict=True,
                              json_schema_extra={"examples": [{"alpha": 0.5}, {"prediction": False}]})

    alpha: float | None = Field(None, gt=0.0, le=1.0, allow_inf_nan=False)
    reuse_mode: Literal["off", "same-pixel", "motion"] | None = None
    spp: int | None = Field(None, ge=1, le=64)
    split_screen: bool | None = None
    prediction: bool | None = None


class ActionResult(BaseModel):
    ok: bool
    message: str
    state: str
