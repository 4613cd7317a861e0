"""NatNet codec: known answers from real Motive captures, and totality on arbitrary bytes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.natnet_protocol import (
    SUPPORTED_VERSIONS,
    MessageId,
    NatNetDecodeError,
    decode_echo_response,
    decode_frame,
    decode_frame_poses,
    decode_model_definitions,
    decode_server_info,
    encode_connect,
    encode_echo_request,
    encode_message,
    parse_version,
    split_message,
)

from .conftest import captured

def test_tracked_frame_decodes_to_published_values():
    msg_id, payload = split_message(captured("mocapframe_packet_v3.bin"))
    assert msg_id == MessageId.FRAME_OF_DATA
    frame = decode_frame(payload, (3, 0))
    assert frame.frame_number == 162734
    rb = frame.rigid_bodies
    assert rb.ids.tolist() == [2]
    np.testing.assert_allclose(rb.positions[0], [0.174, 1.447, -0.734], atol=6e-4)
    np.testing.assert_allclose(rb.quaternions[0], [-0.055, 0.510, 0.044, -0.857], atol=6e-4)
    assert rb.params.tolist() == [1] and rb.tracked.tolist() == [True]
    assert frame.timestamp_s == pytest.approx(1356.117, abs=5e-4)
    assert frame.unlabeled_markers.shape == (5, 3)
    assert frame.precision_timestamp is None  # 3.0 has none


def test_latency_from_frame_timestamps_matches_published_values():
    _, info_payload = split_message(captured("serverinfo_packet_v3.bin"))
    info = decode_server_info(info_payload)
    assert info.app_name == "Motive"
    assert info.app_version == (2, 1, 0, 0) and info.natnet_version == (3, 0, 0, 0)
    assert info.clock_hz == 3_312_787
    assert (info.data_port, info.is_multicast, info.multicast_group) == (1511, True, "239.255.42.99")
    _, payload = split_message(captured("mocapframe_packet_v3.bin"))
    frame = decode_frame(payload, (3, 0))
    assert frame.system_latency_s(info.clock_hz) * 1e3 == pytest.approx(5.50, abs=0.005)
    assert frame.software_latency_s(info.clock_hz) * 1e3 == pytest.approx(0.88, abs=0.005)


def test_occluded_frame_has_marker_sets_and_occluded_labeled_marker():
    _, payload = split_message(captured("mocapframe_packet_occluded_v3.bin"))
    frame = decode_frame(payload, (3, 0))
    assert list(frame.marker_sets) == ["FakeTree", "all"]
    assert [m.shape for m in frame.marker_sets.values()] == [(5, 3), (5, 3)]
    assert frame.rigid_bodies.ids.tolist() == [7]
    # 4 of the 5 markers are labeled; the first carries the occluded bit (param bit 0)
    assert len(frame.labeled_markers.ids) == 4
    assert (frame.labeled_markers.ids >> 16).tolist() == [7, 7, 7, 7]
    assert frame.labeled_markers.params[0] & 1 == 1


def test_model_definitions_map_names_to_ids():
    msg_id, payload = split_message(captured("modeldef_packet_v3.bin"))
    assert msg_id == MessageId.MODEL_DEF
    defs = decode_model_definitions(payload, (3, 0))
    assert defs.rigid_body_names() == {2: "RaceQuad"}
    rb = defs.rigid_bodies[0]
    assert rb.parent_id == -1 and rb.marker_positions.shape == (5, 3)
    assert defs.marker_sets["RaceQuad"] == tuple(f"Marker{i}" for i in range(1, 6))
    assert defs.marker_sets["all"] == tuple(f"RaceQuad_{i}" for i in range(1, 6))


def test_client_requests_encode_byte_for_byte_like_natnet_lib():
    assert encode_connect((3, 0, 0, 0)) == captured("connect_packet_v3.bin")
    assert encode_message(MessageId.REQUEST_MODEL_DEF) == captured("requestmodeldef_packet_v3.bin")
    request = captured("echorequest_packet_v3.bin")
    client_time = int.from_bytes(request[4:12], "little")
    assert encode_echo_request(client_time) == request
    _, payload = split_message(captured("echoresponse_packet_v3.bin"))
    echoed, server_ticks = decode_echo_response(payload)
    assert echoed == client_time and server_ticks > 0


def test_every_truncation_of_a_real_frame_is_rejected():
    _, payload = split_message(captured("mocapframe_packet_v3.bin"))
    payload = bytes(payload)
    for n in range(len(payload)):
        with pytest.raises(NatNetDecodeError):
            decode_frame(payload[:n], (3, 0))


def test_header_length_mismatch_is_rejected():
    datagram = captured("mocapframe_packet_v3.bin")
    with pytest.raises(NatNetDecodeError, match="header says"):
        split_message(datagram[:-1])
    with pytest.raises(NatNetDecodeError, match="header says"):
        split_message(datagram + b"\0")


def test_wrong_version_is_an_error_not_a_wrong_pose():
    _, payload = split_message(captured("mocapframe_packet_v3.bin"))
    with pytest.raises(NatNetDecodeError):
        decode_frame(payload, (4, 1))


def test_nonzero_end_of_data_tag_is_rejected():
    datagram = bytearray(captured("mocapframe_packet_v3.bin"))
    datagram[-1] = 1
    _, payload = split_message(bytes(datagram))
    with pytest.raises(NatNetDecodeError, match="end-of-data"):
        decode_frame(payload, (3, 0))


def test_parse_version():
    assert parse_version("4.1") == (4, 1)
    assert parse_version((3, 0, 0, 0)) == (3, 0)
    with pytest.raises(ValueError, match="not supported"):
        parse_version("2.10")


# ---------------------------------------------------------------- totality (hypothesis)

VERSIONS = st.sampled_from(SUPPORTED_VERSIONS)
FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FUZZ
@given(data=st.binary(max_size=2048), version=VERSIONS)
def test_decode_frame_is_total_on_arbitrary_bytes(data, version):
    try:
        frame = decode_frame(data, version)
    except NatNetDecodeError:
        return
    assert frame.rigid_bodies.positions.shape[1:] == (3,)


@FUZZ
@given(data=st.binary(max_size=2048), version=VERSIONS)
def test_decode_model_definitions_is_total_on_arbitrary_bytes(data, version):
    try:
        decode_model_definitions(data, version)
    except NatNetDecodeError:
        pass


@FUZZ
@given(data=st.binary(max_size=400))
def test_envelope_and_server_info_are_total(data):
    try:
        _, payload = split_message(data)
        decode_server_info(payload)
    except NatNetDecodeError:
        pass


def _mutations():
    edits = st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)), min_size=1, max_size=6)
    return st.tuples(edits, st.integers(0, 400), st.sampled_from(["overwrite", "truncate", "insert"]))


def _mutated(datagram: bytes, mutation) -> bytes:
    """The payload of a captured datagram with one of `_mutations()` applied."""
    edits, cut, kind = mutation
    _, payload = split_message(datagram)
    buf = bytearray(payload)
    if kind == "truncate":
        buf = buf[: cut % len(buf)]
    for pos, value in edits:
        if kind == "insert":
            buf.insert(pos % (len(buf) + 1), value)
        elif buf:
            buf[pos % len(buf)] = value
    return bytes(buf)


@FUZZ
@given(mutation=_mutations(), which=st.sampled_from(["mocapframe_packet_v3.bin", "mocapframe_packet_occluded_v3.bin"]))
def test_mutated_real_frames_decode_or_raise_the_decode_error(mutation, which):
    try:
        decode_frame(_mutated(captured(which), mutation), (3, 0))
    except NatNetDecodeError:
        pass


# ---------------------------------------------------------------- the receiver's poses-only decode


def _frame_outcome(decode, data, version):
    try:
        return "ok", decode(data, version)
    except NatNetDecodeError as exc:
        return "error", str(exc)


def _assert_poses_decode_agrees(data: bytes, version) -> None:
    """`decode_frame_poses` accepts exactly what `decode_frame` accepts, with the same error text,
    and returns the same bodies (as plain floats) and stamps."""
    full_kind, full = _frame_outcome(decode_frame, data, version)
    poses_kind, poses = _frame_outcome(decode_frame_poses, data, version)
    assert poses_kind == full_kind
    if full_kind == "error":
        assert poses == full
        return
    rb = full.rigid_bodies
    want = [(int(i), *map(float, p), *map(float, q), float(e), int(f))
            for i, p, q, e, f in zip(rb.ids, rb.positions, rb.quaternions, rb.mean_errors, rb.params)]
    # compare the bit patterns: NaN payloads included, NaN != NaN aside
    assert [tuple(np.float64(v).tobytes() for v in b) for b in poses.rigid_bodies] == \
        [tuple(np.float64(v).tobytes() for v in b) for b in want]
    assert (poses.frame_number, poses.stamp_mid_exposure, poses.stamp_transmit, poses.params) == (
        full.frame_number, full.stamp_mid_exposure, full.stamp_transmit, full.params)
    assert poses.models_changed == full.models_changed


@FUZZ
@given(data=st.binary(max_size=2048), version=VERSIONS)
def test_poses_decode_agrees_with_the_full_decode_on_arbitrary_bytes(data, version):
    _assert_poses_decode_agrees(data, version)


@FUZZ
@given(mutation=_mutations(), which=st.sampled_from(["mocapframe_packet_v3.bin", "mocapframe_packet_occluded_v3.bin"]),
       version=VERSIONS)
def test_poses_decode_agrees_with_the_full_decode_on_mutated_real_frames(mutation, which, version):
    _assert_poses_decode_agrees(_mutated(captured(which), mutation), version)


def test_poses_decode_of_every_truncation_of_a_real_frame_agrees():
    _, payload = split_message(captured("mocapframe_packet_v3.bin"))
    payload = bytes(payload)
    for n in range(len(payload) + 1):
        _assert_poses_decode_agrees(payload[:n], (3, 0))
