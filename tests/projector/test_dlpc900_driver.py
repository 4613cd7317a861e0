"""Every driver method against the emulated controller: act on the driver, assert on the model."""

from __future__ import annotations

import numpy as np
import pytest
import usb.core

from drivers.dlpc900 import (
    DLPC900, Color, DisplayMode, DLPC900DeviceError, DLPC900Error, DLPC900NotFound, PatternTiming, list_devices,
)
from firmware_mocks.dlpc900_usb import usb_emulation


def test_identity_and_firmware(dlp, emu):
    emu.model.firmware = ((5, 4, 1), (5, 2, 0), (2, 0, 0), (3, 1, 7))
    fw = dlp.firmware_version()
    assert (str(fw.application), str(fw.api), str(fw.sequencer_config)) == ("5.4.1", "5.2.0", "3.1.7")
    emu.model.dmd_type, emu.model.tag = 2, "LCR9000 rig B"
    hw = dlp.hardware_config()
    assert (hw.dmd, hw.dmd_name, hw.tag) == (2, "DLP9000", "LCR9000 rig B")
    assert dlp.serial == "EMU0001"


def test_status_bits_decode_lsb_first(dlp, emu):
    emu.model.hw_status = 0b1100_0001  # init OK, sequencer abort, sequencer error
    hs = dlp.hardware_status()
    assert hs.init_ok and hs.sequencer_abort and hs.sequencer_error
    assert not hs.incompatible_controller_dmd and not hs.secondary_controller_present
    assert hs.faults == ["sequencer_abort", "sequencer_error"]
    emu.model.parked = True
    main = dlp.main_status()
    assert main.dmd_parked and not main.sequencer_running and main.raw == 1
    assert dlp.system_status().memory_test_passed


def test_display_mode_waits_for_settle_and_reads_back(dlp, emu, clock):
    dlp.set_display_mode(DisplayMode.PATTERN_ON_THE_FLY)
    assert emu.model.display_mode == 3 and dlp.display_mode() is DisplayMode.PATTERN_ON_THE_FLY
    assert clock.sleeps == [0.3]


def test_display_mode_without_settle_is_caught_by_read_back(dlp, emu):
    dlp.settle_s = 0  # the emulated switch to video pattern mode still takes 300 ms of (fake) time
    emu.model.video_period_ns = 16_666_667  # a locked 60 Hz source: video pattern mode needs one
    with pytest.raises(DLPC900Error, match="reads back 0"):
        dlp.set_display_mode(DisplayMode.VIDEO_PATTERN)


def test_pattern_sequence_start_pause_stop(dlp, emu, clock, gray):
    pats = gray(64, 8)[:3]
    emu.model.width, emu.model.height = 64, 8
    dlp.upload_patterns(pats, PatternTiming(exposure_us=1000, dark_us=500, color=Color.BLUE), repeat=2)
    assert emu.model.sequencer == "stopped"
    assert dlp.lut_configuration() == (3, 2)
    dlp.start()
    assert emu.model.sequencer == "running" and dlp.main_status().sequencer_running
    assert dlp.sequencer_state() == "running"
    clock.advance(10_000_000)
    dlp.pause()
    assert emu.model.sequencer == "paused"
    dlp.stop()
    assert emu.model.sequencer == "stopped"
    shown = emu.model.displayed()
    assert [p.lut_index for p in shown] == [0, 1, 2, 0, 1, 2]  # repeat = 2 passes
    assert shown[1].t_ns - shown[0].t_ns == 1_500_000  # exposure + dark
    assert all(emu.model.lut[k].color == 4 for k in range(3))


def test_images_are_sent_in_reverse_order_without_replies(dlp, emu):
    emu.model.width, emu.model.height = 40, 4
    rng = np.random.default_rng(1)
    pats = rng.random((50, 4, 40)) < 0.5  # 3 images: 24 + 24 + 2 patterns
    dlp.upload_patterns(pats, exposure_us=105)
    inits = [c for c in emu.model.command_log if c.opcode == 0x1A2A]
    assert [int.from_bytes(c.data[:2], "little") for c in inits] == [2, 1, 0]
    data_cmds = [c for c in emu.model.command_log if c.opcode == 0x1A2B]
    assert data_cmds and not any(c.reply_wanted for c in data_cmds)
    for k in range(50):
        assert np.array_equal(emu.model.dmd_pattern(k).astype(bool), pats[k]), k
    e = emu.model.lut[49]
    assert (e.image_index, e.bit_position) == (2, 1)


@pytest.mark.parametrize("width,height", [(1920, 1080), (912, 1140)])
def test_gray_codes_full_size_round_trip(width, height, clock, gray):
    with usb_emulation(clock=clock, width=width, height=height) as emu:
        with DLPC900.open(sleep=clock.sleep) as dlp:
            for vertical in (True, False):  # column codes, then row codes
                pats = gray(width, height, vertical)
                (image,) = dlp.upload_patterns(pats, exposure_us=5000, start=True)
                assert image.compression == 2 and image.payload_size < 3 * width * height // 50
                for k in range(len(pats)):
                    assert np.array_equal(emu.model.dmd_pattern(k).astype(bool), pats[k]), k
                assert emu.model.sequencer == "running"
        assert emu.model.dark  # leaving the block blanked the projector


