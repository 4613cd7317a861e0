"""`dpmhw bench governor`: the quality governor against a real CPU hog.

One `--mock` session, as `dpmhw bench session` runs it (NatNet mock → real driver → loop →
emulated DLPC900 behind the 60 Hz video link), is measured for `seconds` after its warm-up.
After `hog_after` s, `hog_processes` busy processes start (each a Python `while True: pass`, at
the bench's own priority; default one per core) and run to the end. From the session's frame log:

- **per second** `[k, k + 1)` s after the measurement start: presents, rendered frames (a frame
  replaced before any refresh counts too: rendered numbers are consecutive), the rendered
  frames' median own time, and the governor's level and reason at the end of the second;
- **rates** every 0.1 s over a trailing 1-s window, for the plot and the recovery;
- **recovery**: a rate is *below target* under `target × (1 − governor.down_margin)`, the
  governor's own threshold (the render target is `governor.target_fps`, the present target the
  display's refresh). `*_recovery_s`: from the hog's start until, after the first dip, the
  trailing rate is back at or above the threshold and stays there for `SETTLE_S` (0 if it never
  dropped, None if it was not back before the end); `*_below_s`: the time below the threshold after the hog started;
- then (unless `quality=False`) the PSNR inside the objects of the configuration the governor
  held just before the hog and at the end, beside the configured one
  (`governor_ladder.measure`: the session's stage offline on a few frames against the 64-spp
  references of `dpmhw bench lod`).

Rows are flat dicts with a `kind` ("second", "summary", "quality"); docs/session.md lists the keys.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from dpmhw.machine import cpu_steal, cpu_ticks, steal_percent

__all__ = ["counted", "events", "format_table", "level_steps", "plot", "recovery", "run_governor_hog", "second_rows",
           "summarize", "trailing_rate"]

HOG_CODE = "while True: pass"
WINDOW_S = 1.0  # the trailing window a rate is measured over
STEP_S = 0.1  # the rates' time step
SETTLE_S = 1.0  # back above the threshold for this long counts as recovered
SETTLED_AFTER_S = 2.0  # the "under the hog" rates leave out the hog's first 2 s (the goal's allowance)


# ---- analysis (pure functions of event times: tested on synthetic data) ---------------------

def counted(t: np.ndarray, n: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The running count `n` (non-decreasing, at the sorted event times `t`) at the times `x`:
    the count of the last event at or before each; 0 before the first."""
    if not len(t):
        return np.zeros(np.shape(x))
    i = np.searchsorted(t, x, side="right") - 1
    return np.where(i >= 0, np.asarray(n, float)[np.maximum(i, 0)], 0.0)


def trailing_rate(t: np.ndarray, n: np.ndarray, end_s: float, window_s: float = WINDOW_S, step_s: float = STEP_S):
    """(times, events per second over the `window_s` before each), every `step_s` from
    `window_s` to `end_s`."""
    grid = np.arange(window_s, end_s + 1e-9, step_s)
    return grid, (counted(t, n, grid) - counted(t, n, grid - window_s)) / window_s


def recovery(grid: np.ndarray, rate: np.ndarray, hog_s: float, threshold: float, settle_s: float = SETTLE_S):
    """(recovery_s, below_s) after a hog started at `hog_s` (see the module doc): recovery_s is
    0 if the rate never dropped below `threshold`, None if it was not back (for `settle_s`)
    before the series ends; below_s is the time below it after `hog_s`."""
    step = float(grid[1] - grid[0]) if len(grid) > 1 else 0.0
    after = grid >= hog_s
    low = after & (rate < threshold)
    below_s = round(float(low.sum()) * step, 3)
    if not low.any():
        return 0.0, below_s
    for i in range(int(np.argmax(low)), len(grid)):
        span = (grid >= grid[i]) & (grid <= grid[i] + settle_s + 1e-9)
        if grid[i] + settle_s > grid[-1] + 1e-9:
            break
        if np.all(rate[span] >= threshold):
            return round(float(grid[i] - hog_s), 3), below_s
    return None, below_s


