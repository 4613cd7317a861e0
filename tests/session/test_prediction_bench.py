"""`dpmhw bench prediction`: flat rows, deterministic, and the models behave as their maths says."""

import pytest

from dpmhw.benchmarks.prediction import PredictionBenchConfig, format_table, run_prediction


def test_rows_are_flat_and_the_models_rank_as_expected_without_and_with_noise():
    cfg = PredictionBenchConfig(noise_mm=(0.0, 2.0), seconds=4.0, methods=(("velocity", 8), ("acceleration", 12)))
    rows = run_prediction(cfg)
    assert rows == run_prediction(cfg)  # deterministic (seeded noise)
    assert all(isinstance(v, (int, float, str)) for r in rows for v in r.values())
    err = {(r["noise_mm"], r["model"]): r["error_mm_p99"] for r in rows}
    # exact samples of a curved path: the parabola fit beats constant velocity by far
    assert err[(0.0, "acceleration")] < 0.2 * err[(0.0, "velocity")]
    # 2 mm marker noise: the acceleration fit over 12 samples amplifies it more than the velocity fit
    assert err[(2.0, "acceleration")] > err[(2.0, "velocity")]
    assert "35 ms ahead" in format_table(rows)


@pytest.mark.parametrize("kw, field", [({"horizon_ms": 0.0}, "horizon_ms"), ({"noise_mm": (-1.0,)}, "noise_mm"),
                                       ({"rate_hz": 0.5}, "rate_hz")])
def test_bad_settings_name_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        PredictionBenchConfig(**kw)
