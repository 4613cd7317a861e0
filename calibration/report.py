"""PNG report of a procam calibration: per-view error bars and residual vectors (OpenCV drawing)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from calibration.procam import ProcamResult

CAM = (200, 120, 30)  # BGR
PROJ = (30, 120, 230)
INK = (40, 40, 40)


def _text(img, s, org, scale=0.45, color=INK):
    cv2.putText(img, s, org, cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def render_report(result: ProcamResult, *, width: int = 1200) -> np.ndarray:
    """(H, W, 3) uint8 BGR image: bars of per-view stereo RMS (camera, projector) on top,
    residual vectors of the final model for both devices below (arrows exaggerated)."""
    names = result.stereo_data.get("names", [])
    rows = result.views_table()
    bar_h, panel_h = 300, 420
    img = np.full((bar_h + panel_h + 40, width, 3), 255, np.uint8)
    _text(img, f"stereo RMS {result.stereo_rms:.3f} px   camera {result.camera.rms:.3f} px   projector {result.projector.rms:.3f} px",
          (10, 20), 0.55)
    # -- bars
    n = max(1, len(rows))
    x0, y0, y1 = 60, 40, bar_h - 40
    vals = [v for r in rows if r["stereo_rms_px"] for v in r["stereo_rms_px"]] + [1e-3]
    vmax = max(0.05, 1.2 * max(vals))
    cv2.line(img, (x0, y1), (width - 10, y1), INK, 1)
    for frac in (0.0, 0.5, 1.0):
        y = int(y1 - frac * (y1 - y0))
        _text(img, f"{frac * vmax:.2f}", (5, y + 4), 0.4)
    slot = (width - x0 - 20) / n
    for i, r in enumerate(rows):
        xs = int(x0 + i * slot + slot * 0.15)
        bw = max(2, int(slot * 0.3))
        if r["stereo_rms_px"]:
            for j, (v, col) in enumerate(zip(r["stereo_rms_px"], (CAM, PROJ))):
                h = int(min(v, vmax) / vmax * (y1 - y0))
                cv2.rectangle(img, (xs + j * bw, y1 - h), (xs + (j + 1) * bw, y1), col, -1)
        else:
            _text(img, "rejected", (xs, y1 - 10), 0.35, (0, 0, 200))
        _text(img, r["name"][-8:], (xs, y1 + 15), 0.3)
    _text(img, "camera", (width - 200, 40), 0.45, CAM)
    _text(img, "projector", (width - 120, 40), 0.45, PROJ)
    # -- residual panels
    res = result.residuals() if names else {"camera": [], "projector": []}
    pw = (width - 30) // 2
    for k, (who, lens, col) in enumerate((("camera", result.camera, CAM), ("projector", result.projector, PROJ))):
        ox, oy = 10 + k * (pw + 10), bar_h + 10
        s = min(pw / lens.width, (panel_h - 20) / lens.height)
        cv2.rectangle(img, (ox, oy), (ox + int(lens.width * s), oy + int(lens.height * s)), INK, 1)
        allr = np.concatenate([r for _, r in res[who]]) if res[who] else np.zeros((1, 2))
        rms = float(np.sqrt((allr**2).sum(axis=1).mean()))
        gain = 0.05 * lens.width * s / max(rms, 1e-6) / 3  # an RMS residual draws 1/60 of the panel width
        for pts, r in res[who]:
            for p, d in zip(pts, r):
                a = (int(ox + p[0] * s), int(oy + p[1] * s))
                b = (int(a[0] + d[0] * gain), int(a[1] + d[1] * gain))
                cv2.line(img, a, b, col, 1, cv2.LINE_AA)
                cv2.circle(img, a, 1, INK, -1)
        _text(img, f"{who} residuals x{gain / s:.0f} (RMS {rms:.3f} px)", (ox + 5, oy + int(lens.height * s) + 18), 0.45)
    return img


def write_report(result: ProcamResult, path: str | Path) -> Path:
    path = Path(path)
    if not cv2.imwrite(str(path), render_report(result)):
        raise OSError(f"{path}: could not write the PNG report")
    return path
