"""`dpmhw bench session` plots: series aligned with the frames they describe, and a PNG with axes."""

from __future__ import annotations

from types import SimpleNamespace

import cv2

from dpmhw.benchmarks.session_plots import bench_series, plot_bench_session


def _case(n: int = 50, step: int = 5):
    records = [SimpleNamespace(t_present_ns=1_000_000_000 + k * 2_000_000, stages_s={"frame": 0.001 * (1 + k % 7)})
               for k in range(n)]
    photon = [r.t_present_ns + 500_000 for r in records[::step]]
    errors = [SimpleNamespace(mean_px=0.1 * k) for k in range(len(photon))]
    return bench_series(records, [7.0] * n, photon, errors)


def test_series_times_start_at_zero_and_pair_with_errors():
    s = _case()
    assert s["t_s"][0] == 0.0 and s["t_s"][-1] == 0.098
    assert len(s["registration_t_s"]) == len(s["registration_px"]) == 10
    assert s["registration_t_s"][:2] == [0.0005, 0.0105]  # every 5th present, 2 ms apart, photons 0.5 ms after
    assert s["frame_ms"][:3] == [1.0, 2.0, 3.0]


def test_plot_writes_a_png_with_all_cases(tmp_path):
    cases = [{"case": "linear prediction=on", "prediction": True}, {"case": "linear prediction=off", "prediction": False}]
    series = {c["case"]: _case() for c in cases}
    path = plot_bench_session(cases, series, tmp_path / "sub" / "bench.png")
    img = cv2.imread(str(path))
    assert img is not None and img.shape[:2] == (420, 1300)
