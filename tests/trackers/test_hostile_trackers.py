"""Findings 2–7 of issue 14: corrupt or foreign tracker input loses nothing good and never
reaches the projector.

Each test feeds the real drivers bytes built from the protocol description (the mock's encoder
for NatNet, a hand-packed record for Polhemus) with explicit arrival times, so nothing here
depends on how fast the machine is.
"""

from __future__ import annotations

import socket
import struct

import numpy as np
import pytest

from dpmhw.plausibility import PlausibilityGate, PlausibilityLimits
from dpmhw.session.testing import wait_for
from dpmhw.tracking import ClockMapping, PoseSample
from drivers.natnet import NatNetClient
from drivers.polhemus_protocol import PoseRecord, RecordParser, TextRecord
from drivers.serial_tracker import PolhemusTracker
from firmware_mocks.natnet_server import FrameContent, encode_frame

from .test_natnet_loopback import natnet_pair
from .test_serial_tracker import record_bytes

WAIT_S = 30  # for what must happen eventually: generous, as only broken code waits this long

MS = 1_000_000
PERIOD_NS = 2_777_778  # 360 Hz
CONFIRM = PlausibilityLimits().confirm  # the gate holds a body's first samples until this many agree


def natnet_client(**kw) -> NatNetClient:
    """A client past its handshake (NatNet 4.1, a 1 GHz server clock: one tick is one ns)."""
    client = NatNetClient(**kw)
    client.version, client.clock_hz = (4, 1), 10**9
    return client


def frame(number: int, position=(0.1, 0.2, 0.3), *, mid_ns: int, transmit_ns: int | None = None) -> bytes:
    transmit_ns = mid_ns + 4 * MS if transmit_ns is None else transmit_ns
    content = FrameContent(frame_number=number, rigid_bodies=[(1, position, (0.0, 0.0, 0.0, 1.0), 0.0, 1)],
                           stamp_mid_exposure=mid_ns, stamp_transmit=transmit_ns)
    return encode_frame(content, "4.1")


def stream(client, numbers, *, start_ns=10**12, offset_ns=5 * 10**9, position=lambda k: (0.1, 0.2, 0.3), edit=None):
    """Feed frames `numbers` at 360 Hz; `edit(k, datagram_args)` may corrupt the k-th. Returns
    the published samples per frame (a list per datagram)."""
    out = []
    for k, n in enumerate(numbers):
        mid = start_ns + k * PERIOD_NS
        args = dict(number=n, position=position(k), mid_ns=mid, transmit_ns=mid + 4 * MS)
        if edit is not None:
            edit(k, args)
        out.append(client.process_datagram(frame(args.pop("number"), args.pop("position"), **args),
                                           arrival_ns=mid + 4 * MS + 200_000 + offset_ns))
    return out


# ------------------------------------------------------------------------------- finding 2


def test_finding_2_stray_who_am_i_header_does_not_swallow_the_records_behind_it():
    good = [record_bytes(station=1, ms=1000 + 4 * k) for k in range(14)]
    bogus = b"LY\x00\x16\x00\x00" + (512).to_bytes(2, "little")  # who-am-I declaring a 512-byte body
    items = RecordParser().feed(bogus + b"".join(good))
    records = [i for i in items if isinstance(i, PoseRecord)]
    assert [r.timestamp_ms for r in records] == [1000 + 4 * k for k in range(14)]
    assert not any(isinstance(i, TextRecord) for i in items)


def test_finding_2_bogus_who_am_i_is_rejected_before_its_body_has_arrived():
    parser = RecordParser()
    assert parser.feed(b"LY\x00\x16\x00\x00" + (512).to_bytes(2, "little")) == []  # could still be text
    items = parser.feed(record_bytes(ms=7))  # the third byte of a pose record (station 1) is not text
    assert [i.timestamp_ms for i in items if isinstance(i, PoseRecord)] == [7]


def test_finding_2_a_real_who_am_i_reply_still_decodes_split_across_reads():
    text = b"Polhemus PATRIOT, 2 stations\r\n"
    reply = b"PA\x00\x16\x00\x00" + len(text).to_bytes(2, "little") + text
    parser = RecordParser()
    items = parser.feed(reply[:12]) + parser.feed(reply[12:] + record_bytes(model=b"PA", ms=5))
    assert isinstance(items[0], TextRecord) and items[0].text == text.decode()
    assert isinstance(items[1], PoseRecord) and items[1].timestamp_ms == 5


