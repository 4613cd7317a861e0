"""Injected faults give typed errors at once (never a hang), and blank() still leaves the mock dark."""

from __future__ import annotations

import errno

import numpy as np
import pytest

from drivers.dlpc900 import (
    DLPC900, DLPC900DeviceError, DLPC900Disconnected, DLPC900ProtocolError, DLPC900SafetyError, DLPC900Timeout,
    DLPC900USBError,
)

pytestmark = pytest.mark.timeout(30)


def _lit(dlp, emu):
    """Put the mock in a bright state: a pattern sequence running with LEDs on."""
    emu.model.width, emu.model.height = 16, 4
    dlp.upload_patterns(np.ones((2, 4, 16), bool), exposure_us=500, start=True)
    assert not emu.model.dark


def test_lost_reply_is_a_timeout_then_blank_works(dlp, emu):
    _lit(dlp, emu)
    emu.drop_replies(1)
    with pytest.raises(DLPC900Timeout):
        dlp.main_status()
    assert dlp.blank().method == "idle" and emu.model.dark


def test_stalled_endpoint_is_a_usb_error_with_errno(dlp, emu):
    _lit(dlp, emu)
    emu.stall(1)
    with pytest.raises(DLPC900USBError) as err:
        dlp.set_led_current(1, 2, 3)
    assert err.value.errno == errno.EPIPE
    dlp.blank()
    assert emu.model.dark


def test_error_reply_carries_code_and_description(dlp, emu):
    emu.fail_commands(2, opcode=0x0B01, description="LED driver fault")
    with pytest.raises(DLPC900DeviceError) as err:
        dlp.set_led_current(1, 2, 3)
    assert (err.value.code, err.value.description, err.value.command) == (2, "LED driver fault", 0x0B01)
    assert dlp.error_code() == (2, "LED driver fault")  # reading the error does not clear it


@pytest.mark.parametrize("how", ["short", "sequence", "length", "flags"])
def test_malformed_replies_are_protocol_errors(dlp, emu, how):
    _lit(dlp, emu)
    emu.corrupt_replies(how, opcode=0x1A0C)
    with pytest.raises(DLPC900ProtocolError):
        dlp.main_status()
    # the link is back in step for the next command, and blanking still works
    assert dlp.main_status().sequencer_running
    dlp.blank()
    assert emu.model.dark


def test_malformed_write_ack_is_caught(dlp, emu):
    emu.corrupt_replies("length", opcode=0x0B01)
    with pytest.raises(DLPC900ProtocolError, match="data bytes"):
        dlp.set_led_current(1, 2, 3)


def test_sequencer_abort_is_reported(dlp, emu):
    _lit(dlp, emu)
    emu.model.abort_sequence()
    hs = dlp.hardware_status()
    assert hs.sequencer_abort and "sequencer_abort" in hs.faults
    assert not dlp.main_status().sequencer_running
    dlp.blank()
    assert emu.model.dark


def test_standby_counts_as_dark(dlp, emu):
    dlp.standby()
    report = dlp.blank()
    assert report.method == "standby" and emu.model.dark


def test_blank_falls_back_to_leds_off_when_idle_is_refused(dlp, emu):
    _lit(dlp, emu)
    emu.fail_commands(5, opcode=0x0201, count=1)  # idle rejected once
    report = dlp.blank()
    assert report.method == "leds off" and emu.model.led_enable == 0 and emu.model.dark


def test_blank_raises_when_darkness_cannot_be_confirmed(dlp, emu):
    _lit(dlp, emu)
    emu.fail_commands(5, opcode=0x0201, count=10)
    emu.fail_commands(5, opcode=0x1A07, count=10)
    with pytest.raises(DLPC900SafetyError):
        dlp.blank()


def test_unplug_gives_disconnected(dlp, emu):
    emu.unplug()
    with pytest.raises(DLPC900Disconnected) as err:
        dlp.main_status()
    assert err.value.errno == errno.ENODEV


