"""The simulated world's trajectories and the shared tracking helpers."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dpmhw.tracking import (
    ClockMapping,
    LatestPoses,
    PoseSample,
    Tracker,
    quaternions_xyzw_to_matrices,
)
from dpmhw.transforms import quaternion_xyzw_to_rotation
from drivers.natnet import NatNetClient
from firmware_mocks.world import (
    TRAJECTORY_NAMES,
    Circular,
    Linear,
    RecordedPath,
    RotateWhileOscillating,
    World,
    make_trajectory,
)


def is_rotation(r: np.ndarray) -> bool:
    return np.allclose(r @ np.swapaxes(r, -1, -2), np.eye(3), atol=1e-9) and np.allclose(np.linalg.det(r), 1)


@pytest.mark.parametrize("name", TRAJECTORY_NAMES)
def test_every_trajectory_is_vectorised_and_gives_rotations(name):
    traj = make_trajectory(name)
    t = np.linspace(0, 5, 11)
    rot, pos = traj.pose(t)
    assert rot.shape == (11, 3, 3) and pos.shape == (11, 3)
    assert is_rotation(rot)
    r5, p5 = traj.pose(t[5])  # scalar query agrees with the batch
    np.testing.assert_allclose(r5, rot[5])
    np.testing.assert_allclose(p5, pos[5])


def test_linear_and_circular_follow_their_definitions():
    rot, pos = Linear(start=(0, 1, 0), velocity=(0.2, 0, -0.1)).pose(np.array([0.0, 2.0]))
    np.testing.assert_allclose(pos, [[0, 1, 0], [0.4, 1, -0.2]])
    circ = Circular(center=(0, 1, 0), radius=0.3, period_s=2.0)
    rot, pos = circ.pose(np.linspace(0, 2, 9))
    np.testing.assert_allclose(np.linalg.norm(pos - [0, 1, 0], axis=1), 0.3)
    np.testing.assert_allclose(pos[0], pos[-1], atol=1e-12)  # one full period
    # the body faces along its path: its -z axis is the unit tangent of the motion
    angle = np.linspace(0, 2, 9) * np.pi
    tangent = np.stack([-np.sin(angle), np.zeros(9), -np.cos(angle)], axis=1)
    np.testing.assert_allclose(-rot[:, :, 2], tangent, atol=1e-12)


def test_rotate_while_oscillating_spins_and_moves_back_and_forth():
    traj = RotateWhileOscillating(center=(0, 1, 0), amplitude_m=0.15, oscillation_hz=0.5, spin_rad_s=np.pi / 2)
    t = np.linspace(0, 4, 401)
    rot, pos = traj.pose(t)
    assert pos[:, 0].max() == pytest.approx(0.15, abs=1e-4) and pos[:, 0].min() == pytest.approx(-0.15, abs=1e-4)
    np.testing.assert_allclose(pos[:, 1:], np.tile([1, 0], (401, 1)))
    angle = Rotation.from_matrix(rot[100]).magnitude()
    assert angle == pytest.approx(np.pi / 2)  # 1 s at pi/2 rad/s


def test_recorded_path_interpolates_its_samples_and_holds_the_ends(tmp_path):
    t = np.array([0.0, 1.0, 2.0])
    pos = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0]], float)
    quats = Rotation.from_euler("y", [[0], [90], [180]], degrees=True).as_quat()
    csv = tmp_path / "path.csv"
    csv.write_text("t,x,y,z,qx,qy,qz,qw\n" + "\n".join(",".join(map(str, [ti, *p, *q])) for ti, p, q in zip(t, pos, quats)))
    path = RecordedPath.from_csv(csv)
    rot, p = path.pose(np.array([0.5, 1.0, 5.0, -1.0]))
    np.testing.assert_allclose(p, [[0.5, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0, 0]], atol=1e-12)
    assert Rotation.from_matrix(rot[0]).magnitude() == pytest.approx(np.pi / 4)  # slerp halfway
    looped = RecordedPath(t, pos, quats, loop=True)
    np.testing.assert_allclose(looped.pose(2.5)[1], path.pose(0.5)[1])
    with pytest.raises(ValueError, match="increase"):
        RecordedPath([0, 0], pos[:2], quats[:2])


def test_speed_scales_every_velocity():
    slow, fast = make_trajectory("rotate-oscillate"), make_trajectory("rotate-oscillate", speed=2.0)
    for a, b in zip(slow.pose(1.0), fast.pose(0.5)):
        np.testing.assert_allclose(a, b)
    with pytest.raises(ValueError, match="positive"):
        make_trajectory("linear", speed=0)


def test_world_epoch_and_markers():
    world = World.demo("static", epoch_s=100.0, count=2)
    rot, pos = world.pose(2, 100.0)
    np.testing.assert_allclose(pos, [0, 1, 0.5])
    np.testing.assert_allclose(world.markers(1, 100.0), world.objects[1].markers + [0, 1, 0])
    with pytest.raises(ValueError, match="already"):
        world.add(1, "dup", make_trajectory("static"))


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 1e-3))
def test_quaternion_conversion_matches_scipy(q):
    rot, usable = quaternions_xyzw_to_matrices(np.array([q]))
    assert usable.all()
    np.testing.assert_allclose(rot[0], Rotation.from_quat(q).as_matrix(), atol=1e-12)


def test_zero_quaternion_is_unusable_not_identity():
    rot, usable = quaternions_xyzw_to_matrices(np.array([[0, 0, 0, 0], [0, 0, 0, 1.0]]))
    assert usable.tolist() == [False, True] and np.isnan(rot[0]).all()


def test_clock_mapping_prefers_round_trips_and_takes_the_minimum():
    clock = ClockMapping(window_s=1.0)
    assert clock.offset_ns is None and clock.to_host_ns(0) is None
    for delay in (300, 120, 500):  # one-way: offset 1000 plus transit
        clock.add_one_way(device_ns=10_000, arrival_ns=11_000 + delay)
    assert clock.offset_ns == 1120 and clock.method == "one-way minimum"
    clock.add_round_trip(sent_ns=20_000, device_ns=19_500, received_ns=21_000)  # rtt 1000 → offset 1000
    clock.add_round_trip(sent_ns=30_000, device_ns=29_000, received_ns=32_000)  # rtt 2000, worse
    assert clock.offset_ns == 1000 and clock.method == "round-trip"
    assert clock.to_host_ns(5) == 1005
    clock.reset()  # a new session: the device may have restarted with a new clock origin
    assert clock.offset_ns is None and clock.method == "none"
    clock.add_one_way(device_ns=10_000, arrival_ns=90_000)
    assert clock.offset_ns == 80_000


def test_clock_mapping_forgets_evidence_older_than_its_window():
    """A drifting device clock: old minima must not pin the offset."""
    clock = ClockMapping(window_s=1.0)
    clock.add_one_way(device_ns=0, arrival_ns=1_000)  # offset 1000 at host t = 1 µs
    later = 3 * 10**9
    clock.add_one_way(device_ns=later - 5_000, arrival_ns=later)  # offset now 5000
    assert clock.offset_ns == 5_000
    clock.add_round_trip(sent_ns=10, device_ns=0, received_ns=20)  # tiny rtt, but long ago...
    clock.add_round_trip(sent_ns=later, device_ns=later - 7_000 + 500, received_ns=later + 1_000)
    assert clock.offset_ns == 7_000  # ...so the recent, slower round trip wins


def _sample(i: int, frame: int = 0) -> PoseSample:
    return PoseSample(i, np.eye(3), np.zeros(3), frame, frame + 1, True, 0.0, frame)


def test_subscriptions_are_bounded_and_callback_errors_are_contained():
    board = LatestPoses()
    boom = []

    def bad_callback(sample):
        boom.append(sample)
        raise RuntimeError("consumer bug")

    board.add_callback(bad_callback)
    with board.subscribe(maxlen=3) as sub:
        board.publish([_sample(1, f) for f in range(5)])
        assert sub.dropped == 2
        assert [s.frame_number for s in sub.drain()] == [2, 3, 4]
    board.publish([_sample(2, 9)])  # a closed subscription receives nothing more
    assert sub.drain() == []
    assert board.callback_errors == 6 and "consumer bug" in board.last_callback_error
    assert board.latest(1).frame_number == 4 and set(board.latest_all()) == {1, 2}


def test_subscription_iterator_ends_when_closed():
    board = LatestPoses()
    sub = board.subscribe()
    board.publish([_sample(1, 1)])
    got = []
    t = threading.Thread(target=lambda: got.extend(sub))
    t.start()
    sub.close()
    t.join(timeout=5)
    assert not t.is_alive() and [s.frame_number for s in got] == [1]


def test_a_consumer_blocked_in_get_is_woken_by_put():
    board = LatestPoses()
    sub = board.subscribe()
    got = []
    t = threading.Thread(target=lambda: got.append(sub.get(timeout=60)))
    t.start()
    while not sub._waiting and t.is_alive():  # until it waits
        threading.Event().wait(0.001)
    board.publish([_sample(1, 3)])
    t.join(timeout=30)  # woken by the put, not by its 60 s timeout
    assert not t.is_alive() and [s.frame_number for s in got] == [3]


def test_natnet_client_satisfies_the_tracker_protocol():
    assert isinstance(NatNetClient(), Tracker)


def test_pose_samples_are_read_only_and_shape_checked():
    s = _sample(1)
    with pytest.raises(ValueError):
        s.rotation[0, 0] = 2.0
    with pytest.raises(ValueError, match="translation"):
        PoseSample(1, np.eye(3), np.zeros(4), 0, 0, True)
    np.testing.assert_allclose(s.as_matrix(), np.eye(4))


def test_pose_sample_from_floats_equals_the_generic_constructor():
    rot = quaternion_xyzw_to_rotation(0.1, -0.7, 0.3, 0.6)
    fast = PoseSample.from_floats(3, rot, (0.5, 1.0, -2.0), 100, 200, True, 0.25, 7)
    slow = PoseSample(3, np.array(rot).reshape(3, 3), np.array([0.5, 1.0, -2.0]), 100, 200, True, 0.25, 7)
    for name in ("rigid_body_id", "t_exposure_ns", "t_arrival_ns", "valid", "mean_marker_error", "frame_number"):
        assert getattr(fast, name) == getattr(slow, name)
    for name in ("rotation", "translation"):
        a, b = getattr(fast, name), getattr(slow, name)
        assert a.dtype == b.dtype == np.float64 and a.shape == b.shape and np.array_equal(a, b)
        with pytest.raises(ValueError):
            a[0] = 2.0  # read-only, like the generic constructor's
    with pytest.raises(ValueError, match="translation"):
        PoseSample.from_floats(1, rot, (0.0, 0.0), 0, 0, True)
    with pytest.raises(ValueError):
        PoseSample.from_floats(1, rot[:8], (0.0, 0.0, 0.0), 0, 0, True)


def test_core_and_mocks_do_not_import_drivers():
    import subprocess
    import sys

    code = (
        "import sys, dpmhw.tracking, dpmhw.frame_sink, firmware_mocks.world, firmware_mocks.natnet_server,"
        " firmware_mocks.serial_tracker, firmware_mocks.dlpc900_model, firmware_mocks.dlpc900_usb;"
        "bad = [m for m in sys.modules if m == 'drivers' or m.startswith('drivers.')];"
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


@settings(deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 1e-3))
def test_matrix_to_quaternion_matches_scipy_with_w_non_negative(q):
    from dpmhw.transforms import quat_xyzw_from_matrix

    rot = Rotation.from_quat(q)
    got = np.array(quat_xyzw_from_matrix(rot.as_matrix()))
    want = rot.as_quat()
    want = -want if want[3] < 0 else want
    assert got[3] >= 0 and abs(np.linalg.norm(got) - 1) < 1e-12
    if abs(want[3]) > 1e-9:  # w = 0: q and -q are the same rotation and both have w = 0
        np.testing.assert_allclose(got, want, atol=1e-12)
    np.testing.assert_allclose(Rotation.from_quat(got).as_matrix(), rot.as_matrix(), atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(TRAJECTORY_NAMES), speed=st.floats(0.1, 10.0), epoch=st.floats(-1e4, 1e4),
       times=st.lists(st.floats(-1e5, 1e5), min_size=1, max_size=20))
def test_one_instant_poses_in_plain_floats_equal_the_vectorised_ones(name, speed, epoch, times):
    world = World.demo(name, epoch_s=epoch, count=2, speed=speed)  # body 2 is shifted
    for body in (1, 2):
        rot, pos = world.pose(body, np.array(times))
        for i, t in enumerate(times):
            r, p = world.pose_floats(body, t)
            assert r == tuple(rot[i].ravel().tolist()) and p == tuple(pos[i].tolist())  # bit for bit


@settings(max_examples=40, deadline=None)
@given(name=st.sampled_from(TRAJECTORY_NAMES), t=st.floats(0, 100), noise=st.sampled_from([0.0, 0.002]),
       offset=st.tuples(*[st.floats(-0.1, 0.1)] * 3))
def test_mock_frame_content_matches_the_array_formulation(name, t, noise, offset):
    """The mock's per-marker plain floats against the formulation they replaced: markers
    `obj.markers @ rot.T + pos`, residuals the rows' norms, the quaternion of the true rotation."""
    from firmware_mocks.natnet_server import NatNetServer, NatNetServerConfig

    world = World.demo(name, count=2)
    server = NatNetServer(world, NatNetServerConfig(command_port=0, unicast=True, marker_noise_m=noise, seed=1))
    try:
        server.pose_offset_m = np.array(offset)
        content = server.build_frame(7, 123, t * 1e9)
    finally:
        server.stop()
    t = t * 1e9 / 1e9  # the instant the frame describes, as the server computes it
    sets = dict(content.marker_sets)
    for (rb_id, pos, quat, err, params), obj in zip(content.rigid_bodies, world.objects.values()):
        rot, true_pos = world.pose(obj.rigid_body_id, t)
        assert rb_id == obj.rigid_body_id and params == 1
        np.testing.assert_array_equal(pos, true_pos + np.array(offset))
        np.testing.assert_allclose(Rotation.from_quat(quat).as_matrix(), rot, atol=1e-12)
        ideal = obj.markers @ rot.T + (true_pos + np.array(offset))
        markers = np.array(sets[obj.name])
        residuals = np.linalg.norm(markers - ideal, axis=1)
        assert markers.shape == ideal.shape
        np.testing.assert_allclose(markers, ideal, atol=1e-12 + 10 * noise)
        assert err == pytest.approx(residuals.mean(), abs=1e-15)
        assert (err == 0.0) == (noise == 0.0)
    assert len(sets["all"]) == sum(len(o.markers) for o in world.objects.values())


