"""Known answers: byte streams in each hardware-proven host's conventions, fed to the emulator.

Everything here is written by hand from the DLPC900 programmer's guide (DLPU018): the USB
framing (§1.2), the LUT definition (0x1A34), the load commands (0x1A2A-0x1A2D), the 48-byte
image header and the compression tables. No driver code builds these bytes, so a driver and a
mock that share a mistake cannot agree on it here. Each test checks what the DMD would show,
bit plane by bit plane.

The test image is 8 x 3 pixels holding three 1-bit patterns (pattern k on bit k):
P0 lights columns 0-3, P1 lights row 1, P2 lights column 7. Pixel values (each sent
most significant byte first, so bit positions 0-7 travel in a pixel's third byte):

    row 0:  1 1 1 1 0 0 0 4
    row 1:  3 3 3 3 2 2 2 6
    row 2:  1 1 1 1 0 0 0 4
"""

from __future__ import annotations

import numpy as np
import pytest
import usb.core

from firmware_mocks.dlpc900_usb import usb_emulation

W, H = 8, 3
P = np.zeros((3, H, W), dtype=np.uint8)
P[0][:, :4] = 1
P[1][1, :] = 1
P[2][:, 7] = 1


def px(v: int) -> bytes:
    return v.to_bytes(3, "big")  # most significant byte first


def header(width: int, height: int, count: int, compression: int, signature: bytes = b"\x53\x70\x6C\x64") -> bytes:
    """DLPU018 image header: signature, u16 width, u16 height, u32 byte count, 8 x FF,
    background BB GG RR 00, 00, compression, 01, 21 x 00."""
    out = (signature + width.to_bytes(2, "little") + height.to_bytes(2, "little") + count.to_bytes(4, "little")
           + b"\xFF" * 8 + b"\x00\x00\x00\x00" + b"\x00" + bytes([compression]) + b"\x01" + bytes(21))
    assert len(out) == 48
    return out


# Enhanced RLE (compression 2): repeat n pixel | 00 00 end of line | 00 01 n copy | 00 n literals | 00 01 00 end.
ERLE = (b"\x04" + px(1) + b"\x03" + px(0) + b"\x01" + px(4) + b"\x00\x00"            # row 0
        + b"\x04" + px(3) + b"\x03" + px(2) + b"\x01" + px(6) + b"\x00\x00"          # row 1
        + b"\x00\x02" + px(1) + px(1) + b"\x02" + px(1) + b"\x03" + px(0) + b"\x01" + px(4) + b"\x00\x00"  # row 2
        + b"\x00\x01\x00")
assert len(ERLE) == 53

# Plain RLE (compression 1): repeat n pixel | 00 c literals | 00 00 end of line, then zero padding
# so the next line starts on a 4-byte boundary | 00 01 end of image.
RLE = (b"\x04" + px(1) + b"\x03" + px(0) + b"\x01" + px(4) + b"\x00\x00" + b"\x00\x00"   # 14 bytes + 2 pad
       + b"\x04" + px(3) + b"\x03" + px(2) + b"\x01" + px(6) + b"\x00\x00" + b"\x00\x00"  # 30 + 2 pad
       + b"\x00\x02" + px(1) + px(1) + b"\x02" + px(1) + b"\x03" + px(0) + b"\x01" + px(4)
       + b"\x00\x01")  # the last line ends with end-of-image
assert len(RLE) == 54

RAW = b"".join(px(v) for v in [1, 1, 1, 1, 0, 0, 0, 4, 3, 3, 3, 3, 2, 2, 2, 6, 1, 1, 1, 1, 0, 0, 0, 4])