def test_reconnect_backs_off_then_gives_up(dlp, emu, clock):
    emu.unplug()
    dlp.reconnect_attempts = 4
    with pytest.raises(DLPC900Disconnected, match="4 attempts"):
        dlp.reconnect()
    assert clock.sleeps == [0.05, 0.1, 0.2]  # exponential backoff between attempts


def test_reconnect_restores_configured_state_after_power_cycle(dlp, emu, clock):
    emu.model.width, emu.model.height = 32, 4
    pats = np.random.default_rng(5).random((5, 4, 32)) < 0.5
    dlp.set_led_current(11, 22, 33)
    dlp.set_led_enable(green=True, sequencer_controlled=True)
    dlp.set_trigger_out(2, invert=True, rising_delay_us=40)
    dlp.set_trigger_in1_delay(300)
    dlp.upload_patterns(pats, exposure_us=700, start=True)
    emu.unplug()
    emu.replug(power_cycle=True)  # comes back with power-on defaults, new address
    assert emu.model.led_current == (0x97, 0x78, 0x7D) and not emu.model.images
    dlp.reconnect()
    m = emu.model
    assert m.led_current == (11, 22, 33) and m.led_enable == 0b1010
    assert m.trigger_out[2] == (1, 40, 0) and m.trigger_in1_delay == 300
    assert m.display_mode == 3 and m.lut_config == (5, 0)
    for k in range(5):
        assert np.array_equal(m.dmd_pattern(k).astype(bool), pats[k])
    assert m.sequencer == "stopped"  # not restarted unless asked: light only on purpose
    dlp.start()
    assert m.sequencer == "running"


def test_reconnect_can_resume_the_sequence(dlp, emu):
    _lit(dlp, emu)
    emu.unplug()
    emu.replug()
    dlp.reconnect(resume=True)
    assert emu.model.sequencer == "running"


def test_auto_reconnect_retries_the_command(emu, clock):
    dlp = DLPC900.open(sleep=clock.sleep, auto_reconnect=True)
    dlp.set_led_current(9, 9, 9)
    emu.unplug()
    emu.replug()
    assert dlp.led_current() == (9, 9, 9)  # reconnected, restored, then answered
    dlp.close()


def _unplug_at(emu, opcode: int, nth: int):
    """Unplug and replug (power cycle) `emu` right after the `nth` report carrying `opcode`."""
    receive, seen = emu.receive, []

    def hooked(report):
        receive(report)
        if len(report) >= 6 and int.from_bytes(report[4:6], "little") == opcode:
            seen.append(opcode)
            if len(seen) == nth:
                emu.unplug()
                emu.replug(power_cycle=True)

    emu.receive = hooked


@pytest.mark.parametrize("opcode, nth", [(0x1A2B, 2), (0x1A34, 3), (0x1A2A, 1)], ids=["image-data", "lut", "load-init"])
def test_auto_reconnect_during_upload_sends_the_whole_sequence_again(emu, clock, opcode, nth):
    """A power-cycled controller forgot the half-sent upload: retrying only the interrupted
    command (image data without its load init) used to end in a device error."""
    emu.model.width, emu.model.height = 64, 8
    pats = np.random.default_rng(3).random((30, 8, 64)) < 0.5
    with DLPC900.open(sleep=clock.sleep, auto_reconnect=True) as dlp:
        _unplug_at(emu, opcode, nth)
        dlp.upload_patterns(pats, exposure_us=500, start=True)
        assert emu.generation == 1 and emu.model.sequencer == "running"
        for k in range(len(pats)):
            assert np.array_equal(emu.model.dmd_pattern(k).astype(bool), pats[k]), k
    assert emu.model.dark


