"""An emulated OptiTrack Motive NatNet server on loopback, streaming a simulated `World`.

Device side of the wire, written from the NatNet description in `docs/protocols.md`
(never from `drivers/`): it answers connect, keep-alive, server info, model definitions,
discovery and echo requests on the command port, and streams frames of data at a fixed rate,
either to the multicast group (default) or to every unicast client that keeps itself alive.

Timing is modelled like Motive's: camera frame k is exposed at a fixed rate; its frame carries
the mid-exposure, data-received and transmit stamps on the server's own high-resolution clock
(`clock_hz` ticks/s, with an origin unrelated to the host's), and it is sent `latency_ms`
(+ uniform jitter) after mid-exposure. The pose in frame k is the world's true pose at that
mid-exposure instant; `mid_exposure_host_ns(k)` gives the instant on the host clock so tests
can check a client's timestamps.

Faults to inject: tracking dropouts (tracked flag off), marker noise, truncated and corrupted
datagrams, a stalled stream (`stall(seconds)`), mis-solved poses (`pose_offset_m`), and Motive quit and started again
(`restart(down_s)`: same ports, a new clock origin, frame numbers from 1, unicast clients forgotten).
"""

from __future__ import annotations

import collections
import math
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from dpmhw.thread_priority import MOCK_DEVICE, raise_thread_priority
from dpmhw.transforms import quat_xyzw_of_rows
from firmware_mocks.world import World

__all__ = ["FrameContent", "NatNetServer", "NatNetServerConfig", "encode_frame", "encode_model_definitions"]

# message ids, from the protocol description
CONNECT, SERVER_INFO, REQUEST, RESPONSE, REQUEST_MODEL_DEF, MODEL_DEF = 0, 1, 2, 3, 4, 5
FRAME_OF_DATA, DISCONNECT, KEEP_ALIVE, ECHO_REQUEST, ECHO_RESPONSE, DISCOVERY = 7, 9, 10, 12, 13, 14
UNRECOGNIZED_REQUEST = 100

_SUPPORTED = {(3, 0), (3, 1), (4, 0), (4, 1), (4, 2)}

_HEADER = struct.Struct("<HH")
_I32 = struct.Struct("<i")
_TWO_I32 = struct.Struct("<ii")
_RIGID_BODY = struct.Struct("<i3f4ffh")
_MARKER = struct.Struct("<i3ffhf")
_SUFFIX = struct.Struct("<IIdQQQ")
_PRECISION = struct.Struct("<II")
_TAIL = struct.Struct("<hi")  # frame params, end-of-data tag


def _version_tuple(version: str | tuple) -> tuple[int, int]:
    if isinstance(version, str):
        major, _, minor = version.partition(".")
        v = (int(major), int(minor or 0))
    else:
        v = (int(version[0]), int(version[1]))
    if v not in _SUPPORTED:
        raise ValueError(f"mock NatNet server: version {v[0]}.{v[1]} not emulated (3.0, 3.1, 4.0, 4.1, 4.2)")
    return v


def _message(msg_id: int, payload: bytes | bytearray) -> bytes:
    return _HEADER.pack(msg_id, len(payload)) + payload


def _cstr(text: str) -> bytes:
    return text.encode("utf-8") + b"\0"


# ----------------------------------------------------------------------------- encoding


@dataclass
class FrameContent:
    """Everything a frame of data carries, in wire order."""

    frame_number: int
    marker_sets: list[tuple[str, np.ndarray]] = field(default_factory=list)  # name, (k, 3)
    unlabeled_markers: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    # (id, (x, y, z), (qx, qy, qz, qw), mean error, params)
    rigid_bodies: list[tuple] = field(default_factory=list)
    skeletons: list[tuple[int, list[tuple]]] = field(default_factory=list)
    assets: list[tuple[int, list[tuple], list[tuple]]] = field(default_factory=list)  # 4.1+
    # (id, (x, y, z), size, params, residual)
    labeled_markers: list[tuple] = field(default_factory=list)
    force_plates: list[tuple[int, list[np.ndarray]]] = field(default_factory=list)
    devices: list[tuple[int, list[np.ndarray]]] = field(default_factory=list)
    timecode: int = 0
    timecode_subframe: int = 0
    timestamp_s: float = 0.0
    stamp_mid_exposure: int = 0
    stamp_data_received: int = 0
    stamp_transmit: int = 0
    precision_timestamp: tuple[int, int] = (0, 0)
    params: int = 0


