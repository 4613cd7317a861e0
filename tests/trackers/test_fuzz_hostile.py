"""Seeded, bounded fuzz (hypothesis, a few seconds each) of what issue 14 promised:

- the Polhemus parser loses no good record behind a corrupt one, whatever the corruption;
- the NatNet receiver, fed a clean 4.1 stream with a few mutated datagrams (any bytes, frame
  numbers, stamps, poses), never raises, never publishes an implausible sample, and publishes
  every good frame from `_RESYNC_RUN` frames after the last mutation on.
"""

from __future__ import annotations


import numpy as np
from hypothesis import HealthCheck, given, settings, strategies as st

from dpmhw.plausibility import PlausibilityLimits
from drivers.natnet import NatNetClient
from drivers.polhemus_protocol import PoseRecord, RecordParser
from drivers.tracker_base import _RESYNC_RUN
from firmware_mocks.natnet_server import FrameContent, encode_frame

from .test_serial_tracker import record_bytes

FUZZ = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
MS = 1_000_000

# ------------------------------------------------------------------------------- Polhemus

_headers = st.one_of(
    st.builds(lambda model, station, size: model + bytes([station]) + b"\x16\x00\x00" + size.to_bytes(2, "little"),
              st.sampled_from([b"LY", b"PA", b"LU"]), st.integers(0, 255), st.integers(0, 600)),
    st.builds(lambda model, station, size: model + bytes([station]) + b"C\x00\x00" + size.to_bytes(2, "little"),
              st.sampled_from([b"LY", b"PA"]), st.integers(0, 255), st.integers(0, 600)),
)
_mutation = st.one_of(
    st.tuples(st.just("overwrite"), st.lists(st.tuples(st.integers(0, 40), st.integers(0, 255)), min_size=1, max_size=6)),
    st.tuples(st.just("flip"), st.lists(st.integers(0, 41 * 8 - 1), min_size=1, max_size=4)),
    st.tuples(st.just("truncate"), st.integers(1, 40)),
    st.tuples(st.just("header"), _headers),
    st.tuples(st.just("noise"), st.binary(min_size=1, max_size=60)),
)


def _mutate_record(rec: bytes, mutation) -> bytes:
    kind, arg = mutation
    buf = bytearray(rec)
    if kind == "overwrite":
        for pos, value in arg:
            buf[pos] = value
    elif kind == "flip":
        for bit in arg:
            buf[bit // 8] ^= 1 << (bit % 8)
    elif kind == "truncate":
        buf = buf[:arg]
    elif kind == "header":  # a stray header in front of the (intact) record
        return arg
    elif kind == "noise":
        return arg
    return bytes(buf)


@FUZZ
@given(n=st.integers(4, 20), bad=st.lists(st.tuples(st.integers(0, 19), _mutation), min_size=1, max_size=3),
       chunk=st.integers(1, 64))
def test_polhemus_parser_loses_no_good_record_behind_a_corrupt_one(n, bad, chunk):
    good = [record_bytes(station=1 + k % 4, pos=(1.0 + k, 2.0, 3.0), ms=1000 + 4 * k) for k in range(n)]
    corrupt = {}
    for index, mutation in bad:
        corrupt.setdefault(index % n, mutation)
    stream = bytearray()
    for k, rec in enumerate(good):
        if k in corrupt:
            kind = corrupt[k][0]
            stream += _mutate_record(rec, corrupt[k])
            if kind in ("header", "noise"):
                stream += rec  # inserted junk: the record itself is still there
        else:
            stream += rec
    stream += bytes(41)  # line noise after the last record, so a truncated one is known bad
    parser = RecordParser()
    out = []
    for i in range(0, len(stream), chunk):
        out += parser.feed(bytes(stream[i:i + chunk]))
    got = [r.timestamp_ms for r in out if isinstance(r, PoseRecord)]
    must = [1000 + 4 * k for k in range(n) if k not in corrupt or corrupt[k][0] in ("header", "noise")]
    it = iter(got)
    assert all(ms in it for ms in must), (must, got)  # every good record, in order


# ------------------------------------------------------------------------------- NatNet

PERIOD = 2_777_778
LIMITS = PlausibilityLimits()


def _frame(k: int, *, number=None, position=None, mid=None, transmit=None) -> bytes:
    true_mid = 10**12 + k * PERIOD
    content = FrameContent(
        frame_number=1000 + k if number is None else number,
        rigid_bodies=[(1, (0.1 + 0.001 * k, 0.2, 0.3) if position is None else position, (0.0, 0.0, 0.0, 1.0), 0.0, 1)],
        stamp_mid_exposure=true_mid if mid is None else mid,
        stamp_transmit=true_mid + 4 * MS if transmit is None else transmit)
    return encode_frame(content, "4.1")


_natnet_mutation = st.one_of(
    st.tuples(st.just("bytes"), st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)), min_size=1, max_size=8)),
    st.tuples(st.just("number"), st.integers(-(2**31), 2**31 - 1)),
    st.tuples(st.just("mid"), st.integers(0, 2**63)),
    st.tuples(st.just("transmit"), st.integers(0, 2**63)),
    st.tuples(st.just("position"), st.tuples(*[st.floats(-1e7, 1e7, width=32)] * 3)),
    st.tuples(st.just("truncate"), st.integers(0, 300)),
)


@FUZZ
@given(bad=st.lists(st.tuples(st.integers(5, 34), _natnet_mutation), min_size=1, max_size=3))
def test_natnet_receiver_never_publishes_an_implausible_sample_and_recovers(bad):
    client = NatNetClient(plausibility=LIMITS)
    client.version, client.clock_hz = (4, 1), 10**9
    mutated = dict(bad)
    published = {}
    for k in range(50):
        arrival = 10**12 + k * PERIOD + 4 * MS + 100_000 + 5 * 10**9
        if k in mutated:
            kind, arg = mutated[k]
            if kind == "bytes":
                buf = bytearray(_frame(k))
                for pos, value in arg:
                    buf[pos % len(buf)] = value
                datagram = bytes(buf)
            elif kind == "truncate":
                datagram = _frame(k)[:arg]
            else:
                datagram = _frame(k, **{kind: arg})
        else:
            datagram = _frame(k)
        samples = client.process_datagram(datagram, arrival)
        assert client.internal_errors == 0, client.last_decode_error
        for s in samples:
            assert s.t_exposure_ns - s.t_arrival_ns <= LIMITS.max_future_s * 1e9
            assert s.t_arrival_ns - s.t_exposure_ns <= LIMITS.max_age_s * 1e9
            if s.valid:
                assert np.all(np.abs(s.translation) <= 20.0)
        published[k] = bool(samples)
    last_bad = max(mutated)
    assert all(published[k] for k in range(last_bad + _RESYNC_RUN, 50)), (bad, published)
