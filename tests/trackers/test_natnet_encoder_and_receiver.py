"""The mock's independent NatNet encoder against real bytes and the driver's decoder, and the
receiver's handling of random and mutated datagrams (hypothesis)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dpmhw.plausibility import PlausibilityLimits
from drivers.natnet import NatNetClient
from drivers.natnet_protocol import (
    SUPPORTED_VERSIONS,
    NatNetDecodeError,
    decode_frame,
    decode_model_definitions,
    split_message,
)
from firmware_mocks.natnet_server import FrameContent, encode_frame, encode_model_definitions
from firmware_mocks.world import World

from .conftest import captured
from .test_natnet_protocol import _assert_poses_decode_agrees

def _rb_tuples(rb):
    return [
        (int(i), tuple(map(float, p)), tuple(map(float, q)), float(e), int(f))
        for i, p, q, e, f in zip(rb.ids, rb.positions, rb.quaternions, rb.mean_errors, rb.params)
    ]


def _content_from_decoded(frame) -> FrameContent:
    lm = frame.labeled_markers
    return FrameContent(
        frame_number=frame.frame_number,
        marker_sets=list(frame.marker_sets.items()),
        unlabeled_markers=frame.unlabeled_markers,
        rigid_bodies=_rb_tuples(frame.rigid_bodies),
        skeletons=[(k, _rb_tuples(v)) for k, v in frame.skeletons.items()],
        labeled_markers=[
            (int(i), tuple(map(float, p)), float(s), int(f), float(r))
            for i, p, s, f, r in zip(lm.ids, lm.positions, lm.sizes, lm.params, lm.residuals)
        ],
        timecode=frame.timecode,
        timecode_subframe=frame.timecode_subframe,
        timestamp_s=frame.timestamp_s,
        stamp_mid_exposure=frame.stamp_mid_exposure,
        stamp_data_received=frame.stamp_data_received,
        stamp_transmit=frame.stamp_transmit,
        params=frame.params,
    )


@pytest.mark.parametrize("name", ["mocapframe_packet_v3.bin", "mocapframe_packet_occluded_v3.bin"])
def test_mock_encoder_reproduces_real_motive_bytes(name):
    """The mock, fed the values of a real capture, emits the captured datagram byte for byte."""
    datagram = captured(name)
    _, payload = split_message(datagram)
    frame = decode_frame(payload, (3, 0))
    assert encode_frame(_content_from_decoded(frame), "3.0") == datagram


finite = st.floats(-10, 10, allow_nan=False, width=32)
vec3 = st.tuples(finite, finite, finite)
rigid_body = st.tuples(st.integers(-(2**31), 2**31 - 1), vec3, st.tuples(finite, finite, finite, finite), finite, st.integers(-(2**15), 2**15 - 1))
marker = st.tuples(st.integers(-(2**31), 2**31 - 1), vec3, finite, st.integers(-(2**15), 2**15 - 1), finite)
channels = st.lists(st.lists(finite, max_size=4).map(lambda v: np.array(v, np.float32)), max_size=3)
frames = st.builds(
    FrameContent,
    frame_number=st.integers(0, 2**31 - 1),
    marker_sets=st.lists(
        st.tuples(st.text(st.characters(min_codepoint=33, max_codepoint=0x2FF), max_size=8), st.lists(vec3, max_size=3).map(lambda m: np.array(m, np.float32).reshape(-1, 3))),
        max_size=3,
        unique_by=lambda t: t[0],
    ),
    unlabeled_markers=st.lists(vec3, max_size=3).map(lambda m: np.array(m, np.float32).reshape(-1, 3)),
    rigid_bodies=st.lists(rigid_body, max_size=4),
    skeletons=st.lists(st.tuples(st.integers(0, 100), st.lists(rigid_body, max_size=2)), max_size=2, unique_by=lambda t: t[0]),
    assets=st.lists(st.tuples(st.integers(0, 100), st.lists(rigid_body, max_size=2), st.lists(marker, max_size=2)), max_size=2),
    labeled_markers=st.lists(marker, max_size=4),
    force_plates=st.lists(st.tuples(st.integers(0, 9), channels), max_size=2, unique_by=lambda t: t[0]),
    devices=st.lists(st.tuples(st.integers(0, 9), channels), max_size=2, unique_by=lambda t: t[0]),
    timecode=st.integers(0, 2**32 - 1),
    timestamp_s=st.floats(0, 1e6),
    stamp_mid_exposure=st.integers(0, 2**63),
    stamp_transmit=st.integers(0, 2**63),
    precision_timestamp=st.tuples(st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1)),
    params=st.integers(0, 2**15 - 1),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(content=frames, version=st.sampled_from(SUPPORTED_VERSIONS))
def test_mock_encoder_and_driver_decoder_agree(content, version):
    if version < (4, 1):
        content.assets = []  # assets exist on the wire from 4.1 only
    _, payload = split_message(encode_frame(content, version))
    frame = decode_frame(payload, version)
    assert frame.frame_number == content.frame_number
    assert _rb_tuples(frame.rigid_bodies) == [
        (i, tuple(np.float32(p).tolist()), tuple(np.float32(q).tolist()), float(np.float32(e)), f)
        for i, p, q, e, f in content.rigid_bodies
    ]
    assert list(frame.marker_sets) == [name for name, _ in content.marker_sets]
    assert len(frame.assets) == len(content.assets)
    assert sorted(frame.skeletons) == sorted(k for k, _ in content.skeletons)
    assert [len(c) for c in frame.force_plates.values()] == [len(c) for _, c in content.force_plates]
    assert frame.stamp_mid_exposure == content.stamp_mid_exposure
    assert frame.params == content.params
    assert (frame.precision_timestamp is not None) == (version >= (4, 1))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(content=frames, version=st.sampled_from(SUPPORTED_VERSIONS),
       edits=st.lists(st.tuples(st.integers(0, 2000), st.integers(0, 255)), max_size=3))
def test_poses_decode_agrees_with_the_full_decode_on_every_version(content, version, edits):
    """The receiver's poses-only decode against the full one, on encoded frames of every layout
    (sized sections, skeletons, assets, channels), intact or with a few bytes changed."""
    if version < (4, 1):
        content.assets = []
    _, payload = split_message(encode_frame(content, version))
    buf = bytearray(payload)
    for pos, value in edits:
        buf[pos % len(buf)] = value
    _assert_poses_decode_agrees(bytes(buf), version)


@pytest.mark.parametrize("version", SUPPORTED_VERSIONS)
def test_mock_model_definitions_decode_to_world_names(version):
    world = World.demo("circular", count=3)
    _, payload = split_message(encode_model_definitions(world, version))
    defs = decode_model_definitions(payload, version)
    assert defs.rigid_body_names() == {1: "circular_1", 2: "circular_2", 3: "circular_3"}
    rb = defs.rigid_bodies[1]
    np.testing.assert_allclose(rb.marker_positions, world.objects[2].markers, atol=1e-7)
    assert (rb.marker_names != ()) == (version >= (4, 0))
    assert (rb.offset_rotation is not None) == (version >= (4, 2))


# ---------------------------------------------------------------- the receiver under fuzzing


def primed_client() -> NatNetClient:
    """A client that has seen the real server info (NatNet 3.0, 3,312,787 Hz) but no socket; its
    gate takes a body's first sample on its own (these tests decode single frames)."""
    client = NatNetClient(plausibility=PlausibilityLimits(confirm=1))
    client._info_requested_ns = 0  # the reply to its own connect request (the only kind it applies)
    client.process_datagram(captured("serverinfo_packet_v3.bin"), 0)
    assert client.version == (3, 0) and client.clock_hz == 3_312_787
    return client