def test_pattern_groups_get_their_own_images(clock, gray):
    """Column and row codes packed apart: two small images instead of one incompressible one."""
    with usb_emulation(clock=clock) as emu:
        with DLPC900.open(sleep=clock.sleep) as dlp:
            cols, rows = gray(1920, 1080), gray(1920, 1080, vertical=False)
            images = dlp.upload_patterns([cols, rows], exposure_us=5000)
            assert len(images) == 2 and all(i.compression == 2 and i.payload_size < 20_000 for i in images)
            both = np.concatenate([cols, rows])
            for k in range(len(both)):
                assert np.array_equal(emu.model.dmd_pattern(k).astype(bool), both[k]), k
            assert (emu.model.lut[11].image_index, emu.model.lut[11].bit_position) == (1, 0)


def test_random_patterns_full_hd_round_trip(clock):
    rng = np.random.default_rng(7)
    pats = rng.random((24, 1080, 1920)) < 0.5
    with usb_emulation(clock=clock) as emu:
        with DLPC900.open(sleep=clock.sleep) as dlp:
            (image,) = dlp.upload_patterns(pats, exposure_us=105)
            assert image.compression == 0  # incompressible: sent raw, not inflated by RLE
            got = emu.model.images[0]
            planes = (got[None] >> np.arange(24)[:, None, None]) & 1
            assert np.array_equal(planes.astype(bool), pats)


def test_eight_bit_patterns(dlp, emu):
    emu.model.width, emu.model.height = 16, 2
    pats = np.random.default_rng(3).integers(0, 256, size=(4, 2, 16), dtype=np.uint8)
    dlp.upload_patterns(pats, PatternTiming(exposure_us=4046, bit_depth=8))
    assert len(emu.model.images) == 2
    for k in range(4):
        assert np.array_equal(emu.model.dmd_pattern(k), pats[k])
    assert [emu.model.lut[k].bit_position for k in range(4)] == [0, 8, 16, 0]


@pytest.mark.parametrize("depth,too_short", [(1, 104), (2, 303), (4, 822), (8, 4045)])
def test_exposure_below_minimum_is_refused_before_sending(dlp, emu, depth, too_short):
    before = len(emu.model.command_log)
    with pytest.raises(ValueError, match="exposure_us"):
        dlp.upload_patterns(np.zeros((1, 4, 4), np.uint8), PatternTiming(exposure_us=too_short, bit_depth=depth))
    assert len(emu.model.command_log) == before


def test_device_rejects_short_exposure_from_other_hosts(dlp, emu):
    """The mock enforces the same minimum itself, for host code that does not check."""
    dlp.set_display_mode(3)
    with pytest.raises(DLPC900DeviceError) as err:
        dlp.transact(0x1A34, bytes.fromhex("000064000000000000000000"))  # 100 µs 1-bit
    assert err.value.code == 14 and "105" in err.value.description


def test_triggers(dlp, emu):
    dlp.set_trigger_out(1, invert=True, rising_delay_us=-20, falling_delay_us=20000)
    dlp.set_trigger_out(2, rising_delay_us=150)
    assert emu.model.trigger_out == {1: (1, -20, 20000), 2: (0, 150, 0)}
    t = dlp.trigger_out(1)
    assert (t.invert, t.rising_delay_us, t.falling_delay_us) == (True, -20, 20000)
    dlp.set_trigger_in1_delay(250)
    dlp.set_trigger_in2_polarity(True)
    assert (emu.model.trigger_in1_delay, emu.model.trigger_in2_polarity) == (250, 1)
    assert dlp.trigger_in1_delay() == 250 and dlp.trigger_in2_polarity() == 1
    with pytest.raises(ValueError):
        dlp.set_trigger_in1_delay(103)
    with pytest.raises(ValueError):
        dlp.set_trigger_out(1, rising_delay_us=20001)


def test_leds_and_curtain_and_source(dlp, emu):
    assert dlp.led_current() == (0x97, 0x78, 0x7D)  # reset values
    dlp.set_led_current(10, 20, 30)
    dlp.set_led_enable(red=True, blue=True, sequencer_controlled=False)
    assert emu.model.led_current == (10, 20, 30) and emu.model.led_enable == 0b0101
    led = dlp.led_enable()
    assert led.red and not led.green and led.blue and not led.sequencer_controlled
    dlp.set_curtain_color(1023, 0, 512)
    dlp.set_input_source(3)
    assert emu.model.curtain == (1023, 0, 512) and dlp.input_source() == 3


