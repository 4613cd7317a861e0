"""What a tracker driver takes on trust, and what it does not: server infos it did not ask for,
frames that take the number of the genuine ones, stamps that go back, records cut short, and
poses a corruption moved.

The drivers are fed bytes built from the protocol description with explicit arrival times (no
sockets, no wall clock), except the one loopback test of a restarted server.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from dpmhw.plausibility import PlausibilityGate, PlausibilityLimits
from dpmhw.session.testing import wait_for
from dpmhw.tracking import LatestPoses, PoseSample, TrackerState
from drivers.natnet_protocol import NatNetDecodeError, decode_frame_poses
from drivers.polhemus_protocol import PolhemusDecodeError, PoseRecord, RecordParser, TextRecord
from drivers.serial_tracker import PolhemusTracker

from .conftest import with_state_log
from .test_hostile_trackers import CONFIRM, MS, PERIOD_NS, WAIT_S, frame, natnet_client, stream
from .test_serial_tracker import record_bytes

# ------------------------------------------------------------------------------- NatNet server info


def server_info(clock_hz: int, version=(4, 1), name=b"Motive") -> bytes:
    """A SERVER_INFO datagram packed from the protocol description."""
    payload = (name.ljust(256, b"\0") + bytes((3, 1, 0, 0)) + bytes((*version, 0, 0))
               + struct.pack("<QHB4B", clock_hz, 1511, 0, 239, 255, 42, 99))
    return struct.pack("<HH", 1, len(payload)) + payload


def handshaken(clock_hz=10**9):
    """A client whose own connect request the server answered (NatNet 4.1)."""
    client = natnet_client()
    client.server_info = None
    client._info_requested_ns = 10**12 - MS
    client.process_datagram(server_info(clock_hz), arrival_ns=10**12)
    assert client.server_info.clock_hz == clock_hz and client.unsolicited_server_info == 0
    return client


def test_an_unsolicited_server_info_is_counted_and_ignored():
    """From the server's own address and port, with the clock doubled: before, every stamp after
    it was wrong by 2x and the loop went dark for seconds."""
    client = handshaken()
    first = stream(client, range(1, 50))
    client.process_datagram(server_info(2 * 10**9), arrival_ns=10**12 + 5 * 10**9 + 50 * PERIOD_NS)
    after = stream(client, range(50, 100), start_ns=10**12 + 49 * PERIOD_NS)
    assert client.clock_hz == 10**9 and client.status().details["unsolicited_server_info"] == 1
    assert all(first[CONFIRM - 1:]) and all(after)
    s = after[-1][0]
    assert s.t_arrival_ns - s.t_exposure_ns == 4 * MS  # still stamped on the 1 GHz clock (mid-exposure → transmit)


def test_a_reply_long_after_the_request_is_unsolicited():
    client = handshaken()
    client._info_requested_ns = 10**12
    client.process_datagram(server_info(10**9), arrival_ns=10**12 + int(client.connect_timeout_s * 1e9) + 1)
    assert client.unsolicited_server_info == 1


def test_a_solicited_server_info_with_a_new_clock_ends_the_session_instead_of_being_applied():
    client = handshaken()
    stream(client, range(1, 20))
    t = 10**12 + 5 * 10**9 + 20 * PERIOD_NS
    client._info_requested_ns = t
    client.process_datagram(server_info(10**9), arrival_ns=t + MS)  # the same settings: nothing to do
    assert client._rehandshake == "" and client.unsolicited_server_info == 0
    client._info_requested_ns = t + 2 * MS
    client.process_datagram(server_info(2 * 10**9), arrival_ns=t + 3 * MS)
    assert client.clock_hz == 10**9  # not applied under the running stream...
    assert "clock 1000000000 → 2000000000 Hz" in client._rehandshake  # ...the session ends with this reason
    assert stream(client, range(20, 25), start_ns=10**12 + 20 * PERIOD_NS) == [[]] * 5  # nothing stamped on it


@pytest.mark.parametrize("unicast", [True, False], ids=["unicast", "multicast"])
def test_a_server_restarted_with_another_clock_is_handshaken_again(unicast):
    """Loopback: Motive restarts with its clock at twice the rate; the client's connect probe while
    frames are missing gets the new server info, and the client handshakes again instead of
    stamping frames with the old rate (every stamp would be wrong)."""
    from .test_natnet_loopback import check_against_truth, natnet_pair

    logged = with_state_log(type(natnet_client()))
    kw = dict(stale_after_s=0.05, lost_after_s=30.0, backoff_initial_s=0.05)
    with natnet_pair("4.1", unicast=unicast, client_kw=kw, client_cls=logged) as (world, server, client):
        assert wait_for(lambda: client.status().frames >= 20, WAIT_S)
        server.restart(0.1, server_uptime_s=100.0, clock_hz=2 * server.config.clock_hz)
        assert wait_for(lambda: client.was(TrackerState.LOST, "server info changed"), WAIT_S), client.states
        assert wait_for(lambda: client.clock_hz == server.config.clock_hz, WAIT_S)
        with client.subscribe(maxlen=10_000) as sub:
            frames = client.status().frames
            assert wait_for(lambda: client.status().frames > frames + 20, WAIT_S), client.status()
            got = sub.drain()
        assert got and check_against_truth(got, world, server) == len(got)


# ------------------------------------------------------------------------------- NatNet frame numbers


def test_implausible_frames_ahead_do_not_take_the_frame_number_of_the_genuine_ones():
    """Frames numbered +1/+2 ahead of the stream, with a pose 20 cm off, interleaved with the
    genuine ones for 0.5 s: the gate drops them, and they must not make the genuine frames behind
    them look reordered (before: 185 genuine frames refused, dark for a second)."""
    client = natnet_client()
    genuine = stream(client, range(1, 4))  # the body acquired
    out, offset, t0 = [], 5 * 10**9, 10**12 + 3 * PERIOD_NS
    for k in range(180):  # 0.5 s at 360 Hz
        mid = t0 + k * PERIOD_NS
        n = 4 + k
        bogus = frame(n + 1 + k % 2, (0.3, 0.2, 0.3), mid_ns=mid + PERIOD_NS // 2)
        assert client.process_datagram(bogus, arrival_ns=mid + PERIOD_NS // 2 + 4 * MS + offset) == []
        out.append(client.process_datagram(frame(n, mid_ns=mid), arrival_ns=mid + 4 * MS + 200_000 + offset))
    assert all(genuine[CONFIRM - 1:]) and all(out), [k for k, o in enumerate(out) if not o]
    st = client.status()
    assert st.out_of_order == 0 and st.implausible == 180 and st.frames_missed == 0


def test_refusing_a_malformed_datagram_does_not_walk_what_its_tail_already_refutes(monkeypatch):
    """A 64 KB NatNet 4.1 datagram of 13,000 empty marker sets and a wrong end-of-data tag is
    refused from its section byte counts and its tail, without visiting one marker set."""
    from drivers import natnet_protocol

    sets = (b"\0" + struct.pack("<i", 0)) * 13_000
    empty = struct.pack("<ii", 0, 0)
    payload = (struct.pack("<i", 1) + struct.pack("<ii", 13_000, len(sets)) + sets + empty * 7
               + struct.pack("<IIdQQQIIhi", 0, 0, 0.0, 1, 2, 3, 0, 0, 0, 7))
    visited = []
    real_string = natnet_protocol._Reader.string
    monkeypatch.setattr(natnet_protocol._Reader, "string", lambda self, *a, **k: visited.append(1) or real_string(self, *a, **k))
    with pytest.raises(NatNetDecodeError, match="end-of-data tag"):
        decode_frame_poses(payload, (4, 1))
    assert visited == []


# ------------------------------------------------------------------------------- serial stamps


def polhemus(**kw) -> PolhemusTracker:
    return PolhemusTracker("loop://", warmup_records=0, **kw)


def feed(tracker, records, t0_ns=10**9):
    """(ms, position cm) records of station 1, each arriving 4 ms after it was made."""
    return [tracker.process_bytes(record_bytes(pos=pos, ms=ms), arrival_ns=t0_ns + ms * MS + 4 * MS) for ms, pos in records]


def moving(ms):  # 1 m/s along x, in centimetres
    return (10.0 + 0.1 * ms, 20.0, 30.0)


def test_a_past_stamp_never_replaces_a_newer_sample():
    """A timestamp bit flip 50 ms into the past: before, it was published and became the newest
    sample, so the loop saw a stale pose and went dark."""
    tracker = polhemus()
    stamps = [1000 + round(k * 1000 / 240) for k in range(40)]
    out = feed(tracker, [(ms, moving(ms)) for ms in stamps[:30]])
    newest = tracker.latest(1)
    past = stamps[29] - 50
    assert tracker.process_bytes(record_bytes(pos=moving(past), ms=past), arrival_ns=10**9 + stamps[29] * MS + 5 * MS) == []
    assert tracker.latest(1) is newest and tracker.status().out_of_order == 1
    out += feed(tracker, [(ms, moving(ms)) for ms in stamps[30:]])
    assert all(out[CONFIRM - 1:]) and tracker.latest(1).frame_number == stamps[-1]


def test_a_device_clock_that_began_again_is_followed_after_a_run_of_records():
    tracker = polhemus()
    feed(tracker, [(5000 + 4 * k, (10.0, 20.0, 30.0)) for k in range(10)])
    # the device restarted (its clock reads 0 again) a minute later on the host
    restarted = [(4 * k, 10**9 + 60_000 * MS + 4 * k * MS) for k in range(20)]
    after = [tracker.process_bytes(record_bytes(pos=(10.0, 20.0, 30.0), ms=ms), arrival_ns=t) for ms, t in restarted[:10]]
    st = tracker.status()
    assert st.details["frame_resyncs"] == 1 and st.out_of_order == 2  # two refused, then the run is followed
    # its records pass the stamp check now, but the mapping still holds the old clock (one-way
    # evidence cannot tell a clock that went back from slow transits, and refused records do not
    # feed it): they read a minute old until the session reconnects and the mapping restarts
    assert not any(after) and st.details["implausible_timestamp"] == 8
    tracker.clock.reset()
    after = [tracker.process_bytes(record_bytes(pos=(10.0, 20.0, 30.0), ms=ms), arrival_ns=t) for ms, t in restarted[10:]]
    assert all(after[CONFIRM - 1:]) and tracker.latest(1).frame_number == 76


def test_latest_poses_never_makes_an_older_sample_the_newest():
    poses = LatestPoses()
    newer = PoseSample(1, np.eye(3), (0.0, 0.0, 0.0), 20 * MS, 21 * MS, True)
    older = PoseSample(1, np.eye(3), (0.0, 0.0, 0.0), 10 * MS, 22 * MS, True)
    assert poses.publish([newer]) == [newer] and poses.publish([older]) == []
    assert poses.latest(1) is newer and poses.older_dropped == 1


# ------------------------------------------------------------------------------- serial resync


@pytest.mark.parametrize("cut", [1, 2, 3, 5])
def test_a_who_am_i_reply_cut_short_does_not_eat_the_next_record(cut):
    """Its declared body then takes the next record's "LY" (printable) as text: before, the rest
    of that record was lost as garbage."""
    text = b"Polhemus LIBERTY, 2 stations\r\n"
    reply = b"LY\x00\x16\x00\x00" + len(text).to_bytes(2, "little") + text[:-cut]
    stream_ = reply + b"".join(record_bytes(ms=10 + 4 * k) for k in range(3))
    for chunk in (1, 7, len(stream_)):
        parser, out = RecordParser(), []
        for i in range(0, len(stream_), chunk):
            out += parser.feed(stream_[i:i + chunk])
        assert [o.timestamp_ms for o in out if isinstance(o, PoseRecord)] == [10, 14, 18]
        assert isinstance(out[0], PolhemusDecodeError) and not any(isinstance(o, TextRecord) for o in out)


def test_a_who_am_i_text_naming_the_model_is_still_text():
    text = b"PATRIOT PA LY 2 stations\r\n"  # preambles inside the text, none followed by a pose header
    reply = b"PA\x00\x16\x00\x00" + len(text).to_bytes(2, "little") + text
    out = RecordParser().feed(reply + record_bytes(model=b"PA", ms=5))
    assert isinstance(out[0], TextRecord) and out[0].text == text.decode() and out[1].timestamp_ms == 5


# ------------------------------------------------------------------------------- the gate's bound


def test_a_record_moved_by_a_corruption_is_refused_at_240_hz_and_costs_no_genuine_one():
    """At 1 m/s and 240 Hz the gate allows 2.9 mm off the predicted position (2 × 1 mm noise +
    ½ · 100 m/s² · (4.2 ms)²): a record moved 1 cm by a corrupted byte is refused; the genuine
    ones around it are all published."""
    tracker = polhemus()
    stamps = [1000 + round(k * 1000 / 240) for k in range(60)]
    out = []
    for k, ms in enumerate(stamps):
        if k == 30:  # a corrupt copy of this record, 1 cm off, arrives first
            x, y, z = moving(ms)
            assert tracker.process_bytes(record_bytes(pos=(x, y + 1.0, z), ms=ms), arrival_ns=10**9 + ms * MS + 4 * MS) == []
        out += feed(tracker, [(ms, moving(ms))])
    assert all(out[CONFIRM - 1:]) and tracker.status().details["implausible_jump"] == 1


def test_a_slightly_off_sample_the_bound_lets_through_costs_no_genuine_one():
    """Within the bound (2 mm) a corruption is accepted (harmless); the genuine sample after it
    does not fit its skewed prediction, but fits the one before, so it is not refused."""
    gate = PlausibilityGate()
    for k in range(10):
        assert gate.admit(sample_at(k, x=0.004 * k)) is None or k < CONFIRM - 1
    assert gate.admit(sample_at(10, x=0.004 * 10 + 0.0028)) is None  # off by 2.8 mm: let through
    assert gate.admit(sample_at(11, x=0.004 * 11)) is None
    assert gate.admit(sample_at(12, x=0.004 * 12)) is None and gate.refused == 0


def test_after_a_gap_one_corrupt_sample_is_never_taken_alone():
    """100 ms unseen: the allowed deviation (25 cm) is far above `max_jump_m`, so the body is
    re-acquired from samples that agree; a lone one 5 cm off is not published."""
    gate = PlausibilityGate()
    for k in range(5):
        gate.admit(sample_at(k, x=0.0))
    assert "re-acquiring" in gate.admit(sample_at(30, x=0.05))  # the corrupt one
    assert "re-acquiring" in gate.admit(sample_at(31, x=0.0))  # the genuine ones must agree...
    assert "re-acquiring" in gate.admit(sample_at(32, x=0.0))
    assert gate.admit(sample_at(33, x=0.0)) is None  # ...three in a row


def test_a_rotation_a_corruption_turned_is_refused():
    gate = PlausibilityGate()
    for k in range(5):
        gate.admit(sample_at(k, x=0.0))
    turned = PoseSample(1, _about_z(0.05), (0.0, 0.0, 0.0), 5 * PERIOD_240, 5 * PERIOD_240 + 4 * MS, True)
    assert "°" in gate.admit(turned) and gate.dropped["rotation"] == 1  # 2.9° in 4 ms: 12 rad/s from rest


def test_a_steady_fast_spin_is_taken_and_a_sudden_stop_in_it_refused():
    """At 20 rad/s (within the speed bound) each 240-Hz sample turns 0.083 rad, far beyond the
    0.015 rad the angular-acceleration bound allows around the turn the motion predicts: the gate
    must predict the turn to take them, and refuse a sample that stops turning."""
    def sample(k, turned_k):  # the k-th 240-Hz sample, turned as far as the spin had at sample turned_k
        return PoseSample(1, _about_z(20.0 * turned_k * PERIOD_240 / 1e9), (0.0, 0.0, 0.0), k * PERIOD_240,
                          k * PERIOD_240 + 4 * MS, True)

    gate = PlausibilityGate()
    held = PlausibilityLimits().confirm - 1  # the first samples agree before the body is taken
    answers = [gate.admit(sample(k, k)) for k in range(40)]
    assert all("re-acquiring" in a for a in answers[:held]) and answers[held:] == [None] * (40 - held)
    assert "from the orientation its turning predicts" in gate.admit(sample(40, 39))  # stopped turning


PERIOD_240 = round(1e9 / 240)


def sample_at(k, x):
    t = k * PERIOD_240
    return PoseSample(1, np.eye(3), (x, 0.0, 0.0), t, t + 4 * MS, True)


def _about_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_limits_name_the_bad_field():
    with pytest.raises(ValueError, match="max_accel_m_s2"):
        PlausibilityLimits(max_accel_m_s2=0.0)
    with pytest.raises(ValueError, match="confirm"):
        PlausibilityLimits(confirm=0)