def _rigid_body_record(rb: tuple) -> bytes:
    rb_id, (x, y, z), (qx, qy, qz, qw), err, params = rb
    return _RIGID_BODY.pack(rb_id, x, y, z, qx, qy, qz, qw, err, params)


def _marker_record(m: tuple) -> bytes:
    m_id, (x, y, z), size, params, residual = m
    return _MARKER.pack(m_id, x, y, z, size, params, residual)


def _points(points) -> tuple[int, bytes]:
    """(count, float32 x y z records) of points given as a (k, 3) array or a sequence of 3-tuples
    (what `NatNetServer.build_frame` makes: packing floats beats building an array per frame)."""
    if isinstance(points, np.ndarray):
        arr = np.asarray(points, "<f4").reshape(-1, 3)
        return len(arr), arr.tobytes()
    flat = [v for p in points for v in p]
    return len(flat) // 3, struct.pack(f"<{len(flat)}f", *flat)


def _section(out: bytearray, count: int, body: bytes | bytearray, sized: bool) -> None:
    """Append count, [byte count if 4.1+], records."""
    out += _TWO_I32.pack(count, len(body)) if sized else _I32.pack(count)
    out += body


def _rigid_body_records(rbs: list[tuple]) -> bytes:
    return b"".join([_rigid_body_record(rb) for rb in rbs])


def _channel_items(items: list[tuple[int, list[np.ndarray]]]) -> bytes:
    out = bytearray()
    for item_id, channels in items:
        out += _TWO_I32.pack(item_id, len(channels))
        for values in channels:
            v = np.asarray(values, "<f4").reshape(-1)
            out += _I32.pack(len(v)) + v.tobytes()
    return bytes(out)


def encode_frame(content: FrameContent, version: str | tuple) -> bytes:
    """A complete frame-of-data datagram (header included) for NatNet `version`."""
    v = version if version in _SUPPORTED else _version_tuple(version)
    sized = v >= (4, 1)
    c = content
    out = bytearray(_I32.pack(c.frame_number))
    body = bytearray()
    for name, m in c.marker_sets:
        k, records = _points(m)
        body += _cstr(name)
        body += _I32.pack(k)
        body += records
    _section(out, len(c.marker_sets), body, sized)
    _section(out, *_points(c.unlabeled_markers), sized)
    _section(out, len(c.rigid_bodies), _rigid_body_records(c.rigid_bodies), sized)
    body = bytearray()
    for sk_id, rbs in c.skeletons:
        body += _TWO_I32.pack(sk_id, len(rbs))
        body += _rigid_body_records(rbs)
    _section(out, len(c.skeletons), body, sized)
    if sized:
        body = bytearray()
        for a_id, rbs, mks in c.assets:
            body += _TWO_I32.pack(a_id, len(rbs))
            body += _rigid_body_records(rbs)
            body += _I32.pack(len(mks))
            body += b"".join([_marker_record(m) for m in mks])
        _section(out, len(c.assets), body, sized)
    _section(out, len(c.labeled_markers), b"".join([_marker_record(m) for m in c.labeled_markers]), sized)
    _section(out, len(c.force_plates), _channel_items(c.force_plates), sized)
    _section(out, len(c.devices), _channel_items(c.devices), sized)
    out += _SUFFIX.pack(
        c.timecode, c.timecode_subframe, c.timestamp_s, c.stamp_mid_exposure, c.stamp_data_received, c.stamp_transmit
    )
    if sized:
        out += _PRECISION.pack(*c.precision_timestamp)
    out += _TAIL.pack(c.params, 0)
    return _message(FRAME_OF_DATA, out)


