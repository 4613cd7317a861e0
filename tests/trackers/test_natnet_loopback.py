"""NatNet driver ↔ emulated Motive over real loopback sockets (unicast and multicast)."""

from __future__ import annotations

import contextlib
import time

import numpy as np
import pytest

from dpmhw.tracking import TrackerState, wait_for
from drivers.natnet import NatNetClient
from firmware_mocks.natnet_server import NatNetServer, NatNetServerConfig
from firmware_mocks.world import World

from .conftest import free_udp_port, settle

LATENCY_MS = 4.5
VERSIONS = ["3.0", "3.1", "4.0", "4.1", "4.2"]


@contextlib.contextmanager
def natnet_pair(version="4.1", unicast=False, trajectory="rotate-oscillate", bodies=2, client_kw=None, **server_kw):
    world = World.demo(trajectory, epoch_s=time.monotonic(), count=bodies)
    cfg = NatNetServerConfig(
        version=version, unicast=unicast, command_port=0, data_port=free_udp_port(), latency_ms=LATENCY_MS, **server_kw
    )
    with NatNetServer(world, cfg) as server:
        client = NatNetClient(command_port=server.command_port, **(client_kw or {}))
        try:
            client.start()
            yield world, server, client
        finally:
            client.stop()


def check_against_truth(samples, world, server, pose_tol=2e-6, time_tol_ns=0.5e6):
    """Every valid sample equals the world's true pose at the frame's true mid-exposure, and its
    stamp is that mid-exposure on the host clock within `time_tol_ns`."""
    checked = 0
    for s in samples:
        truth_ns = server.mid_exposure_host_ns(s.frame_number)
        assert truth_ns is not None, f"frame {s.frame_number} was never sent"
        assert abs(s.t_exposure_ns - truth_ns) < time_tol_ns, (s.frame_number, s.t_exposure_ns - truth_ns)
        if not s.valid:
            continue
        rot, pos = world.pose(s.rigid_body_id, truth_ns / 1e9)
        np.testing.assert_allclose(s.translation, pos, atol=pose_tol)
        np.testing.assert_allclose(s.rotation, rot, atol=pose_tol)
        checked += 1
    return checked


@pytest.mark.parametrize("unicast", [False, True], ids=["multicast", "unicast"])
@pytest.mark.parametrize("version", VERSIONS)
def test_round_trip_poses_times_latency_and_offset(version, unicast):
    with natnet_pair(version, unicast) as (world, server, client):
        with client.subscribe(maxlen=10_000) as sub:
            assert wait_for(lambda: client.status().frames >= 150, 20), client.status()
            samples = sub.drain()
        assert wait_for(lambda: client.status().state == TrackerState.STREAMING, 5)
        status = client.status()
        assert status.malformed == 0 and client.internal_errors == 0
        assert client.version == tuple(int(x) for x in version.split("."))
        assert client.rigid_body_names() == {1: "rotate-oscillate_1", 2: "rotate-oscillate_2"}
        assert {s.rigid_body_id for s in samples} == {1, 2}
        assert check_against_truth(samples, world, server) == len(samples) >= 2 * 140
        # clock offset: host = server-clock time + offset; the mock's true offset is its origin
        assert abs(status.clock_offset_ns - server.clock_origin_host_ns) < 0.5e6
        # latency: the server never sends before mid-exposure + latency, and usually right then
        latencies_ms = np.array([s.latency_ns for s in samples]) / 1e6
        assert latencies_ms.min() == pytest.approx(LATENCY_MS, abs=0.5)
        assert client.system_latency_s * 1e3 >= LATENCY_MS - 1e-3
        frames = sorted({s.frame_number for s in samples})
        assert frames == list(range(frames[0], frames[0] + len(frames))) or status.frames_missed > 0


def test_jittered_stream_still_stamps_mid_exposure():
    with natnet_pair("4.1", unicast=True, jitter_ms=2.0, seed=5) as (world, server, client):
        with client.subscribe(maxlen=10_000) as sub:
            assert wait_for(lambda: client.status().frames >= 150, 20)
            samples = sub.drain()
    latencies_ms = np.array([s.latency_ns for s in samples]) / 1e6
    assert latencies_ms.max() - latencies_ms.min() > 1.0  # the jitter is really there...
    assert check_against_truth(samples, world, server) == len(samples)  # ...and does not move the stamps


