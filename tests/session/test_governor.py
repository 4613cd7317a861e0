"""The quality governor as a policy: synthetic frame times on a simulated clock (no threads, no
rendering), so every check is about decisions, never about this machine's speed."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dpmhw.session.config import GovernorSection, SessionConfigError, load_session_config
from dpmhw.session.governor import LADDER, Governor

NS = 1_000_000_000


class Machine:
    """A frame thread on a simulated clock: each frame takes `base_s` × the ladder's cost of its
    settings × `load` (× noise), and the governor's patches take effect on the next frame."""

    def __init__(self, gov: Governor, base_s: float, noise: float = 0.0, seed: int = 0, pinned=(), settings=None):
        self.gov, self.base_s, self.noise = gov, base_s, noise
        self.rng = np.random.default_rng(seed)
        self.settings = settings or load_session_config().live_settings()
        self.configured = self.settings.model_dump()
        self.pinned = frozenset(pinned)
        self.load = 1.0
        self.t_ns = 0
        self.patches: list[dict] = []
        self.levels: list[tuple[int, int]] = []  # (t_ns, level) after each frame

    def cost(self) -> float:
        """The true relative cost of the current settings: each rung's saving where its field moved."""
        saves = {r.name: r.saves for r in LADDER}
        now, c = self.settings, 1.0
        if now.lod_rays == 0 < self.configured["lod_rays"]:
            c *= 1.0 - saves["lod rays off"]
        if now.adaptive_rays == 0 < self.configured["adaptive_rays"]:
            c *= 1.0 - saves["adaptive sampling off"]
        c *= {"lobe": 1.0, "normal": 1.0 - saves["normal-aware filter"],
              "off": (1.0 - saves["normal-aware filter"]) * (1.0 - saves["filter off"])}[now.filter]
        return c

    def run(self, seconds: float) -> None:
        end = self.t_ns + int(seconds * NS)
        while self.t_ns < end:
            frame_s = self.base_s * self.cost() * self.load
            if self.noise:
                frame_s *= math.exp(self.rng.normal(0.0, self.noise))
            self.t_ns += int(frame_s * NS)
            patch = self.gov.observe(self.t_ns, frame_s, {}, self.settings, self.pinned)
            if patch:
                assert not set(patch) & self.pinned, patch
                self.patches.append(patch)
                self.settings = self.settings.model_copy(update=patch)
            self.levels.append((self.t_ns, self.gov.level))

    def fps(self, seconds: float) -> float:
        """The rate over the last `seconds`."""
        t = [ts for ts, _ in self.levels if ts >= self.t_ns - seconds * NS]
        return (len(t) - 1) / ((t[-1] - t[0]) / NS)


def governor(clock=lambda: 0, **kw) -> Governor:
    return Governor(GovernorSection(**kw), refresh_hz=60.0, clock=clock)


def test_steps_down_under_load_and_recovers():
    gov = governor()
    m = Machine(gov, base_s=1 / 50)  # 50 fps at the configured settings: below 60 by more than 10 %
    m.run(3.0)
    assert gov.level > 0 and gov.changes >= 1
    assert m.fps(0.5) >= 60 * 0.9  # the level it chose holds the rate
    assert "down to" in gov.reason
    assert m.settings.filter != "lobe" or m.settings.adaptive_rays == 0
    m.base_s = 1 / 200  # the load is gone: lots of headroom
    m.run(60.0)
    assert gov.level == 0 and "up to" in gov.reason
    assert m.settings.model_dump() == m.configured  # back to exactly the configured settings


def test_no_oscillation_on_a_boundary():
    """A machine whose rate at the configured settings sits right at the step-down threshold, with
    noisy frame times, for ten simulated minutes: at most a handful of changes (hysteresis plus the
    backing-off hold), not one every few seconds."""
    for seed, base in ((1, 1 / 54.0), (2, 1 / 60.0), (3, 1 / 49.0)):
        gov = governor()
        m = Machine(gov, base_s=base, noise=0.15, seed=seed)
        m.run(600.0)
        assert gov.changes <= 6, (seed, gov.changes, m.patches)


def test_reacts_to_a_cpu_hog_within_two_seconds():
    gov = governor()
    m = Machine(gov, base_s=1 / 75, noise=0.05)  # 75 fps: level 0 holds 60 with room
    m.run(10.0)
    assert gov.level == 0
    m.load = 1.5  # a hog starts: 50 fps at level 0
    t_hog = m.t_ns
    m.run(2.0)
    changed = [t for t, level in m.levels if t > t_hog and level > 0]
    assert changed and changed[0] - t_hog <= 1.0 * NS  # one short window (0.5 s) plus a frame or two
    assert m.fps(0.5) >= 60 * 0.9  # and within 2 s the rate is back


