"""OptiTrack Motive client over NatNet/UDP: rigid-body poses stamped at mid-exposure on the host clock.

Handshake on the command port (connect → server info: NatNet version, clock frequency,
multicast or unicast, data port), model definitions (rigid-body names ↔ ids), then frames:
multicast frames arrive on a data socket bound to the group address and joined on an explicit
interface; unicast frames arrive on the command socket, which sends keep-alives.

Timing: each frame carries camera mid-exposure and transmit stamps in server clock ticks. The
server→host clock offset comes from echo round trips (Cristian's method) and, until the first
echo returns, from the running minimum of arrival minus transmit. Each pose is stamped with its
mid-exposure instant mapped to `time.monotonic_ns()`.

A server info is applied only as the reply to this client's own connect request; one that
changes the clock frequency or NatNet version under a running stream makes the client handshake
again. Every datagram is decoded defensively: malformed ones are counted (`status().malformed`) and
dropped; a frame with a flagged-tracked body whose pose is not a pose is malformed too.
Only datagrams from the configured server's address are read at all (and replies to commands
only from its command port; see `_from_server`): any host on the network can send UDP to these
ports, so others are counted (`foreign_datagrams`, per sender in `status().details`) and each new
sender is logged once. Poses that decode but cannot be real
(outside the workspace, too fast, stamped in the future) are dropped by the plausibility gate
of `ReceiverTracker`.
"""

from __future__ import annotations

import logging
import math
import select
import socket
import time
from collections import Counter, deque

from dpmhw.plausibility import PlausibilityLimits
from dpmhw.tracking import ClockMapping, PoseSample, TrackerError, TrackerState
from dpmhw.transforms import quaternion_xyzw_to_rotation
from drivers.natnet_protocol import (
    FramePoses,
    MessageId,
    ModelDefinitions,
    NatNetDecodeError,
    ServerInfo,
    decode_echo_response,
    decode_frame_poses,
    decode_model_definitions,
    decode_server_info,
    encode_connect,
    encode_echo_request,
    encode_message,
    parse_version,
    split_message,
)
from drivers.tracker_base import LinkLost, ReceiverTracker

__all__ = ["NatNetClient"]

log = logging.getLogger(__name__)

_MAX_DATAGRAM = 65536
_FRAME_ID = MessageId.FRAME_OF_DATA.to_bytes(2, "little")  # a datagram's first two bytes
_FOREIGN_SENDERS_KEPT = 64  # distinct foreign addresses counted one by one (the rest as "other")