class RawHost:
    """A host program reduced to the wire: DLPU018 §1.2 framing over plain pyusb.

    `reply_to_writes` asks for an acknowledgement of every write (one public host's habit);
    without it writes go unacknowledged and errors are read from 0x0100 (TI's habit).
    """

    def __init__(self, reply_to_writes: bool, chunk: int = 504):
        self.dev = usb.core.find(idVendor=0x0451, idProduct=0xC900)
        self.dev.set_configuration()
        self.reply_to_writes = reply_to_writes
        self.chunk = chunk
        self.seq = 0

    def command(self, opcode: int, data: bytes = b"", *, read: bool = False) -> tuple[bool, bytes]:
        """(error flag, reply data); (False, b'') for a write sent without a reply."""
        self.seq = (self.seq + 1) & 0xFF
        reply = read or self.reply_to_writes
        flags = (0x80 if read else 0) | (0x40 if reply else 0)
        msg = bytes([flags, self.seq]) + (2 + len(data)).to_bytes(2, "little") + opcode.to_bytes(2, "little") + data
        for i in range(0, len(msg), 64):
            self.dev.write(0x01, msg[i:i + 64].ljust(64, b"\x00"), 100)
        if not reply:
            return False, b""
        first = bytes(self.dev.read(0x81, 64, 100))
        assert first[1] == self.seq
        n = first[2] | first[3] << 8
        body = first[4:]
        while len(body) < n:
            body += bytes(self.dev.read(0x81, 64, 100))
        return bool(first[0] & 0x20), body[:n]

    def error(self) -> int:
        return self.command(0x0100, read=True)[1][0]

    def write_ok(self, opcode: int, data: bytes = b"") -> None:
        failed, _ = self.command(opcode, data)
        assert not failed and self.error() == 0, f"0x{opcode:04X} rejected with error {self.error()}"

    def setup_lut(self, bits: tuple[int, ...] = (0, 1, 2)) -> None:
        """Pattern-on-the-fly mode (no settling time: DLPU018 names one only for video pattern
        mode) and 1-bit white patterns, pattern k = image 0 bit `bits[k]`."""
        self.write_ok(0x1A1B, b"\x03")
        for k, bit in enumerate(bits):
            # u16 index, u24 exposure (1000 µs), options (white = 7 << 4, 1-bit), u24 dark,
            # trigger-out-2 byte, u16 image index | bit position << 11
            self.write_ok(0x1A34, k.to_bytes(2, "little") + (1000).to_bytes(3, "little") + b"\x70"
                          + bytes(3) + b"\x00" + (0 | bit << 11).to_bytes(2, "little"))
        self.write_ok(0x1A31, len(bits).to_bytes(2, "little") + (0).to_bytes(4, "little"))

    def load(self, blob: bytes, *, secondary: bool = False, announce: int | None = None) -> int:
        """0x1A2A (0x1A2C) with the whole length, 0x1A2B (0x1A2D) chunks; returns the error code."""
        init, data = (0x1A2C, 0x1A2D) if secondary else (0x1A2A, 0x1A2B)
        size = len(blob) if announce is None else announce
        failed, _ = self.command(init, (0).to_bytes(2, "little") + size.to_bytes(4, "little"))
        if failed:
            return self.error()
        for i in range(0, len(blob), self.chunk):
            part = blob[i:i + self.chunk]
            self.command(data, len(part).to_bytes(2, "little") + part)
        return self.error()

    def start(self) -> int:
        self.command(0x1A24, b"\x02")
        return self.error()


@pytest.fixture(params=[True, False], ids=["ack-every-write", "ti-no-replies"])
def host(request, emu):
    emu.model.width, emu.model.height = W, H
    h = RawHost(reply_to_writes=request.param, chunk=32)  # several chunks per image
    h.setup_lut()
    return h


def _shows_the_patterns(model) -> None:
    for k in range(3):
        assert np.array_equal(model.dmd_pattern(k), P[k]), f"pattern {k}"


PAD = b"\x00\x00\x00"  # ERLE: 53 bytes -> next 4-byte boundary at 56


@pytest.mark.parametrize("count,tail", [
    (len(ERLE), b""),                     # header counts the data only (TI's host)
    (48 + len(ERLE) + 3, PAD),            # whole image incl. header and padding (another public host)
    (48 + len(ERLE), PAD),                # whole image, padding not counted
    (len(ERLE), PAD),                     # data only, padding not counted
    (len(ERLE) + 3, PAD),                 # data with its padding
    (48 + len(ERLE), b""),                # whole image, no padding
], ids=["data", "whole+pad", "whole,pad-uncounted", "data,pad-uncounted", "data+pad", "whole"])
def test_erle_in_every_byte_count_convention_shows_the_patterns(host, emu, count, tail):
    assert host.load(header(W, H, count, 2) + ERLE + tail) == 0
    assert host.start() == 0
    _shows_the_patterns(emu.model)
    assert emu.model.sequencer == "running"


