"""A started session over in-process doubles behind the app, with a token; stopped after each test."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from dpmhw.session.testing import fake_session
from server.app import build_app

TOKEN = "test-token-123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture
def loop():
    session = fake_session().start()
    yield session
    session.parts.renderer.block.set()
    session.stop()


@pytest.fixture
def client(loop):
    with TestClient(build_app(runtime=loop, token=TOKEN), base_url="http://127.0.0.1") as c:
        yield c
