"""Frame sinks: the FrameSink protocol, the recording and file sinks, the window sink if installed."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_recording_sink_keeps_copies_and_paces(clock):
    sink = RecordingSink(shape=(6, 10), clock=clock, sleep=clock.sleep, pace=True)
    f = _frame()
    t0 = clock()
    at = sink.present(f, t0 + 5_000_000)
    f[:] = 0  # the caller reuses its buffer
    assert at == t0 + 5_000_000 and clock.sleeps == [0.005]
    assert sink.present(_frame(seed=1), t0) == at  # a late frame goes out at once
    assert np.array_equal(sink.frames[0].frame, _frame()) and len(sink.frames) == 2
    with pytest.raises(ValueError, match="expected"):
        sink.present(_frame(7, 10), at)
    sink.close()
    with pytest.raises(RuntimeError):
        sink.present(_frame(), at)


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
    sink = WindowSink(0, size=(w, h), clock=clock, sleep=clock.sleep)
    try:
        assert sink.shape == (h, w)
        f = _frame(h, w)
        assert sink.present(f, clock() + 1_000_000) == clock()
        assert clock.sleeps == [0.001]
        assert np.array_equal(sink.snapshot(), f)
        with pytest.raises(ValueError):
            sink.present(_frame(h + 1, w), 0)  # no silent scaling
    finally:
        sink.close()
    with pytest.raises(ValueError, match="display"):
        WindowSink(7)


def test_unknown_sink_name():
    with pytest.raises(ValueError, match="window"):
        make_sink("hdmi")