@pytest.mark.parametrize("count,tail", [
    (len(RLE), b""), (len(RLE) + 2, bytes(2)), (48 + len(RLE), bytes(2)), (48 + len(RLE) + 2, bytes(2)),
    (len(RLE) + 10, bytes(10)),  # padded to a 16-byte boundary, as TI's reference encoder does
])
def test_plain_rle_with_line_alignment_shows_the_patterns(host, emu, count, tail):
    assert host.load(header(W, H, count, 1) + RLE + tail) == 0
    assert host.start() == 0
    _shows_the_patterns(emu.model)


@pytest.mark.parametrize("count,tail", [(len(RAW), b""), (48 + len(RAW), b""), (48 + len(RAW), b"\x00")])
def test_uncompressed_shows_the_patterns(host, emu, count, tail):
    assert host.load(header(W, H, count, 0) + RAW + tail) == 0
    assert host.start() == 0
    _shows_the_patterns(emu.model)


@pytest.mark.parametrize("pixel,bit", [(b"\x00\x00\x01", 0), (b"\x00\x00\x80", 7), (b"\x00\x01\x00", 8),
                                       (b"\x01\x00\x00", 16), (b"\x80\x00\x00", 23)])
def test_a_pixels_last_byte_carries_bit_positions_0_to_7(emu, pixel, bit):
    """Pixels travel most significant byte first, as hardware-proven hosts send them."""
    emu.model.width, emu.model.height = 1, 1
    host = RawHost(reply_to_writes=False)
    host.setup_lut(bits=(bit, (bit + 1) % 24, (bit + 8) % 24))
    assert host.load(header(1, 1, 7, 2) + b"\x01" + pixel + b"\x00\x01\x00") == 0
    assert host.start() == 0
    assert [int(emu.model.dmd_pattern(k)[0, 0]) for k in range(3)] == [1, 0, 0]


ROW0_OVERRUN = b"\x05" + px(1) + b"\x03" + px(0) + b"\x01" + px(4) + b"\x00\x00"   # 9 pixels
ROW0_UNDERRUN = b"\x04" + px(1) + b"\x02" + px(0) + b"\x01" + px(4) + b"\x00\x00"  # 7 pixels


@pytest.mark.parametrize("blob,code", [
    (header(W, H, len(ERLE), 2, signature=b"Spla") + ERLE, 9),                   # wrong signature
    (header(W, H, len(ERLE), 2) + ROW0_OVERRUN + ERLE[14:], 9),                  # line over-runs
    (header(W, H, len(ERLE), 2) + ROW0_UNDERRUN + ERLE[14:], 9),                 # line under-runs
    (header(W, H, len(ERLE) - 3, 2) + ERLE[:-3], 9),                             # no end-of-image
    (header(W, H, len(ERLE), 2) + ERLE + b"\x00" * 4, 6),                        # 4 bytes of padding
    (header(W, H, len(ERLE), 2) + ERLE + b"\x00\x01\x00", 6),                    # padding not zero
    (header(W, H, len(ERLE) + 1, 2) + ERLE, 6),                                  # count matches neither
    (header(W, H, 48 + len(ERLE) + 2, 2) + ERLE + PAD, 6),                       # count matches neither
    (header(W, H, len(RLE), 1) + RLE[:14] + RLE[16:], 9),                        # RLE line not aligned
    (header(W, H, len(RLE) - 2, 1) + RLE[:-2], 9),                               # RLE without end-of-image
    (header(W, H, len(RLE), 1) + RLE + bytes(16), 6),                            # RLE: 16 bytes of padding
    (header(W, H, len(RAW) - 3, 0) + RAW[:-3], 9),                               # raw pixels short
    (header(W, H, len(ERLE), 3) + ERLE, 9),                                      # unknown compression
    (header(W, 2, len(ERLE), 2) + ERLE, 9),                                      # trailing lines
], ids=["signature", "overrun", "underrun", "no-eoi", "4-pad", "nonzero-pad", "count+1", "whole+2",
        "rle-unaligned", "rle-no-eoi", "rle-16-pad", "raw-short", "compression-3", "extra-line"])