def encode_model_definitions(world: World, version: str | tuple) -> bytes:
    """Model definitions datagram: a marker set and a rigid body per world object."""
    v = _version_tuple(version)
    datasets: list[tuple[int, bytes]] = []
    for obj in world.objects.values():
        names = [f"Marker{i + 1}" for i in range(len(obj.markers))]
        datasets.append((0, _cstr(obj.name) + struct.pack("<i", len(names)) + b"".join(map(_cstr, names))))
        rb = _cstr(obj.name) + struct.pack("<ii3f", obj.rigid_body_id, -1, 0.0, 0.0, 0.0)
        if v >= (4, 2):
            rb += struct.pack("<4f", 0.0, 0.0, 0.0, 1.0)
        rb += struct.pack("<i", len(obj.markers)) + np.asarray(obj.markers, "<f4").tobytes()
        rb += struct.pack(f"<{len(obj.markers)}i", *range(1, len(obj.markers) + 1))
        if v >= (4, 0):
            rb += b"".join(map(_cstr, names))
        datasets.append((1, rb))
    out = bytearray(struct.pack("<i", len(datasets)))
    for dtype, body in datasets:
        out += struct.pack("<i", dtype) + (struct.pack("<i", len(body)) if v >= (4, 1) else b"") + body
    return _message(MODEL_DEF, bytes(out))


# ----------------------------------------------------------------------------- the server


@dataclass
class NatNetServerConfig:
    version: str = "4.1"
    rate_hz: float = 360.0
    latency_ms: float = 4.5  # camera mid-exposure to transmit
    jitter_ms: float = 0.0  # extra delay, uniform in [0, jitter)
    software_latency_ms: float = 0.9  # camera data received to transmit (part of latency_ms)
    unicast: bool = False
    interface: str = "127.0.0.1"
    command_port: int = 1510  # 0: pick a free port (see `NatNetServer.command_port`)
    data_port: int = 1511
    multicast_group: str = "239.255.42.99"
    clock_hz: int = 10_000_000
    server_uptime_s: float = 5000.0  # the server clock's reading when the mock starts
    clock_drift_ppm: float = 0.0  # the server clock runs this much fast against the host's
    dropout_prob: float = 0.0  # per body per frame: tracked flag off
    marker_noise_m: float = 0.0  # std dev of marker position noise
    solve_from_markers: bool = False  # the pose fitted to the noisy markers (Motive's solve), not the true one
    truncate_prob: float = 0.0  # per frame
    corrupt_prob: float = 0.0  # per frame
    client_timeout_s: float = 5.0  # unicast clients without a keep-alive for this long are dropped
    seed: int = 0
    app_name: str = "Motive"


