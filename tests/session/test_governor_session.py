"""The quality governor in a --mock session (firmware mocks, real drivers, the HTTP service): what
it chose and why is in /status, it works around a setting the operator pinned over HTTP, and the
frames record its level."""

from __future__ import annotations

from fastapi.testclient import TestClient

from dpmhw.session.config import load_session_config
from dpmhw.session.factory import build_session
from dpmhw.session.testing import wait_for
from server.app import build_app

TOKEN = "governor-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
WAIT_S = 60  # for what must happen eventually (a first frame may wait for numba); only broken code waits


def test_governor_status_and_pinning_in_a_mock_session():
    # a target no machine renders 64×48 at (1000 fps): the governor must step down, whatever the load
    cfg = load_session_config(overrides=[
        "render.width=64", "render.height=48", "mock.speed=0.3", "safety.stale_after_ms=200", "safety.watchdog_s=5",
        "sink.kind=recording", "governor.target_fps=1000", "governor.down_window_s=0.2"])
    loop = build_session(cfg, mock=True, frame_log=5000).start()
    try:
        with TestClient(build_app(runtime=loop, token=TOKEN), base_url="http://127.0.0.1") as client:
            st = client.get("/status").json()
            assert st["governor"]["level"] == 0 and st["governor"]["target_fps"] == 1000.0
            assert client.patch("/settings", json={"filter": "lobe"}, headers=AUTH).status_code == 200  # pinned
            assert wait_for(lambda: client.get("/status").json()["governor"]["level"] >= 2, WAIT_S), \
                client.get("/status").json()["governor"]
            st = client.get("/status").json()
            gov = st["governor"]
            assert gov["pinned"] == ["filter"] and gov["target_from"] == "governor.target_fps"
            assert gov["reason"].startswith(("down to", "at the cheapest")) and gov["measured_fps"] > 0
            assert gov["choices"]["adaptive_rays"] == 0 and gov["choices"]["filter"] == "lobe"
            assert [r["skipped"] for r in gov["ladder"] if r["field"] in ("filter", "lod_rays")] == [True, True, True]
            assert wait_for(lambda: loop.frame_log[-1].settings.adaptive_rays == 0, WAIT_S)
            assert loop.reconstruct.adaptive.budget_rays == 0  # the live budget reached the sampler
            assert st["settings"]["filter"] == "lobe"  # the operator's, never the governor's
            assert all(r.settings.filter == "lobe" for r in loop.frame_log)
            assert loop.frame_log[-1].governor_level == loop.governor.level >= 2
            assert loop.status()["governor"]["level"] == loop.governor.level
    finally:
        loop.stop()
