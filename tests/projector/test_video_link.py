"""The emulated video link and the DLPC900's video input: refresh grid, frames never shown, and
video-pattern decoding of a packed frame; the driver's video-pattern configuration, byte for
byte, against the emulated controller, and the LUTs the controller refuses."""

from __future__ import annotations

import numpy as np
import pytest

from dpmhw.display import DisplayTiming
from dpmhw.frame_sink import FrameSink
from drivers.dlpc900 import Color, DisplayMode, DLPC900DeviceError, DLPC900Error, PatternTiming
from firmware_mocks.dlpc900_model import DLPC900Model
from firmware_mocks.video_link import VideoLink

P60 = DisplayTiming(refresh_hz=60.0).period_ns  # 16 666 667 ns


def _frame(seed=0, h=4, w=6):
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def test_present_latches_at_the_next_refresh_and_waits_for_it(clock):
    model = DLPC900Model(width=6, height=4, clock=clock)
    link = VideoLink(model, timing=DisplayTiming(controller_delay_ns=1_000_000), clock=clock, sleep=clock.sleep,
                     phase_ns=clock())
    assert isinstance(link, FrameSink) and link.vsync_phase_ns() == clock()
    t0 = clock()
    at = link.present(_frame(), t0 + 1)  # just after a refresh: the next one, waited for
    assert at == t0 + P60 == clock() and clock.sleeps == [P60 / 1e9]
    assert link.present(_frame(1), 0) == t0 + 2 * P60  # a late target: the next refresh not yet scanning out
    clock.advance(3 * P60)
    link.poll()
    rows = list(link.exposures)
    assert [(r.frame, r.scanout_ns, r.repeat) for r in rows] == [(0, t0 + P60, False), (1, t0 + 2 * P60, False)] + [
        (1, t0 + k * P60, True) for k in (3, 4, 5)]  # no new frame: the last one scanned out again
    assert rows[0].t_start_ns == t0 + P60 + 1_000_000 and rows[0].t_end_ns == rows[0].t_start_ns + P60
    assert rows[0].leds == (True, True, True) and rows[0].lut_index is None and rows[0].bit_depth == 24
    assert (link.frames_shown, link.never_shown, link.repeats) == (2, 0, 3)
    link.close()
    assert model.video_period_ns is None  # the cable is out: no sync
    with pytest.raises(RuntimeError):
        link.present(_frame(), 0)


