"""`dpmhw bench governor`'s analysis on synthetic event times (no session, no hog, no timing):
rates, recovery, per-second rows from frame records, the table and the plot."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from dpmhw.benchmarks import governor_hog as gh

NS = 1_000_000_000


def _times(rate_segments):
    """Event times for piecewise-constant rates [(start_s, end_s, per_s)], evenly spaced."""
    return np.concatenate([np.arange(a, b, 1.0 / r) + 0.5 / r for a, b, r in rate_segments])


def test_trailing_rate_counts_the_window_before_each_time():
    t = _times([(0, 10, 40)])
    grid, rate = gh.trailing_rate(t, np.arange(1, len(t) + 1), 10.0)
    assert grid[0] == pytest.approx(1.0) and grid[-1] == pytest.approx(10.0)
    assert np.allclose(rate, 40.0)


def test_recovery_after_a_dip_is_when_the_trailing_rate_is_back_and_stays():
    # 40/s, 20/s for 1.5 s after the hog at 10 s, 40/s again: the trailing 1-s window [t − 1, t]
    # is at ≥ 36/s while at most 0.2 s of the slow spell is in it: below from 10.2 s, back once
    # 11.5 − (t − 1) ≤ 0.2, at t = 12.3 s, i.e. 2.3 s after the hog
    t = _times([(0, 10, 40), (10, 11.5, 20), (11.5, 25, 40)])
    grid, rate = gh.trailing_rate(t, np.arange(1, len(t) + 1), 25.0)
    back, below = gh.recovery(grid, rate, 10.0, 36.0)
    assert back == pytest.approx(2.3, abs=0.15)
    assert below == pytest.approx(2.1, abs=0.15)


def test_no_events_give_zero_rates_and_empty_seconds():
    ev = gh.events([], 0)
    grid, rate = gh.trailing_rate(ev["render_t"], ev["render_n"], 3.0)
    assert np.all(rate == 0)
    rows = gh.second_rows(ev, 3.0, 1.0)
    assert [(r["present_fps"], r["render_fps"], r["governor_level"]) for r in rows] == [(0, 0, None)] * 3
    assert gh.level_steps(ev) == ([], [])


def test_recovery_is_zero_without_a_dip_and_none_when_never_back():
    t = _times([(0, 20, 60)])
    grid, rate = gh.trailing_rate(t, np.arange(1, len(t) + 1), 20.0)
    assert gh.recovery(grid, rate, 8.0, 54.0) == (0.0, 0.0)
    t = _times([(0, 8, 60), (8, 20, 30)])
    grid, rate = gh.trailing_rate(t, np.arange(1, len(t) + 1), 20.0)
    back, below = gh.recovery(grid, rate, 8.0, 54.0)
    assert back is None and below == pytest.approx(11.9, abs=0.15)
    # back only in the last half second: not settled for a second, so not back
    t = _times([(0, 8, 60), (8, 19.5, 30), (19.5, 20, 60)])
    grid, rate = gh.trailing_rate(t, np.arange(1, len(t) + 1), 20.0)
    assert gh.recovery(grid, rate, 8.0, 54.0)[0] is None


def _records(t0_ns, seconds=4.0, refresh=60.0, render_every=2, skipped=(7,), level_from=(2.0, 3)):
    """Presents at `refresh`, a new rendered frame every `render_every` presents (each shown
    twice), rendered numbers with the frames in `skipped` never shown (replaced before a
    refresh), the governor at `level_from[1]` from `level_from[0]` s."""
    out, number = [], 100
    for k in range(int(seconds * refresh)):
        t_present = t0_ns + int((k + 0.5) / refresh * NS)
        if k % render_every == 0:
            number += 1 + (number + 1 in skipped)
        frame_s = 0.02
        t_start = t_present - int((frame_s + 0.004) * NS)  # rendered, then shown at the next refresh
        out.append(SimpleNamespace(t_present_ns=t_present, t_start_ns=t_start, stages_s={"frame": frame_s}, rendered=number,
                                   governor_level=level_from[1] if t_present - t0_ns >= level_from[0] * NS else 0))
    return out


def test_events_and_seconds_count_each_rendered_frame_once_and_the_unshown_ones():
    t0 = 5 * NS
    early = SimpleNamespace(t_present_ns=t0 - 1000, t_start_ns=t0 - NS, stages_s={"frame": 0.02}, rendered=99, governor_level=0)
    recs = [early, *_records(t0, skipped=(107,))]
    ev = gh.events(recs, t0)
    assert len(ev["present_t"]) == 240  # the present before t0 is left out
    assert ev["render_n"][0] == 1 and len(ev["render_t"]) == 120  # 120 shown renders, numbers 101 … 221 minus 107
    assert ev["render_n"][-1] == 121  # the frame never shown still counts
    rows = gh.second_rows(ev, 4.0, hog_s=2.0, reasons=["a", "b", "c", "d"])
    assert [r["present_fps"] for r in rows] == [60, 60, 60, 60]
    assert [r["render_fps"] for r in rows] == [31, 30, 30, 30]  # second 0 holds the unshown frame
    assert [r["hog"] for r in rows] == [False, False, True, True]
    assert [r["hog"] for r in gh.second_rows(ev, 4.0, hog_s=1.5)] == [False, True, True, True]  # it ran in second 1
    assert [r["governor_level"] for r in rows] == [0, 0, 3, 3] and rows[3]["governor_reason"] == "d"
    assert rows[0]["frame_ms_p50"] == pytest.approx(20.0)


def test_level_steps_keep_the_first_present_and_each_change():
    ev = gh.events(_records(0, seconds=4.0, level_from=(2.0, 3)), 0)
    t, level = gh.level_steps(ev)
    assert level == [0, 3] and t[0] == pytest.approx(0.5 / 60, abs=1e-4) and t[1] == pytest.approx(2.0, abs=1 / 60)


def test_summary_thresholds_follow_the_governor_margin():
    t0 = 0
    ev = gh.events(_records(t0, seconds=6.0), t0)
    s = gh.summarize(ev, 6.0, 3.0, present_target=60.0, render_target=30.0, margin=0.1)
    assert s["present_threshold_fps"] == 54.0 and s["render_threshold_fps"] == 27.0
    assert s["present_recovery_s"] == 0.0 and s["render_recovery_s"] == 0.0
    assert s["present_fps_quiet"] == pytest.approx(60.0, abs=0.5) and s["render_fps_hog"] == pytest.approx(30.0, abs=1.0)


def _result():
    t0 = 0
    ev = gh.events(_records(t0, seconds=6.0), t0)
    rows = gh.second_rows(ev, 6.0, 3.0, ["r"] * 6)
    summary = {"kind": "summary", "scene": "dpm-bunny", "output_width": 1024, "output_height": 768, "shading_scale": 0.25,
               "display": "video", "seconds": 6.0, "hog_after_s": 3.0, "hog_processes": 2, "hog_cpu_s": 6.0, "load_before": 0.5,
               "cpu_steal_quiet": 0.012, "cpu_steal_hog": None,
               **gh.summarize(ev, 6.0, 3.0, 60.0, 60.0, 0.1), "level_before_hog": 0, "level_end": 3, "governor_changes": 1,
               "governor_reason": "r", "cpu_ms_per_render_quiet": 60.0, "cpu_ms_per_render_hog": 70.0, "late_presents": 0}
    quality = {"kind": "quality", "held": "configured", "level": 0, "filter": "lobe", "adaptive_rays": 2048, "psnr_db": 40.0,
               "psnr_db_object": 28.2, "cpu_ms": 33.0, "cpu_vs_level0": 1.0}
    series = {n: gh.trailing_rate(ev[f"{n}_t"], ev[f"{n}_n"], 6.0) for n in ("present", "render")}
    series["level"] = gh.level_steps(ev)
    return {"rows": [*rows, summary, quality], "series": series}


def test_table_and_plot(tmp_path):
    result = _result()
    table = gh.format_table(result["rows"])
    assert "not back before the end" in table  # renders at 30/s never reach 54/s
    assert "inside the objects 28.20 dB" in table
    assert "the host's steal 1.2% quiet, - under the hog" in table
    path = gh.plot(result, tmp_path / "sub" / "hog.png")
    img = cv2.imread(str(path))
    assert img is not None and img.shape[:2] == (480, 1100)
