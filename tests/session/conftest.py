"""Fixtures: sessions over in-process doubles (dpmhw.session.testing), stopped after each test."""

from __future__ import annotations

import pytest

from dpmhw.session.testing import fake_session


@pytest.fixture
def make_loop():
    loops = []

    def make(overrides=(), **kw):
        loop = fake_session(overrides, **kw)
        loops.append(loop)
        return loop

    yield make
    for loop in loops:
        if hasattr(loop.parts.renderer, "block"):
            loop.parts.renderer.block.set()
        loop.stop()