def test_idle_park_standby_wake(dlp, emu):
    dlp.set_idle(True)
    assert emu.model.idle and dlp.idle() and emu.model.dark
    dlp.set_idle(False)
    assert not emu.model.idle
    dlp.park()
    assert emu.model.parked and dlp.main_status().dmd_parked and emu.model.dark
    dlp.unpark()
    assert not emu.model.parked and not dlp.main_status().dmd_parked
    dlp.standby()
    assert emu.model.standby and dlp.in_standby()
    with pytest.raises(DLPC900DeviceError) as err:
        dlp.set_led_current(1, 2, 3)  # only wake is accepted in standby
    assert err.value.code == 5 and "standby" in err.value.description
    dlp.wake()
    assert not emu.model.standby
    dlp.set_led_current(1, 2, 3)
    assert emu.model.led_current == (1, 2, 3)


def test_starting_without_lut_is_rejected_with_description(dlp, emu):
    dlp.set_display_mode(3)
    with pytest.raises(DLPC900DeviceError) as err:
        dlp.start()
    assert err.value.code == 16 and err.value.command == 0x1A24
    assert "LUT" in err.value.description and "error 16" in str(err.value)
    # the error read-back used 0x0100 then 0x0101, after the failing command
    ops = [c.opcode for c in emu.model.command_log[-3:]]
    assert ops == [0x1A24, 0x0100, 0x0101]


def test_blank_stops_idles_and_confirms(dlp, emu):
    emu.model.width, emu.model.height = 8, 2
    dlp.upload_patterns(np.ones((2, 2, 8), bool), exposure_us=200, start=True)
    assert not emu.model.dark
    report = dlp.blank()
    assert report.method == "idle" and emu.model.dark and emu.model.sequencer == "stopped"
    reads = [c.opcode for c in emu.model.command_log if c.read]
    assert 0x0201 in reads and 0x1A0C in reads  # confirmed by read-back


def test_context_manager_blanks_on_exception(emu, clock):
    with pytest.raises(RuntimeError, match="boom"):
        with DLPC900.open(sleep=clock.sleep) as dlp:
            dlp.set_idle(False)
            assert not emu.model.dark
            raise RuntimeError("boom")
    assert emu.model.dark and dlp.closed


def test_find_by_serial_and_refuse_ambiguity(clock):
    with usb_emulation("A100", "B200", clock=clock) as first:
        second = first.backend.devices[1]
        assert [d.serial for d in list_devices()] == ["A100", "B200"]
        with pytest.raises(DLPC900NotFound, match="pass serial"):
            DLPC900.open()
        with DLPC900.open("B200", sleep=clock.sleep) as dlp:
            dlp.set_led_current(1, 1, 1)
        assert second.model.led_current == (1, 1, 1) and first.model.led_current != (1, 1, 1)
        with pytest.raises(DLPC900NotFound, match="Z9"):
            DLPC900.open("Z9")


def test_unmodified_host_code_finds_the_emulator(emu):
    """Code written against plain pyusb (no backend argument) talks to the emulated device."""
    dev = usb.core.find(idVendor=0x0451, idProduct=0xC900)
    assert dev is not None and dev.product == "DLPC900" and dev.manufacturer == "Texas Instruments"
    dev.set_configuration()
    cfg = dev.get_active_configuration()
    intf = cfg[(0, 0)]
    assert intf.bInterfaceClass == 3 and [e.bEndpointAddress for e in intf] == [0x81, 0x01]
    dev.write(0x01, bytes([0xC0, 0x2A, 0x02, 0x00, 0x05, 0x02]).ljust(64, b"\0"), 100)
    reply = bytes(dev.read(0x81, 64, 100))
    assert reply[:4] == bytes([0xC0, 0x2A, 16, 0])
    assert reply[4:8] == bytes([0, 0, 3, 5])  # application 5.3.0: patch u16, minor, major
    with pytest.raises(usb.core.USBTimeoutError):
        dev.read(0x81, 64, 100)  # nothing more to read: a timeout, never a hang


def test_emulation_restores_pyusb(clock):
    import usb.backend.libusb1 as libusb1

    before = libusb1.get_backend
    with usb_emulation(clock=clock):
        assert libusb1.get_backend is not before
    assert libusb1.get_backend is before


def test_not_found_outside_emulation_is_typed():
    with pytest.raises(DLPC900NotFound):
        DLPC900.open(backend=_EmptyBackend())


class _EmptyBackend(usb.backend.IBackend if hasattr(usb, "backend") else object):
    def enumerate_devices(self):
        return iter(())


def test_the_emulators_logs_stay_bounded_over_a_long_session(dlp, emu):
    """`dpmhw run --mock` polls the emulated projector for as long as the session runs."""
    logs = (emu.raw_out, emu.raw_in, emu.model.command_log)
    for log in logs:
        log.limit = 40
    for _ in range(100):
        dlp.status()
    assert all(20 <= len(log) <= 40 for log in logs)
    assert emu.model.command_log[-1].opcode == 0x1A0B  # the newest entries are the ones kept
    assert dlp.status()["firmware"] == "5.3.0"