def test_auto_reconnect_blank_goes_dark_without_restoring_first(emu, clock):
    emu.model.width, emu.model.height = 16, 4
    with DLPC900.open(sleep=clock.sleep, auto_reconnect=True) as dlp:
        _lit(dlp, emu)
        emu.unplug()
        emu.replug(power_cycle=False)  # the controller kept showing the sequence
        n = len(emu.model.command_log)
        dlp.blank()
        assert emu.model.dark
        assert not [c for c in emu.model.command_log[n:] if c.opcode in (0x1A2A, 0x1A2B, 0x1A34)]


def test_blank_after_unplug_and_replug_leaves_the_mock_dark(dlp, emu):
    _lit(dlp, emu)
    emu.unplug()
    emu.replug(power_cycle=False)  # controller kept running while the cable was out
    assert not emu.model.dark
    dlp.blank()
    assert emu.model.dark


def test_blank_while_unplugged_is_a_safety_error(dlp, emu):
    emu.unplug()
    dlp.reconnect_attempts = 2
    with pytest.raises(DLPC900SafetyError, match="unreachable"):
        dlp.blank()


def test_context_exit_blanks_after_a_fault(emu, clock):
    with pytest.raises(DLPC900Timeout):
        with DLPC900.open(sleep=clock.sleep) as dlp:
            _lit(dlp, emu)
            emu.drop_replies(1)
            dlp.hardware_status()
    assert emu.model.dark and dlp.closed


def test_image_upload_error_is_read_back(dlp, emu):
    """Image data goes without replies; a decode failure is still reported via 0x0100."""
    emu.model.width, emu.model.height = 16, 4  # patterns below are 8 pixels wide
    with pytest.raises(DLPC900DeviceError) as err:
        dlp.upload_patterns(np.ones((1, 4, 8), bool), exposure_us=200)
    assert err.value.code == 6 and "8x4" in err.value.description


def test_long_error_description_spans_reports(dlp, emu):
    text = "sequencer LUT entry 3 names an image that was never loaded: " * 2  # 122 chars
    emu.fail_commands(7, opcode=0x1A24, description=text)
    with pytest.raises(DLPC900DeviceError) as err:
        dlp.start()
    assert err.value.description == text[:127]
    replies = [r for r in emu.raw_in if r[0] == 0xC0 and r[2] == len(text[:127]) + 1]
    assert replies  # the 0x0101 reply announced all its bytes in the first report


def test_reply_claiming_more_data_than_sent_times_out(dlp, emu):
    emu.fail_commands(6, opcode=0x0B01, description="x" * 57)  # 58 bytes: exactly one report
    emu.corrupt_replies("length", opcode=0x0101)  # claims 61: the driver waits for a 2nd report
    with pytest.raises(DLPC900Timeout):
        dlp.set_led_current(1, 2, 3)


def test_permission_denied_points_to_the_udev_rule(emu, monkeypatch):
    import usb.core

    def denied(dev):
        raise usb.core.USBError("Access denied (insufficient permissions)", -3, errno.EACCES)

    monkeypatch.setattr(emu.backend, "open_device", denied)
    with pytest.raises(DLPC900USBError, match="99-dlpc900.rules") as err:
        DLPC900.open()
    assert err.value.errno == errno.EACCES


def test_status_in_standby_reads_only_what_is_allowed(dlp, emu):
    dlp.standby()
    st = dlp.status()
    assert st["standby"] is True and st["firmware"] is None and st["hardware_faults"] == []
    assert all(c.error == 0 for c in emu.model.command_log[-4:])


def test_reconnect_retries_a_device_that_is_back_but_not_ready(dlp, emu, clock, monkeypatch):
    """A timeout while configuring the replugged device is one more failed attempt, not the end."""
    import usb.core

    set_configuration, calls = emu.backend.set_configuration, []

    def slow_first(handle, value):
        calls.append(value)
        if len(calls) == 1:
            raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
        return set_configuration(handle, value)

    monkeypatch.setattr(emu.backend, "set_configuration", slow_first)
    emu.unplug()
    emu.replug()
    dlp.reconnect()
    assert len(calls) == 2 and clock.sleeps == [0.05]
    assert dlp.main_status().raw == 0