def test_drifting_server_clock_is_followed():
    # 300 ppm (several times a real clock's) is 0.3 ms of drift per second of streaming; over
    # this test a fixed offset would be off by more than the 0.5 ms tolerance
    client_kw = dict(clock_window_s=0.5, echo_interval_s=0.02)
    with natnet_pair("4.1", clock_drift_ppm=300.0, client_kw=client_kw) as (world, server, client):
        with client.subscribe(maxlen=10_000) as sub:
            assert wait_for(lambda: client.status().frames >= 720, 20)
            samples = sub.drain()
    span_s = (samples[-1].t_exposure_ns - samples[0].t_exposure_ns) / 1e9
    assert span_s * 300e-6 * 1e3 > 0.5  # ms of drift accumulated: the window is what keeps up
    assert check_against_truth(samples, world, server) == len(samples)


def test_unicast_keep_alives_keep_the_stream_flowing():
    # the server forgets unicast clients silent for 0.2 s; keep-alives every 0.05 s prevent that
    client_kw = dict(keepalive_interval_s=0.05, lost_after_s=0.5)
    with natnet_pair("4.1", unicast=True, client_timeout_s=0.2, client_kw=client_kw) as (world, server, client):
        assert wait_for(lambda: client.status().frames >= 10, 10)
        time.sleep(0.6)
        assert wait_for(lambda: client.status().state == TrackerState.STREAMING, 5)
        assert client.status().reconnects == 0
        assert server.commands[10] >= 5  # keep-alive is message 10
        assert server.clients


def test_model_changes_are_picked_up_while_streaming():
    from firmware_mocks.world import make_trajectory

    with natnet_pair("4.2", bodies=1) as (world, server, client):
        assert wait_for(lambda: client.rigid_body_names() == {1: "rotate-oscillate_1"}, 10)
        assert client.rigid_body_id("rotate-oscillate_1") == 1
        with pytest.raises(KeyError, match="no rigid body named 'bunny'"):
            client.rigid_body_id("bunny")
        server.add_body(7, "bunny", make_trajectory("circular"))
        assert wait_for(lambda: client.rigid_body_names().get(7) == "bunny", 10)
        assert wait_for(lambda: client.latest(7) is not None, 10)
        assert client.rigid_body_id("bunny") == 7
        assert check_against_truth([client.latest(7)], world, server) == 1


def test_latest_is_newest_per_body_and_callbacks_fire():
    got = []
    with natnet_pair("4.1", bodies=3) as (world, server, client):
        client.add_callback(got.append)
        assert wait_for(lambda: len(client.latest_all()) == 3 and len(got) >= 60, 10)
        newest = client.latest(2)
        assert newest.rigid_body_id == 2 and newest.valid
        assert client.latest(99) is None
        later = newest
        assert wait_for(lambda: client.latest(2).frame_number > newest.frame_number, 5)
        later = client.latest(2)
        assert later.t_exposure_ns > newest.t_exposure_ns
        assert check_against_truth(got[:60], world, server) == 60


@pytest.mark.parametrize("version", ["3.0", "4.1"])
def test_injected_faults_are_counted_and_never_published(version):
    with natnet_pair(version, seed=7) as (world, server, client):
        assert wait_for(lambda: client.status().frames >= 10, 10)
        server.stall(60)
        frames0, malformed0 = settle(client)
        sent0 = server.frames_sent
        assert malformed0 == 0
        with client.subscribe(maxlen=10_000) as sub:
            server.config.truncate_prob = server.config.corrupt_prob = 0.1
            server.resume()
            assert wait_for(lambda: sum(server.faults.values()) >= 30, 20)
            server.stall(60)
            frames1, malformed1 = settle(client)
            samples = sub.drain()
        sent = server.frames_sent - sent0
        assert server.faults["truncated"] > 0 and server.faults["corrupted"] > 0
        assert malformed1 - malformed0 == sum(server.faults.values())
        assert frames1 - frames0 == sent - sum(server.faults.values())
        assert client.internal_errors == 0
        assert check_against_truth(samples, world, server) == len(samples) > 0


