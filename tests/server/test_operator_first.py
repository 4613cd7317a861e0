"""At most a few requests are worked on at once; the operator's blank never waits for a place."""

from __future__ import annotations

import threading

from fastapi.testclient import TestClient

from dpmhw.session.testing import wait_for
from server.app import build_app

TOKEN = "test-token-123"  # the `loop` fixture's app token (conftest.py)
AUTH = {"Authorization": f"Bearer {TOKEN}"}

WAIT_S = 30


class HeldPatches:
    """The session, with settings changes held until `gate` is set (a slow command)."""

    def __init__(self, loop):
        self.loop, self.gate, self.entered = loop, threading.Event(), threading.Event()

    def __getattr__(self, name):
        return getattr(self.loop, name)

    def update_settings(self, patch):
        self.entered.set()
        self.gate.wait(WAIT_S)
        return self.loop.update_settings(patch)


def test_with_every_place_taken_a_blank_is_served_and_a_status_waits(loop):
    runtime = HeldPatches(loop)
    with TestClient(build_app(runtime=runtime, token=TOKEN, max_concurrent_requests=1),
                    base_url="http://127.0.0.1") as client:
        assert wait_for(lambda: loop.status()["state"] == "running", WAIT_S)
        replies = {}
        patch = threading.Thread(target=lambda: replies.update(
            patch=client.patch("/settings", json={"alpha": 0.33}, headers=AUTH)))
        patch.start()
        try:
            assert runtime.entered.wait(WAIT_S)  # the one place is held
            status = threading.Thread(target=lambda: replies.update(status=client.get("/status")))
            status.start()
            r = client.post("/session/blank", headers=AUTH)  # served while the place is held
            assert r.status_code == 200 and r.json()["state"] == "blanked"
            assert "status" not in replies and "patch" not in replies  # the status waits for the place
        finally:
            runtime.gate.set()
        patch.join(WAIT_S)
        status.join(WAIT_S)
        assert replies["patch"].status_code == 200 and replies["status"].status_code == 200
        assert wait_for(lambda: loop.parts.projector.dark, WAIT_S)