# ------------------------------------------------------------------------------- finding 3


def test_finding_3_one_flipped_timestamp_bit_does_not_shift_the_clock():
    tracker = PolhemusTracker("loop://", warmup_records=4)
    arrival0, published = 50 * 10**9, []
    for k in range(60):
        ms = 2000 + 4 * k
        stamped = ms ^ (1 << 30) if k == 30 else ms
        arrival = arrival0 + ms * MS + 4 * MS  # 4 ms transit
        published += tracker.process_bytes(record_bytes(ms=stamped), arrival_ns=arrival)
    assert len(published) == 60 - 4 - 1 - (CONFIRM - 1)  # warm-up, the corrupt record dropped, the body confirmed
    assert all(ms != 2000 + 4 * 30 for ms in [s.frame_number for s in published])
    ages = np.array([s.t_arrival_ns - s.t_exposure_ns for s in published])
    # one-way mapping with a constant transit: every good record is stamped its device latency
    # before it arrived, also the ones after the corrupt one (before the fix: 10^9 ms before)
    assert np.all(ages == tracker.device_latency_ns)
    st = tracker.status()
    # the gate refused it before it could reach the clock mapping (only accepted records feed it)
    assert st.implausible == 1 and st.details["clock_outliers"] == 0 and st.frames_missed == 0


def test_clock_mapping_ignores_a_low_outlier_but_follows_a_confirmed_jump():
    clock = ClockMapping(window_s=2.0, jump_tolerance_s=0.05, confirm=3)
    for k in range(10):
        clock.add_one_way(device_ns=k * 10 * MS, arrival_ns=10**9 + k * 10 * MS)
    assert clock.offset_ns == 10**9
    assert not clock.add_one_way(device_ns=2**40, arrival_ns=10**9 + 100 * MS)  # corrupt: held back
    assert clock.offset_ns == 10**9 and clock.outliers == 1
    for k in range(3):  # the device clock really jumped ahead by 10 s: three readings agree
        clock.add_one_way(device_ns=10 * 10**9 + (11 + k) * 10 * MS, arrival_ns=10**9 + (11 + k) * 10 * MS)
    assert clock.offset_ns == 10**9 - 10 * 10**9


# ------------------------------------------------------------------------------- finding 4


def test_finding_4_one_frame_number_999_ahead_costs_a_few_frames_not_999():
    client = natnet_client()
    numbers = list(range(100, 140))
    numbers[10] += 999
    published = stream(client, numbers)
    lost = [numbers[k] for k, samples in enumerate(published) if not samples and k >= CONFIRM - 1]
    assert len(lost) <= 2 and all(n in (111, 112) for n in lost)  # recovered within a few samples
    st = client.status()
    assert st.details["frame_resyncs"] == 1 and st.frames_missed == 0
    assert client.latest(1).frame_number == 139


def test_udp_reordering_is_still_refused():
    client = natnet_client()
    published = stream(client, [1, 2, 3, 4, 5, 7, 6, 8, 9])
    assert [bool(s) for s in published][CONFIRM - 1:] == [True, True, True, True, False, True, True]
    assert client.status().out_of_order == 1 and client.status().details["frame_resyncs"] == 0


# ------------------------------------------------------------------------------- finding 5


def test_finding_5_frame_stamped_in_the_future_is_dropped_so_a_stall_goes_stale_on_time():
    client = natnet_client()

    def future(k, args):
        if k == 20:  # mid-exposure and transmit 900 ms ahead of the true time
            args["mid_ns"] += 900 * MS
            args["transmit_ns"] += 900 * MS

    published = stream(client, range(1, 22), edit=future)
    assert published[20] == [] and all(published[CONFIRM - 1:20])
    latest = client.latest(1)
    assert latest.frame_number == 20 and latest.t_exposure_ns <= latest.t_arrival_ns
    assert client.status().implausible == 1 and "after it arrived" in client.status().details["last_implausible"]


# ------------------------------------------------------------------------------- finding 6