class NatNetClient(ReceiverTracker):
    """Receive rigid-body poses from Motive (or `firmware_mocks.natnet_server`).

    server : Motive's address; command_port : its command port (1510).
    local_interface : the address of this host's interface towards Motive (used to bind the
        command socket and to join the multicast group on the right NIC).
    multicast : None follows what the server announces in its server info.
    natnet_version : force a bitstream version (e.g. "4.1"); None uses the server's.
    clock_window_s : how long clock-offset evidence is kept; shorter follows a drifting server
        clock more closely (error <= drift x window), longer rides out network hiccups.
    """

    kind = "natnet"

    def __init__(
        self,
        server: str = "127.0.0.1",
        *,
        command_port: int = 1510,
        local_interface: str = "127.0.0.1",
        multicast: bool | None = None,
        data_port: int | None = None,
        multicast_group: str | None = None,
        natnet_version: str | None = None,
        connect_timeout_s: float = 1.0,
        keepalive_interval_s: float = 1.0,
        echo_interval_s: float = 0.25,
        clock_window_s: float = 2.0,
        stale_after_s: float = 0.1,
        lost_after_s: float = 1.0,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 2.0,
        plausibility: PlausibilityLimits | None = None,
    ):
        super().__init__(
            stale_after_s=stale_after_s, lost_after_s=lost_after_s,
            backoff_initial_s=backoff_initial_s, backoff_max_s=backoff_max_s, plausibility=plausibility,
        )
        self.server = server
        self.command_port = command_port
        self.local_interface = local_interface
        self.multicast = multicast
        self.data_port = data_port
        self.multicast_group = multicast_group
        self.forced_version = parse_version(natnet_version) if natnet_version else None
        self.version: tuple[int, int] | None = self.forced_version
        self.clock = ClockMapping(window_s=clock_window_s)
        self.connect_timeout_s = connect_timeout_s
        self.keepalive_interval_s = keepalive_interval_s
        self.echo_interval_s = echo_interval_s
        self.server_info: ServerInfo | None = None
        self.clock_hz: int | None = None
        self.models = ModelDefinitions()
        self.system_latency_s: float | None = None  # Motive's own mid-exposure→transmit
        self.other_messages = 0
        self.unsolicited_server_info = 0
        self._info_requested_ns: int | None = None  # when this client last asked for a server info
        self._rehandshake = ""  # why the running session must handshake again
        self.foreign_datagrams = 0
        self.foreign_senders: Counter[str] = Counter()
        self._server_ip: str | None = None
        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._echoes_sent: deque[int] = deque(maxlen=64)
        self._rx_buffer = bytearray(_MAX_DATAGRAM)  # receiver thread only
        self._rx_view = memoryview(self._rx_buffer)
        self._want_models = False

    # -- names ---------------------------------------------------------------------------------

    @property
    def local_address(self) -> tuple[str, int] | None:
        """(host, port) of the command socket (where unicast frames arrive); None when closed."""
        sock = self._cmd
        return None if sock is None else sock.getsockname()[:2]

    def rigid_body_names(self) -> dict[int, str]:
        return self.models.rigid_body_names()

    def rigid_body_id(self, name: str) -> int:
        for rb_id, rb_name in self.rigid_body_names().items():
            if rb_name == name:
                return rb_id
        known = ", ".join(sorted(self.rigid_body_names().values())) or "none yet"
        raise KeyError(f"no rigid body named {name!r} in Motive's model definitions (known: {known})")

    # -- datagram handling (also usable directly, e.g. for replaying captures) -----------------

    def process_datagram(self, datagram: bytes, arrival_ns: int | None = None) -> list[PoseSample]:
        """Handle one datagram from the server; returns the samples it published (may be empty).

        Never raises for bad input: malformed datagrams are counted and dropped.
        """
        arrival_ns = time.monotonic_ns() if arrival_ns is None else arrival_ns
        try:
            msg_id, payload = split_message(datagram)
            if msg_id == MessageId.FRAME_OF_DATA:
                return self._handle_frame(payload, arrival_ns)
            if msg_id == MessageId.SERVER_INFO:
                self._on_server_info(decode_server_info(payload), arrival_ns)
            elif msg_id == MessageId.MODEL_DEF:
                if self.version is None:
                    raise NatNetDecodeError("model definitions arrived before the server info (version unknown)")
                self.models = decode_model_definitions(payload, self.version)
            elif msg_id == MessageId.ECHO_RESPONSE:
                self._handle_echo(payload, arrival_ns)
            else:
                self.other_messages += 1
        except (NatNetDecodeError, TrackerError) as exc:
            self._count_malformed(exc)
        except Exception as exc:
            self._count_internal_error(exc)
        return []

    def _on_server_info(self, info: ServerInfo, arrival_ns: int) -> None:
        """Apply a server info only as the answer to this client's own connect request (within
        `connect_timeout_s` of it): one at any other time (from the server's address and command
        port, so a spoofed or stray datagram) could change the clock every stamp is derived from.
        Those are counted (`status().details['unsolicited_server_info']`) and ignored."""
        requested = self._info_requested_ns
        if requested is None or not 0 <= arrival_ns - requested <= self.connect_timeout_s * 1e9:
            self.unsolicited_server_info += 1
            return
        self._info_requested_ns = None
        self._apply_server_info(info)

    def _apply_server_info(self, info: ServerInfo) -> None:
        """Take the handshake's server info; a later one that changes the clock frequency or the
        NatNet version (a Motive restarted with other settings) is not applied under a running
        stream: it ends the session (`_rehandshake`), and the next one handshakes afresh."""
        try:
            server_version = parse_version(info.natnet_version)
        except ValueError as exc:
            raise TrackerError(f"{info.app_name} at {self.server}: {exc}") from None
        if info.clock_hz is None:
            raise TrackerError(f"{info.app_name} at {self.server}: server info lacks the clock frequency")
        old = self.server_info
        if old is not None:
            if (info.clock_hz, info.natnet_version[:2]) != (old.clock_hz, old.natnet_version[:2]):
                self._rehandshake = (
                    f"the server info changed mid-stream (clock {old.clock_hz} → {info.clock_hz} Hz, NatNet "
                    f"{'.'.join(map(str, old.natnet_version[:2]))} → {'.'.join(map(str, info.natnet_version[:2]))}); "
                    "handshaking again")
            return
        self.server_info = info
        self.version = self.forced_version or server_version
        self.clock_hz = info.clock_hz

    def _ticks_to_ns(self, ticks: int) -> int:
        return ticks * 1_000_000_000 // self.clock_hz

    def _handle_echo(self, payload, arrival_ns: int) -> None:
        echoed, server_ticks = decode_echo_response(payload)
        if echoed not in self._echoes_sent or self.clock_hz is None:
            raise NatNetDecodeError(f"echo response: client time {echoed} is not one this client sent")
        self._echoes_sent.remove(echoed)
        jumps = self.clock.jumps
        self.clock.add_round_trip(echoed, self._ticks_to_ns(server_ticks), arrival_ns)
        if self.clock.jumps != jumps:  # the server restarted under us: its frame numbers begin again too
            self._first_frame_of_session = True
            log.warning("natnet: the server's clock changed (restarted?); clock mapping and frame numbers start over")

    def _handle_frame(self, payload, arrival_ns: int) -> list[PoseSample]:
        if self._rehandshake:
            self.other_messages += 1  # stamped on a clock the server no longer uses: not read
            return []
        clock_hz = self.clock_hz
        if self.version is None or clock_hz is None:
            raise NatNetDecodeError("frame arrived before the server info (version and clock unknown)")
        frame = decode_frame_poses(payload, self.version)
        mid, transmit = frame.stamp_mid_exposure, frame.stamp_transmit
        if not 0 < mid <= transmit:
            raise NatNetDecodeError(
                f"frame {frame.frame_number}: camera mid-exposure stamp {mid} is not "
                f"positive and before the transmit stamp {transmit}"
            )
        bodies = self._check_bodies(frame)  # validates before anything is counted
        transmit_ns = self._ticks_to_ns(transmit)
        unmapped = self.clock.offset_ns is None
        if unmapped:  # the first evidence: there is nothing yet to check it against
            self.clock.add_one_way(transmit_ns, arrival_ns)
        if frame.models_changed:
            self._want_models = True
        self.system_latency_s = (transmit - mid) / clock_hz  # Motive's mid-exposure → transmit
        mid_host = self.clock.to_host_ns(self._ticks_to_ns(mid))
        samples = [
            PoseSample.from_floats(rb_id, rotation, position, mid_host, arrival_ns, valid, error, frame.frame_number)
            for rb_id, rotation, position, valid, error in bodies
        ]
        published = self._publish_frame(samples, arrival_ns, frame.frame_number)
        if self.frame_taken and not unmapped:  # only a frame the checks believe feeds the clock
            self.clock.add_one_way(transmit_ns, arrival_ns)
        return published

    @staticmethod
    def _check_bodies(frame: FramePoses) -> list[tuple[int, tuple, tuple, bool, float]]:
        """(id, rotation (9 floats, row-major), position (3 floats), valid, mean error) per rigid body.

        A body flagged tracked must carry a finite position and a unit quaternion; otherwise the
        frame is malformed (a pose we cannot trust is worse than none). Per body in plain floats
        (a frame holds a handful; numpy's per-call cost dominated at 360 frames a second); the
        wire's float32 signalling NaNs widen to quiet ones without floating-point warnings.
        """
        bodies = []
        for rb_id, x, y, z, qx, qy, qz, qw, error, params in frame.rigid_bodies:
            tracked = params & 1
            if tracked:
                norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
                if not (math.isfinite(x + y + z) and abs(norm - 1.0) < 1e-3):
                    raise NatNetDecodeError(
                        f"frame {frame.frame_number}: rigid body {rb_id} is flagged tracked but its pose is not "
                        f"valid (position {[x, y, z]}, quaternion norm {norm:.4g})"
                    )
            # valid = tracked: a tracked body's quaternion passed the unit check, so its rotation is usable
            bodies.append((rb_id, quaternion_xyzw_to_rotation(qx, qy, qz, qw), (x, y, z), bool(tracked), error))
        return bodies

    # -- the session ---------------------------------------------------------------------------

    def _details(self) -> dict:
        return {**super()._details(), "foreign_datagrams": self.foreign_datagrams,
                "unsolicited_server_info": self.unsolicited_server_info,
                "foreign_senders": dict(self.foreign_senders)}

    def _from_server(self, sender: tuple, data: bytes, command_socket: bool) -> bool:
        """True for a datagram the configured server sent; others are counted, each sender logged once.

        The address must be the server's (`server`, resolved): Motive sends multicast frames from
        the interface it streams on, so `server` must be Motive's address on that interface (its
        "local interface"); a datagram from any other address is refused. Replies to commands
        (server info, model definitions, echoes) come from the command port the client sent them
        to, which the protocol fixes, so on the command socket anything but a frame must also come
        from `command_port`. Frames are checked by address only: their source port is Motive's
        data socket, which the protocol does not fix (unicast frames may come from it)."""
        host, port = sender[:2]
        if host == self._server_ip and (
                not command_socket or port == self.command_port
                or data[:2] == _FRAME_ID):
            return True
        self.foreign_datagrams += 1
        who = host if host != self._server_ip else f"{host}:{port}"  # the server's address, a wrong port
        if who not in self.foreign_senders and len(self.foreign_senders) >= _FOREIGN_SENDERS_KEPT:
            who = "other"
        if who not in self.foreign_senders:
            log.warning("natnet: ignoring datagrams from %s (only the server %s is accepted, its replies from port "
                        "%d); further ones are counted in status().details['foreign_senders']", who,
                        self._server_ip, self.command_port)
        self.foreign_senders[who] += 1
        return False

    def _recv(self, sock: socket.socket, flags: int = 0) -> bytes | None:
        """One datagram from the server, or None for one from anyone else."""
        size, sender = sock.recvfrom_into(self._rx_buffer, _MAX_DATAGRAM, flags)  # no 64 KiB allocation per call
        data = self._rx_view[:size].tobytes()
        return data if self._from_server(sender, data, sock is self._cmd) else None

    def _send(self, datagram: bytes) -> None:
        self._cmd.sendto(datagram, (self.server, self.command_port))

    def _send_connect(self, version: tuple[int, int]) -> None:
        """A connect request; its server-info reply is the only one this client applies."""
        self._info_requested_ns = time.monotonic_ns()
        self._send(encode_connect((*version, 0, 0)))

    def _send_echo(self) -> int:
        """Echo request stamped with the host clock; the response is matched by that stamp."""
        stamp = time.monotonic_ns()
        self._echoes_sent.append(stamp)
        self._send(encode_echo_request(stamp))
        return stamp

    def _close_transport(self) -> None:
        for sock in (self._cmd, self._data):
            if sock is not None:
                sock.close()
        self._cmd = self._data = None

    def _handshake(self) -> None:
        try:
            self._server_ip = socket.gethostbyname(self.server)
        except OSError as exc:
            raise LinkLost(f"cannot resolve the NatNet server {self.server!r}: {exc}") from None
        self._cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._cmd.bind((self.local_interface, 0))
        self.server_info = None
        self._rehandshake = ""
        deadline = time.monotonic() + self.connect_timeout_s
        next_try = 0.0
        while self.server_info is None:
            if self._stop.is_set():
                return
            now = time.monotonic()
            if now > deadline:
                raise LinkLost(
                    f"no server info from {self.server}:{self.command_port} within {self.connect_timeout_s} s "
                    "(is Motive streaming, and are the address and command port right?)"
                )
            if now >= next_try:
                self._send_connect(self.forced_version or (4, 1))
                next_try = now + 0.2
            if select.select([self._cmd], [], [], 0.02)[0]:
                data = self._recv(self._cmd)
                if data is None:
                    continue
                try:
                    msg_id, payload = split_message(data)
                    if msg_id == MessageId.SERVER_INFO:
                        self._on_server_info(decode_server_info(payload), time.monotonic_ns())
                except NatNetDecodeError as exc:
                    self._count_malformed(exc)

    def _sync_clock(self, round_trips: int = 8, timeout_s: float = 0.5) -> None:
        """Echo burst before streaming, so even the first frame is stamped with a round-trip
        clock offset. Frames arriving meanwhile (unicast) are skipped, not mis-stamped."""
        deadline = time.monotonic() + timeout_s
        got = 0
        while got < round_trips and time.monotonic() < deadline and not self._stop.is_set():
            self._send_echo()
            reply_deadline = time.monotonic() + 0.05
            while time.monotonic() < reply_deadline:
                if not select.select([self._cmd], [], [], 0.01)[0]:
                    continue
                data = self._recv(self._cmd)
                arrival = time.monotonic_ns()
                if data is None:
                    continue
                if len(data) >= 2 and int.from_bytes(data[:2], "little") == MessageId.FRAME_OF_DATA:
                    self.other_messages += 1
                    continue
                before = len(self._echoes_sent)
                self.process_datagram(data, arrival)
                if len(self._echoes_sent) < before:  # our echo came back
                    got += 1
                    break

    def _open_data_socket(self, info: ServerInfo) -> None:
        group = self.multicast_group or info.multicast_group
        port = self.data_port or info.data_port
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            # Linux: bind the group address (not the interface's) so only this group's datagrams
            # arrive, then join on the explicit interface (8-byte ip_mreq: group, interface).
            sock.bind((group, port))
            mreq = socket.inet_aton(group) + socket.inet_aton(self.local_interface)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
        except OSError as exc:
            sock.close()
            raise TrackerError(f"cannot join multicast {group}:{port} on {self.local_interface}: {exc}") from None
        self._data = sock

    def _session(self) -> None:
        self._handshake()
        if self._stop.is_set():
            return
        self._sync_clock()
        info = self.server_info
        use_multicast = info.is_multicast if self.multicast is None else self.multicast
        if use_multicast:
            self._open_data_socket(info)
        mode = f"multicast {self.multicast_group or info.multicast_group}" if use_multicast else "unicast"
        self._set_state(TrackerState.CONNECTED, f"{info.app_name} NatNet {self.version[0]}.{self.version[1]}, {mode}")
        self._send(encode_message(MessageId.REQUEST_MODEL_DEF))
        # One datagram per readiness, then the timers: a poll on registered sockets costs less than
        # draining each socket until a failed read raises (datagrams come one at a time at 360 Hz).
        sockets = {s.fileno(): s for s in (self._cmd, self._data) if s is not None}
        poller = select.poll()
        for fd in sockets:
            poller.register(fd, select.POLLIN)
        stale_ns, lost_ns = self.stale_after_s * 1e9, self.lost_after_s * 1e9
        probe_ns = max(self.stale_after_s, 0.02) * 1e9
        keepalive_ns, echo_ns = self.keepalive_interval_s * 1e9, self.echo_interval_s * 1e9
        stop, monotonic_ns, dont_wait = self._stop, time.monotonic_ns, socket.MSG_DONTWAIT
        connected_ns = last_keepalive = last_echo = last_probe = monotonic_ns()
        while not stop.is_set():
            for fd, _ in poller.poll(20):
                try:
                    data = self._recv(sockets[fd], dont_wait)
                except (BlockingIOError, InterruptedError):
                    continue
                if data is not None:
                    self.process_datagram(data, monotonic_ns())
            now = monotonic_ns()
            since = max(self._last_arrival_ns or 0, connected_ns)  # the newest plausible frame of this session
            if now - since > stale_ns and now - last_probe > probe_ns:
                # Frames are missing: Motive may have restarted. Every `stale_after_s`, connect
                # again (a restarted Motive has forgotten its unicast clients, and a CONNECT
                # registers one; its server-info reply ends the session if the clock or version
                # changed) and send an echo (its round trip teaches the client a restarted
                # server's clock at once), instead of waiting for the next keep-alive, echo or
                # the link timeout.
                self._send_connect(self.forced_version or self.version or (4, 1))
                if not use_multicast:
                    last_keepalive = now
                last_probe = last_echo = self._send_echo()
            elif not use_multicast and now - last_keepalive > keepalive_ns:
                self._send(encode_message(MessageId.KEEP_ALIVE))
                last_keepalive = now
            if now - last_echo > echo_ns:  # keeps following clock drift
                last_echo = self._send_echo()
            if self._want_models:
                self._want_models = False
                self._send(encode_message(MessageId.REQUEST_MODEL_DEF))
            if now - since > lost_ns:
                self._check_alive(since, "frame of data")
            if self._rehandshake:
                raise LinkLost(self._rehandshake)