def test_what_the_firmware_rejects_is_still_rejected(host, emu, blob, code):
    assert host.load(blob) == code
    assert 0 not in emu.model.images
    assert host.start() == 7  # the image is not present: the sequence does not start
    assert emu.model.sequencer == "stopped"


# ---- two controllers (DLP9000): each takes one half, with its own half-width header ----------

RIGHT = (b"\x01" + px(4) + b"\x07" + px(0) + b"\x00\x00"     # row 0: P2 lights column 8
         + b"\x01" + px(6) + b"\x07" + px(2) + b"\x00\x00"   # row 1: P1 everywhere, P2 at column 8
         + b"\x01" + px(4) + b"\x07" + px(0)                 # row 2, closed by end-of-image
         + b"\x00\x01\x00")


@pytest.fixture
def dual(clock):
    with usb_emulation(clock=clock, dmd_type=2) as emu:
        emu.model.width, emu.model.height = 2 * W, H
        yield emu


def test_two_controllers_show_both_halves(dual):
    host = RawHost(reply_to_writes=False)
    assert host.command(0x1A0A, read=True)[1][0] & 0x10  # hardware status: secondary controller present
    host.setup_lut()
    assert host.load(header(W, H, 48 + len(ERLE) + 3, 2) + ERLE + PAD) == 0
    assert host.start() == 7  # the secondary's half is missing
    assert host.load(header(W, H, len(RIGHT), 2) + RIGHT, secondary=True) == 0
    assert host.start() == 0
    full = np.zeros((3, H, 2 * W), dtype=np.uint8)
    full[0][:, :4] = 1
    full[1][1, :] = 1
    full[2][:, 7:9] = 1
    for k in range(3):
        assert np.array_equal(dual.model.dmd_pattern(k), full[k]), k


def test_a_full_width_image_is_refused_by_each_controller(dual):
    host = RawHost(reply_to_writes=True)
    host.setup_lut()
    data = (bytes([2 * W]) + px(0) + b"\x00\x00") * H + b"\x00\x01\x00"  # 16 black pixels a line
    wide = header(2 * W, H, len(data), 2) + data
    assert host.load(wide) == 6
    assert host.load(wide, secondary=True) == 6


def test_secondary_load_on_a_single_controller_is_not_allowed(emu):
    emu.model.width, emu.model.height = W, H
    host = RawHost(reply_to_writes=True)
    host.setup_lut()
    assert host.load(header(W, H, len(ERLE), 2) + ERLE, secondary=True) == 5


# ---- framing: the continuation of an over-long message is never run as commands --------------

def test_overlong_message_continuation_is_discarded_not_executed(emu):
    host = RawHost(reply_to_writes=True)
    # Every 64 bytes of this body look like a complete "display mode 3, reply wanted" command,
    # so a controller that took continuation reports for new commands would switch mode.
    imposter = bytes([0x40, 0x77, 0x03, 0x00, 0x1B, 0x1A, 0x03]).ljust(64, b"\x00")
    body = b"\x00" * 58 + imposter * 9  # 6 header bytes + 58 = first report, then 9 continuations
    length = 2 + len(body)  # 4 + 2 + 634 = 640 bytes > the 512-byte command buffer
    msg = bytes([0x40, 0x55]) + length.to_bytes(2, "little") + (0x1A2B).to_bytes(2, "little") + body
    reports = [msg[i:i + 64] for i in range(0, len(msg), 64)]
    assert len(reports) == 10 and reports[3][:6] == imposter[:6]
    for r in reports[:-1]:
        host.dev.write(0x01, r, 100)
        with pytest.raises(usb.core.USBTimeoutError):
            host.dev.read(0x81, 64, 100)  # nothing is answered before the message is complete
    host.dev.write(0x01, reports[-1], 100)
    reply = bytes(host.dev.read(0x81, 64, 100))
    assert reply[0] == 0x40 | 0x20 and reply[1] == 0x55  # one answer, with the error bit
    assert host.error() == 8
    assert emu.model.display_mode == 0
    assert all(c.opcode != 0x1A1B for c in emu.model.command_log)
    host.write_ok(0x1A1B, b"\x03")  # the next real command is understood
    assert emu.model.display_mode == 3