def test_receiver_rotation_of_a_huge_or_tiny_quaternion_is_unusable():
    rot, usable = quaternions_xyzw_to_matrices(np.array([[1e200, 0, 0, 0], [1e-7, 0, 0, 0], [np.nan, 0, 0, 1], [0, 0, 0, 2.0]]))
    assert usable.tolist() == [False, False, False, True]
    assert np.isnan(rot[:3]).all() and np.allclose(rot[3], np.eye(3))


def test_turning_trajectories_rotate_about_y_as_scipy_does():
    t = np.linspace(-3.0, 7.0, 41)
    for traj, rate in ((RotateWhileOscillating(), RotateWhileOscillating().spin_rad_s), (Circular(), 2 * np.pi / Circular().period_s)):
        rot, _ = traj.pose(t)
        np.testing.assert_allclose(rot, Rotation.from_rotvec((rate * t)[:, None] * np.array([0.0, 1.0, 0.0])).as_matrix(), atol=1e-12)


def test_a_pose_solved_from_noisy_markers_is_their_least_squares_fit():
    """With `solve_from_markers`, the streamed pose carries the model markers closest to the
    noisy ones: near the truth (within a few noise deviations), not equal to it, and no other
    pose fits the markers better (checked against small perturbations of it)."""
    from firmware_mocks.natnet_server import NatNetServer, NatNetServerConfig
    from dpmhw.transforms import rotation_about_axis

    world = World.demo("rotate-oscillate", count=1)
    noise = 0.0005
    server = NatNetServer(world, NatNetServerConfig(command_port=0, unicast=True, marker_noise_m=noise,
                                                    solve_from_markers=True, seed=2))
    try:
        content = server.build_frame(7, 123, 0.37e9)
    finally:
        server.stop()
    (_, pos, quat, err, _), = content.rigid_bodies
    obj = next(iter(world.objects.values()))
    rot_true, pos_true = world.pose(obj.rigid_body_id, 0.37)
    rot = Rotation.from_quat(quat).as_matrix()
    seen = np.array(dict(content.marker_sets)[obj.name])

    def cost(R, t):
        return float(np.sum((obj.markers @ R.T + t - seen) ** 2))

    assert 0 < np.linalg.norm(np.array(pos) - pos_true) < 5 * noise
    assert np.degrees(Rotation.from_matrix(rot @ rot_true.T).magnitude()) < 2.0
    best = cost(rot, np.array(pos))
    assert best < cost(rot_true, pos_true)
    for axis in np.eye(3):
        for d in (-1e-4, 1e-4):
            assert best <= cost(rotation_about_axis(axis, d) @ rot, np.array(pos))
            assert best <= cost(rot, np.array(pos) + d * axis)
    assert err == pytest.approx(np.linalg.norm(obj.markers @ rot.T + np.array(pos) - seen, axis=1).mean(), rel=1e-6)