def test_real_frame_through_the_receiver():
    client = primed_client()
    datagram = captured("mocapframe_packet_v3.bin")
    _, payload = split_message(datagram)
    transmit = decode_frame(payload, (3, 0)).stamp_transmit
    arrival = 10**12
    samples = client.process_datagram(datagram, arrival)
    assert len(samples) == 1 and samples[0].rigid_body_id == 2 and samples[0].valid
    # with one-way evidence only, arrival is mapped to transmit: latency = Motive's 5.50 ms
    assert samples[0].latency_ns / 1e6 == pytest.approx(5.50, abs=0.01)
    assert abs(client.clock.to_host_ns(transmit * 10**9 // 3_312_787) - arrival) <= 1
    assert client.status().frames == 1 and client.status().malformed == 0


def _mutate(datagram: bytes, edits, cut, kind) -> bytes:
    buf = bytearray(datagram)
    if kind == "truncate":
        buf = buf[: cut % len(buf)]
    elif kind == "truncate-fix-header":
        buf = buf[: max(4, cut % len(buf))]
        struct.pack_into("<H", buf, 2, len(buf) - 4)
    for pos, value in edits:
        if kind == "insert":
            buf.insert(pos % (len(buf) + 1), value)
        elif kind != "truncate" and buf:
            buf[pos % len(buf)] = value
    return bytes(buf)


datagrams = st.one_of(
    st.binary(max_size=600),
    st.tuples(
        st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)), max_size=6),
        st.integers(0, 400),
        st.sampled_from(["overwrite", "truncate", "truncate-fix-header", "insert"]),
    ).map(lambda m: _mutate(captured("mocapframe_packet_occluded_v3.bin"), *m)),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(batch=st.lists(datagrams, min_size=1, max_size=5))