def test_finding_6_datagrams_from_other_hosts_are_counted_and_ignored():
    with natnet_pair("4.1", unicast=True) as (world, server, client):
        assert wait_for(lambda: client.status().frames >= 20, WAIT_S)
        port = client._cmd.getsockname()[1]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
            attacker.bind(("127.0.0.2", 0))  # another address on this host's loopback net
            for k in range(50):
                bogus = frame(10**6 + k, (1000.0, 0.0, 0.0), mid_ns=1, transmit_ns=2)
                attacker.sendto(bogus, ("127.0.0.1", port))
        assert wait_for(lambda: client.foreign_datagrams == 50, WAIT_S), client.foreign_datagrams
        st = client.status()
        assert st.details["foreign_senders"] == {"127.0.0.2": 50}
        assert st.malformed == 0 and st.implausible == 0
        assert client.latest(1).translation[0] < 100  # never the injected pose


def test_finding_6_replies_must_come_from_the_command_port_frames_from_the_server_address():
    """The protocol fixes where replies come from (the command port the client sent to), not the
    source port of frames (Motive's data socket): a server info or echo reply from the server's
    address but another port is refused; a frame from there is read."""
    client = natnet_client(server="127.0.0.1", command_port=1510)
    client._server_ip = "127.0.0.1"
    reply = (1).to_bytes(2, "little") + (4).to_bytes(2, "little") + b"\0" * 4  # a (short) SERVER_INFO
    assert not client._from_server(("127.0.0.1", 40000), reply, command_socket=True)
    assert client._from_server(("127.0.0.1", 1510), reply, command_socket=True)
    genuine = frame(1, mid_ns=10**9)
    assert client._from_server(("127.0.0.1", 1511), genuine, command_socket=True)
    assert client._from_server(("127.0.0.1", 1511), genuine, command_socket=False)  # multicast data socket
    assert not client._from_server(("127.0.0.9", 1510), genuine, command_socket=False)
    assert client.status().details["foreign_senders"] == {"127.0.0.1:40000": 1, "127.0.0.9": 1}


def test_finding_6_multicast_frames_from_another_address_are_counted_and_ignored():
    with natnet_pair("4.1", unicast=False) as (world, server, client):
        assert wait_for(lambda: client.status().frames >= 20, WAIT_S)
        group, port = server.config.multicast_group, server.config.data_port
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
            attacker.bind(("127.0.0.2", 0))
            attacker.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
            attacker.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            for k in range(50):
                attacker.sendto(frame(10**6 + k, (1000.0, 0.0, 0.0), mid_ns=1, transmit_ns=2), (group, port))
        assert wait_for(lambda: client.foreign_datagrams == 50, WAIT_S), client.foreign_datagrams
        assert client.status().details["foreign_senders"] == {"127.0.0.2": 50}
        frames = client.status().frames
        assert wait_for(lambda: client.status().frames > frames + 10, WAIT_S)  # the server's frames still arrive
        assert client.latest(1).translation[0] < 100


# ------------------------------------------------------------------------------- finding 7


@pytest.mark.parametrize("distance_m", [1e3, 1e6])
def test_finding_7_poses_kilometres_away_are_dropped_and_counted(distance_m):
    client = natnet_client()
    published = stream(client, range(1, 31), position=lambda k: (distance_m, 0.0, 0.0) if k in (10, 11) else (0.1, 0.2, 0.3))
    assert published[10] == published[11] == [] and all(published[k] for k in range(CONFIRM - 1, 30) if k not in (10, 11))
    assert client.status().implausible == 2 and client.status().details["implausible_workspace"] == 2


def sample(body=1, x=0.0, t_ms=0.0, valid=True, arrival_ms=None):
    t = int(t_ms * MS)
    return PoseSample(body, np.eye(3), (x, 0.0, 0.0), t, t + 4 * MS if arrival_ms is None else int(arrival_ms * MS), valid)


def confirmed(gate, body=1, x=0.0, t_ms=0.0):
    """Admit `CONFIRM` agreeing samples of a still body, the last at `t_ms`: the body is acquired."""
    for k in range(CONFIRM - 1, -1, -1):
        verdict = gate.admit(sample(body=body, x=x, t_ms=t_ms - 4 * k))
    assert verdict is None


