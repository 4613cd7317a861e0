"""The display timing model: photon windows per mode and the refresh grid."""

import pytest

from dpmhw.display import DisplayTiming


def test_video_mode_is_one_window_of_one_period_after_the_delay():
    t = DisplayTiming("video", 60.0, 2_000_000)
    (w,) = t.windows
    assert (w.channel, w.start_ns, w.duration_ns, w.leds) == (None, 2_000_000, 16_666_667, (True, True, True))
    assert t.photon_mid_ns(1_000) == [1_000 + 2_000_000 + 16_666_667 // 2]


def test_pattern_8bit_is_three_channels_back_to_back_at_three_times_the_rate():
    t = DisplayTiming("pattern-8bit", 60.0, 0)
    ws = t.windows
    assert [w.channel for w in ws] == [0, 1, 2]
    assert [w.leds for w in ws] == [(True, False, False), (False, True, False), (False, False, True)]
    assert all(b.start_ns == a.start_ns + a.duration_ns for a, b in zip(ws, ws[1:]))
    assert ws[-1].start_ns + ws[-1].duration_ns <= t.period_ns
    assert 1e9 / ws[0].duration_ns == pytest.approx(180.0, rel=1e-6)


def test_next_vsync_is_on_the_grid_and_not_before():
    t = DisplayTiming(refresh_hz=50.0)
    assert t.next_vsync(100, 100) == 100
    assert t.next_vsync(101, 100) == 100 + 20_000_000
    assert t.next_vsync(-5_000_000, 100) == 100
    assert t.next_vsync(100 + 40_000_000, 100) == 100 + 40_000_000


@pytest.mark.parametrize("kw, field", [({"mode": "hdmi"}, "display.mode"), ({"refresh_hz": 0.0}, "display.refresh_hz"),
                                       ({"controller_delay_ns": -1}, "display.controller_delay_ms")])
def test_bad_values_name_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        DisplayTiming(**kw)