def test_receiver_never_raises_counts_every_malformed_datagram_and_publishes_none_from_it(batch):
    client = primed_client()
    arrival = 10**12
    for datagram in batch:
        arrival += 3_000_000
        before = client.status()
        try:
            _, payload = split_message(datagram)
            decode_frame(payload, (3, 0))
            well_formed = True
        except NatNetDecodeError:
            well_formed = False
        samples = client.process_datagram(datagram, arrival)  # must not raise
        after = client.status()
        assert client.internal_errors == 0, client.last_decode_error
        if after.malformed > before.malformed:
            assert after.malformed == before.malformed + 1 and samples == []
            assert after.frames == before.frames
        else:
            assert after.frames <= before.frames + 1
        if samples:
            assert well_formed
            assert all(np.isfinite(s.rotation).all() and np.isfinite(s.translation).all() for s in samples if s.valid)
            assert all(abs(np.linalg.det(s.rotation) - 1) < 1e-6 for s in samples if s.valid)
        if not well_formed:
            assert samples == []


unit_or_not = st.one_of(
    st.tuples(finite, finite, finite, finite),
    st.tuples(finite, finite, finite, finite).filter(lambda q: np.linalg.norm(q) > 1e-3).map(
        lambda q: tuple(np.float32(np.array(q) / np.linalg.norm(q)).tolist())),
    st.just((0.0, 0.0, 0.0, 0.0)),
)
body = st.tuples(st.integers(-(2**31), 2**31 - 1), vec3, unit_or_not, finite, st.integers(-(2**15), 2**15 - 1))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(bodies=st.lists(body, max_size=4, unique_by=lambda b: b[0]))
def test_receiver_samples_equal_the_array_formulation(bodies):
    """The receiver's per-body plain-float path against the formulation it replaced: the full
    decode's arrays, `quaternions_xyzw_to_matrices` and `valid = tracked & usable`, value for value;
    a tracked body with a non-unit quaternion makes the frame malformed."""
    from dpmhw.tracking import quaternions_xyzw_to_matrices

    client = primed_client()
    content = FrameContent(frame_number=5, rigid_bodies=bodies, stamp_mid_exposure=10**9, stamp_transmit=10**9 + 20_000)
    datagram = encode_frame(content, "3.0")
    samples = client.process_datagram(datagram, 10**12)
    rb = decode_frame(split_message(datagram)[1], (3, 0)).rigid_bodies
    q = rb.quaternions.astype(np.float64)
    bad = rb.tracked & ((np.abs(np.linalg.norm(q, axis=1) - 1) >= 1e-3) | ~np.isfinite(rb.positions).all(axis=1))
    if bad.any():
        assert samples == [] and client.status().malformed == 1
        assert f"rigid body {rb.ids[bad.argmax()]} is flagged tracked" in client.last_decode_error
        return
    rotations, usable = quaternions_xyzw_to_matrices(rb.quaternions)
    assert [s.rigid_body_id for s in samples] == rb.ids.tolist()
    for i, s in enumerate(samples):
        np.testing.assert_array_equal(s.rotation, rotations[i])
        np.testing.assert_array_equal(s.translation, rb.positions[i].astype(np.float64))
        assert s.valid == bool(rb.tracked[i] & usable[i])
        assert s.mean_marker_error == float(rb.mean_errors[i]) and s.frame_number == 5


