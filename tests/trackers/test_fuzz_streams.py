"""Seeded stream fuzz of the tracker drivers: genuine frames or records of a moving body, with
mutated copies of them (and, for NatNet, server infos) between them, fed straight into the
drivers with modelled arrival times (no sockets, no wall clock).

What must hold, for a loop that blanks the output when its newest pose is older than 50 ms:
- NatNet: dark for at most 1 % of the run, and no published pose more than 1 cm off the truth
  at the instant it claims to describe;
- serial (Polhemus binary, no checksum): no published pose more than 1 cm off, at most 0.5 % of
  the genuine records lost, dark for at most 5 % of the run.

The default suite runs a few thousand datagrams and records per seed; the `slow` versions run
100,000 (the figures the drivers are held to).
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from drivers.natnet import NatNetClient
from drivers.serial_tracker import PolhemusTracker
from firmware_mocks.natnet_server import FrameContent, encode_frame
from firmware_mocks.world import make_trajectory

from .test_serial_tracker import record_bytes
from .test_tracker_gates import server_info

MS = 1_000_000
STALE_NS = 50 * MS  # the loop's default `stale_after_ms`
WRONG_M = 0.01
# a hand-held pace: 0.3 m at 1 Hz (up to 1.9 m/s, 12 m/s²) while spinning at π rad/s
TRAJECTORY = make_trajectory("rotate-oscillate", speed=2.0)


def truth(t_s: float) -> np.ndarray:
    return np.array(TRAJECTORY.pose_floats(t_s)[1])


def quat_xyzw(t_s: float) -> tuple[float, float, float, float]:
    r = np.array(TRAJECTORY.pose_floats(t_s)[0]).reshape(3, 3)  # about +Y
    half = np.arctan2(r[0, 2], r[0, 0]) / 2
    return 0.0, float(np.sin(half)), 0.0, float(np.cos(half))


class Dark:
    """Time during which the newest published pose is older than `STALE_NS`, sampled at every
    genuine arrival (the instants the loop would look)."""

    def __init__(self):
        self.newest_ns: int | None = None
        self.dark_ns = 0
        self.last_ns: int | None = None

    def observe(self, now_ns: int, published) -> None:
        for s in published:
            if s.valid and (self.newest_ns is None or s.t_exposure_ns > self.newest_ns):
                self.newest_ns = s.t_exposure_ns
        if self.last_ns is not None and (self.newest_ns is None or now_ns - self.newest_ns > STALE_NS):
            self.dark_ns += now_ns - self.last_ns
        self.last_ns = now_ns


# ------------------------------------------------------------------------------- NatNet

PERIOD_360 = 2_777_778
OFFSET_NS = 5 * 10**9  # host = server clock (1 GHz ticks) + this


def _natnet_frame(number: int, mid: int, t_s: float, *, position=None, transmit=None) -> bytes:
    content = FrameContent(
        frame_number=number,
        rigid_bodies=[(1, tuple(truth(t_s)) if position is None else position, quat_xyzw(t_s), 0.0005, 1)],
        stamp_mid_exposure=mid, stamp_transmit=mid + 4 * MS if transmit is None else transmit)
    return encode_frame(content, "4.1")


def _natnet_mutant(rng: np.random.Generator, number: int, mid: int, t_s: float) -> bytes:
    kind = rng.integers(9)
    if kind == 0:  # a server info: the clock changed, another version, or bytes flipped
        info = bytearray(server_info(int(10**9 * rng.choice([2, 0.5, 1.001])), ((3, 0), (4, 1), (4, 2))[rng.integers(3)]))
        for _ in range(rng.integers(0, 3)):
            info[rng.integers(len(info))] ^= 1 << rng.integers(8)
        return bytes(info)
    if kind == 1:  # frame number a little or far ahead, the pose off
        return _natnet_frame(number + int(rng.choice([1, 2, 3, 1000, -5])), mid, t_s,
                             position=tuple(truth(t_s) + rng.normal(0, 0.05, 3)))
    if kind == 2:  # stamps moved
        shift = int(rng.choice([-1, 1]) * rng.choice([10**3, 10**5, 10**6, 10**7, 10**9, 2**40]))
        return _natnet_frame(number, max(1, mid + shift), t_s, transmit=max(1, mid + shift) + 4 * MS)
    if kind == 3:  # the pose moved by 1 mm ... 1 m
        return _natnet_frame(number, mid, t_s, position=tuple(truth(t_s) + rng.normal(0, 10.0 ** rng.uniform(-3, 0), 3)))
    datagram = bytearray(_natnet_frame(number, mid, t_s))
    if kind in (4, 5):  # bit flips
        for _ in range(rng.integers(1, 4)):
            datagram[rng.integers(len(datagram))] ^= 1 << rng.integers(8)
    elif kind == 6:  # bytes overwritten
        for _ in range(rng.integers(1, 6)):
            datagram[rng.integers(len(datagram))] = rng.integers(256)
    elif kind == 7:  # truncated
        datagram = datagram[:rng.integers(len(datagram))]
    else:  # 13,000 empty marker sets ... and a wrong tail
        sets = b"\0\0\0\0\0" * 13_000
        payload = (struct.pack("<i", number) + struct.pack("<ii", 13_000, len(sets)) + sets + struct.pack("<ii", 0, 0) * 7
                   + struct.pack("<IIdQQQIIhi", 0, 0, 0.0, mid, mid, mid + 4 * MS, 0, 0, 0, int(rng.integers(1, 9))))
        return struct.pack("<HH", 7, len(payload)) + payload
    return bytes(datagram)


def run_natnet(datagrams: int, seed: int) -> dict:
    """Half genuine frames at 360 Hz, half mutants between them (1 in 9 a server info)."""
    rng = np.random.default_rng(seed)
    client = NatNetClient()
    client._info_requested_ns = 10**12  # the handshake: the reply to its own connect request
    client.process_datagram(server_info(10**9), arrival_ns=10**12 + MS)
    assert client.clock_hz == 10**9
    dark, wrong, published_total, genuine = Dark(), [], 0, 0
    k = 0
    sent = 0
    while sent < datagrams:
        number, mid = 1000 + k, 10**12 + k * PERIOD_360
        t_s = mid / 1e9
        arrival = mid + OFFSET_NS + 4 * MS + 100_000 + int(rng.exponential(200_000))
        out = client.process_datagram(_natnet_frame(number, mid, t_s), arrival)
        sent, genuine = sent + 1, genuine + 1
        for _ in range(rng.poisson(1.0)):
            out += client.process_datagram(_natnet_mutant(rng, number, mid, t_s), arrival + int(rng.integers(0, 2 * MS)))
            sent += 1
        for s in out:
            if s.valid:
                error = np.linalg.norm(s.translation - truth((s.t_exposure_ns - OFFSET_NS) / 1e9))
                if error > WRONG_M:
                    wrong.append((s.frame_number, error))
        published_total += len(out)
        dark.observe(arrival, out)
        k += 1
    run_ns = dark.last_ns - (10**12 + OFFSET_NS)
    st = client.status()
    return dict(wrong=wrong, dark=dark.dark_ns / run_ns, published=published_total, genuine=genuine, status=st,
                internal=client.internal_errors, unsolicited=client.unsolicited_server_info, clock_hz=client.clock_hz)


def _check_natnet(r: dict) -> None:
    assert r["internal"] == 0, r["status"].details["last_decode_error"]
    assert r["wrong"] == [], r["wrong"][:10]
    assert r["dark"] <= 0.01, (r["dark"], r["status"])
    assert r["clock_hz"] == 10**9 and r["unsolicited"] > 0  # every server info was unsolicited, none applied


@pytest.mark.parametrize("seed", [1, 2])
def test_natnet_fuzz_with_server_infos(seed):
    _check_natnet(run_natnet(3000, seed))


@pytest.mark.slow
def test_natnet_fuzz_100k():
    _check_natnet(run_natnet(100_000, 31))


# ------------------------------------------------------------------------------- serial

SCALE_CM = 100.0


def _record(ms: int) -> bytes:
    """The genuine record stamped `ms` (device time = the trajectory's time)."""
    t_s = ms / 1000
    _, qy, _, qw = quat_xyzw(t_s)
    return record_bytes(station=1, pos=tuple(truth(t_s) * SCALE_CM), quat_wxyz=(qw, 0.0, qy, 0.0), ms=ms)


def _serial_mutant(rng: np.random.Generator, stamps: list[int], k: int) -> bytes:
    ms = stamps[max(0, k - int(rng.integers(0, 2)))]  # a corrupted copy of a record already sent (this or the one before)
    rec = bytearray(_record(ms))
    kind = rng.integers(6)
    if kind == 0:  # bit flips anywhere
        for _ in range(rng.integers(1, 4)):
            rec[rng.integers(len(rec))] ^= 1 << rng.integers(8)
    elif kind == 1:  # bytes overwritten
        for _ in range(rng.integers(1, 5)):
            rec[rng.integers(len(rec))] = rng.integers(256)
    elif kind == 2:  # a bit of the position or the stamp flipped
        field = rng.choice([8, 12, 16, 36])
        bit = rng.integers(32)
        word = int.from_bytes(rec[field:field + 4], "little") ^ (1 << int(bit))
        rec[field:field + 4] = word.to_bytes(4, "little")
    elif kind == 3:  # truncated
        rec = rec[:rng.integers(1, len(rec))]
    elif kind == 4:  # a who-am-I cut short
        text = b"Polhemus LIBERTY, 2 stations\r\n"
        rec = bytearray(b"LY\x00\x16\x00\x00" + len(text).to_bytes(2, "little") + text[:-int(rng.integers(1, 4))])
    else:  # line noise
        rec = bytearray(rng.integers(0, 256, rng.integers(1, 50), dtype=np.uint8).tobytes())
    return bytes(rec)


def run_serial(genuine: int, seed: int, mutants_per_record: float = 2.0) -> dict:
    """Genuine 240 Hz records of station 1; about `mutants_per_record` mutated ones between each
    two; bytes read in chunks of 1–64 at modelled arrival times."""
    rng = np.random.default_rng(seed)
    tracker = PolhemusTracker("loop://", warmup_records=16)
    stamps = [10_000 + round(k * 1000 / 240) for k in range(genuine)]
    pending = bytearray()
    dark, wrong, delivered = Dark(), [], set()
    t0 = 10**9
    for k, ms in enumerate(stamps):
        pending += _record(ms)
        for _ in range(rng.poisson(mutants_per_record)):
            pending += _serial_mutant(rng, stamps, k)
        arrival = t0 + ms * MS + 4 * MS + int(rng.exponential(300_000))
        out = []
        while pending:  # the reader takes what the port holds in pieces
            n = int(rng.integers(1, 65))
            out += tracker.process_bytes(bytes(pending[:n]), arrival_ns=arrival)
            del pending[:n]
        for s in out:
            if s.valid:  # against the truth at the instant its stamp claims (device ms = host - t0 - 4 ms transit)
                claimed_s = (s.t_exposure_ns + tracker.device_latency_ns - t0 - 4 * MS) / 1e9
                error = np.linalg.norm(s.translation - truth(claimed_s))
                if error > WRONG_M:
                    wrong.append((s.frame_number, error))
                delivered.add(s.frame_number)
        if k >= tracker.warmup_records:
            dark.observe(arrival, out)
    counted = stamps[tracker.warmup_records + 2:]  # after the warm-up and the body's acquisition
    lost = [ms for ms in counted if ms not in delivered]
    run_ns = dark.last_ns - (t0 + stamps[tracker.warmup_records] * MS)
    return dict(wrong=wrong, lost=len(lost) / len(counted), dark=dark.dark_ns / run_ns, status=tracker.status(),
                internal=tracker.internal_errors)


def _check_serial(r: dict) -> None:
    assert r["internal"] == 0
    assert r["wrong"] == [], r["wrong"][:10]
    assert r["lost"] <= 0.005, (r["lost"], r["status"])
    assert r["dark"] <= 0.05, (r["dark"], r["status"])


@pytest.mark.parametrize("seed", [1, 2])
def test_serial_fuzz_between_genuine_240_hz_records(seed):
    _check_serial(run_serial(1500, seed))


@pytest.mark.slow
def test_serial_fuzz_100k_mutants():
    _check_serial(run_serial(50_000, 31))