def events(records, t0_ns: int) -> dict[str, np.ndarray]:
    """Event times (s after `t0_ns`) from the loop's frame records (one per present): each
    present with the governor's level then, and each rendered frame once (its end: start + own
    time) with its own time and its running count (from its rendered number, so frames replaced
    before any refresh count too, at the next shown one)."""
    recs = [r for r in records if r.t_present_ns >= t0_ns]
    seen, renders = set(), []
    for r in recs:
        end = (r.t_start_ns - t0_ns) / 1e9 + r.stages_s["frame"]
        if r.rendered not in seen and end >= 0.0:
            seen.add(r.rendered)
            renders.append((end, r.rendered, r.stages_s["frame"] * 1e3))
    renders.sort()
    n = np.array([x[1] for x in renders], float)
    return {"present_t": np.array([(r.t_present_ns - t0_ns) / 1e9 for r in recs]),
            "present_n": np.arange(1, len(recs) + 1, dtype=float),
            "level": np.array([r.governor_level for r in recs], int),
            "render_t": np.array([x[0] for x in renders], float),
            "render_n": n - n[0] + 1 if len(n) else n,
            "frame_ms": np.array([x[2] for x in renders], float)}


def second_rows(ev: dict, seconds: float, hog_s: float, reasons: list[str] | None = None) -> list[dict]:
    """One row per whole second of the measurement (see the module doc); `reasons[k]`: the
    governor's reason read at the end of second k."""
    rows = []
    for k in range(int(math.floor(seconds + 1e-9))):
        lo, hi = float(k), float(k + 1)
        presented = (ev["present_t"] >= lo) & (ev["present_t"] < hi)
        rendered = (ev["render_t"] >= lo) & (ev["render_t"] < hi)
        before_lo, before_hi = counted(ev["render_t"], ev["render_n"], np.array([lo, hi]) - 1e-9)
        shown = ev["level"][presented]
        rows.append({"kind": "second", "t_s": lo, "hog": hi > hog_s, "present_fps": int(presented.sum()),
                     "render_fps": int(before_hi - before_lo),
                     "frame_ms_p50": round(float(np.median(ev["frame_ms"][rendered])), 3) if rendered.any() else None,
                     "governor_level": int(shown[-1]) if len(shown) else None,
                     "governor_level_max": int(shown.max()) if len(shown) else None,
                     "governor_reason": reasons[k] if reasons is not None and k < len(reasons) else None})
    return rows


def level_steps(ev: dict) -> tuple[list[float], list[int]]:
    """The governor's level over time: (times, levels) at the first present and at each change."""
    level, t = ev["level"], ev["present_t"]
    keep = np.flatnonzero(np.r_[True, level[1:] != level[:-1]]) if len(level) else np.zeros(0, int)
    return t[keep].round(4).tolist(), level[keep].tolist()


def _mean_rate(t: np.ndarray, n: np.ndarray, lo: float, hi: float) -> float | None:
    if hi - lo <= 0:
        return None
    c = counted(t, n, np.array([lo, hi]))
    return round(float(c[1] - c[0]) / (hi - lo), 2)


def summarize(ev: dict, seconds: float, hog_s: float, present_target: float, render_target: float, margin: float) -> dict:
    """The summary row's rates and recoveries (see the module doc)."""
    out = {"refresh_hz": present_target, "target_fps": render_target, "threshold_margin": margin,
           "present_threshold_fps": round(present_target * (1 - margin), 3),
           "render_threshold_fps": round(render_target * (1 - margin), 3)}
    for name, t, n in (("present", ev["present_t"], ev["present_n"]), ("render", ev["render_t"], ev["render_n"])):
        grid, rate = trailing_rate(t, n, seconds)
        out[f"{name}_recovery_s"], out[f"{name}_below_s"] = recovery(grid, rate, hog_s, out[f"{name}_threshold_fps"])
        out[f"{name}_fps_quiet"] = _mean_rate(t, n, 0.0, hog_s)
        out[f"{name}_fps_hog"] = _mean_rate(t, n, min(hog_s + SETTLED_AFTER_S, seconds), seconds)
        after = grid >= hog_s
        out[f"{name}_fps_min_hog"] = round(float(rate[after].min()), 2) if after.any() else None
    return out


