"""One declaration of the live settings: the config, the API, the page and the recording all
carry exactly `LiveSettings`' fields, with its bounds; absurd values are refused naming the field."""

from __future__ import annotations

import csv
import json

import pytest

from dpmhw.reconstruct.settings import ALPHA_MIN
from dpmhw.session.config import LIVE_FIELDS, LiveSettings, SessionConfig, SessionConfigError, load_session_config
from dpmhw.session.recording import SessionRecorder
from dpmhw.session.testing import wait_for
from server.models import SettingsModel, SettingsPatch
from server.pages import STATIC_DIR
from tests.server.conftest import AUTH

WAIT_S = 60  # for what must happen eventually (a first frame may wait for numba); only broken code waits
SOURCE = list(LiveSettings.model_fields)


def _bounds(schema: dict) -> dict:
    """A field's JSON schema without what may differ between a body and a patch."""
    branch = next((s for s in schema.get("anyOf", [schema]) if s.get("type") != "null"), schema)
    return {k: v for k, v in branch.items() if k not in ("default", "title", "description")}


def test_every_consumer_has_exactly_the_live_fields(client, tmp_path):
    assert list(LIVE_FIELDS) == SOURCE
    config = SessionConfig()
    assert list(config.live_settings().model_dump()) == SOURCE
    for name, (section, field) in LIVE_FIELDS.items():  # the section field is the declaration
        declared = type(getattr(config, section)).model_json_schema()["properties"][field]
        assert _bounds(LiveSettings.model_json_schema()["properties"][name]) == _bounds(declared), name
    # the API's bodies, as models and as the published schema the operator page builds its controls from
    assert list(SettingsModel.model_fields) == SOURCE and list(SettingsPatch.model_fields) == SOURCE
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    live = schemas["SettingsModel"]["properties"]
    assert list(live) == SOURCE and list(schemas["SettingsPatch"]["properties"]) == SOURCE
    for name in SOURCE:
        assert _bounds(schemas["SettingsPatch"]["properties"][name]) == _bounds(live[name]), name
    assert "components.schemas.SettingsModel" in (STATIC_DIR / "app.js").read_text()
    # what the service answers
    assert list(client.get("/settings").json()) == SOURCE
    assert list(client.get("/status").json()["settings"]) == SOURCE
    # the recording's columns
    recorder = SessionRecorder(tmp_path / "rec")
    recorder.close()
    with open(tmp_path / "rec" / "frames.csv", newline="") as f:
        header = next(csv.reader(f))
    assert header[header.index("frame_ms") + 1:header.index("body")] == SOURCE


def test_filter_is_read_changed_and_applied_like_every_setting(client, loop):
    assert client.get("/settings").json()["filter"] == "lobe"
    r = client.patch("/settings", json={"filter": "off"}, headers=AUTH)
    assert r.status_code == 200 and r.json()["filter"] == "off"
    assert client.get("/settings").json()["filter"] == "off"
    assert wait_for(lambda: loop.frame_log and loop.frame_log[-1].settings.filter == "off", WAIT_S)
    r = client.patch("/settings", json={"filter": "magic"}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "filter"
    assert load_session_config(None, ["render.filter=normal"]).live_settings().filter == "normal"


@pytest.mark.parametrize("body, field", [
    ('{"alpha": 1e-320}', "alpha"), ('{"alpha": 5e-324}', "alpha"), ('{"alpha": 1e-7}', "alpha"),
    ('{"alpha": 0.0}', "alpha"), ('{"alpha": -0.0}', "alpha"), ('{"alpha": -1}', "alpha"), ('{"alpha": 1e308}', "alpha"),
    ('{"alpha": 1e400}', "alpha"), ('{"spp": 65}', "spp"), ('{"spp": 1180591620717411303424}', "spp"),
    ('{"spp": 0}', "spp"), ('{"filter": "Lobe"}', "filter"), ('{"reuse_mode": ""}', "reuse_mode"),
])
def test_subnormal_and_absurd_values_are_422_naming_the_field(client, body, field):
    before = client.get("/settings").json()
    r = client.patch("/settings", content=body, headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert [d["loc"][-1] for d in detail] == [field], detail
    assert client.get("/settings").json() == before


def test_the_smallest_alpha_the_reuse_honours_is_accepted(client):
    r = client.patch("/settings", content=json.dumps({"alpha": ALPHA_MIN}), headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code == 200 and r.json()["alpha"] == ALPHA_MIN


@pytest.mark.parametrize("override, field", [
    ("reuse.alpha=1e-320", "reuse.alpha"), ("reuse.alpha=nan", "reuse.alpha"), ("render.exposure=inf", "render.exposure"),
    ("tracker.workspace_min=[nan, 0.0, 0.0]", "tracker.workspace_min[0]"),
])
def test_the_config_refuses_the_same_values_naming_the_field(override, field):
    with pytest.raises(SessionConfigError) as info:
        load_session_config(None, [override])
    assert str(info.value).startswith(f"command line: {field}: "), info.value
