"""The present thread: one present per refresh, at the photon windows' own poses, never waiting
for a render."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from dpmhw.session.testing import wait_for

WAIT_S = 60  # what must happen eventually (a loaded machine, a first compile); only broken code waits
PERIOD_NS = 16_666_667  # 60 Hz


def small_mock_session(*overrides: str):
    """A mocked session at 64×48 on the moving trajectory, with a frame log (not started)."""
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import build_session

    cfg = load_session_config(overrides=["render.width=64", "render.height=48", "api.enabled=false",
                                         "mock.trajectory=rotate-oscillate", "safety.stale_after_ms=500", *overrides])
    return build_session(cfg, mock=True, frame_log=1000)


def test_presents_go_on_while_a_render_is_stuck(make_loop):
    loop = make_loop(["safety.watchdog_s=30", "safety.stale_after_ms=2000"]).start()
    assert wait_for(lambda: loop.status()["frame_number"] >= 5 and loop.status()["output_on"], WAIT_S), loop.status()
    renderer = loop.parts.renderer
    renderer.block.clear()  # the next render waits
    calls = renderer.calls
    assert wait_for(lambda: renderer.calls > calls, WAIT_S)  # a render is inside the block now
    rendered, presents = loop._frame_number, loop._present_number
    # the display's refreshes keep coming: ten presents while no frame is rendered (60 Hz: 170 ms;
    # a loaded machine may take longer, never forever)
    assert wait_for(lambda: loop._present_number >= presents + 10, WAIT_S), loop.status()
    assert loop._frame_number <= rendered + 1  # at most the frame already past its render
    loop.parts.renderer.block.set()


def test_every_present_lands_on_the_refresh_grid_with_its_photon_window(make_loop):
    loop = make_loop().start()
    assert wait_for(lambda: len(loop.frame_log or []) >= 10, WAIT_S), loop.status()
    timing, phase = loop.timing, loop._vsync_phase
    for r in list(loop.frame_log)[-10:]:
        # the recording sink answers when it took the frame: a display shows it at the next refresh
        assert [t for t, _ in r.windows] == timing.photon_mid_ns(timing.next_vsync(r.t_present_ns, phase))
        assert r.t_target_ns == r.windows[len(r.windows) // 2][0]


@pytest.mark.parametrize("mode", ["video", "pattern-8bit"])
def test_mock_session_reprojects_each_photon_window_to_its_own_instant(mode):
    """A mock session on the rotating trajectory: each present's windows lie where the emulated
    projector lit them, and with three windows each shows the body where it is at its own instant
    (poses differ between sub-frames), closer to the truth than the rendered pose (own poses
    always: a loaded machine must not make them share one)."""
    loop = small_mock_session(f'display.mode="{mode}"', 'display.shared_pose="never"')
    try:
        loop.start()
        assert wait_for(lambda: len(loop.frame_log) >= 20, WAIT_S), loop.status()
        records = list(loop.frame_log)[-15:]
        link = loop.parts.mock.video
        link.poll()
        lit = {(e.scanout_ns, e.channel): (e.t_start_ns + e.t_end_ns) // 2 for e in link.exposures}
        windows = loop.timing.windows
        body = next(iter(loop.parts.bindings.values()))
        world = loop.parts.mock.world
        matched = 0
        for r in records:
            assert len(r.windows) == len(windows)
            for (t, poses), w in zip(r.windows, windows):
                if (r.t_present_ns, w.channel) in lit:  # scanned out (not replaced before its refresh)
                    assert abs(lit[(r.t_present_ns, w.channel)] - t) <= 2_000  # the LUT counts in µs
                    matched += 1
            if len(windows) == 3:
                ts = [poses[body].t for _, poses in r.windows]
                assert not np.allclose(ts[0], ts[2])  # each sub-frame at its own instant
            # the reprojection's thread CPU time: spent, and within the wall time around it
            assert 0 < r.stages_s["reproject_cpu"] <= r.stages_s["reproject"] + 1e-4
        assert matched >= len(records)  # most presents were lit (a loaded machine misses some refreshes)
        # the shown pose is nearer the truth at photon time than the pose the frame was rendered at
        shown_err, rendered_err = [], []
        for r in records:
            for t, poses in r.windows:
                R, p = world.pose(body, t / 1e9)
                shown_err.append(np.linalg.norm(poses[body].t - p))
            rendered_err.append(np.linalg.norm(r.measured[body].t - world.pose(body, r.windows[0][0] / 1e9)[1]))
        assert np.median(shown_err) < np.median(rendered_err)
    finally:
        loop.stop()


def test_sharing_presents_show_every_sub_frame_at_the_middle_ones_pose():
    """While the lead says sub-frames share a pose, a pattern present predicts the body once, for
    its middle sub-frame, and shows it in all three (one splat): counted, and in the status."""
    loop = small_mock_session('display.mode="pattern-8bit"')
    try:
        loop.start()
        assert wait_for(lambda: len(loop.frame_log) >= 10, WAIT_S), loop.status()
        loop.lead.shared = True  # as after presents too slow for their own poses
        first = loop._present_number
        assert wait_for(lambda: loop.status()["counters"].get("shared_pose_presents", 0) >= 10
                        and len([r for r in list(loop.frame_log) if r.number > first + 1]) >= 5, WAIT_S), loop.status()
        assert loop.status()["display"]["sub_frame_poses"] == "shared"
        body = next(iter(loop.parts.bindings.values()))
        world = loop.parts.mock.world
        records = [r for r in list(loop.frame_log) if r.number > first + 1][:10]
        middle = 0
        for r in records:
            (t0, p0), (t1, p1), (t2, p2) = r.windows
            assert t0 < t1 < t2  # still lit at three instants
            assert np.array_equal(p0[body].t, p1[body].t) and np.array_equal(p2[body].t, p1[body].t)
            err = [np.linalg.norm(p1[body].t - world.pose(body, t / 1e9)[1]) for t in (t0, t1, t2)]
            middle += err[1] < min(err[0], err[2])  # predicted for the middle one
        assert middle >= len(records) / 2  # a present that missed its refresh shows a period later
    finally:
        loop.stop()


def test_split_presents_share_their_splats_with_the_helper_thread(monkeypatch):
    """While the lead says so, an own-pose pattern present's splats go to the reprojection's
    helper thread too: counted, in the status; stopping the session ends the helper."""
    import dpmhw.session.present_lead as present_lead

    monkeypatch.setattr(present_lead, "SPLIT_ABOVE", 0.0)  # any lead splits
    monkeypatch.setattr(present_lead, "SPLIT_BELOW", 0.0)
    loop = small_mock_session('display.mode="pattern-8bit"', 'display.shared_pose="never"')
    try:
        loop.start()
        assert wait_for(lambda: loop.status()["counters"].get("split_presents", 0) >= 10, WAIT_S), loop.status()
        assert loop.status()["display"]["present_threads"] == 2
        helper = loop.reprojector._helper
        assert helper is not None and helper._thread.is_alive()
    finally:
        loop.stop()
    assert not helper._thread.is_alive()


def test_each_lit_exposure_is_matched_to_the_present_it_scanned_out():
    """A refresh with no new frame shows the last present again (a repeat, at that present's
    poses); exposures before the first or after the last measured present are left out."""
    from types import SimpleNamespace as N

    from dpmhw.benchmarks.session import _photon_windows

    records = [N(t_present_ns=100, windows=((110, {1: "a"}),)), N(t_present_ns=200, windows=((210, {1: "b"}),))]
    lit = [N(scanout_ns=v, channel=None, t_start_ns=v, t_end_ns=v + 20) for v in (50, 100, 150, 200, 250)]
    assert [(t, r.t_present_ns, pose[1], k) for t, r, pose, k in _photon_windows(records, lit)] == [
        (110, 100, "a", 0), (160, 100, "a", 0), (210, 200, "b", 0)]


def test_a_present_ready_too_late_for_its_refresh_is_made_again_for_the_next():
    """A reprojection that finishes after its refresh (made slow here once) is predicted and
    reprojected again for the refresh after: that present is counted late and retargeted, the
    refresh it reaches carries it, and its pose is where the body is then (not a period off)."""
    loop = small_mock_session()
    try:
        loop.start()
        assert wait_for(lambda: len(loop.frame_log) >= 10, WAIT_S), loop.status()
        made_for = loop._reproject_for
        slowed: list[int] = []

        def slow_once(cap, vsync, settings):
            made = made_for(cap, vsync, settings)
            if not slowed:
                slowed.append(vsync)
                time.sleep(max(0.0, (vsync - loop.clock()) / 1e9) + 0.002)  # ready only after its refresh
            return made

        loop._reproject_for = slow_once
        period = loop.timing.period_ns
        assert wait_for(lambda: slowed and any(r.t_present_ns >= slowed[0] + period for r in list(loop.frame_log)),
                        WAIT_S), loop.status()
        counted = lambda: loop.status()["counters"]  # noqa: E731  (the status is published, not live)
        assert wait_for(lambda: counted().get("retargeted_presents", 0) >= 1 and counted().get("late_presents", 0) >= 1,
                        WAIT_S), loop.status()
        r = next(r for r in list(loop.frame_log) if r.t_present_ns >= slowed[0] + period)
        assert r.t_present_ns == slowed[0] + period  # the refresh after the one it missed
        assert [t for t, _ in r.windows] == loop.timing.photon_mid_ns(r.t_present_ns)
        body = next(iter(loop.parts.bindings.values()))
        world = loop.parts.mock.world
        for t, poses in r.windows:  # predicted for the instant it is lit: well under the period's motion
            assert np.linalg.norm(poses[body].t - world.pose(body, t / 1e9)[1]) < 1e-3
    finally:
        loop.stop()


def test_the_lead_covers_all_but_the_slowest_one_or_two_recent_presents():
    """A few slow presents among the last 240 (a busy stretch of the machine) set the lead, so a
    present as slow as they were still makes its refresh; one alone (a hiccup) does not lengthen
    every prediction after it."""
    from dpmhw.session.present_lead import HANDOFF_NS, PresentLead

    ms = 1_000_000
    busy, hiccup = PresentLead(PERIOD_NS, False), PresentLead(PERIOD_NS, False)
    for k in range(240):
        busy.add(7 * ms if k % 60 == 0 else 2 * ms, late=False)  # 4 of 240 slow
        hiccup.add(7 * ms if k == 100 else 2 * ms, late=False)  # 1 of 240 slow
    assert busy.lead_ns - HANDOFF_NS >= 7 * ms, busy.lead_ns
    assert hiccup.lead_ns < 7 * ms, hiccup.lead_ns


@pytest.mark.parametrize("share_poses", [True, False])
def test_pattern_presents_share_one_pose_while_their_own_would_need_more_than_the_longest_lead(share_poses):
    """When more than 1 in 100 of the last 240 presents would miss their refresh at the longest
    lead (¾ of a period; a slow CPU), or 6 of the last 240 missed it there, a pattern present's
    three sub-frames share one pose; a few slow ones or five misses (hiccups) do not make them.
    Own poses come back once the shared presents' times, scaled by how much dearer own poses
    were, fit with room again, not before a hold. With `display.shared_pose = "never"` the lead
    only saturates."""
    from dpmhw.session.present_lead import HISTORY, SHARED_HOLD, PresentLead

    ms = 1_000_000
    longest = PERIOD_NS * 3 // 4
    hiccups = PresentLead(PERIOD_NS, True)
    for k in range(2 * HISTORY):  # 2 in 240 far too slow, the rest quick
        assert hiccups.add(30 * ms if k % 120 == 0 else 3 * ms, late=False) is None
    assert not hiccups.shared and hiccups.lead_ns == longest

    missing = PresentLead(PERIOD_NS, True)  # presents that miss at the longest lead: seen before 240 are measured
    for k in range(100):
        assert missing.add(11 * ms, late=k in (20, 40, 60, 80, 90)) is None  # five misses in 240 presents: hiccups
    assert missing.lead_ns == longest and not missing.shared
    assert "6 of the last 101 missed" in missing.add(11 * ms, late=True) and missing.shared

    lead = PresentLead(PERIOD_NS, share_poses)
    for _ in range(HISTORY - 1):  # own poses: 12.4 ms to a frame ready, plus the hand-over: past the longest lead
        assert lead.add(12.4 * ms, late=False) is None
    assert not lead.shared and lead.lead_ns == longest  # not before 240 presents are measured
    change = lead.add(12.4 * ms, late=False)
    assert lead.shared == share_poses and lead.lead_ns == longest
    if not share_poses:
        assert change is None
        return
    assert "would miss it, needing a lead over 12.7 ms" in change
    for _ in range(SHARED_HOLD - 1):  # shared: 3.1 ms (a quarter of the work); 4 × 3.1 + 2 = 14.4 ms own: stay
        assert lead.add(3.1 * ms, late=False) is None
        assert lead.shared
    assert lead.lead_ns == 5.1 * ms  # the shared presents' own lead
    assert lead.add(3.1 * ms, late=False) is None and lead.shared  # past the hold, but own poses still would not fit
    for _ in range(HISTORY):  # the machine is quicker now: 1.5 ms shared, so 4 × 1.5 + 2 = 8 ms own, under 0.8 × 12.5
        change = lead.add(1.5 * ms, late=False)
        if change is not None:
            break
    assert change is not None and "own pose again" in change and not lead.shared
    assert lead.lead_ns == 8 * ms  # the estimate, until own-pose presents are measured
    for _ in range(HISTORY):
        lead.add(6 * ms, late=False)
    assert not lead.shared and lead.lead_ns == 8 * ms  # measured own poses: 6 + 2 ms


def test_own_pose_splats_go_to_two_threads_while_the_lead_is_near_its_longest_and_back_once_it_is_short():
    """Own-pose pattern presents share their splats with the helper thread once the lead passes
    0.8 of the longest (10 ms at 60 Hz: near where their sub-frames would share one pose), and go
    back to one thread only below 0.65 of it: the shorter times of split presents alone do not
    switch them back. Presents sharing one pose make one splat: not split. Without a helper
    (present_threads 1, or video mode) they never split."""
    from dpmhw.session.present_lead import HISTORY, PresentLead

    ms = 1_000_000
    lead, alone = PresentLead(PERIOD_NS, True, split_splats=True), PresentLead(PERIOD_NS, True)
    for p in (lead, alone):
        for _ in range(HISTORY):  # 7 ms + 2 = 9 ms: under 0.8 of the longest
            p.add(7 * ms, late=False)
        assert not p.split and p.lead_ns == 9 * ms
        changes = [p.add(9 * ms, late=False) for _ in range(HISTORY)]  # a slower stretch: 9 ms, an 11-ms lead
        said = [c for c in changes if c]
        assert len(said) == (p is lead) and all(re.fullmatch(
            r"pattern presents make their splats on two threads \(lead 1\d\.\d ms of at most 12\.5\)", c) for c in said), said
    assert lead.split and not alone.split
    assert not lead.shared
    for _ in range(HISTORY):  # split: 7 ms, a 9-ms lead, above 0.65 of the longest (8.1 ms): stays split
        lead.add(7 * ms, late=False)
    assert lead.split and lead.lead_ns == 9 * ms
    for _ in range(HISTORY):  # the machine is quicker: 5 ms, a 7-ms lead
        lead.add(5 * ms, late=False)
    assert not lead.split
    changes = [lead.add(12.4 * ms, late=False) for _ in range(2 * HISTORY)]  # too slow even split: one pose, one splat
    assert lead.shared and not lead.split and any(c and "share one pose" in c for c in changes)


def test_own_poses_are_weighed_for_sharing_only_once_split_and_by_whether_they_would_miss():
    """With the helper thread, own-pose presents share one pose only once their split presents
    would miss: one-thread times and misses before the split say nothing about split ones. Split
    presents that fit the longest lead with the hand-over to spare, missing now and then, keep
    their own poses (the two-thread presents of a 3× slower CPU, docs/session.md)."""
    from dpmhw.session.present_lead import HISTORY, PresentLead

    ms = 1_000_000
    lead = PresentLead(PERIOD_NS, True, split_splats=True)
    lead.lead_ns = lead.longest_ns  # a one-thread present at the longest lead, missing, as at a slow start
    lead.add(14 * ms, late=True)
    assert lead.split
    for k in range(3 * HISTORY):  # split: 11.8 ms, 12.1 with the hand-over; a miss every ~50 presents
        assert lead.add(11.8 * ms, late=k % 49 == 10) is None
    assert lead.split and not lead.shared and lead.lead_ns == lead.longest_ns
    changes = [lead.add(12.4 * ms, late=False) for _ in range(HISTORY)]  # slower: more than 1 in 100 would miss
    assert lead.shared and sum(c is not None for c in changes) == 1


def test_a_present_back_after_its_next_planned_wake_still_makes_the_next_refresh():
    """The present thread back from a present later than the next one's planned wake (its sink
    held it, here a few times), with more than the median time to a ready frame left before the
    next refresh, presents for that refresh rather than skipping it (which would show the last
    frame twice for certain)."""
    loop = small_mock_session()
    try:
        loop.start()
        assert wait_for(lambda: len(loop.frame_log) >= 30, WAIT_S), loop.status()
        loop.lead.penalty_ns = 8_000_000  # a wide lead, as after missed refreshes: room between the wake and the median
        assert wait_for(lambda: len(loop.frame_log) >= 40, WAIT_S), loop.status()
        period, sink = loop.timing.period_ns, loop.parts.sink
        present, held = sink.present, []  # (refresh presented for, back at, least time then)

        def held_now_and_then(frame, t_target_ns):
            v = present(frame, t_target_ns)
            if len(held) < 5 and (not held or v >= held[-1][0] + 10 * period):
                lead = loop.lead.lead_ns
                time.sleep(max(0.0, (v + period - lead + 500_000 - loop.clock()) / 1e9))  # just past the next planned wake
                held.append((v, loop.clock(), loop.lead.time_ns))
            return v

        sink.present = held_now_and_then
        assert wait_for(lambda: len(held) == 5 and any(r.t_present_ns > held[-1][0] for r in list(loop.frame_log)),
                        WAIT_S), loop.status()
        presented = [r.t_present_ns for r in list(loop.frame_log)]
        clean = [(v, back) for v, back, least in held if v + period - back > least + 1_000_000]  # not overshot by the machine
        assert clean, [(back - v, least) for v, back, least in held]
        for v, back in clean:
            nxt = min(t for t in presented if t > v)
            assert nxt == v + period, f"back {(back - v) / 1e6:.2f} ms after its refresh, next present {(nxt - v) / period:.0f} periods on"
    finally:
        loop.stop()
