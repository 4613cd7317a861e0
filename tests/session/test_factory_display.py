"""The factory's display wiring: a mock session presents through the emulated video link into the
rig's DLPC900, which the session has put into the display mode `display.mode` names."""

from __future__ import annotations

import time

import numpy as np
import pytest

from dpmhw.session.config import load_session_config
from dpmhw.session.factory import open_session_parts
from dpmhw.session.testing import FlatRenderer


def _close(parts):
    for close in (parts.tracker.stop, parts.sink.close, parts.projector.close, *reversed(parts.closers)):
        close()


@pytest.mark.parametrize("mode", ["video", "pattern-8bit"])
def test_mock_session_presents_through_the_emulated_projector(mode):
    cfg = load_session_config(overrides=["render.width=32", "render.height=24", f'display.mode="{mode}"',
                                         "display.controller_delay_ms=2"])
    parts = open_session_parts(cfg, mock=True, renderer=FlatRenderer(32, 24))
    try:
        link, model = parts.mock.video, parts.mock.projector.model
        assert parts.sink is link and link.timing == cfg.display_timing()
        assert model.display_mode == (2 if mode == "pattern-8bit" else 0) and model.dark  # opened dark
        parts.projector.unblank()
        assert not model.dark and (mode == "video" or model.sequencer == "running")
        frame = np.random.default_rng(3).integers(0, 256, (24, 32, 3), dtype=np.uint8)
        v = parts.sink.present(frame, time.monotonic_ns())
        assert v <= time.monotonic_ns() and (v - parts.sink.vsync_phase_ns()) % link.timing.period_ns == 0
        time.sleep(link.timing.period_ns / 1e9)  # the next refresh scans it out for sure (the link never waits longer)
        link.poll()
        shown = [e for e in link.exposures if e.scanout_ns == v]
        windows = link.timing.windows
        assert [e.channel for e in shown] == [w.channel for w in windows]
        assert [e.leds for e in shown] == [w.leds for w in windows]
        assert all(abs(e.t_start_ns - (v + w.start_ns)) <= 2000 for e, w in zip(shown, windows))  # the LUT's µs
    finally:
        _close(parts)
    assert model.video_period_ns is None  # the cable is out with the session
