"""Compare a calibration with the synthetic world's ground truth."""

from __future__ import annotations

import cv2
import numpy as np

from dpmhw.projector_calibration import ProjectorCalibration


def rotation_error_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of ``Ra @ Rb.T`` in degrees."""
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(np.asarray(Ra) @ np.asarray(Rb).T)[0])))


def _lens_rows(who: str, K: np.ndarray, dist: np.ndarray, tK: np.ndarray, tdist: np.ndarray) -> list[dict]:
    rows = []
    for name, est, tru in (("fx", K[0, 0], tK[0, 0]), ("fy", K[1, 1], tK[1, 1]), ("cx", K[0, 2], tK[0, 2]), ("cy", K[1, 2], tK[1, 2])):
        rows.append({"param": f"{who}.{name}", "true": float(tru), "estimated": float(est), "error": float(est - tru),
                     "rel_error": float((est - tru) / tru) if name.startswith("f") else None, "unit": "px"})
    for j, name in enumerate(("k1", "k2", "p1", "p2", "k3")):
        rows.append({"param": f"{who}.{name}", "true": float(tdist[j]), "estimated": float(dist[j]),
                     "error": float(dist[j] - tdist[j]), "rel_error": None, "unit": ""})
    return rows


def compare_with_truth(cal: ProjectorCalibration, truth: dict, *, n_points: int = 2000, seed: int = 0) -> dict:
    """Errors of ``cal`` (world = camera frame or tracker frame) against ``truth``.

    Returns a dict with ``rows`` (parameter table), ``rotation_deg``, ``translation_mm``
    (projector_from_camera), and ``heldout_rms_px`` / ``heldout_max_px``: random points the
    camera and projector both see (0.45-0.95 m), projected with the estimated and the true
    projector model; this is the error the renderer would make.
    """
    tp, tc = truth["projector"], truth["camera"]
    tK, tdist = np.array(tp["K"]), np.array(tp["dist"])
    rows = _lens_rows("projector", cal.K, cal.dist, tK, tdist)
    if cal.camera is not None:
        rows += _lens_rows("camera", cal.camera.K, cal.camera.dist, np.array(tc["K"]), np.array(tc["dist"]))
    out: dict = {"rows": rows}
    if cal.frame == "camera":
        R_pc_true = np.array(truth["projector_from_camera"]["R"])
        t_pc_true = np.array(truth["projector_from_camera"]["t"])
        R_pc, t_pc = cal.projector_from_world
        to_world = (np.eye(3), np.zeros(3))
    else:
        Rw, tw = np.array(truth["world_from_camera"]["R"]), np.array(truth["world_from_camera"]["t"])
        R_pw, t_pw = cal.projector_from_world
        R_pc, t_pc = R_pw @ Rw, R_pw @ tw + t_pw
        R_pc_true = np.array(truth["projector_from_camera"]["R"])
        t_pc_true = np.array(truth["projector_from_camera"]["t"])
        to_world = (Rw, tw)
    out["rotation_deg"] = rotation_error_deg(R_pc, R_pc_true)
    out["translation_mm"] = float(np.linalg.norm(t_pc - t_pc_true) * 1000)
    # held-out points, sampled in the projector's frustum and kept where the camera sees them too
    rng = np.random.default_rng(seed)
    w, h = tp["width"], tp["height"]
    uv = np.column_stack([rng.uniform(0, w - 1, 4 * n_points), rng.uniform(0, h - 1, 4 * n_points)])
    rays = cv2.undistortPoints(uv.reshape(-1, 1, 2), tK, tdist).reshape(-1, 2)
    z = rng.uniform(0.45, 0.95, len(rays))
    p_proj = np.column_stack([rays * z[:, None], z])
    p_cam = (p_proj - t_pc_true) @ R_pc_true  # camera frame
    K_c, d_c = np.array(tc["K"]), np.array(tc["dist"])
    uc, _ = cv2.projectPoints(p_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K_c, d_c)
    uc = uc.reshape(-1, 2)
    seen = (p_cam[:, 2] > 0) & (uc[:, 0] >= 0) & (uc[:, 0] < tc["width"]) & (uc[:, 1] >= 0) & (uc[:, 1] < tc["height"])
    p_cam = p_cam[seen][:n_points]
    true_uv, _ = cv2.projectPoints(p_cam.reshape(-1, 1, 3), cv2.Rodrigues(R_pc_true)[0], t_pc_true, tK, tdist)
    Rw, tw = to_world
    est_uv = cal.project(p_cam @ Rw.T + tw)
    err = np.linalg.norm(est_uv - true_uv.reshape(-1, 2), axis=1)
    out["heldout_points"] = int(len(err))
    out["heldout_rms_px"] = float(np.sqrt((err**2).mean()))
    out["heldout_max_px"] = float(err.max())
    return out


def format_table(cmp: dict) -> str:
    lines = [f"{'parameter':<14} {'true':>12} {'estimated':>12} {'error':>11} {'rel':>8}"]
    for r in cmp["rows"]:
        rel = f"{100 * r['rel_error']:.3f}%" if r["rel_error"] is not None else ""
        lines.append(f"{r['param']:<14} {r['true']:>12.5f} {r['estimated']:>12.5f} {r['error']:>+11.5f} {rel:>8}")
    lines.append(f"{'rotation':<14} {'':>12} {'':>12} {cmp['rotation_deg']:>10.4f}° ")
    lines.append(f"{'translation':<14} {'':>12} {'':>12} {cmp['translation_mm']:>8.3f} mm")
    lines.append(
        f"held-out projector reprojection over {cmp['heldout_points']} points: RMS {cmp['heldout_rms_px']:.3f} px, "
        f"max {cmp['heldout_max_px']:.3f} px"
    )
    return "\n".join(lines)