def test_dropouts_arrive_invalid_with_nan_rotation():
    with natnet_pair("4.1", bodies=1, dropout_prob=0.3, marker_noise_m=0.001, seed=3) as (world, server, client):
        with client.subscribe(maxlen=10_000) as sub:
            assert wait_for(lambda: client.status().frames >= 100, 10)
            samples = sub.drain()
    invalid = [s for s in samples if not s.valid]
    valid = [s for s in samples if s.valid]
    assert invalid and valid
    assert all(np.isnan(s.rotation).all() for s in invalid)
    check_against_truth(samples, world, server)
    errors = np.array([s.mean_marker_error for s in valid])
    assert 0.0005 < np.median(errors) < 0.003  # mean |noise| of a 1 mm Gaussian in 3-D ≈ 1.6 mm


def test_stalled_stream_goes_stale_then_lost_then_recovers():
    client_kw = dict(stale_after_s=0.05, lost_after_s=0.3, backoff_initial_s=0.05, backoff_max_s=0.2)
    with natnet_pair("4.1", unicast=True, client_kw=client_kw) as (world, server, client):
        assert wait_for(lambda: client.status().state == TrackerState.STREAMING, 10)
        server.stall(1.0)
        assert wait_for(lambda: (s := client.status()).state == TrackerState.STALE and "no frame for" in s.reason, 5)
        assert wait_for(lambda: (s := client.status()).state == TrackerState.LOST and "no frame of data" in s.reason, 5)
        frames_before = client.status().frames
        assert wait_for(lambda: client.status().frames > frames_before + 20, 10), client.status()
        assert wait_for(lambda: client.status().state == TrackerState.STREAMING, 5)
        status = client.status()
        assert status.reconnects >= 1
        assert status.frames_missed > 0  # the frames the stall swallowed


def test_no_server_is_reported_lost_with_an_actionable_reason():
    client = NatNetClient(command_port=free_udp_port(), connect_timeout_s=0.2, backoff_initial_s=0.05)
    with client:
        assert wait_for(lambda: (s := client.status()).state == TrackerState.LOST and "no server info from 127.0.0.1" in s.reason, 5)
    assert client.status().state == TrackerState.STOPPED


def test_explicit_version_mismatch_is_counted_not_published():
    # the client insists on 4.1 while the server streams 3.0: every frame fails validation
    with natnet_pair("3.0", unicast=True, client_kw=dict(natnet_version="4.1")) as (world, server, client):
        assert wait_for(lambda: client.status().malformed >= 20, 10)
        assert client.status().frames == 0 and client.latest_all() == {}
        assert "end-of-data" in client.last_decode_error or "bytes" in client.last_decode_error


def test_restarted_server_whose_frame_numbers_began_again_is_followed():
    """Motive restarted: after the reconnect its frame numbers start low again. They used to be
    dropped as 'out of order' until they passed the last number seen before the restart (up to
    1000 frames, below which a backwards jump is taken for UDP reordering)."""
    world = World.demo("circular", epoch_s=time.monotonic(), count=1)
    cfg = NatNetServerConfig(unicast=True, command_port=0, latency_ms=LATENCY_MS)
    client_kw = dict(lost_after_s=0.3, backoff_initial_s=0.05, backoff_max_s=0.1)
    first = NatNetServer(world, cfg).start()
    client = NatNetClient(command_port=first.command_port, **client_kw)
    client.start()
    try:
        with first:
            assert wait_for(lambda: client.status().frames >= 300, 10), client.status()
        before = client.latest(1).frame_number  # far fewer than the 1000 that read as a restart
        assert wait_for(lambda: client.status().state == TrackerState.LOST, 5), client.status()
        cfg = NatNetServerConfig(unicast=True, command_port=client.command_port, latency_ms=LATENCY_MS)
        with NatNetServer(world, cfg) as second:
            assert wait_for(lambda: client.latest(1).frame_number < before, 10), client.status()
            assert wait_for(lambda: client.status().state == TrackerState.STREAMING, 5)
            assert client.status().out_of_order == 0
            assert check_against_truth([client.latest(1)], world, second) == 1
    finally:
        client.stop()