def test_gate_one_bad_sample_never_drops_the_good_ones_after_it():
    gate = PlausibilityGate(PlausibilityLimits(max_speed_m_s=10.0))
    confirmed(gate, x=0.0, t_ms=0)
    assert "m/s" in gate.admit(sample(x=3.0, t_ms=3))  # 3 m in 3 ms
    assert gate.admit(sample(x=0.002, t_ms=6)) is None  # measured against the last accepted one
    assert gate.dropped["speed"] == 1


def test_gate_accepts_a_real_move_once_enough_time_has_passed_and_it_is_confirmed():
    gate = PlausibilityGate(PlausibilityLimits(max_speed_m_s=10.0))
    confirmed(gate, x=0.0, t_ms=0)
    assert gate.admit(sample(x=1.0, t_ms=50)) is not None  # 1 m in 50 ms: 20 m/s
    assert "re-acquiring" in gate.admit(sample(x=1.0, t_ms=110))  # 1 m in 110 ms: 9 m/s, once...
    assert "re-acquiring" in gate.admit(sample(x=1.0, t_ms=114))
    assert gate.admit(sample(x=1.0, t_ms=118)) is None  # ...and again, consistently


def test_gate_passes_invalid_samples_and_keeps_bodies_apart():
    gate = PlausibilityGate()
    confirmed(gate, body=1, x=0.0, t_ms=0)
    confirmed(gate, body=2, x=5.0, t_ms=1)
    assert gate.admit(PoseSample(1, np.full((3, 3), np.nan), (np.nan,) * 3, 2 * MS, 6 * MS, False)) is None


def test_gate_limits_are_checked():
    with pytest.raises(ValueError, match="workspace_min"):
        PlausibilityLimits(workspace_min=(0, 0, 0), workspace_max=(1, 0, 1))
    with pytest.raises(ValueError, match="max_speed_m_s"):
        PlausibilityLimits(max_speed_m_s=float("nan"))


# ------------------------------------------------------------------------------- resume timing


@pytest.mark.parametrize("unicast", [True, False], ids=["unicast", "multicast"])
def test_restarted_server_is_rejoined_and_its_new_clock_learnt_without_a_reconnect(unicast):
    """Issue 14 (resume timing): a restarted Motive has forgotten its unicast clients and its
    clock began again. While frames are missing the client connects again (unicast) and sends an
    echo every `stale_after_s`, so streaming resumes, stamped right, as soon as the new server
    answers — not at the next keep-alive, echo or link timeout (all 30 s here, so the old way
    could not pass)."""
    import dataclasses

    from firmware_mocks.natnet_server import NatNetServer

    from .test_natnet_loopback import check_against_truth

    kw = dict(stale_after_s=0.05, keepalive_interval_s=30.0, echo_interval_s=30.0, lost_after_s=30.0)
    with natnet_pair("4.1", unicast=unicast, client_kw=kw) as (world, server, client):
        assert wait_for(lambda: client.status().frames >= 20, WAIT_S)
        server.stop()
        assert wait_for(lambda: client.status().state.value == "stale", WAIT_S)
        frames = client.status().frames
        cfg = dataclasses.replace(server.config, command_port=server.command_port, server_uptime_s=100.0)  # clock back 4900 s
        with NatNetServer(world, cfg) as again:
            assert wait_for(lambda: client.status().frames > frames + 20, WAIT_S), client.status()
            assert again.commands[12] >= 1  # an echo request (ECHO_REQUEST = 12) reached the new server
            assert check_against_truth([client.latest(1)], world, again) == 1
        st = client.status()
        # exactly the restart: one-way readings read late right after it, then timely ones, are not
        # a second jump (test_clock_stamping.py::test_late_readings_after_a_restart_…)
        assert st.reconnects == 0 and st.details["clock_jumps"] == 1


