"""A started session over in-process doubles behind the app, with a token; stopped after each test."""

from __future__ import annotations

import socket

import pytest
from fastapi.testclient import TestClient

from dpmhw.session.testing import fake_session
from server.app import build_app

TOKEN = "test-token-123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture
def loop():
    session = fake_session(["governor.enabled=false"]).start()  # what changes the settings here is the requests alone
    yield session
    session.parts.renderer.block.set()
    session.stop()


@pytest.fixture
def client(loop):
    with TestClient(build_app(runtime=loop, token=TOKEN), base_url="http://127.0.0.1") as c:
        yield c


def closed_by_server(sock: socket.socket) -> bool:
    """Whether the server has closed (or reset) this connection; never blocks."""
    sock.setblocking(False)
    try:
        return sock.recv(4096) == b""
    except BlockingIOError:
        return False
    except ConnectionError:
        return True


def open_with(host: str, port: int, sends, timeout_s: float = 60.0) -> list[socket.socket]:
    """One fresh connection per item of `sends`, each sent its bytes (b"": nothing) and left open."""
    socks = []
    for data in sends:
        s = socket.create_connection((host, port), timeout=timeout_s)
        s.sendall(data)
        socks.append(s)
    return socks
