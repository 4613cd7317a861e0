"""/frame.png's cache: each frame encoded at most once, and at most once per interval however fast
frames come, except a turn to dark or lit, which is encoded at once (injected clock)."""

from __future__ import annotations

import threading

import cv2
import numpy as np

from dpmhw.session.loop import LatestFrame
from server.routers.status import PngCache


def frame(number: int, blank: bool = False) -> LatestFrame:
    image = np.full((6, 8, 3), 0 if blank else number % 256, np.uint8)
    return LatestFrame(number, number * 1000, image, None, blank)


def decoded(png: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]


def test_frames_are_encoded_at_most_once_per_interval_and_a_blank_at_once():
    now = [0.0]
    cache = PngCache(min_interval_s=0.25, clock=lambda: now[0])
    assert cache.take(frame(1)) is None
    png, number, blank = cache.get(frame(1))
    assert (number, blank, cache.encoded) == (1, False, 1) and np.all(decoded(png) == 1)
    assert cache.take(frame(1))[1] == 1 and cache.get(frame(1))[1] == 1 and cache.encoded == 1
    now[0] = 0.1
    assert cache.take(frame(2))[1] == 1  # too soon: the frame before is served
    png, number, blank = cache.get(frame(3, blank=True))  # a blank is shown at once
    assert (number, blank, cache.encoded) == (3, True, 2) and np.all(decoded(png) == 0)
    now[0] = 0.2
    assert cache.get(frame(4))[1:] == (4, False) and cache.encoded == 3  # and so is the resume
    now[0] = 0.5
    assert cache.take(frame(5)) is None and cache.get(frame(5))[1] == 5 and cache.encoded == 4


def test_while_one_frame_is_encoded_the_others_get_the_last_one(monkeypatch):
    cache = PngCache(min_interval_s=0.0)
    assert cache.take(frame(1)) is None
    cache.get(frame(1))
    inside, release = threading.Event(), threading.Event()
    real = cv2.imencode

    def slow(*args):
        inside.set()
        release.wait(30)
        return real(*args)

    monkeypatch.setattr(cv2, "imencode", slow)
    assert cache.take(frame(2)) is None  # this caller encodes
    t = threading.Thread(target=cache.get, args=(frame(2),))
    t.start()
    assert inside.wait(30)
    assert cache.take(frame(3))[1] == 1  # the others are not queued behind the encode
    release.set()
    t.join(30)
    assert cache.take(frame(2))[1] == 2 and cache.encoded == 2