def _fit_rigid(model: np.ndarray, seen) -> tuple[tuple[float, ...], tuple[float, float, float]]:
    """The rotation (row-major) and translation that carry the body's `model` markers closest
    to the `seen` ones, in the least-squares sense (Kabsch: the SVD of their cross-covariance,
    a reflection excluded)."""
    b = np.asarray(seen, np.float64)
    ca, cb = model.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((model - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return tuple(rot.reshape(-1).tolist()), tuple((cb - rot @ ca).tolist())


class NatNetServer:
    """Run with `start()` / `stop()` or as a context manager. One thread serves commands and
    paces frames; nothing it holds grows without bound."""

    def __init__(self, world: World, config: NatNetServerConfig | None = None):
        self.world = world
        self.config = cfg = config or NatNetServerConfig()
        self.version = _version_tuple(cfg.version)
        if cfg.rate_hz <= 0:
            raise ValueError(f"rate_hz must be positive, got {cfg.rate_hz}")
        if cfg.software_latency_ms > cfg.latency_ms:
            raise ValueError("software_latency_ms cannot exceed latency_ms")
        self._rng = np.random.default_rng(cfg.seed)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._clients: dict[tuple[str, int], int] = {}  # unicast address -> last seen (host ns)
        self._stall_until_ns = 0
        self._models_changed = False
        self._truth: collections.OrderedDict[int, float] = collections.OrderedDict()
        self.frames_sent = 0  # frames put on the wire (to the group, or to at least one client)
        self.frames_skipped = 0  # frames never sent (stall or the server fell behind)
        self.faults: collections.Counter[str] = collections.Counter()
        self.commands: collections.Counter[int] = collections.Counter()
        self.bad_commands = 0

        self.restarts = 0
        # a mis-solve (a body fitted onto the wrong markers): every reported pose and its markers
        # are this far (metres) from the world's truth while set; the world itself is unchanged
        self.pose_offset_m = np.zeros(3)
        self._open_sockets(cfg.command_port)
        self._zero_ns = time.monotonic_ns() - int(cfg.server_uptime_s * 1e9)
        self._ticks_per_ns = cfg.clock_hz * (1 + cfg.clock_drift_ppm * 1e-6) / 1e9

    def _open_sockets(self, command_port: int) -> None:
        cfg = self.config
        self._cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._mcast: socket.socket | None = None
        try:
            self._cmd.bind((cfg.interface, command_port))
            self.command_port = self._cmd.getsockname()[1]
            if not cfg.unicast:
                self._mcast = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                self._mcast.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(cfg.interface))
                self._mcast.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
                self._mcast.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
        except OSError:
            self._cmd.close()
            if self._mcast is not None:
                self._mcast.close()
            raise

    # -- clock ---------------------------------------------------------------------------------

    def ticks(self, host_ns: int) -> int:
        """Server clock reading at host monotonic time `host_ns`."""
        if self.config.clock_drift_ppm == 0:
            return (host_ns - self._zero_ns) * self.config.clock_hz // 1_000_000_000
        return int((host_ns - self._zero_ns) * self._ticks_per_ns)

    @property
    def clock_origin_host_ns(self) -> int:
        """Host monotonic time at which the server clock read 0: without drift,
        host_ns = origin + ticks * 1e9 / clock_hz."""
        return self._zero_ns

    def ticks_to_host_ns(self, ticks: int) -> float:
        return self._zero_ns + ticks / self._ticks_per_ns

    def mid_exposure_host_ns(self, frame_number: int) -> float | None:
        """Host time (ns) that frame `frame_number` describes; None if not (or no longer) logged."""
        with self._lock:
            return self._truth.get(frame_number)

    # -- control -------------------------------------------------------------------------------

    def start(self) -> "NatNetServer":
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="natnet-mock", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self._cmd.close()
        if self._mcast is not None:
            self._mcast.close()

    def __enter__(self) -> "NatNetServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def restart(self, down_s: float, server_uptime_s: float = 10.0, clock_hz: int | None = None) -> None:
        """Motive quits, and `down_s` later is running again on the same ports: its clock restarted
        (reading `server_uptime_s`; ticking at `clock_hz` if given, as after a change of its
        settings), frame numbers from 1, unicast clients forgotten (they must connect again).
        Blocks for `down_s`."""
        self.stop()
        if clock_hz is not None:
            self.config.clock_hz = int(clock_hz)
            self._ticks_per_ns = self.config.clock_hz * (1 + self.config.clock_drift_ppm * 1e-6) / 1e9
        time.sleep(down_s)
        for _ in range(50):  # the closed socket may take a moment to release its port
            try:
                self._open_sockets(self.command_port)
                break
            except OSError:
                time.sleep(0.02)
        else:
            raise RuntimeError(f"NatNet mock: cannot bind command port {self.command_port} again")
        with self._lock:
            self._clients.clear()
            self._truth.clear()
        self._zero_ns = time.monotonic_ns() - int(server_uptime_s * 1e9)
        self._stall_until_ns = 0
        self._stop.clear()
        self.restarts += 1
        self.start()

    def stall(self, seconds: float) -> None:
        """Send no frames for `seconds` (frame numbers keep counting, like a network stall)."""
        self._stall_until_ns = time.monotonic_ns() + int(seconds * 1e9)

    def add_body(self, rigid_body_id: int, name: str, trajectory) -> None:
        """Add a rigid body while streaming, as when an asset is created in Motive: the next
        frame flags the tracked-model list as changed, so clients re-request model definitions."""
        with self._lock:
            self.world.add(rigid_body_id, name, trajectory)
            self._models_changed = True

    def resume(self) -> None:
        """End a stall now."""
        self._stall_until_ns = 0

    @property
    def clients(self) -> list[tuple[str, int]]:
        with self._lock:
            return list(self._clients)

    # -- loop ----------------------------------------------------------------------------------

    def _run(self) -> None:
        raise_thread_priority(MOCK_DEVICE, "NatNet mock")
        cfg = self.config
        period_ticks = cfg.clock_hz / cfg.rate_hz
        period_ns = 1e9 / cfg.rate_hz
        first_mid = self.ticks(time.monotonic_ns()) + int(period_ticks)
        latency_ns = int(cfg.latency_ms * 1e6)
        k = 0
        pending = None  # frame k, encoded ahead of its send time; only the transmit stamp is left
        next_send = 0.0
        while not self._stop.is_set():
            if pending is None:
                mid = first_mid + int(round(k * period_ticks))
                mid_host = self.ticks_to_host_ns(mid)
                jitter_ns = self._rng.uniform(0, cfg.jitter_ms * 1e6) if cfg.jitter_ms > 0 else 0.0
                next_send = mid_host + latency_ns + jitter_ns
                behind = time.monotonic_ns() - next_send
                if behind > 50e6:  # more than 50 ms behind (host overloaded): skip ahead
                    skip = int(behind / period_ns)
                    self.frames_skipped += skip
                    k += skip
                    continue
                pending = (k + 1, mid_host, self._encode_pending(k + 1, mid, mid_host))
            now = time.monotonic_ns()
            wait_s = min(0.02, max(0.0, (next_send - now) / 1e9))
            if select.select([self._cmd], [], [], wait_s)[0]:  # µs timeouts (poll and epoll round to ms)
                self._serve_commands()
            if time.monotonic_ns() < next_send:
                continue
            frame_number, mid_host, datagram = pending
            pending = None
            k += 1
            if time.monotonic_ns() < self._stall_until_ns:
                self.frames_skipped += 1
                continue
            self._send_frame(frame_number, mid_host, datagram)

    def _serve_commands(self) -> None:
        for _ in range(64):  # bounded: never starve the frame pacing
            try:
                data, addr = self._cmd.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            self._handle_command(data, addr)
            r, _, _ = select.select([self._cmd], [], [], 0)
            if not r:
                return

    def _handle_command(self, data: bytes, addr: tuple[str, int]) -> None:
        if len(data) < 4:
            self.bad_commands += 1
            return
        msg_id, size = struct.unpack_from("<HH", data)
        if size != len(data) - 4:
            self.bad_commands += 1
            return
        self.commands[msg_id] += 1
        payload = data[4:]
        now = time.monotonic_ns()
        if msg_id in (CONNECT, KEEP_ALIVE) and self.config.unicast:
            with self._lock:
                self._clients[addr] = now
        if msg_id in (CONNECT, DISCOVERY):
            self._reply(addr, _message(SERVER_INFO, self._server_info()))
        elif msg_id == REQUEST_MODEL_DEF:
            with self._lock:  # `add_body` may be changing the world on another thread
                datagram = encode_model_definitions(self.world, self.version)
            self._reply(addr, datagram)
        elif msg_id == ECHO_REQUEST and len(payload) == 8:
            (client_time,) = struct.unpack("<Q", payload)
            self._reply(addr, _message(ECHO_RESPONSE, struct.pack("<QQ", client_time, self.ticks(time.monotonic_ns()))))
        elif msg_id == DISCONNECT:
            with self._lock:
                self._clients.pop(addr, None)
        elif msg_id == KEEP_ALIVE:
            pass
        else:
            self._reply(addr, _message(UNRECOGNIZED_REQUEST, b""))

    def _reply(self, addr, datagram: bytes) -> None:
        try:
            self._cmd.sendto(datagram, addr)
        except OSError:
            pass

    def _server_info(self) -> bytes:
        cfg = self.config
        app_version = {(3, 0): (2, 1), (3, 1): (2, 2), (4, 0): (3, 0), (4, 1): (3, 1), (4, 2): (3, 2)}[self.version]
        return (
            cfg.app_name.encode()[:255].ljust(256, b"\0")
            + bytes((*app_version, 0, 0))
            + bytes((*self.version, 0, 0))
            + struct.pack("<QHB", cfg.clock_hz, cfg.data_port, 0 if cfg.unicast else 1)
            + socket.inet_aton(cfg.multicast_group)
        )

    # -- frames --------------------------------------------------------------------------------

    def build_frame(self, frame_number: int, mid_ticks: int, mid_host_ns: float) -> FrameContent:
        """The frame describing the world at `mid_host_ns` (transmit stamp filled at send time).

        In plain floats per body and marker: this runs 360 times a second on the streaming thread,
        where numpy's per-call cost on 3-vectors and 4×3 marker sets was most of the frame's cost."""
        cfg = self.config
        rng = self._rng
        t = mid_host_ns / 1e9
        rbs, labeled, marker_sets, all_markers = [], [], [], []
        with self._lock:
            objects = list(self.world.objects.values())
            params, self._models_changed = (2 if self._models_changed else 0), False
        ox, oy, oz = np.asarray(self.pose_offset_m, np.float64).tolist()
        for obj in objects:
            (r00, r01, r02, r10, r11, r12, r20, r21, r22), (px, py, pz) = self.world.pose_floats(obj.rigid_body_id, t)
            px, py, pz = px + ox, py + oy, pz + oz
            # markers @ rot.T + pos, marker by marker
            ideal = [(r00 * mx + r01 * my + r02 * mz + px, r10 * mx + r11 * my + r12 * mz + py,
                      r20 * mx + r21 * my + r22 * mz + pz) for mx, my, mz in obj.markers.tolist()]
            if cfg.marker_noise_m > 0:
                noise = rng.normal(0.0, cfg.marker_noise_m, (len(ideal), 3)).tolist()
                markers = [(ix + nx, iy + ny, iz + nz) for (ix, iy, iz), (nx, ny, nz) in zip(ideal, noise)]
                if cfg.solve_from_markers:  # the pose as the tracker solves it: fitted to what it saw
                    (r00, r01, r02, r10, r11, r12, r20, r21, r22), (px, py, pz) = _fit_rigid(obj.markers, markers)
                    ideal = [(r00 * mx + r01 * my + r02 * mz + px, r10 * mx + r11 * my + r12 * mz + py,
                              r20 * mx + r21 * my + r22 * mz + pz) for mx, my, mz in obj.markers.tolist()]
                residuals = [math.sqrt((mx - ix) ** 2 + (my - iy) ** 2 + (mz - iz) ** 2)
                             for (mx, my, mz), (ix, iy, iz) in zip(markers, ideal)]
            else:
                markers, residuals = ideal, [0.0] * len(ideal)
            tracked = not (cfg.dropout_prob > 0 and rng.random() < cfg.dropout_prob)
            if tracked:
                quat = quat_xyzw_of_rows(r00, r01, r02, r10, r11, r12, r20, r21, r22)
                mean_residual = sum(residuals) / len(residuals) if residuals else math.nan
                rbs.append((obj.rigid_body_id, (px, py, pz), quat, mean_residual, 1))
                for i, (m, res) in enumerate(zip(markers, residuals)):
                    labeled.append(((obj.rigid_body_id << 16) | (i + 1), m, 0.014, 0, res))
            else:  # Motive reports an untracked body with the tracked bit clear and no pose
                rbs.append((obj.rigid_body_id, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), 0.0, 0))
                markers = []
            marker_sets.append((obj.name, markers))
            all_markers += markers
        marker_sets.append(("all", all_markers))
        latency_rx = int((cfg.latency_ms - cfg.software_latency_ms) * 1e-3 * cfg.clock_hz)
        host_s = mid_host_ns / 1e9
        return FrameContent(
            frame_number=frame_number,
            marker_sets=marker_sets,
            unlabeled_markers=(),
            rigid_bodies=rbs,
            labeled_markers=labeled,
            timestamp_s=frame_number / cfg.rate_hz,
            stamp_mid_exposure=mid_ticks,
            stamp_data_received=mid_ticks + latency_rx,
            precision_timestamp=(int(host_s), int((host_s % 1.0) * 2**32)),
            params=params,  # bit 1: tracked-model list changed
        )

    def _encode_pending(self, frame_number: int, mid_ticks: int, mid_host_ns: float) -> bytearray:
        return bytearray(encode_frame(self.build_frame(frame_number, mid_ticks, mid_host_ns), self.version))

    def _send_frame(self, frame_number: int, mid_host_ns: float, datagram: bytearray) -> None:
        with self._lock:
            self._truth[frame_number] = mid_host_ns
            while len(self._truth) > 50_000:
                self._truth.popitem(last=False)
            if self.config.unicast:
                cutoff = time.monotonic_ns() - int(self.config.client_timeout_s * 1e9)
                for addr in [a for a, seen in self._clients.items() if seen < cutoff]:
                    del self._clients[addr]
                targets = list(self._clients)
            else:
                targets = [(self.config.multicast_group, self.config.data_port)]
        if not targets:
            return  # unicast without clients: nothing goes on the wire
        sock = self._cmd if self.config.unicast else self._mcast
        # The transmit stamp sits at a fixed distance from the end of the frame:
        # ... transmit u64, [precision timestamp u32 u32 (4.1+)], params i16, end-of-data i32.
        tail = 2 + 4 + (8 if self.version >= (4, 1) else 0)
        struct.pack_into("<Q", datagram, len(datagram) - tail - 8, self.ticks(time.monotonic_ns()))
        datagram = self._inject_fault(bytes(datagram))
        for addr in targets:
            try:
                sock.sendto(datagram, addr)
            except OSError:
                pass
        self.frames_sent += 1

    def _inject_fault(self, datagram: bytes) -> bytes:
        cfg = self.config
        if not (cfg.truncate_prob > 0 or cfg.corrupt_prob > 0 or cfg.dropout_prob > 0 or cfg.marker_noise_m > 0
                or cfg.jitter_ms > 0):
            # nothing random is configured, so no draw can tell whether this roll was taken: skip it
            # (a numpy draw per frame costs as much as encoding the frame's bodies)
            return datagram
        roll = self._rng.random()
        if roll < cfg.truncate_prob:
            self.faults["truncated"] += 1
            cut = int(self._rng.integers(1, len(datagram)))
            short = bytearray(datagram[:cut])
            if cut >= 4 and self._rng.random() < 0.5:  # also fix the header: the frame parser must notice
                struct.pack_into("<H", short, 2, cut - 4)
            return bytes(short)
        if roll < cfg.truncate_prob + cfg.corrupt_prob:
            self.faults["corrupted"] += 1
            buf = bytearray(datagram)
            kind = int(self._rng.integers(0, 3))
            if kind == 0:  # end-of-data tag not zero
                struct.pack_into("<i", buf, len(buf) - 4, int(self._rng.integers(1, 2**31 - 1)))
            elif kind == 1:  # trailing junk, header updated to cover it
                buf += bytes(self._rng.integers(0, 256, 3, dtype=np.uint8))
                struct.pack_into("<H", buf, 2, len(buf) - 4)
            else:  # marker-set count far beyond the datagram
                struct.pack_into("<i", buf, 8, 0x7FFF0000)
            return bytes(buf)
        return datagram
