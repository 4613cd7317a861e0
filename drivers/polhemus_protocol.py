"""Polhemus Liberty / Patriot binary records, host side: find, validate and decode them in a byte
stream that may carry garbage (line noise, a half-written record after a reconnect).

Binary record (output list `2,7,8,0`, 41 bytes), little-endian:

    0  2 bytes  preamble, the model's two letters: "LY" Liberty, "PA" Patriot, "LU" Latus
    2  u8       station (sensor) number, 1-based
    3  u8       command that produced it: 'C' continuous, 'P' single record, 0x16 who-am-I
    4  u8       error indicator (0 = none)
    5  u8       reserved
    6  u16      body byte count (33 for 2,7,8,0)
    8  f32 x 3  position, in the configured unit (inches by default, `U1` centimetres)
   20  f32 x 4  orientation quaternion w, x, y, z
   36  u32      timestamp, milliseconds on the device clock
   40  ' '      output item 0 (a space)

On a malformed record the parser drops one byte and resynchronises on the next preamble, so
good records behind it are never lost. A who-am-I reply may declare up to 512 body bytes, so a
stray or corrupt who-am-I header would swallow the records behind it if its body were taken on
trust: its body must be printable text, and the first byte that is not (every pose record
carries its station number, 1…16, in its third byte) rejects the header at once. A reply cut
short takes the next record's printable "LY" as text, so a body in which a pose-record header
begins is refused there and the record kept. A truncated record is only known to be bad once a full
record's worth of bytes follows it, so the good record right behind it is delayed by about one
record period (never dropped).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

import numpy as np

from dpmhw.tracking import TrackerDecodeError

__all__ = ["PREAMBLES", "PolhemusDecodeError", "PoseRecord", "RecordParser", "TextRecord", "decode_record"]

PREAMBLES = {b"LY": "Liberty", b"PA": "Patriot", b"LU": "Latus"}
HEADER = struct.Struct("<2sBBBBH")
POSE_BODY = struct.Struct("<3f4fIc")
POSE_RECORD_BYTES = HEADER.size + POSE_BODY.size  # 41
WHO_AM_I = 0x16
_POSE_COMMANDS = (ord("C"), ord("P"))
_MAX_TEXT_BODY = 512
_PREAMBLE_RE = re.compile(b"|".join(re.escape(p) for p in PREAMBLES))
# Text a who-am-I body may hold: printable ASCII, tab, CR, LF.
_NOT_TEXT_RE = re.compile(rb"[^\x20-\x7e\t\r\n]")


class PolhemusDecodeError(TrackerDecodeError):
    """Bytes that start like a Polhemus record but are not one."""


@dataclass(frozen=True, eq=False)
class PoseRecord:
    model: str
    station: int
    command: int
    error: int
    position: np.ndarray  # (3,) float32, device units
    quaternion_wxyz: np.ndarray  # (4,) float32
    timestamp_ms: int


@dataclass(frozen=True)
class TextRecord:
    """A binary-framed reply whose body is text (who-am-I)."""

    model: str
    station: int
    command: int
    error: int
    text: str


def _header(buf: bytes | memoryview) -> tuple[str, int, int, int, int]:
    preamble, station, command, error, _reserved, size = HEADER.unpack_from(buf, 0)
    model = PREAMBLES.get(bytes(preamble))
    if model is None:
        raise PolhemusDecodeError(f"record preamble {bytes(preamble)!r} is not one of {', '.join(p.decode() for p in PREAMBLES)}")
    if command in _POSE_COMMANDS:
        if size != POSE_BODY.size:
            raise PolhemusDecodeError(
                f"{model} station {station}: body of {size} bytes, expected {POSE_BODY.size} for output list 2,7,8,0"
            )
        if not 1 <= station <= 16:
            raise PolhemusDecodeError(f"{model}: station {station} outside 1..16")
    elif command == WHO_AM_I:
        if size > _MAX_TEXT_BODY:
            raise PolhemusDecodeError(f"{model}: who-am-I body of {size} bytes exceeds {_MAX_TEXT_BODY}")
    else:
        raise PolhemusDecodeError(f"{model}: record from unknown command byte 0x{command:02x}")
    return model, station, command, error, size


def _check_text(model: str, buf, start: int, end: int) -> None:
    bad = _NOT_TEXT_RE.search(buf, start, end)
    if bad is not None:
        raise PolhemusDecodeError(
            f"{model} who-am-I: body byte {bad.start() - start} is 0x{buf[bad.start()]:02x}, not text"
        )


def decode_record(buf: bytes | memoryview) -> PoseRecord | TextRecord:
    """Decode exactly one complete record; raises PolhemusDecodeError otherwise."""
    buf = bytes(buf)
    if len(buf) < HEADER.size:
        raise PolhemusDecodeError(f"record of {len(buf)} bytes is shorter than the {HEADER.size}-byte header")
    model, station, command, error, size = _header(buf)
    if len(buf) != HEADER.size + size:
        raise PolhemusDecodeError(f"{model} record: header declares {size} body bytes, got {len(buf) - HEADER.size}")
    if command == WHO_AM_I:
        _check_text(model, buf, HEADER.size, len(buf))
        return TextRecord(model, station, command, error, buf[HEADER.size:].decode("ascii"))
    x, y, z, qw, qx, qy, qz, ms, tail = POSE_BODY.unpack_from(buf, HEADER.size)
    if tail != b" ":
        raise PolhemusDecodeError(f"{model} station {station}: record does not end in the space item (got {tail!r})")
    position = np.array([x, y, z], np.float32)
    quat = np.array([qw, qx, qy, qz], np.float32)
    if not (np.isfinite(position).all() and np.isfinite(quat).all()):
        raise PolhemusDecodeError(f"{model} station {station}: non-finite position or orientation")
    norm = float(np.linalg.norm(quat.astype(np.float64)))
    if abs(norm - 1.0) > 1e-3:
        raise PolhemusDecodeError(f"{model} station {station}: quaternion norm {norm:.4g} is not 1")
    return PoseRecord(model, station, command, error, position, quat, ms)


class RecordParser:
    """Incremental parser: `feed(bytes)` returns the records and decode errors found, in order.

    The buffer is bounded: garbage without a preamble is discarded as it arrives.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.garbage_bytes = 0  # bytes skipped while looking for a preamble

    @property
    def pending(self) -> int:
        return len(self._buf)

    def _record_inside_text(self, end: int) -> int | None:
        """Where a valid pose-record header begins inside a who-am-I body (buffer offset); 0 when
        none does, None when one may but its header has not fully arrived.

        A text body may hold "LY" or "PA" (printable), so a reply cut short would otherwise take
        the start of the record behind it as text and swallow the rest of that record."""
        start = HEADER.size
        while True:
            m = _PREAMBLE_RE.search(self._buf, start, min(end + 1, len(self._buf)))  # one may straddle the end
            if m is None:
                if len(self._buf) < end or (len(self._buf) == end and self._buf[end - 1:end] in (b"L", b"P")):
                    return None
                return 0
            j = m.start()
            if len(self._buf) < j + HEADER.size:
                return None
            try:
                _, _, command, _, _ = _header(bytes(self._buf[j:j + HEADER.size]))
            except PolhemusDecodeError:
                start = j + 1
                continue
            if command in _POSE_COMMANDS:
                return j
            start = j + 1

    def feed(self, data: bytes) -> list[PoseRecord | TextRecord | PolhemusDecodeError]:
        self._buf += data
        out: list[PoseRecord | TextRecord | PolhemusDecodeError] = []
        while True:
            m = _PREAMBLE_RE.search(self._buf)
            if m is None:
                keep = 1 if self._buf[-1:] in (b"L", b"P") else 0  # a preamble may straddle reads
                self.garbage_bytes += len(self._buf) - keep
                del self._buf[: len(self._buf) - keep]
                return out
            if m.start():
                self.garbage_bytes += m.start()
                del self._buf[: m.start()]
            if len(self._buf) < HEADER.size:
                return out
            try:
                model, _, command, _, size = _header(self._buf)
                if command == WHO_AM_I:  # reject a bogus text header before it waits for its body
                    _check_text(model, self._buf, HEADER.size, min(len(self._buf), HEADER.size + size))
            except PolhemusDecodeError as exc:
                out.append(exc)
                del self._buf[:1]  # resynchronise on the next preamble
                continue
            if command == WHO_AM_I:
                cut = self._record_inside_text(HEADER.size + size)
                if cut is None:
                    return out  # a preamble near its end: wait for the bytes that tell
                if cut:
                    out.append(PolhemusDecodeError(f"{model} who-am-I: a pose record begins at body byte "
                                                   f"{cut - HEADER.size}: the reply was cut short"))
                    del self._buf[:cut]
                    continue
            if len(self._buf) < HEADER.size + size:
                return out
            try:
                out.append(decode_record(self._buf[: HEADER.size + size]))
                del self._buf[: HEADER.size + size]
            except PolhemusDecodeError as exc:
                out.append(exc)
                del self._buf[:1]
