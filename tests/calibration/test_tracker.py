"""Projector pose in the tracker frame."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.errors import CaptureError, DegenerateViewsError
from calibration.evaluate import rotation_error_deg
from calibration.tracker import (
    load_tracker_poses,
    projector_pose_from_points,
    projector_pose_from_tracked_board,
)
from dpmhw.transforms import rotation_from_quat_xyzw


def _truth_world_from_projector(rig):
    tr = rig.truth()["world_from_projector"]
    return np.array(tr["R"]), np.array(tr["t"])


def test_pose_from_tracked_board_matches_truth(world):
    rig = world.rig
    rng = np.random.default_rng(0)
    poses = {}
    for i, o in enumerate(world.observations):
        R, t = rig.world_from_board(i)
        poses[o.name] = (R, t + rng.normal(0, 0.0002, 3))  # 0.2 mm tracker noise
    cal = world.result.to_calibration()
    pose = projector_pose_from_tracked_board(world.observations, poses, rig.board, cal)
    R_true, t_true = _truth_world_from_projector(rig)
    assert rotation_error_deg(pose.R, R_true) < 0.05
    assert np.linalg.norm(pose.t - t_true) < 1e-3
    assert pose.rms_px < 0.5 and pose.inliers.all()
    assert set(pose.per_view_rms_px) == set(poses)


def test_pose_from_markers_rejects_a_mistracked_marker():
    rng = np.random.default_rng(1)
    K = np.array([[1500.0, 0, 640], [0, 1500.0, 880], [0, 0, 1]])
    dist = np.array([0.02, -0.01, 0, 0, 0])
    R_wp = rotation_from_quat_xyzw([0.1, -0.7, 0.05, 0.7])
    t_wp = np.array([1.0, 2.2, -0.5])
    P_p = np.column_stack([rng.uniform(-0.4, 0.4, 40), rng.uniform(-0.5, 0.0, 40), rng.uniform(1.5, 2.5, 40)])
    world = P_p @ R_wp.T + t_wp
    import cv2

    uv, _ = cv2.projectPoints(P_p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    uv = uv.reshape(-1, 2) + rng.normal(0, 0.1, (40, 2))
    world[7] += [0.05, 0, 0]  # one marker mis-tracked by 5 cm
    pose = projector_pose_from_points(world, uv, K, dist)
    assert not pose.inliers[7] and pose.inliers.sum() == 39
    assert rotation_error_deg(pose.R, R_wp) < 0.02
    assert np.linalg.norm(pose.t - t_wp) < 1e-3


def test_too_few_points():
    with pytest.raises(DegenerateViewsError, match="only 5"):
        projector_pose_from_points(np.zeros((5, 3)), np.zeros((5, 2)), np.eye(3), np.zeros(5))


def test_tracker_pose_file_units_quaternions_and_errors(tmp_path):
    p = tmp_path / "poses.json"
    p.write_text(json.dumps({"units": "mm", "world_from_board": [{"pose": "pose_000", "q": [0, 0, 0, 1], "t": [100, 200, 300]}]}))
    poses = load_tracker_poses(p)
    R, t = poses["pose_000"]
    assert np.allclose(R, np.eye(3)) and np.allclose(t, [0.1, 0.2, 0.3])
    p.write_text(json.dumps({"units": "inch", "world_from_board": []}))
    with pytest.raises(CaptureError, match=r"poses\.json: units"):
        load_tracker_poses(p)
    p.write_text(json.dumps({"world_from_board": [{"pose": "a", "R": [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "t": [0, 0, 0]}]}))
    with pytest.raises(CaptureError, match=r"world_from_board\[0\]\.R"):
        load_tracker_poses(p)