def test_mock_server_restart_surface_is_what_the_driver_sees_of_a_restarted_motive():
    """The NatNet mock's `restart` (used by the soak): the same ports, frame numbers from 1, its
    clock begun again; the real client follows it and stamps its frames right."""
    from .test_natnet_loopback import check_against_truth

    kw = {"stale_after_s": 0.05, "lost_after_s": 30.0}
    with natnet_pair("4.1", unicast=True, client_kw=kw) as (world, server, client):
        assert wait_for(lambda: client.status().frames >= 300, WAIT_S)
        port, before = server.command_port, client.latest(1).frame_number
        with client.subscribe(maxlen=100_000) as sub:
            server.restart(0.1, server_uptime_s=100.0)
            assert server.command_port == port and server.restarts == 1
            frames = client.status().frames
            assert wait_for(lambda: client.status().frames > frames + 20, WAIT_S), client.status()
            got = sub.drain()
        # every sample read, not `latest`: a test thread held off the CPU for a second would find
        # the new numbers already past `before`
        restarted = [s for s in got if s.frame_number < before]
        assert restarted and check_against_truth(restarted, world, server) == len(restarted)
        assert client.status().reconnects == 0


def test_a_round_trip_that_contradicts_the_offset_restarts_the_mapping_a_backlog_does_not():
    """A Motive restarted without the link dropping: its clock begins again far behind. One-way
    evidence cannot tell that from a backlog read late (both look like slow transits), so it is
    kept; a round trip bounds the offset, and one that contradicts it restarts the mapping."""
    clock = ClockMapping(window_s=2.0)
    for k in range(10):
        clock.add_one_way(device_ns=100 * 10**9 + k * 10 * MS, arrival_ns=200 * 10**9 + k * 10 * MS + MS)
    clock.add_round_trip(sent_ns=200 * 10**9, device_ns=100 * 10**9, received_ns=200 * 10**9 + 2 * MS)
    assert clock.offset_ns == 100 * 10**9 + MS
    t = 200 * 10**9 + 200 * MS
    for k in range(5):  # a 2 s backlog read at once: slow transits, no jump
        assert clock.add_one_way(device_ns=100 * 10**9 - 2 * 10**9 + 200 * MS + k * 4 * MS, arrival_ns=t)
    clock.add_round_trip(sent_ns=t, device_ns=100 * 10**9 + 200 * MS + 400 * MS, received_ns=t + 800 * MS)  # slow, consistent
    assert clock.offset_ns == 100 * 10**9 + MS and clock.jumps == 0
    # the new server's clock reads 5 s: a 2 ms round trip says the offset is now 195.2 s
    clock.add_round_trip(sent_ns=t + 10**9, device_ns=5 * 10**9, received_ns=t + 10**9 + 2 * MS)
    assert clock.offset_ns == t + 10**9 + MS - 5 * 10**9 and clock.jumps == 1 and clock.method == "round-trip"


def test_restarted_server_frames_are_stamped_right_from_its_first_echo():
    """The same at the driver: frames of a server whose clock and frame numbers began again (no
    reconnect) are dropped until the first echo from it; then they are stamped right and its
    frame numbers, below the old ones, are taken at once (not refused as reordered)."""
    client = natnet_client()
    stream(client, range(1, 400))  # the old server: host = device + 5 s
    t = 10**12 + 5 * 10**9
    client.clock.add_round_trip(t, t - 5 * 10**9 + MS // 2, t + MS)  # its echo: a 1 ms round trip (preferred)
    h = 10**12 + 400 * PERIOD_NS + 5 * 10**9 + 200 * MS  # the new server's first frame, on the host
    new_offset = h - 10**9  # its clock read 1 s then
    before = stream(client, range(1, 3), start_ns=10**9, offset_ns=new_offset)
    assert before == [[], []]
    sent = h + 3 * MS  # the echo request the client sends while frames are missing, answered in 2 ms
    client._echoes_sent.append(sent)
    reply = struct.pack("<HHQQ", 13, 16, sent, sent + MS - new_offset)  # ECHO_RESPONSE: our stamp, its clock
    client.process_datagram(reply, arrival_ns=sent + 2 * MS)
    assert client.status().details["clock_jumps"] == 1
    after = stream(client, range(3, 20), start_ns=10**9 + 2 * PERIOD_NS, offset_ns=new_offset)
    assert all(after[CONFIRM - 1:]) and client.status().out_of_order <= 2  # re-acquired after the gap
    s = after[-1][0]
    assert s.t_arrival_ns - s.t_exposure_ns == 4 * MS + 200_000  # mid-exposure → arrival, exactly
