"""The projector's pose in the tracker's world frame, projector intrinsics held fixed.

Two sources of 3D-2D correspondences:

* a **tracked board**: the board carries a rigid body the tracker reports
  (``world_from_board`` per pose, optionally through a fixed ``rigid_body_from_board``);
  its corners' projector pixels come from the Gray code + local homographies exactly as in
  :mod:`calibration.procam`;
* **tracked markers** whose projector pixels are known (e.g. a crosshair moved onto each
  marker): pass them straight to :func:`projector_pose_from_points`.

``solvePnPRansac`` (to drop mis-tracked points) then ``solvePnPRefineLM`` on the inliers
gives projector_from_world; the result is reported as world_from_projector in the tracker's
axes, in metres (positions in millimetres are converted when the input says so).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibration.board import BoardSpec
from calibration.errors import CaptureError, DegenerateViewsError
from calibration.procam import (
    Observation,
    corner_spacing,
    projector_corners,
    undistortion_grid,
)
from dpmhw.transforms import rotation_from_quat_xyzw

UNITS = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}


@dataclass
class TrackerPose:
    """world_from_projector with its residuals.

    R : (3, 3), t : (3,) metres; rms_px / residuals_px : reprojection in projector pixels
    """

    R: np.ndarray
    t: np.ndarray
    rms_px: float
    residuals_px: np.ndarray
    inliers: np.ndarray
    per_view_rms_px: dict[str, float]


def projector_pose_from_points(
    world_points: np.ndarray,
    projector_px: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    *,
    views: list[str] | None = None,
    ransac_px: float = 3.0,
) -> TrackerPose:
    """Projector pose from world points (n, 3) metres and their projector pixels (n, 2).

    ``views`` (n,) optionally labels each point with its board pose for per-view residuals.
    """
    P = np.asarray(world_points, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(projector_px, dtype=np.float64).reshape(-1, 2)
    if len(P) != len(uv):
        raise ValueError(f"{len(P)} world points but {len(uv)} projector pixels")
    ok = np.isfinite(P).all(axis=1) & np.isfinite(uv).all(axis=1)
    if ok.sum() < 6:
        raise DegenerateViewsError("tracker", "points", f"only {int(ok.sum())} usable correspondences; at least 6 are needed")
    idx = np.nonzero(ok)[0]
    found, rvec, tvec, inl = cv2.solvePnPRansac(P[idx], uv[idx], K, dist, reprojectionError=ransac_px,
                                                iterationsCount=500, confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
    if not found or inl is None or len(inl) < 6:
        raise DegenerateViewsError("tracker", "points", "no consistent projector pose: check the tracker units and the board's rigid body")
    inliers = np.zeros(len(P), bool)
    inliers[idx[inl.ravel()]] = True
    sel = np.nonzero(inliers)[0]
    rvec, tvec = cv2.solvePnPRefineLM(P[sel], uv[sel], K, dist, rvec, tvec,
                                      (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))
    R_pw = cv2.Rodrigues(rvec)[0]
    t_pw = tvec.ravel()
    proj, _ = cv2.projectPoints(P[ok].reshape(-1, 1, 3), rvec, tvec, K, dist)
    res = np.full(len(P), np.nan)
    res[ok] = np.linalg.norm(proj.reshape(-1, 2) - uv[ok], axis=1)
    per_view: dict[str, float] = {}
    if views is not None:
        labels = np.asarray(views)
        for v in dict.fromkeys(views):
            m = (labels == v) & inliers
            if m.any():
                per_view[str(v)] = float(np.sqrt(np.mean(res[m] ** 2)))
    return TrackerPose(R_pw.T, -R_pw.T @ t_pw, float(np.sqrt(np.mean(res[inliers] ** 2))), res, inliers, per_view)


def load_tracker_poses(path: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read ``{"units": "m", "rigid_body_from_board": {R, t}?, "world_from_board": [{"pose": name,
    "R": 3x3 | "q": [x, y, z, w], "t": [x, y, z]}, ...]}`` -> name -> world_from_board (metres)."""
    src = str(path)
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CaptureError(src, "(file)", "no such tracker pose file") from None
    except json.JSONDecodeError as exc:
        raise CaptureError(src, "(file)", f"not valid JSON: {exc.msg} at line {exc.lineno}") from None
    units = doc.get("units", "m") if isinstance(doc, dict) else None
    if units not in UNITS:
        raise CaptureError(src, "units", f"expected one of {sorted(UNITS)}, got {units!r}")
    scale = UNITS[units]
    entries = doc.get("world_from_board")
    if not isinstance(entries, list) or not entries:
        raise CaptureError(src, "world_from_board", "missing or empty; expected a list of {pose, R or q, t}")
    offset = doc.get("rigid_body_from_board")
    R_o, t_o = np.eye(3), np.zeros(3)
    if offset is not None:
        R_o, t_o = _pose(offset, "rigid_body_from_board", src, scale)
    out = {}
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not isinstance(e.get("pose"), str):
            raise CaptureError(src, f"world_from_board[{i}].pose", "expected the name of a pose folder")
        R, t = _pose(e, f"world_from_board[{i}]", src, scale)
        out[e["pose"]] = (R @ R_o, R @ t_o + t)
    return out


def _pose(e: dict, field: str, src: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    try:
        R = rotation_from_quat_xyzw(e["q"]) if "q" in e else np.array(e["R"], dtype=np.float64)
        t = np.array(e["t"], dtype=np.float64).reshape(3) * scale
    except (KeyError, TypeError, ValueError):
        raise CaptureError(src, field, "expected R (3x3) or q (x, y, z, w) and t (3 numbers)") from None
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise CaptureError(src, f"{field}.R", "not a rotation matrix")
    return R, t


def projector_pose_from_tracked_board(
    observations: list[Observation],
    world_from_board: dict[str, tuple[np.ndarray, np.ndarray]],
    board: BoardSpec,
    calibration,
    *,
    ransac_px: float = 3.0,
) -> TrackerPose:
    """Projector pose in the tracker frame from board poses the tracker reports.

    ``calibration`` : :class:`dpmhw.projector_calibration.ProjectorCalibration` with a
    ``camera`` (its intrinsics are needed for the local homographies).
    """
    if calibration.camera is None:
        raise DegenerateViewsError("tracker", "camera", "the calibration file has no camera intrinsics; run `calibrate procam` first")
    cam = calibration.camera
    grid = None
    P, uv, labels = [], [], []
    obj = board.object_points()
    for o in observations:
        if o.camera_px is None or o.name not in world_from_board:
            continue
        if grid is None:
            grid = undistortion_grid(cam.K, cam.dist, o.image_size)
        win = int(np.clip(round(0.5 * corner_spacing(o.camera_px, board, o.ids)), 6, 40))
        px, _ = projector_corners(o.decoded, o.camera_px, grid, cam.K, cam.dist, window=win)
        R, t = world_from_board[o.name]
        P.append(obj[o.ids] @ R.T + t)
        uv.append(px)
        labels += [o.name] * len(px)
    if not P:
        raise DegenerateViewsError("tracker", "views", "no pose has both a detected board and a tracker pose with the same name")
    return projector_pose_from_points(np.concatenate(P), np.concatenate(uv), calibration.K, calibration.dist,
                                      views=labels, ransac_px=ransac_px)
