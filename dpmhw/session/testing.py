"""In-process doubles of a session's parts, for tests of the loop and the service.

They implement the same protocols as the real parts (Tracker, ProjectorControl, a renderer)
with switches a test flips to inject each fault. The end-to-end tests use the real drivers
against the firmware mocks instead.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from dpmhw.tracking import LatestPoses, PoseSample, TrackerState, TrackerStatus

__all__ = ["FakeProjector", "FakeTracker", "FlatRenderer", "fake_session", "wait_for"]


class FakeTracker:
    """Publishes a sample of body 1 on demand or continuously from a thread (a test controls validity)."""

    kind = "fake"

    def __init__(self):
        self.poses = LatestPoses()
        self.state = TrackerState.STREAMING
        self.valid = True
        self.streaming = True
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.stopped = False

    def _run(self):
        k = 0
        while not self._stop.wait(0.003):
            if not self.streaming:
                continue
            now = time.monotonic_ns()
            rot = np.eye(3) if self.valid else np.full((3, 3), np.nan)
            self.poses.publish([PoseSample(1, rot, np.array([0.01 * np.sin(k / 50), 0.0, 0.0]), now - 4_500_000,
                                           now, self.valid, frame_number=k)])
            k += 1

    def start(self):
        self._thread.start()

    def stop(self):
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5)
        self.stopped = True

    def latest(self, body):
        return self.poses.latest(body)

    def latest_all(self):
        return self.poses.latest_all()

    def subscribe(self, maxlen: int = 4096):  # every sample, as the real drivers offer the loop
        return self.poses.subscribe(maxlen)

    def status(self):
        return TrackerStatus(self.state, "" if self.state == TrackerState.STREAMING else "test says so")


class FakeProjector:
    def __init__(self):
        self.calls: list[str] = []
        self.fail_health = False
        self.fail_blank = False
        self.dark = True

    def blank(self):
        self.calls.append("blank")
        if self.fail_blank:
            raise RuntimeError("blank read-back failed")
        self.dark = True
        return "idle"

    def unblank(self):
        self.calls.append("unblank")
        self.dark = False

    def health(self):
        if self.fail_health:
            raise RuntimeError("device unplugged")
        return {"idle": self.dark}

    def reconnect(self):
        if self.fail_health:
            raise RuntimeError("still unplugged")

    def close(self):
        self.calls.append("close")


class FlatRenderer:
    """Radiance = constant plus noise where the object is: cheap, and reuse changes its output."""

    def __init__(self, width=32, height=24):
        self.width, self.height = width, height
        self.block = threading.Event()
        self.block.set()
        self.fail: Exception | None = None
        self.calls = 0

    def render(self, time=0.0, seed=0, spp=1, poses=None, **kw):
        self.calls += 1
        self.block.wait(30)
        if self.fail is not None:
            raise self.fail
        return flat_frame(self.width, self.height, seed)


def flat_frame(width: int, height: int, seed: int = 0):
    """A renderer `Frame` of one diffuse object facing the camera at depth 1, noisy radiance."""
    from dpmhw.render.frame import Frame

    rng = np.random.default_rng(seed)
    shape = (height, width)
    radiance = (0.2 + 0.2 * rng.random((*shape, 3))).astype(np.float32)
    normal = np.zeros((*shape, 3), np.float32)
    normal[..., 2] = -1.0
    ones = np.ones((*shape, 3), np.float32)
    return Frame(radiance=radiance, diffuse=radiance.copy(), specular=np.zeros_like(radiance),
                 object_id=np.zeros(shape, np.int32), model_position=np.zeros_like(radiance),
                 position=np.zeros_like(radiance), normal=normal, depth=np.ones(shape, np.float32), albedo=ones,
                 specular_albedo=np.zeros_like(radiance), roughness=np.ones(shape, np.float32), spp=1,
                 time=0.0, seed=seed)




def fake_session(overrides=(), renderer=None, projector=True, tracker=None, frame_log=2000, **loop_kw):
    """A SessionLoop (not started) over the doubles and an in-memory sink, 32×24 dpm-bunny;
    `loop_kw` goes to the loop (e.g. a simulated `clock` and `wait`)."""
    from dpmhw.scene_file import load_scene
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import resolve_bindings
    from dpmhw.session.loop import SessionLoop, SessionParts
    from drivers.frame_sinks import RecordingSink

    scene = load_scene("dpm-bunny").at_size(32, 24)
    cfg = load_session_config(overrides=["safety.holdoff_s=0.1", "safety.stale_after_ms=200", "safety.watchdog_s=1.0",
                                         "projector.poll_interval_s=0.02", "reuse.mode=same-pixel", *overrides])
    parts = SessionParts(scene, renderer or FlatRenderer(), tracker or FakeTracker(), RecordingSink(max_frames=4096),
                         resolve_bindings(cfg, scene), FakeProjector() if projector else None)
    parts.tracker.start()
    return SessionLoop(cfg, parts, frame_log=frame_log, **loop_kw)


def wait_for(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.005) -> bool:
    """Poll `predicate` until true or `timeout_s` elapses; returns its last value. For tests and
    benches that watch a running session from outside, where no event says what they wait for."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)
