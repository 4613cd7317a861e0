"""Plots of `dpmhw bench session` (matplotlib, axes with units): registration error and
latency over the measured seconds, and the frame-time histogram, one line per case.

`bench_series` is what `run_case` keeps per case for this; the CLI removes it from the JSON rows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["bench_series", "plot_bench_session"]


def bench_series(records, latency_ms, photon_ns, errors) -> dict:
    """Per-present series of one case: time (s from its first measured present), the rendered
    frame's time and the latency (ms), and the registration error (px) of the photon windows
    measured (at `photon_ns`)."""
    t0 = records[0].t_present_ns
    return {"t_s": [round((r.t_present_ns - t0) / 1e9, 5) for r in records],
            "frame_ms": [round(r.stages_s["frame"] * 1e3, 4) for r in records],
            "latency_ms": [round(x, 4) for x in latency_ms],
            "registration_t_s": [round((t - t0) / 1e9, 5) for t in photon_ns],
            "registration_px": [round(e.mean_px, 4) for e in errors]}


def plot_bench_session(cases: list[dict], series: dict[str, dict], path: str | Path) -> Path:
    """One PNG with three panels for the cases in `cases` (rows of run_bench) whose series exist."""
    from matplotlib.figure import Figure

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(13, 4.2), dpi=100, layout="constrained")
    reg, lat, hist = fig.subplots(1, 3)
    shown = [c for c in cases if c["case"] in series]
    all_frame_ms = np.concatenate([series[c["case"]]["frame_ms"] for c in shown]) if shown else np.zeros(1)
    bins = np.linspace(0, float(np.percentile(all_frame_ms, 99.5)) * 1.05 + 1e-6, 60)
    for c in shown:
        s = series[c["case"]]
        style = "-" if c.get("reprojection") else "--" if c.get("prediction") else ":"
        label = c["case"]
        reg.plot(s["registration_t_s"], s["registration_px"], style, lw=1, label=label)
        lat.plot(s["t_s"], s["latency_ms"], style, lw=0.8, label=label)
        hist.hist(np.clip(s["frame_ms"], 0, bins[-1]), bins=bins, histtype="step", linestyle=style, label=label)
    reg.set(title="Registration error at photon time (mean over the outline)", xlabel="time in the measured window (s)",
            ylabel="error in projector pixels (px)")
    lat.set(title="Latency: tracker exposure → photons", xlabel="time in the measured window (s)", ylabel="latency (ms)")
    hist.set(title="Frame time", xlabel="frame time (ms; the last bin holds the slowest 0.5 %)", ylabel="frames (log scale)",
             yscale="log")
    for ax in (reg, lat, hist):
        ax.grid(alpha=0.3)
    if shown:
        reg.legend(fontsize=8)
    fig.suptitle("dpmhw bench session (solid: late reprojection; dashed: prediction only; dotted: neither)")
    fig.savefig(path)
    return path
