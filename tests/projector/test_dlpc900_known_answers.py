"""Raw bytes, written by hand from protocols.md / DLPU018, checked against both sides."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from drivers.dlpc900 import Color, PatternTiming
from drivers.dlpc900_images import encode_image, erle_encode, image_header, pack_patterns
from drivers.dlpc900_wire import DLPC900ProtocolError, parse_reply_header, request_reports
from firmware_mocks.dlpc900_model import ImageDecodeError, decode_pattern_image


def test_read_request_report_bytes():
    (report,) = request_reports(5, 0x1A0C, read=True)
    assert report == bytes([0xC0, 0x05, 0x02, 0x00, 0x0C, 0x1A]) + bytes(58)


def test_write_request_with_and_without_reply():
    (with_reply,) = request_reports(7, 0x1A1B, b"\x03")
    assert with_reply[:7] == bytes([0x40, 0x07, 0x03, 0x00, 0x1B, 0x1A, 0x03])
    (no_reply,) = request_reports(7, 0x1A1B, b"\x03", reply=False)
    assert no_reply[0] == 0x00


def test_long_message_continues_in_raw_reports():
    data = struct.pack("<H", 504) + bytes(range(256)) + bytes(range(248))
    reports = request_reports(9, 0x1A2B, data, reply=False)
    assert len(reports) == 8 and all(len(r) == 64 for r in reports)
    # length = 2 (command) + 506 data bytes = 508 = 0x01FC; count 504 = 0x01F8
    assert reports[0][:8] == bytes([0x00, 0x09, 0xFC, 0x01, 0x2B, 0x1A, 0xF8, 0x01])
    assert b"".join(reports)[6:6 + len(data)] == data
    with pytest.raises(ValueError):
        request_reports(9, 0x1A2B, bytes(507))  # 4 + 2 + 507 > 512-byte command buffer


def test_reply_header_parsing():
    head = parse_reply_header(bytes([0xE0, 0x11, 0x02, 0x00, 0xAA, 0xBB]))
    assert (head.flags, head.seq, head.length, head.error) == (0xE0, 0x11, 2, True)
    with pytest.raises(DLPC900ProtocolError):
        parse_reply_header(b"\xc0\x11")


def test_lut_definition_matches_ti_example(dlp, emu):
    # DLPU018 pre-stored pattern example, steps 2-4: 200 µs red 1-bit; 400 µs green, clear, bit 1.
    dlp.set_display_mode(1)
    dlp.define_pattern(0, PatternTiming(200, color=Color.RED), image_index=0, bit_position=0)
    dlp.define_pattern(1, PatternTiming(400, color=Color.GREEN, clear_after=True), image_index=0, bit_position=1)
    dlp.configure_lut(2, 0)
    sent = [c for c in emu.model.command_log if c.opcode in (0x1A34, 0x1A31)]
    assert sent[0].data == bytes.fromhex("0000C800001000000000 0000".replace(" ", ""))
    assert sent[1].data == bytes.fromhex("01009001002100000000 0008".replace(" ", ""))
    assert sent[2].data == bytes.fromhex("020000000000")
    e1 = emu.model.lut[1]
    assert (e1.exposure_us, e1.color, e1.clear_after, e1.bit_position, e1.bit_depth) == (400, 2, True, 1, 1)


def test_image_header_layout():
    h = image_header(1920, 1080, 0x01020304, compression=2, background_bgr=(1, 2, 3))
    assert h[:4] == b"Spld" and h[4:8] == bytes([0x80, 0x07, 0x38, 0x04])
    assert h[8:12] == bytes([4, 3, 2, 1]) and h[12:20] == b"\xff" * 8
    assert h[20:24] == bytes([1, 2, 3, 0]) and h[24:27] == bytes([0, 2, 1]) and h[27:] == bytes(21)


A, B, C = 0x060504, 0x0C0B0A, 0xBC9A78


def _px(v: int) -> bytes:
    return v.to_bytes(3, "big")  # most significant byte first


def test_erle_repeat_single_copy_and_end_codes():
    img = np.array([[A, A, A, B], [A, A, A, B]], dtype=np.uint32)
    expected = b"\x03" + _px(A) + b"\x01" + _px(B) + b"\x00\x00" + b"\x00\x01\x04" + b"\x00\x00" + b"\x00\x01\x00"
    assert erle_encode(img) == expected


def test_erle_uncompressed_block_and_two_byte_count():
    img = np.array([[A, B, C]], dtype=np.uint32)
    assert erle_encode(img) == b"\x00\x03" + _px(A) + _px(B) + _px(C) + b"\x00\x00\x00\x01\x00"
    wide = np.full((1, 130), C, dtype=np.uint32)
    assert erle_encode(wide) == b"\x82\x01" + _px(C) + b"\x00\x00\x00\x01\x00"  # 130 = 0x02 | 1 << 7


def test_mock_decodes_hand_written_erle():
    # Written from the control-byte table, not produced by the driver.
    payload = (b"\x03" + _px(A) + b"\x00\x02" + _px(B) + _px(C) + b"\x00\x00"  # line 0: A A A B C
               + b"\x00\x01\x02" + b"\x03" + _px(C) + b"\x00\x00"              # line 1: copy 2, C C C
               + b"\x00\x01\x00")
    img = decode_pattern_image(image_header(5, 2, len(payload)) + payload)
    assert img.tolist() == [[A, A, A, B, C], [A, A, C, C, C]]


@pytest.mark.parametrize("bad", [
    b"\x03" + _px(A) + b"\x00\x00\x00\x01\x00",           # line 0 ends after 3 of 5 pixels
    b"\x06" + _px(A) + b"\x00\x00\x00\x01\x00",           # repeat overruns the line
    b"\x00\x01\x05\x00\x00\x00\x01\x00",                  # copy on the first line
    b"\x05" + _px(A) + b"\x00\x00",                       # no end-of-image code
])
def test_mock_rejects_malformed_erle(bad):
    with pytest.raises(ImageDecodeError):
        decode_pattern_image(image_header(5, 1, len(bad)) + bad)


def test_bit_plane_order():
    pats = np.zeros((24, 1, 1), dtype=bool)
    pats[0] = pats[9] = pats[23] = True
    assert pack_patterns(pats)[0, 0] == (1 | 1 << 9 | 1 << 23)
    eight = np.array([[[0x12]], [[0x34]], [[0x56]]], dtype=np.uint8)
    assert pack_patterns(eight, bit_depth=8)[0, 0] == 0x563412
    with pytest.raises(ValueError):
        pack_patterns(np.zeros((25, 2, 2), bool))
    with pytest.raises(ValueError):
        pack_patterns(np.full((1, 2, 2), 4, np.uint8), bit_depth=2)


def test_encoded_image_is_header_plus_payload():
    img = np.arange(12, dtype=np.uint32).reshape(3, 4)
    enc = encode_image(img, compression=2)
    assert enc.data[:48] == image_header(4, 3, enc.payload_size)
    assert np.array_equal(decode_pattern_image(enc.data), img)
    raw = encode_image(img, compression=0)
    assert raw.payload_size == 36 and np.array_equal(decode_pattern_image(raw.data), img)
    assert encode_image(img).compression == 0  # "auto": RLE would be larger than the raw pixels
    assert encode_image(np.zeros((3, 4), np.uint32)).compression == 2