def test_latency_budget_steps_down():
    gov = governor(latency_budget_ms=30.0, target_fps=10.0)  # 100 fps, but each frame 33 ms start to present
    settings = load_session_config().live_settings()
    t = 0
    for _ in range(200):
        t += NS // 100
        patch = gov.observe(t, 0.033, {}, settings, frozenset())
        if patch:
            settings = settings.model_copy(update=patch)
    assert gov.level > 0 and "budget" in gov.reason


def test_never_touches_pinned_fields_and_uses_other_rungs():
    gov = governor()
    m = Machine(gov, base_s=1 / 30, pinned={"filter"})  # far too slow: all the way down
    m.run(5.0)
    assert all("filter" not in p for p in m.patches)
    assert m.settings.filter == "lobe" and m.settings.adaptive_rays == 0
    st = gov.status()
    assert st["pinned"] == ["filter"]
    assert [r["skipped"] for r in st["ladder"] if r["field"] == "filter"] == [True, True]
    assert "cheapest" in st["reason"]


def test_a_field_pinned_later_is_left_where_the_operator_put_it():
    gov = governor()
    m = Machine(gov, base_s=1 / 30)
    m.run(3.0)
    assert m.settings.filter == "off"
    m.settings = m.settings.model_copy(update={"filter": "normal"})  # the operator's choice
    m.pinned = frozenset({"filter"})
    m.base_s = 1 / 500
    m.run(60.0)
    assert m.settings.filter == "normal" and m.settings.adaptive_rays == m.configured["adaptive_rays"]


def test_status_is_json_and_says_what_and_why():
    clock = [0]
    gov = governor(clock=lambda: clock[0])
    json.dumps(gov.status(), allow_nan=False)  # before any frame
    m = Machine(gov, base_s=1 / 50)
    m.run(2.0)
    clock[0] = m.t_ns
    st = json.loads(json.dumps(gov.status(), allow_nan=False))
    assert st["level"] == gov.level > 0 and st["target_fps"] == 60.0 and st["target_from"] == "the display's refresh"
    assert st["measured_fps"] > 0 and st["reason"].startswith("down to") and st["pinned"] == []
    assert st["choices"]["filter"] == m.settings.filter


def test_gap_and_disabled():
    gov = governor()
    s = load_session_config().live_settings()
    t = 0
    for _ in range(20):  # 20 fps
        t += NS // 20
        gov.observe(t, 0.01, {}, s, ())
    assert gov.level > 0
    gov2 = governor(enabled=False)
    assert all(gov2.observe(k * NS // 5, 0.2, {}, s, ()) is None for k in range(50))
    assert gov2.status()["level"] == 0 and gov2.status()["enabled"] is False
    gov3 = governor()  # a dark spell is no slow rate: frames 1 s apart at 60 fps bursts
    for burst in range(5):
        for k in range(3):
            assert gov3.observe(burst * 2 * NS + k * NS // 60, 0.01, {}, s, ()) is None
    assert gov3.level == 0


def test_target_from_config_and_inert_rungs():
    gov = Governor(GovernorSection(target_fps=30.0), refresh_hz=120.0, clock=lambda: 0, inert=frozenset({"lod_rays"}))
    assert gov.target_fps == 30.0
    s = load_session_config().live_settings()
    t = 0
    for _ in range(40):
        t += NS // 10
        patch = gov.observe(t, 0.1, {}, s, ())
        if patch:
            assert "lod_rays" not in patch
            s = s.model_copy(update=patch)
    assert gov.level > 1  # the LOD rung was skipped


@pytest.mark.parametrize("override, field", [
    ("governor.target_fps=0", "governor.target_fps"),
    ("governor.target_fps=nan", "governor.target_fps"),
    ("governor.latency_budget_ms=-1", "governor.latency_budget_ms"),
    ("governor.down_margin=2", "governor.down_margin"),
    ("governor.headroom=inf", "governor.headroom"),
    ("governor.up_window_s=0", "governor.up_window_s"),
    ("governor.speed=1", "governor.speed"),
])
def test_config_errors_name_the_field(override, field):
    with pytest.raises(SessionConfigError) as e:
        load_session_config(overrides=[override])
    assert field in str(e.value)


def test_refresh_rate_must_be_a_rate():
    with pytest.raises(ValueError, match="refresh_hz"):
        Governor(GovernorSection(), refresh_hz=math.nan, clock=lambda: 0)
