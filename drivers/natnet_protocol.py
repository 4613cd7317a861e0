"""NatNet wire format, host side: decode what Motive sends, encode what a client sends.

Written from OptiTrack's public description of the bitstream (see `docs/protocols.md`):
every message is `u16 id, u16 payload bytes, payload`, little-endian. Frames of data for
NatNet 3.0, 3.1, 4.0 (identical layouts), 4.1 and 4.2 (per-section byte counts, assets and a
precision timestamp). Model definitions for the same versions (4.0 adds rigid-body marker
names, 4.1 per-dataset byte counts, 4.2 a rigid-body offset rotation).

Every decoder validates as it goes: counts are bounded by the bytes left, 4.1+ section byte
counts must match what was parsed, the end-of-data tag must be 0 and a frame must consume its
payload exactly. Anything else raises `NatNetDecodeError` naming the field and byte offset.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from dpmhw.tracking import TrackerDecodeError

__all__ = [
    "SUPPORTED_VERSIONS",
    "FramePoses",
    "MessageId",
    "MocapFrame",
    "ModelDefinitions",
    "NatNetDecodeError",
    "RigidBodies",
    "RigidBodyDescription",
    "ServerInfo",
    "decode_echo_response",
    "decode_frame",
    "decode_frame_poses",
    "decode_model_definitions",
    "decode_server_info",
    "encode_connect",
    "encode_echo_request",
    "encode_message",
    "parse_version",
    "split_message",
]

SUPPORTED_VERSIONS: tuple[tuple[int, int], ...] = ((3, 0), (3, 1), (4, 0), (4, 1), (4, 2))


class NatNetDecodeError(TrackerDecodeError):
    """A NatNet message is malformed: the receiver drops it and counts it."""


class MessageId(enum.IntEnum):
    CONNECT = 0
    SERVER_INFO = 1
    REQUEST = 2
    RESPONSE = 3
    REQUEST_MODEL_DEF = 4
    MODEL_DEF = 5
    REQUEST_FRAME = 6
    FRAME_OF_DATA = 7
    MESSAGE_STRING = 8
    DISCONNECT = 9
    KEEP_ALIVE = 10
    DISCONNECT_BY_TIMEOUT = 11
    ECHO_REQUEST = 12
    ECHO_RESPONSE = 13
    DISCOVERY = 14
    UNRECOGNIZED_REQUEST = 100


# Fixed-size records, decoded in one vectorised `np.frombuffer` per section.
RIGID_BODY_DTYPE = np.dtype(
    [("id", "<i4"), ("position", "<f4", (3,)), ("quaternion", "<f4", (4,)), ("mean_error", "<f4"), ("params", "<i2")]
)
LABELED_MARKER_DTYPE = np.dtype(
    [("id", "<i4"), ("position", "<f4", (3,)), ("size", "<f4"), ("params", "<i2"), ("residual", "<f4")]
)
assert RIGID_BODY_DTYPE.itemsize == 38 and LABELED_MARKER_DTYPE.itemsize == 26

_HEADER = struct.Struct("<HH")


def parse_version(text: str | tuple) -> tuple[int, int]:
    """`"4.1"` or `(4, 1, 0, 0)` → `(4, 1)`; raises ValueError for unsupported versions."""
    if isinstance(text, str):
        parts = text.strip().split(".")
        try:
            major, minor = int(parts[0]), int(parts[1]) if len(parts) > 1 else 0
        except ValueError:
            raise ValueError(f"NatNet version {text!r}: expected MAJOR.MINOR such as 4.1") from None
    else:
        major, minor = int(text[0]), int(text[1])
    if (major, minor) not in SUPPORTED_VERSIONS:
        supported = ", ".join(f"{a}.{b}" for a, b in SUPPORTED_VERSIONS)
        raise ValueError(f"NatNet version {major}.{minor} is not supported (supported: {supported})")
    return major, minor


# ----------------------------------------------------------------------------- decoded types


@dataclass(frozen=True)
class ServerInfo:
    app_name: str
    app_version: tuple[int, int, int, int]
    natnet_version: tuple[int, int, int, int]
    clock_hz: int | None  # high-resolution clock of the frame timestamps (3.0+)
    data_port: int | None
    is_multicast: bool | None
    multicast_group: str | None


@dataclass(frozen=True, eq=False)
class RigidBodies:
    """A section of rigid-body records, as arrays.

    ids : (n,) int32; positions : (n, 3) float32 metres; quaternions : (n, 4) float32 (x, y, z, w);
    mean_errors : (n,) float32 metres; params : (n,) int16, bit 0 = tracked in this frame
    """

    ids: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    mean_errors: np.ndarray
    params: np.ndarray

    @property
    def tracked(self) -> np.ndarray:
        return (self.params & 1).astype(bool)

    def __len__(self) -> int:
        return len(self.ids)

    @classmethod
    def from_records(cls, records: np.ndarray) -> "RigidBodies":
        return cls(
            records["id"].copy(),
            records["position"].copy(),
            records["quaternion"].copy(),
            records["mean_error"].copy(),
            records["params"].copy(),
        )


@dataclass(frozen=True, eq=False)
class LabeledMarkers:
    """ids : (n,) int32 (model id << 16 | marker id); positions (n, 3); sizes, params, residuals (n,)."""

    ids: np.ndarray
    positions: np.ndarray
    sizes: np.ndarray
    params: np.ndarray
    residuals: np.ndarray


@dataclass(frozen=True, eq=False)
class Asset:
    asset_id: int
    rigid_bodies: RigidBodies
    markers: LabeledMarkers


@dataclass(frozen=True, eq=False)
class MocapFrame:
    """One decoded frame of data (message 7)."""

    frame_number: int
    marker_sets: dict[str, np.ndarray]
    unlabeled_markers: np.ndarray
    rigid_bodies: RigidBodies
    skeletons: dict[int, RigidBodies]
    assets: tuple[Asset, ...]
    labeled_markers: LabeledMarkers
    force_plates: dict[int, list[np.ndarray]]
    devices: dict[int, list[np.ndarray]]
    timecode: int
    timecode_subframe: int
    timestamp_s: float
    stamp_mid_exposure: int  # server clock ticks
    stamp_data_received: int
    stamp_transmit: int
    precision_timestamp: tuple[int, int] | None  # (seconds, fraction) 4.1+
    params: int

    @property
    def is_recording(self) -> bool:
        return bool(self.params & 1)

    @property
    def models_changed(self) -> bool:
        return bool(self.params & 2)

    def system_latency_s(self, clock_hz: int) -> float:
        """Camera mid-exposure to transmit, as Motive measures it."""
        return (self.stamp_transmit - self.stamp_mid_exposure) / clock_hz

    def software_latency_s(self, clock_hz: int) -> float:
        """Camera data received to transmit (Motive's processing time)."""
        return (self.stamp_transmit - self.stamp_data_received) / clock_hz


@dataclass(frozen=True, eq=False)
class RigidBodyDescription:
    name: str
    id: int
    parent_id: int
    offset: np.ndarray  # (3,)
    offset_rotation: np.ndarray | None  # (4,) x y z w, 4.2+
    marker_positions: np.ndarray  # (n, 3)
    marker_labels: np.ndarray  # (n,)
    marker_names: tuple[str, ...]  # 4.0+, else empty


@dataclass(frozen=True)
class OtherDescription:
    """A dataset the tracker does not use (force plate, device, camera, asset, unknown)."""

    type: int
    name: str


@dataclass(frozen=True, eq=False)
class ModelDefinitions:
    marker_sets: dict[str, tuple[str, ...]] = field(default_factory=dict)
    rigid_bodies: tuple[RigidBodyDescription, ...] = ()
    skeletons: dict[int, tuple[str, tuple[RigidBodyDescription, ...]]] = field(default_factory=dict)
    others: tuple[OtherDescription, ...] = ()

    def rigid_body_names(self) -> dict[int, str]:
        return {rb.id: rb.name for rb in self.rigid_bodies}


# ----------------------------------------------------------------------------- the reader


class _Reader:
    """Bounds-checked little-endian cursor over one payload."""

    __slots__ = ("buf", "pos", "end", "what", "sized")

    def __init__(self, buf: bytes | memoryview, what: str, sized: bool = False):
        self.buf = buf if type(buf) is bytes else bytes(buf)
        self.pos = 0
        self.end = len(self.buf)
        self.what = what
        self.sized = sized  # NatNet 4.1+: every section count is followed by its byte count

    def fail(self, field_name: str, message: str) -> NatNetDecodeError:
        return NatNetDecodeError(f"{self.what}: {field_name} at payload byte {self.pos}: {message}")

    def need(self, n: int, field_name: str) -> None:
        if n < 0 or self.pos + n > self.end:
            raise self.fail(field_name, f"needs {n} bytes, only {self.end - self.pos} left (truncated?)")

    def unpack(self, fmt: struct.Struct, field_name: str) -> tuple:
        self.need(fmt.size, field_name)
        values = fmt.unpack_from(self.buf, self.pos)
        self.pos += fmt.size
        return values

    def i32(self, field_name: str) -> int:
        pos = self.pos
        if pos + 4 > self.end:
            raise self.fail(field_name, f"needs 4 bytes, only {self.end - pos} left (truncated?)")
        self.pos = pos + 4
        return _I32.unpack_from(self.buf, pos)[0]

    def skip(self, nbytes: int, field_name: str) -> int:
        """Step over `nbytes` (bounds-checked); returns where they start."""
        pos = self.pos
        if nbytes < 0 or pos + nbytes > self.end:
            raise self.fail(field_name, f"needs {nbytes} bytes, only {self.end - pos} left (truncated?)")
        self.pos = pos + nbytes
        return pos

    def string(self, field_name: str, limit: int | None = None) -> str:
        stop = self.end if limit is None else min(self.end, self.pos + limit)
        nul = self.buf.find(b"\0", self.pos, stop)
        if nul < 0:
            raise self.fail(field_name, "string has no NUL terminator before the end of the payload")
        try:
            text = self.buf[self.pos:nul].decode("utf-8")
        except UnicodeDecodeError as exc:
            raise self.fail(field_name, f"string is not UTF-8 ({exc.reason})") from None
        self.pos = nul + 1
        return text

    def count(self, field_name: str, min_item_bytes: int) -> int:
        """A non-negative i32 count whose items (≥ `min_item_bytes` each) fit in what is left."""
        pos = self.pos
        if pos + 4 > self.end:
            raise self.fail(field_name, f"needs 4 bytes, only {self.end - pos} left (truncated?)")
        self.pos = pos + 4
        (n,) = _I32.unpack_from(self.buf, pos)
        if n < 0:
            raise self.fail(field_name, f"count {n} is negative")
        if n * min_item_bytes > self.end - self.pos:
            raise self.fail(
                field_name, f"count {n} needs at least {n * min_item_bytes} bytes, only {self.end - self.pos} left"
            )
        return n

    def records(self, dtype: np.dtype, n: int, field_name: str) -> np.ndarray:
        return np.frombuffer(self.buf, dtype=dtype, count=n, offset=self.skip(dtype.itemsize * n, field_name))

    def section(self, count_field: str, min_item_bytes: int, size_field: str) -> tuple[int, tuple[int, int] | None]:
        """A section's item count (as `count`) and, from NatNet 4.1, its byte count:
        (count, (start, size) to hand to `finish`, or None before 4.1)."""
        pos, left = self.pos, self.end - self.pos
        if self.sized and left >= 8:  # both words at once when both are valid (the checks below, inline)
            n, size = _TWO_I32.unpack_from(self.buf, pos)
            if 0 <= n and n * min_item_bytes <= left - 4 and 0 <= size <= left - 8:
                self.pos = pos + 8
                return n, (pos + 8, size)
        n = self.count(count_field, min_item_bytes)
        if not self.sized:
            return n, None
        size = self.i32(size_field)
        if size < 0 or size > self.end - self.pos:
            raise self.fail(size_field, f"{size} does not fit in the {self.end - self.pos} bytes left")
        return n, (self.pos, size)

    def finish(self, field_name: str, section: tuple[int, int] | None) -> None:
        """The records parsed since `section` must fill the declared byte count exactly."""
        if section is not None and self.pos - section[0] != section[1]:
            raise self.fail(field_name, f"declares {section[1]} bytes but its records occupy {self.pos - section[0]}")

    def floats(self, n: int, field_name: str) -> np.ndarray:
        return self.records(_F32, n, field_name).astype(np.float32)


_I32 = struct.Struct("<i")
_RIGID_BODY = struct.Struct("<i3f4ffh")  # one RIGID_BODY_DTYPE record, as plain values
assert _RIGID_BODY.size == RIGID_BODY_DTYPE.itemsize
_F32 = np.dtype("<f4")
_SUFFIX_3 = struct.Struct("<IIdQQQ")
_PRECISION = struct.Struct("<II")
_I16 = struct.Struct("<h")
# what follows the sections: timestamps, [precision timestamp 4.1+], params, end-of-data tag
_SUFFIX_30 = struct.Struct("<IIdQQQhi")
_SUFFIX_41 = struct.Struct("<IIdQQQIIhi")
_SERVER_INFO_TAIL = struct.Struct("<QHB4s")
_VEC3 = np.dtype(("<f4", (3,)))


# ----------------------------------------------------------------------------- envelope


def split_message(datagram: bytes | memoryview) -> tuple[int, memoryview]:
    """(message id, payload) of one datagram; the payload length must match the header."""
    view = memoryview(datagram)
    if len(view) < 4:
        raise NatNetDecodeError(f"datagram of {len(view)} bytes is shorter than the 4-byte NatNet header")
    msg_id, size = _HEADER.unpack_from(view, 0)
    if size != len(view) - 4:
        raise NatNetDecodeError(
            f"message {msg_id}: header says {size} payload bytes, datagram carries {len(view) - 4} (truncated or padded)"
        )
    return msg_id, view[4:]


def encode_message(msg_id: int, payload: bytes = b"") -> bytes:
    if len(payload) > 0xFFFF:
        raise ValueError(f"NatNet payload of {len(payload)} bytes exceeds 65535")
    return _HEADER.pack(int(msg_id), len(payload)) + payload


def encode_connect(natnet_version: tuple[int, ...] = (3, 0, 0, 0), app_name: str = "NatNetLib") -> bytes:
    """Connect request as NatNet's own library sends it: name char[256], version u8[4] twice."""
    name = app_name.encode("utf-8")[:255].ljust(256, b"\0")
    v = bytes(tuple(natnet_version) + (0,) * (4 - len(natnet_version)))
    return encode_message(MessageId.CONNECT, name + v + v)


def encode_echo_request(client_time: int) -> bytes:
    return encode_message(MessageId.ECHO_REQUEST, struct.pack("<Q", client_time & 0xFFFFFFFFFFFFFFFF))


def decode_echo_response(payload: bytes | memoryview) -> tuple[int, int]:
    """(echoed client time, server clock ticks when it answered)."""
    if len(payload) != 16:
        raise NatNetDecodeError(f"echo response: payload is {len(payload)} bytes, expected 16")
    return struct.unpack("<QQ", payload)


def decode_server_info(payload: bytes | memoryview) -> ServerInfo:
    r = _Reader(payload, "server info")
    r.need(264, "sender")
    app_name = r.buf[:256].split(b"\0", 1)[0].decode("utf-8", errors="replace")
    app_version = tuple(r.buf[256:260])
    natnet_version = tuple(r.buf[260:264])
    r.pos = 264
    clock_hz = data_port = is_multicast = group = None
    if natnet_version[0] >= 3:
        clock_hz, data_port, mc, group_bytes = r.unpack(_SERVER_INFO_TAIL, "clock frequency / data port / multicast")
        if clock_hz <= 0:
            raise r.fail("clock frequency", "must be positive")
        is_multicast = bool(mc)
        group = ".".join(str(b) for b in group_bytes)
    return ServerInfo(app_name, app_version, natnet_version, clock_hz, data_port, is_multicast, group)


# ----------------------------------------------------------------------------- frame of data


class FramePoses(NamedTuple):
    """What a tracker client needs of a frame of data (`decode_frame_poses`): the rigid bodies as
    plain tuples `(id, x, y, z, qx, qy, qz, qw, mean_error, params)` in wire order, and the stamps."""

    frame_number: int
    rigid_bodies: list[tuple]
    stamp_mid_exposure: int  # server clock ticks
    stamp_transmit: int
    params: int

    @property
    def models_changed(self) -> bool:
        return bool(self.params & 2)


def _labeled(r: _Reader, n: int, field_name: str, keep: bool) -> LabeledMarkers | None:
    start = r.skip(LABELED_MARKER_DTYPE.itemsize * n, field_name)
    if not keep:
        return None
    arr = np.frombuffer(r.buf, LABELED_MARKER_DTYPE, n, start)
    return LabeledMarkers(
        arr["id"].copy(), arr["position"].copy(), arr["size"].copy(), arr["params"].copy(), arr["residual"].copy()
    )


def _rigid_bodies(r: _Reader, n: int, field_name: str, keep: bool) -> RigidBodies | list[tuple] | None:
    start = r.skip(_RIGID_BODY.size * n, field_name)
    if keep:
        return RigidBodies.from_records(np.frombuffer(r.buf, RIGID_BODY_DTYPE, n, start))
    return [_RIGID_BODY.unpack_from(r.buf, start + _RIGID_BODY.size * i) for i in range(n)]


def _channels(r: _Reader, what: str, keep: bool) -> dict[int, list[np.ndarray]]:
    items: dict[int, list[np.ndarray]] = {}
    size_field = f"{what} byte count"
    n, section = r.section(f"{what} count", 8, size_field)
    for _ in range(n):
        item_id = r.i32(f"{what} id")
        n_ch = r.count(f"{what} {item_id} channel count", 4)
        channels = []
        for _ in range(n_ch):
            n_frames = r.count(f"{what} {item_id} channel frame count", 4)
            start = r.skip(4 * n_frames, f"{what} {item_id} channel values")
            if keep:
                channels.append(np.frombuffer(r.buf, _F32, n_frames, start).astype(np.float32))
        items[item_id] = channels
    r.finish(size_field, section)
    return items


# marker sets, unlabeled markers, rigid bodies, skeletons, assets, labeled markers, force plates, devices
_SECTIONS_41 = 8


def _check_outline(r: _Reader, sized: bool) -> None:
    """Refuse a frame its outline already refutes, before any section is walked: the end-of-data
    tag (the last 4 bytes) must be 0 and, from NatNet 4.1, the section byte counts must chain to
    exactly the suffix. Refusing a malformed datagram then costs a few reads, not a walk of
    everything before its flaw (a 64 KB datagram holds 13,000 empty marker sets)."""
    buf, end = r.buf, r.end
    if end - r.pos >= 4:
        (eod,) = _I32.unpack_from(buf, end - 4)
        if eod != 0:
            raise NatNetDecodeError(f"{r.what}: end-of-data tag at payload byte {end - 4}: is {eod}, expected 0 "
                                    "(wrong NatNet version or corrupt frame?)")
    if not sized:
        return
    pos = r.pos
    for _ in range(_SECTIONS_41):
        if end - pos < 8:
            return  # the walk names the short field
        n, size = _TWO_I32.unpack_from(buf, pos)
        if n < 0 or not 0 <= size <= end - pos - 8:
            return  # likewise: the walk's own check of that count names it
        pos += 8 + size
    if end - pos != _SUFFIX_41.size:
        raise NatNetDecodeError(f"{r.what}: section byte counts at payload byte {pos}: the sections end "
                                f"{end - pos} bytes before the end of the frame, its suffix is {_SUFFIX_41.size}")


def _parse_frame(payload: bytes | memoryview, version: tuple[int, int], keep: bool) -> tuple:
    """Walk and validate a whole frame-of-data payload; the fields of `MocapFrame` in order.

    keep=False checks every section as strictly but builds no arrays: markers, skeletons and
    assets are stepped over and the top-level rigid bodies come back as tuples (what the
    receiver thread needs, hundreds of times a second)."""
    major, minor = version
    sized = (major, minor) >= (4, 1)
    r = _Reader(payload, f"NatNet {major}.{minor} frame", sized)
    buf = r.buf
    frame_number = r.i32("frame number")
    _check_outline(r, sized)

    n, section = r.section("marker set count", 5, "marker sets byte count")
    marker_sets: dict[str, np.ndarray] = {}
    end, find, i32 = r.end, buf.find, _I32.unpack_from
    for i in range(n):
        # The common case inline (a set of markers: name, count, positions); anything amiss is
        # parsed again by the checked reader, which names the field. A datagram can hold 13,000
        # empty sets: their cost is a few operations each, not a formatted field name.
        pos = r.pos
        nul = find(b"\0", pos, end)
        k = i32(buf, nul + 1)[0] if 0 <= nul <= end - 5 else -1
        stop = nul + 5 + 12 * k
        if k < 0 or stop > end or not buf[pos:nul].isascii():
            name = r.string(f"marker set {i} name")
            k = r.count(f"marker set {name!r} marker count", 12)
            start = r.skip(12 * k, f"marker set {name!r} positions")
        else:
            name = buf[pos:nul].decode("ascii") if keep else ""
            start, r.pos = nul + 5, stop
        if keep:
            marker_sets[name] = np.frombuffer(buf, _VEC3, k, start).copy()
    r.finish("marker sets byte count", section)

    n, section = r.section("unlabeled marker count", 12, "unlabeled markers byte count")
    start = r.skip(12 * n, "unlabeled marker positions")
    unlabeled = np.frombuffer(buf, _VEC3, n, start).copy() if keep else None
    r.finish("unlabeled markers byte count", section)

    n, section = r.section("rigid body count", _RIGID_BODY.size, "rigid bodies byte count")
    bodies = _rigid_bodies(r, n, "rigid bodies", keep)
    r.finish("rigid bodies byte count", section)

    n, section = r.section("skeleton count", 8, "skeletons byte count")
    skeletons: dict[int, RigidBodies] = {}
    for _ in range(n):
        sk_id = r.i32("skeleton id")
        k = r.count(f"skeleton {sk_id} rigid body count", _RIGID_BODY.size)
        rbs = _rigid_bodies(r, k, f"skeleton {sk_id} rigid bodies", keep)
        if keep:
            skeletons[sk_id] = rbs
    r.finish("skeletons byte count", section)

    assets: list[Asset] = []
    if sized:
        n, section = r.section("asset count", 12, "assets byte count")
        for _ in range(n):
            asset_id = r.i32("asset id")
            k = r.count(f"asset {asset_id} rigid body count", _RIGID_BODY.size)
            rbs = _rigid_bodies(r, k, f"asset {asset_id} rigid bodies", keep)
            k = r.count(f"asset {asset_id} marker count", LABELED_MARKER_DTYPE.itemsize)
            mks = _labeled(r, k, f"asset {asset_id} markers", keep)
            if keep:
                assets.append(Asset(asset_id, rbs, mks))
        r.finish("assets byte count", section)

    n, section = r.section("labeled marker count", LABELED_MARKER_DTYPE.itemsize, "labeled markers byte count")
    labeled = _labeled(r, n, "labeled markers", keep)
    r.finish("labeled markers byte count", section)

    force_plates = _channels(r, "force plate", keep)
    devices = _channels(r, "device", keep)

    suffix = _SUFFIX_41 if sized else _SUFFIX_30
    if r.end - r.pos >= suffix.size:  # all of it at once; else field by field, to name the short one
        timecode, subframe, timestamp, mid, received, transmit, *precision, params, eod = suffix.unpack_from(buf, r.pos)
        precision = tuple(precision) if sized else None
        r.pos += suffix.size
    else:
        timecode, subframe, timestamp, mid, received, transmit = r.unpack(_SUFFIX_3, "frame suffix timestamps")
        precision = r.unpack(_PRECISION, "precision timestamp") if sized else None
        (params,) = r.unpack(_I16, "frame params")
        eod = r.i32("end-of-data tag")
    if eod != 0:
        r.pos -= 4
        raise r.fail("end-of-data tag", f"is {eod}, expected 0 (wrong NatNet version or corrupt frame?)")
    if r.pos != r.end:
        raise r.fail("end of frame", f"{r.end - r.pos} unparsed bytes follow the end-of-data tag (wrong NatNet version?)")
    return (frame_number, marker_sets, unlabeled, bodies, skeletons, tuple(assets), labeled, force_plates, devices,
            timecode, subframe, timestamp, mid, received, transmit, precision, params)


def decode_frame(payload: bytes | memoryview, version: tuple[int, int]) -> MocapFrame:
    """Decode a frame-of-data payload (header already removed) for NatNet `version`."""
    return MocapFrame(*_parse_frame(payload, version, True))


def decode_frame_poses(payload: bytes | memoryview, version: tuple[int, int]) -> FramePoses:
    """The rigid bodies and stamps of a frame-of-data payload, validated exactly as `decode_frame`
    validates it (same errors), without building the marker arrays a tracker client ignores."""
    f = _parse_frame(payload, version, False)
    return FramePoses(f[0], f[3], f[12], f[14], f[16])


# ----------------------------------------------------------------------------- model definitions


def _rigid_body_description(r: _Reader, version: tuple[int, int]) -> RigidBodyDescription:
    name = r.string("rigid body name")
    rb_id, parent = r.unpack(_TWO_I32, f"rigid body {name!r} id / parent")
    offset = r.floats(3, f"rigid body {name!r} offset")
    rotation = r.floats(4, f"rigid body {name!r} offset rotation") if version >= (4, 2) else None
    k = r.count(f"rigid body {name!r} marker count", 16)
    positions = r.records(_VEC3, k, f"rigid body {name!r} marker positions").copy()
    labels = r.records(np.dtype("<i4"), k, f"rigid body {name!r} marker labels").copy()
    names: tuple[str, ...] = ()
    if version >= (4, 0):
        names = tuple(r.string(f"rigid body {name!r} marker {i} name") for i in range(k))
    return RigidBodyDescription(name, rb_id, parent, offset, rotation, positions, labels, names)


_TWO_I32 = struct.Struct("<ii")


def _skip_other(r: _Reader, dtype: int, version: tuple[int, int]) -> OtherDescription:
    """Parse (to find its end) a dataset the tracker does not use."""
    if dtype == 3:  # force plate
        fp_id = r.i32("force plate id")
        serial = r.string(f"force plate {fp_id} serial")
        r.floats(2 + 3 + 144 + 12, f"force plate {fp_id} geometry / calibration")
        r.unpack(_TWO_I32, f"force plate {fp_id} plate / channel type")
        k = r.count(f"force plate {fp_id} channel count", 1)
        for i in range(k):
            r.string(f"force plate {fp_id} channel {i} name")
        return OtherDescription(3, serial)
    if dtype == 4:  # device
        dev_id = r.i32("device id")
        name = r.string(f"device {dev_id} name")
        r.string(f"device {dev_id} serial")
        r.unpack(_TWO_I32, f"device {dev_id} device / channel type")
        k = r.count(f"device {dev_id} channel count", 1)
        for i in range(k):
            r.string(f"device {dev_id} channel {i} name")
        return OtherDescription(4, name)
    if dtype == 5:  # camera
        name = r.string("camera name")
        r.floats(7, f"camera {name!r} pose")
        return OtherDescription(5, name)
    if dtype == 6:  # asset
        name = r.string("asset name")
        r.unpack(_TWO_I32, f"asset {name!r} type / id")
        k = r.count(f"asset {name!r} rigid body count", 1)
        for _ in range(k):
            _rigid_body_description(r, version)
        k = r.count(f"asset {name!r} marker count", 23)
        for i in range(k):
            r.string(f"asset {name!r} marker {i} name")
            r.need(22, f"asset {name!r} marker {i} record")
            r.pos += 22
        return OtherDescription(6, name)
    raise r.fail("dataset type", f"{dtype} is not a known NatNet dataset type (0-6)")


def decode_model_definitions(payload: bytes | memoryview, version: tuple[int, int]) -> ModelDefinitions:
    """Decode a model-definitions payload (message 5) for NatNet `version`."""
    r = _Reader(payload, f"NatNet {version[0]}.{version[1]} model definitions")
    sized = version >= (4, 1)
    n = r.count("dataset count", 4)
    marker_sets: dict[str, tuple[str, ...]] = {}
    rigid_bodies: list[RigidBodyDescription] = []
    skeletons: dict[int, tuple[str, tuple[RigidBodyDescription, ...]]] = {}
    others: list[OtherDescription] = []
    for i in range(n):
        dtype = r.i32(f"dataset {i} type")
        size = start = None
        if sized:
            size = r.i32(f"dataset {i} byte count")
            if size < 0 or size > r.end - r.pos:
                raise r.fail(f"dataset {i} byte count", f"{size} does not fit in the {r.end - r.pos} bytes left")
            start = r.pos
        if dtype == 0:
            name = r.string(f"dataset {i} marker set name")
            k = r.count(f"marker set {name!r} marker count", 1)
            marker_sets[name] = tuple(r.string(f"marker set {name!r} marker {j} name") for j in range(k))
        elif dtype == 1:
            rigid_bodies.append(_rigid_body_description(r, version))
        elif dtype == 2:
            name = r.string(f"dataset {i} skeleton name")
            sk_id = r.i32(f"skeleton {name!r} id")
            k = r.count(f"skeleton {name!r} rigid body count", 1)
            skeletons[sk_id] = (name, tuple(_rigid_body_description(r, version) for _ in range(k)))
        elif sized:
            # 4.1+: step over datasets we do not use by their byte count (robust to layouts we
            # do not parse, including dataset types newer than this code)
            r.pos = start + size
            others.append(OtherDescription(dtype, ""))
        else:
            others.append(_skip_other(r, dtype, version))
        if sized and r.pos - start != size:
            raise r.fail(f"dataset {i} byte count", f"declares {size} bytes but the dataset occupies {r.pos - start}")
    if r.pos != r.end:
        raise r.fail("end of model definitions", f"{r.end - r.pos} unparsed bytes after {n} datasets")
    return ModelDefinitions(marker_sets, tuple(rigid_bodies), skeletons, tuple(others))
