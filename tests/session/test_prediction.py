"""Constant-velocity prediction on SE(3): exact on constant-velocity motion, better than none on curves."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dpmhw.session.prediction import PosePredictor
from dpmhw.tracking import PoseSample

RATE_HZ = 360.0


def sample(body, t_s, R, p, valid=True):
    ns = int(round(t_s * 1e9))
    return PoseSample(body, R, p, t_exposure_ns=ns, t_arrival_ns=ns + 4_500_000, valid=valid)


def screw(t):
    """Constant linear velocity and constant angular velocity about a tilted world axis."""
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    R0 = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    R = Rotation.from_rotvec(axis * 2.0 * t).as_matrix() @ R0
    return R, np.array([0.1, 1.0, -0.2]) + np.array([0.5, -0.1, 0.25]) * t


@pytest.mark.parametrize("history", [2, 4, 8])
def test_constant_velocity_screw_motion_is_predicted_exactly(history):
    pred = PosePredictor(history=history, max_horizon_s=1.0)
    for k in range(10):
        pred.observe(sample(1, k / RATE_HZ, *screw(k / RATE_HZ)))
    t_target = 9 / RATE_HZ + 0.05
    pose, horizon = pred.predict(1, int(round(t_target * 1e9)))
    R_true, p_true = screw(t_target)
    assert horizon == pytest.approx(0.05e9, abs=2)
    np.testing.assert_allclose(pose.t, p_true, atol=1e-9)
    np.testing.assert_allclose(pose.R, R_true, atol=1e-9)


def test_disabled_returns_newest_measured_pose_and_horizon_is_capped():
    pred = PosePredictor(history=4, max_horizon_s=0.02)
    for k in range(4):
        pred.observe(sample(7, k / RATE_HZ, *screw(k / RATE_HZ)))
    pose, horizon = pred.predict(7, int(1e9), enabled=False)
    np.testing.assert_allclose(pose.t, screw(3 / RATE_HZ)[1])
    assert horizon == 0
    pose, horizon = pred.predict(7, int(10e9))
    assert horizon == int(0.02e9)
    np.testing.assert_allclose(pose.t, screw(3 / RATE_HZ + 0.02)[1], atol=1e-9)


def test_invalid_duplicate_and_older_samples_are_ignored():
    pred = PosePredictor(history=4)
    assert pred.predict(1, 0) is None
    R, p = screw(0.0)
    pred.observe(sample(1, 0.0, R, p))
    pred.observe(sample(1, 0.0, R, p + 1))  # same instant: a repeat of `latest`
    pred.observe(sample(1, -0.1, R, p + 2))  # older
    pred.observe(sample(1, 0.01, np.full((3, 3), np.nan), p + 3, valid=False))
    pose, _ = pred.predict(1, int(0.05e9))
    np.testing.assert_allclose(pose.t, p)  # one sample: zero velocity
    pred.reset()
    assert pred.predict(1, 0) is None


def test_prediction_beats_none_on_the_papers_motion():
    """Rotate-while-oscillating (curved): prediction is not exact, but far closer than no prediction."""
    from firmware_mocks.world import RotateWhileOscillating

    traj = RotateWhileOscillating(center=(0, 0, 0), amplitude_m=0.15, oscillation_hz=0.5, spin_rad_s=np.pi / 2)
    pred = PosePredictor(history=4, max_horizon_s=1.0)
    err_pred, err_none = [], []
    horizon = 0.03
    for k in range(0, 720):
        t = k / RATE_HZ
        pred.observe(sample(1, t, *traj.pose(t)))
        if k < 4:
            continue
        target = int(round((t + horizon) * 1e9))
        R_true, p_true = traj.pose(t + horizon)
        err_pred.append(np.linalg.norm(pred.predict(1, target)[0].t - p_true))
        err_none.append(np.linalg.norm(pred.predict(1, target, enabled=False)[0].t - p_true))
    assert np.median(err_pred) < 0.1 * np.median(err_none)


def test_acceleration_model_is_exact_on_constant_acceleration_and_beats_velocity_on_curves():
    from firmware_mocks.world import RotateWhileOscillating

    acc = np.array([0.3, -0.2, 0.5])
    pred = PosePredictor(history=6, max_horizon_s=1.0, model="acceleration")
    for k in range(6):
        t = k / RATE_HZ
        pred.observe(sample(1, t, np.eye(3), np.array([0.1, 1.0, 0.0]) + 0.2 * t + 0.5 * acc * t * t))
    t_target = 5 / RATE_HZ + 0.1
    pose, _ = pred.predict(1, int(round(t_target * 1e9)))
    np.testing.assert_allclose(pose.t, np.array([0.1, 1.0, 0.0]) + 0.2 * t_target + 0.5 * acc * t_target ** 2, atol=1e-7)

    traj = RotateWhileOscillating(center=(0, 0, 0), amplitude_m=0.08, oscillation_hz=0.5, spin_rad_s=np.pi / 2)
    errors = {}
    for model in ("velocity", "acceleration"):
        p = PosePredictor(history=12, max_horizon_s=1.0, model=model)
        e = []
        for k in range(720):
            t = k / RATE_HZ
            p.observe(sample(1, t, *traj.pose(t)))
            if k >= 12:
                e.append(np.linalg.norm(p.predict(1, int(round((t + 0.1) * 1e9)))[0].t - traj.pose(t + 0.1)[1]))
        errors[model] = np.median(e)
    assert errors["acceleration"] < 0.5 * errors["velocity"], errors


def test_unknown_model_is_refused():
    with pytest.raises(ValueError, match="prediction model"):
        PosePredictor(model="psychic")


@settings(deadline=None, max_examples=300)
@given(st.lists(st.floats(-1, 1), min_size=3, max_size=3), st.sampled_from([1e-12, 1e-7, 1e-3, 0.5, 2.0, np.pi - 1e-6, np.pi]))
def test_rotation_vector_maps_match_scipy_from_zero_to_pi(axis, angle):
    from dpmhw.transforms import matrix_to_rotvec, rotvec_to_matrix

    axis = np.asarray(axis)
    assume(np.linalg.norm(axis) > 1e-3)
    w = axis / np.linalg.norm(axis) * angle
    R = rotvec_to_matrix(w)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
    back = matrix_to_rotvec(R)
    want = Rotation.from_matrix(R).as_rotvec()
    if angle < np.pi - 1e-3:
        np.testing.assert_allclose(back, want, atol=1e-9)
    else:  # at π, w and −w are the same rotation
        assert min(np.abs(back - want).max(), np.abs(back + want).max()) < 1e-6
    np.testing.assert_allclose(rotvec_to_matrix(back), R, atol=1e-9)
