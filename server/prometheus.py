"""The status snapshot in Prometheus text exposition format (version 0.0.4)."""

from __future__ import annotations

import math

_STATES = ("starting", "running", "blanked", "fault", "stopped")


def _num(v) -> str:
    if v is None:
        return "NaN"
    if isinstance(v, float) and math.isinf(v):
        return "+Inf" if v > 0 else "-Inf"
    return repr(float(v)) if isinstance(v, float) else str(v)


def render_metrics(status: dict) -> str:
    lines: list[str] = []

    def metric(name: str, kind: str, help_: str, samples: list[tuple[str, object]]) -> None:
        lines.append(f"# HELP {name} {help_}")
        lines.append(f"# TYPE {name} {kind}")
        for labels, value in samples:
            lines.append(f"{name}{labels} {_num(value)}")

    state = status.get("state", "")
    metric("dpmhw_session_state", "gauge", "1 for the session's current state.",
           [(f'{{state="{s}"}}', int(s == state)) for s in _STATES])
    metric("dpmhw_fps", "gauge", "Presented frames per second over the rolling window.", [("", status.get("fps", 0.0))])
    counters = status.get("counters", {})
    metric("dpmhw_frames_presented_total", "counter", "Frames sent to the projector.", [("", counters.get("frames_presented", 0))])
    metric("dpmhw_deadline_misses_total", "counter", "Frames slower than 1/target_fps.", [("", counters.get("deadline_misses", 0))])
    metric("dpmhw_frames_dropped_total", "counter", "Frames rendered but not presented (output dark) or failed.",
           [("", counters.get("frames_withheld", 0) + counters.get("present_errors", 0) + counters.get("render_errors", 0))])
    metric("dpmhw_blanks_total", "counter", "Times the output went dark.", [("", counters.get("blanks", 0))])
    metric("dpmhw_faults_total", "counter", "Times each safety cause became active.",
           [(f'{{cause="{k}"}}', v) for k, v in sorted(status.get("faults", {}).items())] or [('{cause="none"}', 0)])
    lat = status.get("latency_ms", {})
    metric("dpmhw_latency_seconds_quantile", "gauge", "Motion-to-photon latency over the rolling window.",
           [(f'{{quantile="{q}"}}', None if lat.get(k) is None else lat[k] / 1e3)
            for q, k in (("0.5", "p50"), ("0.95", "p95"), ("0.99", "p99"))])
    metric("dpmhw_stage_seconds_mean", "gauge", "Mean duration of each loop stage over the rolling window.",
           [(f'{{stage="{name}"}}', None if v.get("mean_ms") is None else v["mean_ms"] / 1e3)
            for name, v in status.get("stages_ms", {}).items()])
    for name, help_ in (("latency_seconds", "Motion-to-photon latency (tracker mid-exposure to present)."),
                        ("frame_seconds", "Loop iteration time (frame start to present).")):
        h = status.get("histograms", {}).get(name)
        if not h:
            continue
        full = f"dpmhw_{name}"
        lines.append(f"# HELP {full} {help_}")
        lines.append(f"# TYPE {full} histogram")
        for bound, count in h["buckets"]:
            lines.append(f'{full}_bucket{{le="{bound:g}"}} {count}')
        lines.append(f'{full}_bucket{{le="+Inf"}} {h["count"]}')
        lines.append(f"{full}_sum {_num(float(h['sum']))}")
        lines.append(f"{full}_count {h['count']}")
    return "\n".join(lines) + "\n"
