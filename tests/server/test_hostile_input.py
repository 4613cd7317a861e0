"""Findings 1 and 9 of issue 14, and every mutating route against hostile bodies.

Finding 1: `PATCH /settings` with NaN / Infinity answered 500 (the 422 echoed a float JSON
cannot carry). Finding 9: the body was parsed before the token was checked, without a size cap;
loose coercion took `true` / `"0.5"` / `"yes"`; any Host header was served.
"""

from __future__ import annotations

import asyncio

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings, strategies as st

from dpmhw.session.config import LiveSettings
from server.app import MAX_BODY_BYTES, build_app

TOKEN = "test-token-123"
AUTH = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
NON_FINITE = ["NaN", "Infinity", "-Infinity"]


def mutating_routes(app) -> list[tuple[str, str]]:
    out = []
    for route in app.routes:
        for method in sorted(getattr(route, "methods", None) or ()):
            if method not in ("GET", "HEAD", "OPTIONS"):
                out.append((method, route.path))
    return out


@pytest.mark.parametrize("literal", NON_FINITE)
def test_finding_1_non_finite_settings_are_422_not_500(client, literal):
    before = client.get("/settings").json()
    r = client.patch("/settings", content=f'{{"alpha": {literal}}}', headers=AUTH)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail[0]["loc"][-1] == "alpha" and "finite" in detail[0]["msg"]
    assert client.get("/settings").json() == before


@pytest.mark.parametrize("body, field", [
    ('{"alpha": true}', "alpha"), ('{"alpha": "0.5"}', "alpha"), ('{"split_screen": "yes"}', "split_screen"),
    ('{"spp": 2.5}', "spp"), ('{"spp": "2"}', "spp"), ('{"prediction": 1}', "prediction"),
])
def test_finding_9_settings_types_are_strict(client, body, field):
    r = client.patch("/settings", content=body, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == field


def test_finding_9_integer_alpha_is_still_a_number(client):
    assert client.patch("/settings", json={"alpha": 1}, headers=AUTH).json()["alpha"] == 1.0


def test_finding_9_bad_token_is_refused_before_the_body_is_read(loop):
    """The 401 comes from the middleware without one call to `receive`: a 10 MB body is never read."""
    app = build_app(runtime=loop, token=TOKEN)
    sent = []

    async def receive():
        raise AssertionError("the body was read before the token was checked")

    async def send(message):
        sent.append(message)

    for headers in ([], [(b"authorization", b"Bearer wrong")]):
        sent.clear()
        scope = {"type": "http", "method": "PATCH", "path": "/settings", "raw_path": b"/settings", "root_path": "",
                 "query_string": b"", "scheme": "http", "server": ("127.0.0.1", 80), "client": ("127.0.0.1", 1),
                 "http_version": "1.1", "headers": [(b"host", b"127.0.0.1"), (b"content-length", b"10000000"),
                                                    (b"content-type", b"application/json"), *headers]}
        asyncio.run(app(scope, receive, send))
        assert sent[0]["status"] == 401


def test_finding_9_oversized_body_is_413_after_auth_and_not_echoed(client):
    big = '{"alpha": "' + "x" * (10 * 1024 * 1024) + '"}'
    r = client.patch("/settings", content=big, headers={"Content-Type": "application/json"})
    assert r.status_code == 401  # auth first
    r = client.patch("/settings", content=big, headers=AUTH)
    assert r.status_code == 413 and str(MAX_BODY_BYTES) in r.json()["detail"] and len(r.content) < 1000


def test_finding_9_chunked_body_without_length_is_cut_off_at_the_cap(client):
    def chunks():
        for _ in range(1000):
            yield b"x" * 1024

    r = client.patch("/settings", content=chunks(), headers=AUTH)
    assert r.status_code == 413


def test_finding_9_a_foreign_host_header_is_refused(loop):
    with TestClient(build_app(runtime=loop, token=TOKEN), base_url="http://evil.example") as c:
        assert c.get("/status").status_code == 400
    with TestClient(build_app(runtime=loop, token=TOKEN, trusted_hosts=["projector-lab.local"]),
                    base_url="http://projector-lab.local") as c:
        assert c.get("/livez").status_code == 200


def test_the_validation_error_never_echoes_a_huge_input(client):
    r = client.patch("/settings", content='{"reuse_mode": "' + "m" * 10_000 + '"}', headers=AUTH)
    assert r.status_code == 422 and len(r.content) < 1000


_hostile_value = st.one_of(
    st.sampled_from(NON_FINITE), st.sampled_from(['"0.5"', "true", "false", "null", "[]", "{}", '"yes"', "1e400"]),
    st.integers(min_value=-(2**70), max_value=2**70).map(str), st.text(max_size=20).map(lambda s: '"' + s.replace("\\", "").replace('"', "") + '"'),
)


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from([*LiveSettings.model_fields, "colour"]), value=_hostile_value,
       auth=st.sampled_from(["good", "none", "wrong", "scheme"]), oversize=st.booleans())
def test_every_mutating_route_survives_nan_infinity_wrong_types_oversized_bodies_and_bad_tokens(
        client, field, value, auth, oversize):
    headers = {"Content-Type": "application/json"}
    headers.update({"good": {"Authorization": f"Bearer {TOKEN}"}, "none": {},
                    "wrong": {"Authorization": "Bearer nope"}, "scheme": {"Authorization": f"Basic {TOKEN}"}}[auth])
    body = f'{{"{field}": {value}}}'
    if oversize:
        body = body[:-1] + ', "pad": "' + "p" * (MAX_BODY_BYTES + 1) + '"}'
    before = client.get("/settings").json()
    for method, path in mutating_routes(client.app):
        r = client.request(method, path, content=body, headers=headers)
        assert r.status_code != 500 and r.status_code < 600
        if auth != "good":
            assert r.status_code == 401
        elif oversize:
            assert r.status_code == 413
        r.json()  # always a JSON body
    if auth != "good" or oversize:
        assert client.get("/settings").json() == before
    client.post("/session/resume", headers={"Authorization": f"Bearer {TOKEN}"})
