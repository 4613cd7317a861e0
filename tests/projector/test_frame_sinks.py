"""Frame sinks: the FrameSink protocol, the recording and file sinks, the window sink if installed."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from dpmhw.display import DisplayTiming
from dpmhw.frame_sink import FrameSink, check_frame
from drivers.frame_sinks import FileSink, RecordingSink, make_sink


def _frame(h=6, w=10, seed=0):
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def test_sinks_implement_the_protocol(tmp_path):
    assert isinstance(RecordingSink(), FrameSink)
    assert isinstance(FileSink(tmp_path / "png"), FrameSink)


@pytest.mark.parametrize("bad", [np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), np.uint8),
                                 np.zeros((4, 4, 4), np.uint8), [[0, 0, 0]]])
def test_bad_frames_are_refused(bad):
    with pytest.raises(ValueError, match="frame"):
        check_frame(bad)
    with pytest.raises(ValueError):
        RecordingSink().present(bad, 0)


def test_recording_sink_keeps_copies_and_paces_to_the_refresh_grid(clock):
    timing = DisplayTiming(refresh_hz=50.0)  # 20 ms refreshes, from the clock's reading at construction
    sink = RecordingSink(shape=(6, 10), timing=timing, clock=clock, sleep=clock.sleep, pace=True)
    t0 = sink.vsync_phase_ns()
    assert t0 == clock()
    f = _frame()
    at = sink.present(f, t0 + 5_000_000)  # shown at the first refresh after the target
    f[:] = 0  # the caller reuses its buffer
    assert at == t0 + 20_000_000 == clock() and clock.sleeps == [0.02]
    assert sink.present(_frame(seed=1), t0) == at  # a late target: the refresh now (no wait)
    clock.advance(1)
    assert sink.present(_frame(seed=2), t0) == t0 + 40_000_000  # just past a refresh: the next one
    assert np.array_equal(sink.frames[0].frame, _frame()) and len(sink.frames) == 3
    assert [p.presented_at_ns for p in sink.frames] == [at, at, t0 + 40_000_000]
    with pytest.raises(ValueError, match="expected"):
        sink.present(_frame(7, 10), at)
    sink.close()
    with pytest.raises(RuntimeError):
        sink.present(_frame(), at)


def test_unpaced_and_file_sinks_have_no_refresh(clock, tmp_path):
    timing = DisplayTiming("pattern-8bit", 60.0, 0)
    sink = RecordingSink(timing=timing, clock=clock)
    clock.advance(3)
    assert sink.present(_frame(), clock() + 10**9) == clock() and sink.timing is timing
    files = FileSink(tmp_path / "seq", timing=timing, clock=clock)
    assert files.present(_frame(), clock() + 10**9) == clock() and files.timing is timing


def test_png_sequence_is_lossless(tmp_path):
    import cv2

    sink = make_sink("file", path=tmp_path / "seq")
    frames = [_frame(seed=s) for s in range(3)]
    for i, f in enumerate(frames):
        sink.present(f, i)
    sink.close()
    for i, f in enumerate(frames):
        back = cv2.imread(str(tmp_path / "seq" / f"frame_{i:06d}.png"))[..., ::-1]
        assert np.array_equal(back, f)


def test_video_file_has_every_frame(tmp_path):
    import cv2

    sink = FileSink(tmp_path / "review.avi", fps=30)
    for i in range(5):
        sink.present(np.full((32, 48, 3), 40 * i, np.uint8), i)
    sink.close()
    cap = cv2.VideoCapture(str(tmp_path / "review.avi"))
    means = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        means.append(img.mean())
    cap.release()
    assert len(means) == 5 and np.allclose(means, [0, 40, 80, 120, 160], atol=4)


def test_window_sink_on_a_dummy_display(monkeypatch, clock):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    from drivers.frame_sinks import WindowSink

    import pygame

    pygame.display.init()
    w, h = pygame.display.get_desktop_sizes()[0]
    pygame.display.quit()
    with pytest.raises(ValueError, match=f"runs at {w}×{h}, but the session outputs 40×20"):
        WindowSink(0, size=(40, 20), clock=clock, sleep=clock.sleep)  # not the projector's native size
    timing = DisplayTiming(refresh_hz=60.0)
    sink = WindowSink(0, size=(w, h), timing=timing, clock=clock, sleep=clock.sleep)
    try:
        # the dummy driver's flips never block: no vsync, so the software refresh grid paces
        assert sink.shape == (h, w) and not sink.vsync_locked
        phase = sink.vsync_phase_ns()
        clock.sleeps.clear()
        f = _frame(h, w)
        at = sink.present(f, clock() + 1_000_000)
        assert at == timing.next_vsync(clock() - 1, phase) == clock() and (at - phase) % timing.period_ns == 0
        assert len(clock.sleeps) == 1 and 0 < clock.sleeps[0] <= timing.period_ns / 1e9
        assert np.array_equal(sink.snapshot(), f)
        assert sink.present(f, 0) == at  # a late target: the refresh now
        with pytest.raises(ValueError):
            sink.present(_frame(h + 1, w), 0)  # no silent scaling
    finally:
        sink.close()
    with pytest.raises(ValueError, match="display"):
        WindowSink(7)


class _FakeVsync:
    """pygame.display.flip blocking until the next refresh of a 60 Hz display, on the fake clock."""

    def __init__(self, clock, period_ns: int, phase_ns: int):
        self.clock, self.period_ns, self.phase_ns = clock, period_ns, phase_ns
        self.flips: list[int] = []

    def __call__(self) -> None:
        t = self.clock()
        nxt = self.phase_ns + (-(-(t - self.phase_ns + 1) // self.period_ns)) * self.period_ns  # strictly after now
        self.clock.advance(nxt - t)
        self.flips.append(nxt)


def test_window_sink_locks_to_a_blocking_vsync(monkeypatch, clock):
    """A flip that blocks until the refresh locks the sink; presents return the refreshes."""
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    import pygame

    from drivers.frame_sinks import WindowSink

    timing = DisplayTiming(refresh_hz=60.0)
    vsync = _FakeVsync(clock, timing.period_ns, clock() + 1234567)
    monkeypatch.setattr(pygame.display, "flip", vsync)
    set_mode = pygame.display.set_mode  # the dummy driver has no renderer: grant the vsync request
    monkeypatch.setattr(pygame.display, "set_mode",
                        lambda size, flags=0, display=0, vsync=0: set_mode(size, flags & ~pygame.SCALED, display=display))
    pygame.display.init()
    size = tuple(pygame.display.get_desktop_sizes()[0])
    pygame.display.quit()
    sink = WindowSink(0, size=size, timing=timing, clock=clock, sleep=clock.sleep)
    try:
        assert sink.vsync_locked and sink.vsync_phase_ns() == vsync.flips[-1]
        f = _frame(size[1], size[0])
        target = clock() + 2 * timing.period_ns + 10
        at = sink.present(f, target)
        assert at == vsync.flips[-1] == timing.next_vsync(target, vsync.phase_ns)
        assert sink.present(f, 0) == at + timing.period_ns  # the next refresh, never the one already gone
    finally:
        sink.close()


def test_window_sink_refuses_a_throttled_flip(monkeypatch, clock):
    """A flip throttled to one period after the previous one (Xvfb's software swap) is no vsync."""
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    import pygame

    from drivers.frame_sinks import WindowSink

    timing = DisplayTiming(refresh_hz=60.0)
    last = [0]

    def throttled():
        wait = last[0] + timing.period_ns - clock()
        if wait > 0:
            clock.advance(wait)
        last[0] = clock()

    monkeypatch.setattr(pygame.display, "flip", throttled)
    pygame.display.init()
    size = tuple(pygame.display.get_desktop_sizes()[0])
    pygame.display.quit()
    sink = WindowSink(0, size=size, timing=timing, clock=clock, sleep=clock.sleep)
    try:
        assert not sink.vsync_locked
    finally:
        sink.close()


def test_unknown_sink_name():
    with pytest.raises(ValueError, match="window"):
        make_sink("hdmi")


_XVFB_PROBE = """
import json, time
import numpy as np
from dpmhw.display import DisplayTiming
from drivers.frame_sinks import WindowSink
sink = WindowSink(0, timing=DisplayTiming(refresh_hz=60.0))
frame = np.zeros((*sink.shape, 3), np.uint8)
out = []
for k in range(5):
    target = time.monotonic_ns() + k * 3_000_000
    out.append((target, sink.present(frame, target), time.monotonic_ns()))
print(json.dumps({"locked": sink.vsync_locked, "phase": sink.vsync_phase_ns(), "p": sink.timing.period_ns, "out": out}))
sink.close()
"""


@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="xvfb-run is not installed (apt install xvfb)")
def test_window_sink_under_xvfb_paces_the_software_grid():
    """Xvfb has no vsync (its swaps are throttled): the sink must see that and keep a software grid."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    env.pop("SDL_VIDEODRIVER", None)
    run = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 320x240x24", sys.executable, "-c", _XVFB_PROBE],
                         capture_output=True, text=True, timeout=120, env=env)
    assert run.returncode == 0, run.stderr
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert not got["locked"]
    for target, at, returned in got["out"]:
        assert (at - got["phase"]) % got["p"] == 0  # a refresh of the grid
        assert at >= target and returned >= at  # never before the target, and waited for