def test_a_frame_superseded_within_one_refresh_is_never_shown(clock):
    model = DLPC900Model(width=6, height=4, clock=clock)
    link = VideoLink(model, clock=clock, phase_ns=clock(), block=False, keep_images=4)
    t0 = clock()
    a, b, c = _frame(0), _frame(1), _frame(2)
    assert link.present(a, t0) == t0 + P60  # the refresh at t0 is scanning out already
    clock.advance(P60 // 2)
    assert link.present(b, t0) == t0 + P60  # replaces a before its refresh: a is never shown
    clock.advance(P60)
    assert link.present(c, clock()) == t0 + 2 * P60
    clock.advance(P60)
    link.poll()
    rows = list(link.exposures)
    assert [r.frame for r in rows] == [1, 2] and link.never_shown == 1 and link.frames_presented == 3
    assert np.array_equal(rows[0].image, b) and np.array_equal(rows[1].image, c)
    with pytest.raises(ValueError, match="frame"):
        link.present(np.zeros((4, 6, 3), np.float32), 0)


def test_idle_projector_shows_nothing(clock):
    model = DLPC900Model(width=6, height=4, clock=clock)
    link = VideoLink(model, clock=clock, block=False)
    model.idle = True
    link.present(_frame(), 0)
    clock.advance(2 * P60)
    link.poll()
    assert not link.exposures and link.frames_shown == 1


def test_refreshes_the_projector_spent_dark_stay_dark_when_scanned_out_later(clock):
    """The link scans out refreshes lazily (at the next present or poll): one the projector
    spent idle (a blank, by command) shows nothing, though it is lit again by then."""
    model = DLPC900Model(width=6, height=4, clock=clock)
    link = VideoLink(model, clock=clock, phase_ns=clock(), block=False)
    t0 = clock()
    link.present(_frame(), t0)
    clock.advance(P60 + P60 // 2)
    link.poll()  # the refresh at t0 + P60 lit
    model.execute(0x0201, bytes([1]), False)  # idle on: dark
    clock.advance(3 * P60)
    model.execute(0x0201, bytes([0]), False)  # lit again before anything scanned out the gap
    link.present(_frame(1), clock())
    clock.advance(2 * P60)
    link.poll()
    assert [(r.frame, (r.scanout_ns - t0) // P60, r.repeat) for r in link.exposures] == [(0, 1, False), (1, 5, False),
                                                                                       (1, 6, True)]
    assert model.dark_at(t0 + 2 * P60) and not model.dark_at(t0 + P60) and not model.dark_at(clock())


def test_driver_configures_video_pattern_mode_byte_for_byte(dlp, emu, clock):
    link = VideoLink(emu.model, clock=clock, sleep=clock.sleep)  # the source: sync locked
    emu.model.command_log.clear()
    dlp.set_video_pattern_mode(60.0)
    writes = [(c.opcode, c.data) for c in emu.model.command_log if not c.read]
    # 5555 µs = 0x0015B3; options: bits 3:1 = 7 (8-bit), colour in 6:4, bit 7 wait for trigger
    assert writes == [
        (0x1A24, b"\x00"),                                   # stop
        (0x1A1B, b"\x02"),                                   # video pattern mode
        (0x1A34, bytes.fromhex("0000 b31500 9e 000000 00 0040")),  # red: bit position 8
        (0x1A34, bytes.fromhex("0100 b31500 2e 000000 00 0000")),  # green: bit position 0
        (0x1A34, bytes.fromhex("0200 b31500 4e 000000 00 0080")),  # blue: bit position 16
        (0x1A31, bytes.fromhex("0300 00000000")),              # 3 entries, forever
        (0x1A24, b"\x02"),                                   # start
    ]
    assert dlp.display_mode() is DisplayMode.VIDEO_PATTERN and dlp.lut_configuration() == (3, 0)
    assert dlp.main_status().sequencer_running and dlp.main_status().external_source_locked
    dlp.set_display_mode(DisplayMode.VIDEO)  # and back: the sequencer stops, the LUT is gone
    assert emu.model.display_mode == 0 and emu.model.sequencer == "stopped" and not emu.model.lut
    assert dlp.configured.video_pattern_hz is None
    link.close()


def test_pattern_decode_gives_three_channels_as_sub_frames(dlp, emu, clock):
    emu.model.width, emu.model.height = 6, 4
    link = VideoLink(emu.model, timing=DisplayTiming("pattern-8bit", 60.0, 2_000_000), clock=clock,
                     sleep=clock.sleep, block=False, keep_images=8)
    dlp.set_video_pattern_mode(60.0)
    frame = _frame(7)
    v = link.present(frame, clock())
    clock.advance(v - clock())
    link.poll()
    rows = list(link.exposures)
    assert [(r.lut_index, r.channel, r.bit_position, r.bit_depth, r.leds) for r in rows] == [
        (0, 0, 8, 8, (True, False, False)), (1, 1, 0, 8, (False, True, False)), (2, 2, 16, 8, (False, False, True))]
    for k, r in enumerate(rows):
        assert np.array_equal(r.image, frame[..., k]), k  # each sub-frame is its colour channel
        assert r.scanout_ns == v and r.t_start_ns == v + 2_000_000 + k * 5_555_000
        assert r.t_end_ns - r.t_start_ns == 5_555_000
    # the host's timing model agrees with the controller to within the LUT's µs rounding
    for r, w in zip(rows, link.timing.windows):
        assert abs(r.t_start_ns - (v + w.start_ns)) <= 2000 and w.channel == r.channel and w.leds == r.leds
    dlp.blank()  # idle: no light from the next frame on
    link.present(frame, clock())
    clock.advance(2 * P60)
    link.poll()
    assert len(link.exposures) == 3
    link.close()


def test_reconnect_restores_video_pattern_mode(dlp, emu, clock):
    link = VideoLink(emu.model, clock=clock, sleep=clock.sleep)
    dlp.set_video_pattern_mode(60.0)
    emu.model.power_on()  # a power cycle forgets the mode and the LUT
    dlp.reconnect(restore=True, resume=True)
    assert emu.model.display_mode == 2 and emu.model.lut_config == (3, 0) and emu.model.sequencer == "running"
    link.close()


def test_video_pattern_mode_needs_a_locked_source(dlp, emu):
    with pytest.raises(DLPC900Error, match="locked video source"):
        dlp.set_video_pattern_mode(60.0)
    with pytest.raises(DLPC900DeviceError) as err:  # the controller refuses the bare switch too
        dlp._write(0x1A1B, [2])
    assert err.value.code == 5


@pytest.mark.parametrize("exposure_us, bit, code", [
    (4045, 0, 14),  # below the DMD's 8-bit minimum (4046 µs)
    (6000, 4, 10),  # an 8-bit field of the 24-bit word starts at bit 0, 8 or 16
])
def test_invalid_lut_entries_are_refused(dlp, emu, clock, exposure_us, bit, code):
    link = VideoLink(emu.model, clock=clock, sleep=clock.sleep)
    dlp.set_display_mode(DisplayMode.VIDEO_PATTERN)
    entry = (b"\x00\x00" + exposure_us.to_bytes(3, "little") + b"\x1e" + bytes(4)  # 8-bit, red
             + (bit << 11).to_bytes(2, "little"))
    with pytest.raises(DLPC900DeviceError) as err:  # sent raw: past the driver's own checks
        dlp.transact(0x1A34, entry)
    assert err.value.code == code
    link.close()


def test_a_frame_whose_patterns_overrun_the_period_is_refused(dlp, emu, clock):
    link = VideoLink(emu.model, clock=clock, sleep=clock.sleep)
    dlp.set_display_mode(DisplayMode.VIDEO_PATTERN)
    for k, bit in enumerate((8, 0, 16)):  # 3 × 5600 µs = 16.8 ms > 16.67 ms
        dlp.define_pattern(k, PatternTiming(5600, bit_depth=8, color=Color.WHITE, wait_for_trigger=k == 0),
                           image_index=0, bit_position=bit)
    with pytest.raises(DLPC900DeviceError, match="video frame period") as err:
        dlp.configure_lut(3, 0)
    assert err.value.code == 14
    with pytest.raises(ValueError, match="exposure_us"):  # the driver refuses a rate whose thirds are too short
        dlp.set_video_pattern_mode(120.0)
    link.close()


def test_frames_take_turns_through_the_lut_and_a_repeat_count_ends_the_run(dlp, emu, clock):
    """Two VSYNC-started groups alternate frame by frame; 6 patterns in all, then darkness."""
    link = VideoLink(emu.model, timing=DisplayTiming(controller_delay_ns=0), clock=clock, sleep=clock.sleep,
                     block=False)
    dlp.set_display_mode(DisplayMode.VIDEO_PATTERN)
    colors = (Color.RED, Color.GREEN, Color.BLUE)
    for k in range(6):
        dlp.define_pattern(k, PatternTiming(5000, dark_us=100, bit_depth=8, color=colors[k % 3] if k < 3 else Color.WHITE,
                                            wait_for_trigger=k % 3 == 0), image_index=0, bit_position=(8, 0, 16)[k % 3])
    dlp.configure_lut(6, 6)
    dlp.start()
    for _ in range(3):
        link.present(_frame(), clock())
        clock.advance(P60)
    link.poll()
    rows = list(link.exposures)
    assert [(r.frame, r.lut_index) for r in rows] == [(0, 0), (0, 1), (0, 2), (1, 3), (1, 4), (1, 5)]
    assert [r.leds for r in rows[3:]] == [(True, True, True)] * 3
    assert rows[1].t_start_ns - rows[0].t_start_ns == 5_100_000  # exposure, then dark
    assert link.frames_shown == 3  # the third frame was scanned out, but the run had ended: no light
    link.close()