# ---- the run ---------------------------------------------------------------------------------

def start_hog(processes: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", HOG_CODE], stdin=subprocess.DEVNULL) for _ in range(processes)]


def stop_hog(procs: list[subprocess.Popen]) -> float:
    """Kill the hog's processes; the CPU seconds they used (their rusage)."""
    cpu = 0.0
    for p in procs:
        p.kill()
    for p in procs:
        try:
            _, _, usage = os.wait4(p.pid, 0)
            p.returncode = -9  # reaped here: Popen must not wait for it again
            cpu += usage.ru_utime + usage.ru_stime
        except ChildProcessError:
            pass
    return round(cpu, 3)


def _sleep_until(clock, ns: int) -> None:
    while clock() < ns:
        time.sleep(min(0.05, (ns - clock()) / 1e9))


def run_governor_hog(*, seconds: float = 25.0, hog_after: float = 10.0, hog_processes: int | None = None,
                     warmup_s: float = 2.0, trajectory: str = "rotate-oscillate", overrides: tuple[str, ...] = (),
                     quality: bool = True, progress=None) -> dict:
    """Run the bench (module doc); `progress(text)` hears one line per measured second and each
    later step. Returns {"rows": per-second rows, the summary and the quality rows (flat, for
    JSON), "series": the trailing rates {"present"|"render": (times, rates)} for `plot`}."""
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import build_session
    from dpmhw.session.testing import wait_for

    if not (0 < hog_after < seconds):
        raise ValueError(f"hog_after must be inside the measurement (0 < hog_after < seconds = {seconds:g}), got {hog_after:g}")
    n_hog = hog_processes if hog_processes is not None else (os.cpu_count() or 1)
    say = progress or (lambda text: None)
    cfg = load_session_config(overrides=[f"mock.trajectory={trajectory}", "api.enabled=false", *overrides])
    loop = build_session(cfg, mock=True, frame_log=int((seconds + warmup_s + 10) * 240))
    clock = loop.clock
    hog: list[subprocess.Popen] = []
    hog_cpu_s, reasons, cpu, rendered, ticks = 0.0, [], {}, {}, {}
    load_before = round(os.getloadavg()[0], 2)
    try:
        loop.start()
        if not wait_for(lambda: loop.status()["state"] == "running", 60):
            raise RuntimeError(f"bench governor: the session did not start: {loop.status()['reason']}")
        time.sleep(warmup_s)
        t0 = clock()
        cpu["quiet"], rendered["quiet"], ticks["quiet"] = time.process_time(), loop.status()["frames_rendered"], cpu_ticks()
        hog_ns = t0 + int(hog_after * 1e9)
        last = loop.status()
        for k in range(int(math.ceil(seconds))):
            end_ns = t0 + int(min(k + 1, seconds) * 1e9)
            if not hog and hog_ns <= end_ns:  # the hog starts inside this second
                _sleep_until(clock, hog_ns)
                cpu["hog"], rendered["hog"], ticks["hog"] = time.process_time(), loop.status()["frames_rendered"], cpu_ticks()
                hog, hog_ns = start_hog(n_hog), clock()
            _sleep_until(clock, end_ns)
            st = loop.status()
            g = st["governor"]
            reasons.append(g["reason"])
            say(f"t {k + 1:>3d} s  {f'hog ({n_hog} processes)' if hog else 'quiet':<17}  "
                f"presents {st['frame_number'] - last['frame_number']:>3d}  renders {st['frames_rendered'] - last['frames_rendered']:>3d}  "
                f"{g['rung']}")
            last = st
        status = loop.status()
        cpu["end"], rendered["end"], ticks["end"] = time.process_time(), status["frames_rendered"], cpu_ticks()
        records = list(loop.frame_log)
    finally:
        if hog:
            hog_cpu_s = stop_hog(hog)
        loop.stop()
    hog_s = (hog_ns - t0) / 1e9
    ev = events(records, t0)
    rows = second_rows(ev, seconds, hog_s, reasons)
    g = status["governor"]

    def cpu_per_render(a: str, b: str) -> float | None:
        n = rendered[b] - rendered[a]
        return round((cpu[b] - cpu[a]) * 1e3 / n, 3) if n > 0 else None

    before = [r for r in records if r.t_present_ns < hog_ns]
    held = {"configured": (0, cfg.live_settings()),
            "before the hog": (before[-1].governor_level, before[-1].settings) if before else None,
            "at the end": (records[-1].governor_level, records[-1].settings) if records else None}
    summary = {"kind": "summary", "scene": cfg.scene.source, "trajectory": trajectory, "display": cfg.display.mode,
               "shading_scale": cfg.render.shading_scale, "output_width": status["output_size"][0],
               "output_height": status["output_size"][1], "seconds": seconds, "hog_after_s": round(hog_s, 3),
               "hog_processes": n_hog, "hog_cpu_s": hog_cpu_s, "load_before": load_before,
               "cpu_steal_quiet": cpu_steal(ticks["quiet"], ticks.get("hog")),
               "cpu_steal_hog": cpu_steal(ticks.get("hog"), ticks["end"]),
               **summarize(ev, seconds, hog_s, float(status["display"]["refresh_hz"]), float(g["target_fps"]),
                           cfg.governor.down_margin),
               "governor_enabled": g["enabled"], "level_before_hog": held["before the hog"] and held["before the hog"][0],
               "level_end": held["at the end"] and held["at the end"][0], "governor_changes": g["changes"],
               "governor_reason": g["reason"], "cpu_ms_per_render_quiet": cpu_per_render("quiet", "hog"),
               "cpu_ms_per_render_hog": cpu_per_render("hog", "end"), "late_presents": status["counters"].get("late_presents", 0)}
    rows.append(summary)
    if quality:
        rows += _quality_rows(cfg, held, say)
    series = {name: tuple(np.round(x, 4).tolist() for x in trailing_rate(ev[f"{name}_t"], ev[f"{name}_n"], seconds))
              for name in ("present", "render")}
    series["level"] = level_steps(ev)
    return {"rows": rows, "series": series}


def _quality_rows(cfg, held: dict, say) -> list[dict]:
    """PSNR of each distinct configuration held (the configured one first), offline."""
    from dpmhw.benchmarks.governor_ladder import measure

    configs: dict[int, dict] = {}  # by level: one level is one configuration within a run
    for name, got in held.items():
        if got is None:
            continue
        level, settings = got
        if level in configs:
            configs[level]["held"] += f" / {name}"
        else:
            s = settings.model_dump()
            configs[level] = {"level": level, "held": name, **{k: s[k] for k in ("filter", "adaptive_rays", "reuse_mode", "alpha")}}
    say(f"quality: PSNR inside the objects of {len(configs)} configuration(s) against the 64-spp references")
    rows = measure(cfg.scene.source, list(configs.values()), reps=1, frames=range(6, 19), eval_k=(18,),
                   shading_scale=cfg.render.shading_scale)
    return [{"kind": "quality", **r} for r in rows]


# ---- output ------------------------------------------------------------------------------------

def format_table(rows: list[dict]) -> str:
    seconds = [r for r in rows if r["kind"] == "second"]
    s = next(r for r in rows if r["kind"] == "summary")
    lines = [f"{'t (s)':>6} {'hog':>4} {'presents/s':>10} {'renders/s':>9} {'frame p50 ms':>12} {'level':>5}  governor's reason"]
    for r in seconds:
        fm = "-" if r["frame_ms_p50"] is None else f"{r['frame_ms_p50']:.1f}"
        lines.append(f"{r['t_s']:>6.0f} {'on' if r['hog'] else '':>4} {r['present_fps']:>10d} {r['render_fps']:>9d} {fm:>12} "
                     f"{'-' if r['governor_level'] is None else r['governor_level']:>5}  {r['governor_reason'] or ''}")

    def rec(x):
        return "never dropped" if x == 0.0 else "not back before the end" if x is None else f"{x:.1f} s"

    lines += [
        f"{s['scene']} {s['output_width']}×{s['output_height']} (shading ×{s['shading_scale']:g}), {s['display']} at "
        f"{s['refresh_hz']:g} Hz; {s['hog_processes']} hog processes from t = {s['hog_after_s']:.1f} s "
        f"({s['hog_cpu_s']:.1f} CPU-s), load average {s['load_before']} before; the host's steal "
        f"{steal_percent(s.get('cpu_steal_quiet'))} quiet, {steal_percent(s.get('cpu_steal_hog'))} under the hog",
        f"presents: {s['present_fps_quiet']}/s quiet, {s['present_fps_hog']}/s under the hog (after its first "
        f"{SETTLED_AFTER_S:g} s), min {s['present_fps_min_hog']}/s; below {s['present_threshold_fps']:g}/s for "
        f"{s['present_below_s']:.1f} s; back: {rec(s['present_recovery_s'])}",
        f"renders:  {s['render_fps_quiet']}/s quiet, {s['render_fps_hog']}/s under the hog, min {s['render_fps_min_hog']}/s; "
        f"target {s['target_fps']:g}, below {s['render_threshold_fps']:g}/s for {s['render_below_s']:.1f} s; back: "
        f"{rec(s['render_recovery_s'])}",
        f"governor: level {s['level_before_hog']} before the hog, {s['level_end']} at the end, {s['governor_changes']} changes; "
        f"{s['governor_reason']}",
        f"CPU-ms per rendered frame (session process): {s['cpu_ms_per_render_quiet']} quiet, {s['cpu_ms_per_render_hog']} "
        f"under the hog; late presents {s['late_presents']}",
    ]
    for r in (r for r in rows if r["kind"] == "quality"):
        lines.append(f"quality, {r['held']} (level {r['level']}: filter {r['filter']}, adaptive {r['adaptive_rays']}): "
                     f"PSNR {r['psnr_db']:.2f} dB, inside the objects {r['psnr_db_object']:.2f} dB, "
                     f"{r['cpu_ms']:.1f} CPU-ms offline ({r['cpu_vs_level0']:.3f}×)")
    return "\n".join(lines)


def plot(result: dict, path: str | Path, title: str = "") -> Path:
    """Rates over time (trailing 1 s), thresholds, the hog's start, and the governor's level on a
    second axis, from `run_governor_hog`'s result."""
    from matplotlib.figure import Figure

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = result["rows"]
    s = next(r for r in rows if r["kind"] == "summary")
    fig = Figure(figsize=(11, 4.8), dpi=100, layout="constrained")
    ax = fig.subplots()
    same = s["present_threshold_fps"] == s["render_threshold_fps"]
    for name, colour in (("present", "tab:blue"), ("render", "tab:orange")):
        grid, rate = result["series"][name]
        ax.plot(grid, rate, color=colour, lw=1.2, label=f"{name}s/s (trailing {WINDOW_S:g} s)")
        if not (same and name == "render"):
            ax.axhline(s[f"{name}_threshold_fps"], color="0.3" if same else colour, ls=":", lw=1.2,
                       label=f"{'threshold' if same else name + ' threshold'} {s[f'{name}_threshold_fps']:g}/s "
                             f"(target × (1 − {s['threshold_margin']:g}))")
    ax.axvline(s["hog_after_s"], color="k", lw=1.2, ls="--", label=f"hog starts ({s['hog_processes']} busy processes)")
    ax.axvspan(s["hog_after_s"], s["seconds"], color="0.9", zorder=0)
    ax.set(xlabel="time since the measurement started (s)", ylabel="frames per second", xlim=(0, s["seconds"]), ylim=(0, None))
    ax.grid(alpha=0.3)
    lv = ax.twinx()
    t, level = result["series"]["level"]
    if level:
        lv.step([*t, s["seconds"]], [*level, level[-1]], where="post", color="tab:green", lw=1.5,
                label="governor level (at each present)")
    lv.set_ylabel("governor level (0: configured)")
    lv.set_ylim(-0.2, max([4, *level]) + 0.5)
    handles = ax.get_legend_handles_labels()[0] + lv.get_legend_handles_labels()[0]
    ax.legend(handles, [h.get_label() for h in handles], fontsize=8, loc="lower left")
    ax.set_title(title or f"dpmhw bench governor: {s['scene']}, hog at {s['hog_after_s']:.1f} s")
    fig.savefig(path)
    return path
