"""Request and response bodies (the OpenAPI schema is generated from these).

The settings bodies are derived from `dpmhw.session.config.LiveSettings`: a live setting added
there appears in GET and PATCH /settings and on the operator page (built from this schema) by
itself, with the same bounds.
"""

from __future__ import annotations

from typing import Annotated, Any, Optional

from pydantic import BaseModel, ConfigDict, Field, create_model

from dpmhw.session.config import LiveSettings

__all__ = ["ActionResult", "SettingsModel", "SettingsPatch"]


class SettingsModel(LiveSettings):
    """The accepted live settings (`LiveSettings`, under the name the API's schema has always used)."""


def _optional(info) -> tuple[Any, Any]:
    """The field's type and bounds, or null (left out: unchanged)."""
    constrained = Annotated[(info.annotation, *info.metadata)] if info.metadata else info.annotation
    return Optional[constrained], Field(None, description=info.description)


SettingsPatch = create_model(
    "SettingsPatch",
    __config__=ConfigDict(extra="forbid", strict=True, allow_inf_nan=False,
                          json_schema_extra={"examples": [{"alpha": 0.5}, {"prediction": False}]}),
    __doc__="Any subset of the live settings; unknown fields are refused (422). Strict: no string or "
            "boolean coercion (`\"0.5\"`, `true` for a number, `\"yes\"` for a flag are refused), and no NaN "
            "or infinity.",
    __module__=__name__,
    **{name: _optional(info) for name, info in LiveSettings.model_fields.items()},
)


class ActionResult(BaseModel):
    ok: bool
    message: str
    state: str
