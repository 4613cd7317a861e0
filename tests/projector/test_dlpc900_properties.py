"""Hypothesis: the codec and the framing are inverses across the two independent sides."""

from __future__ import annotations

from array import array

import numpy as np
import usb.core
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.dlpc900_images import encode_image, image_header, pack_patterns
from drivers.dlpc900_wire import request_reports
from firmware_mocks.dlpc900_model import ERROR_NAMES, ImageDecodeError, decode_pattern_image
from firmware_mocks.dlpc900_usb import DLPC900Backend, EmulatedDLPC900


@st.composite
def images(draw):
    """Small 24-bit images with runs, isolated pixels and repeated lines (every ERLE token)."""
    h = draw(st.integers(1, 12))
    w = draw(st.integers(1, 300))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    palette = rng.integers(0, 1 << 24, size=draw(st.integers(1, 6)), dtype=np.uint32)
    img = palette[rng.integers(0, len(palette), size=(h, w))]
    runs = draw(st.integers(0, 3))
    for _ in range(runs):
        y, x0 = rng.integers(0, h), rng.integers(0, w)
        img[y, x0:x0 + rng.integers(1, 200)] = palette[0]
    for y in range(1, h):
        if rng.random() < 0.3:
            img[y] = img[y - 1]
    return img


@settings(max_examples=150, deadline=None)
@given(img=images())
def test_erle_encode_then_mock_decode_is_identity(img):
    assert np.array_equal(decode_pattern_image(encode_image(img).data), img)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 24), h=st.integers(1, 9), w=st.integers(1, 70), seed=st.integers(0, 2**32 - 1))
def test_random_bit_planes_survive_packing_and_codec(n, h, w, seed):
    pats = np.random.default_rng(seed).random((n, h, w)) < 0.5
    img = decode_pattern_image(encode_image(pack_patterns(pats)).data)
    planes = (img[None] >> np.arange(n)[:, None, None]) & 1
    assert np.array_equal(planes.astype(bool), pats)


@settings(max_examples=200, deadline=None)
@given(payload=st.binary(max_size=300), w=st.integers(1, 40), h=st.integers(1, 5), compression=st.sampled_from([0, 1, 2]))
def test_mock_decoder_is_total_on_garbage(payload, w, h, compression):
    """Arbitrary payloads decode to an image or raise ImageDecodeError, nothing else."""
    try:
        img = decode_pattern_image(image_header(w, h, len(payload), compression) + payload)
    except ImageDecodeError:
        return
    assert img.shape == (h, w)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seq=st.integers(0, 255), cmd=st.sampled_from([0x1A34, 0x1A2B, 0x0B01, 0x1100, 0x7777]),
       data=st.binary(max_size=506), reply=st.booleans())
def test_framing_round_trip_through_the_mock(seq, cmd, data, reply):
    """Whatever the driver frames, the device reassembles the same opcode, sequence and data."""
    dev = EmulatedDLPC900("P")
    for r in request_reports(seq, cmd, data, reply=reply):
        dev.receive(r)
    (logged,) = dev.model.command_log
    assert (logged.seq, logged.opcode, logged.data, logged.reply_wanted) == (seq, cmd, data, reply)
    if reply:
        first = dev.send(64)
        assert first[1] == seq and first[0] & 0x40
        assert bool(first[0] & 0x20) == (logged.error != 0)


@settings(max_examples=200, deadline=None)
@given(cmd=st.integers(0, 0xFFFF), data=st.binary(max_size=40), read=st.booleans())
def test_garbage_commands_get_error_replies_not_crashes(cmd, data, read):
    dev = EmulatedDLPC900("G")
    dev.receive(request_reports(3, cmd, data, read=read)[0])
    head = dev.send(64)
    assert head[1] == 3
    code = dev.model.command_log[-1].error
    assert bool(head[0] & 0x20) == (code != 0)
    assert code in ERROR_NAMES
    # The device is still in step: the error code read answers with that code.
    dev.receive(request_reports(4, 0x0100, read=True)[0])
    answer = dev.send(64)
    assert answer[:5] == bytes([0xC0, 4, 1, 0, code])


@settings(max_examples=200, deadline=None)
@given(report=st.binary(min_size=0, max_size=64))
def test_raw_garbage_reports_never_crash_the_backend(report):
    dev = EmulatedDLPC900("R")
    backend = DLPC900Backend([dev])
    handle = backend.open_device(dev)
    backend.intr_write(handle, 0x01, 0, array("B", report.ljust(64, b"\x00")), 100)
    buf = array("B", bytes(64))
    try:
        n = backend.intr_read(handle, 0x81, 0, buf, 100)
    except usb.core.USBTimeoutError:
        return  # no reply asked for (or the message is still incomplete)
    assert n == 64
    if buf[0] & 0x20:
        assert dev.model.error_code != 0


@settings(max_examples=60, deadline=None)
@given(text=st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=127),
       code=st.sampled_from([2, 3, 5, 6, 7, 14, 16, 255]))
def test_error_replies_of_any_length_reach_the_driver_intact(text, code):
    """Reply framing, device -> host: 0x0101 answers of 1..128 bytes span one to three reports."""
    from drivers.dlpc900 import DLPC900, DLPC900DeviceError
    from firmware_mocks.dlpc900_usb import usb_emulation

    with usb_emulation() as emu:
        dlp = DLPC900.open(settle_s=0)
        emu.fail_commands(code, opcode=0x0B01, description=text)
        try:
            dlp.set_led_current(1, 2, 3)
        except DLPC900DeviceError as exc:
            assert exc.code == code and exc.command == 0x0B01
            assert exc.description == (text or exc.description)
        else:
            raise AssertionError("the injected error was not raised")
        assert dlp.led_current() == (0x97, 0x78, 0x7D)  # and the link is still in step
        dlp.close()