def test_frame_gaps_and_reordering_are_detected():
    from firmware_mocks.natnet_server import FrameContent, encode_frame

    client = primed_client()

    def frame(n, mid=None):
        mid = 1000 * n if mid is None else mid
        content = FrameContent(
            frame_number=n,
            rigid_bodies=[(1, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, 1)],
            stamp_mid_exposure=mid,
            stamp_transmit=mid + 500,
        )
        return encode_frame(content, "3.0")

    arrival = 10**12
    for n in (10, 11, 9, 14):
        arrival += 3_000_000
        client.process_datagram(frame(n), arrival)
    status = client.status()
    assert status.frames == 3 and status.out_of_order == 1 and status.frames_missed == 2
    assert client.latest(1).frame_number == 14
    client.process_datagram(frame(5), arrival + 3_000_000)  # a little back: reordered, dropped
    client.process_datagram(frame(6000, 24_000), arrival + 6_000_000)
    client.process_datagram(frame(2, 34_000), arrival + 9_000_000)  # far back: the server restarted
    assert client.latest(1).frame_number == 2 and client.status().out_of_order == 2


def test_signalling_nan_in_a_tracked_pose_is_malformed_not_a_crash():
    """Found by the fuzzer: a float32 sNaN used to raise a cast warning inside the receiver."""
    client = primed_client()
    datagram = bytearray(captured("mocapframe_packet_occluded_v3.bin"))
    y = datagram.index(bytes.fromhex("24de903e"))  # rigid body 7, position y
    datagram[y + 3] = 0x7F  # 0x7f90de24: a signalling NaN
    assert client.process_datagram(bytes(datagram), 10**12) == []
    assert client.status().malformed == 1 and client.internal_errors == 0
    assert "rigid body 7 is flagged tracked" in client.last_decode_error


def test_unknown_dataset_types_are_skipped_by_byte_count_from_4_1_and_rejected_before():
    world = World.demo("static", count=1)
    for version, ok in (((4, 1), True), ((3, 0), False)):
        _, payload = split_message(encode_model_definitions(world, version))
        count = int.from_bytes(payload[:4], "little")
        extra = (9).to_bytes(4, "little") + ((3).to_bytes(4, "little") + b"abc" if ok else b"abc\0")
        payload = (count + 1).to_bytes(4, "little") + extra + bytes(payload[4:])
        if ok:
            defs = decode_model_definitions(payload, version)
            assert defs.rigid_body_names() == {1: "static_1"} and defs.others[0].type == 9
        else:
            with pytest.raises(NatNetDecodeError, match="dataset type"):
                decode_model_definitions(payload, version)
