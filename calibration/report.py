"""PNG report of a procam calibration, drawn with matplotlib: per-view stereo RMS bars (camera
and projector, rejected views marked) and the residual vector field of the final model on each
device's image plane, with axes in pixels."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.procam import ProcamResult

__all__ = ["CAMERA_COLOUR", "PROJECTOR_COLOUR", "report_figure", "write_report"]

CAMERA_COLOUR, PROJECTOR_COLOUR = "#1f77b4", "#e6550d"


def report_figure(result: ProcamResult):
    """A matplotlib Figure (no pyplot state, so it is safe in any thread or server)."""
    from matplotlib.figure import Figure

    rows = result.views_table()
    fig = Figure(figsize=(12, 8.5), dpi=100, layout="constrained")
    grid = fig.add_gridspec(2, 2, height_ratios=[1, 1.35])
    fig.suptitle(f"Projector–camera calibration: stereo RMS {result.stereo_rms:.3f} px "
                 f"(camera {result.camera.rms:.3f} px, projector {result.projector.rms:.3f} px)")

    bars = fig.add_subplot(grid[0, :])
    x = np.arange(len(rows))
    cam = [r["stereo_rms_px"][0] if r["stereo_rms_px"] else np.nan for r in rows]
    proj = [r["stereo_rms_px"][1] if r["stereo_rms_px"] else np.nan for r in rows]
    bars.bar(x - 0.2, cam, 0.4, label="camera", color=CAMERA_COLOUR)
    bars.bar(x + 0.2, proj, 0.4, label="projector", color=PROJECTOR_COLOUR)
    for i, r in enumerate(rows):
        if not r["used"]:
            bars.annotate("rejected", (i, 0), xytext=(0, 4), textcoords="offset points", ha="center",
                          rotation=90, va="bottom", color="crimson", fontsize=8)
    bars.set_xticks(x, [r["name"] for r in rows], rotation=45 if len(rows) > 8 else 0, ha="right" if len(rows) > 8 else "center")
    bars.set_xlabel("board pose (view)")
    bars.set_ylabel("RMS reprojection error (px)")
    bars.set_title("Per-view error of the final stereo model")
    bars.legend(loc="upper right")
    bars.grid(axis="y", alpha=0.3)

    res = result.residuals() if result.stereo_data.get("names") else {"camera": [], "projector": []}
    for k, (who, lens, colour) in enumerate((("camera", result.camera, CAMERA_COLOUR),
                                              ("projector", result.projector, PROJECTOR_COLOUR))):
        ax = fig.add_subplot(grid[1, k])
        if res[who]:
            pts = np.concatenate([p for p, _ in res[who]])
            d = np.concatenate([r for _, r in res[who]])
            rms = float(np.sqrt((d ** 2).sum(axis=1).mean()))
            gain = 0.02 * lens.width / max(rms, 1e-9)  # an RMS-sized residual draws 2 % of the image width
            ax.quiver(pts[:, 0], pts[:, 1], d[:, 0], d[:, 1], color=colour, angles="xy", scale_units="xy",
                      scale=1 / gain, width=0.002)
            ax.scatter(pts[:, 0], pts[:, 1], s=1, color="0.3")
            ax.set_title(f"{who} residuals, RMS {rms:.3f} px (arrows ×{gain:.0f})")
        else:
            ax.set_title(f"{who} residuals: no view was used")
        ax.set_xlim(0, lens.width)
        ax.set_ylim(lens.height, 0)  # image rows grow downwards
        ax.set_aspect("equal")
        ax.set_xlabel(f"{who} x (px)")
        ax.set_ylabel(f"{who} y (px)")
    return fig


def write_report(result: ProcamResult, path: str | Path) -> Path:
    path = Path(path)
    try:
        report_figure(result).savefig(path)
    except (OSError, ValueError) as exc:
        raise OSError(f"{path}: could not write the report: {exc}") from None
    return path
