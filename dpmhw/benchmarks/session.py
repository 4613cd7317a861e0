"""`dpmhw bench session`: the whole system on the firmware mocks, measured against ground truth.

Each case runs a `--mock` session (NatNet mock at 360 Hz → real NatNet driver → loop → emulated
DLPC900 + in-memory sink) for a few seconds and reports fps, motion-to-photon latency and the
frame-time percentiles from the loop's own metrics, plus the registration error of the presented
frames against the simulated world's true pose at the moment each frame was presented.

The API-load case serves one session's API from its own process (`server.process.ApiProcess`, as
`dpmhw session start` does) and then from a thread of the session's process, each time with a
separate process of clients polling /status, /metrics and /frame.png (each at most `rate_hz`
requests/s: bounded) during every other window, so loaded and unloaded frame times come from the
same session under the same machine conditions. The p99 ratio comes with a 90 % interval
(resampling whole windows) and the unloaded-vs-unloaded ratio as its noise floor.
"""

from __future__ import annotations

import hashlib
import math
import multiprocessing
import os
import queue
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from dpmhw.benchmarks.load_process import LoadProcess, run_threads
from dpmhw.benchmarks.session_plots import bench_series
from dpmhw.machine import cpu_steal, cpu_ticks, steal_percent
from dpmhw.session.config import MOCK_EXPOSURE_ROWS_MAX, REFRESH_HZ_MAX, load_session_config
from dpmhw.session.testing import wait_for
from dpmhw.transforms import Pose

__all__ = ["BenchCase", "format_table", "run_bench", "run_case"]


@dataclass(frozen=True)
class BenchCase:
    trajectory: str
    prediction: bool
    reprojection: bool = True  # the late reprojection at each present

    @property
    def label(self) -> str:
        onoff = lambda b: "on" if b else "off"  # noqa: E731
        return f"{self.trajectory} prediction={onoff(self.prediction)} reprojection={onoff(self.reprojection)}"


def _pct(values, qs=(50, 95, 99)):
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return [None if not len(v) else round(float(x), 3) for x in (np.percentile(v, qs) if len(v) else [0] * len(qs))]


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process so far (Linux /proc; None elsewhere)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _load_clients(port: int, clients: int, rate_hz: float, priority: str, counts, active, stop, ready, out) -> None:
    """The load generator's process: `clients` threads polling the read endpoints (bounded), each
    on one keep-alive connection with the standard library's client (little CPU of its own, like
    a dashboard or a Prometheus scraper); (ok, failed) counted live in `counts`, each client's
    response times put on `out` when it stops."""
    import http.client

    from server.process import lower_priority

    lower_priority(priority)
    period_s = 1.0 / rate_hz if rate_hz > 0 else 0.0
    paths = ("/status", "/metrics", "/frame.png")

    def client(_: int) -> None:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5.0)
        seconds: list[float] = []
        k = 0
        while not stop.is_set():
            if not active.wait(0.05):
                continue
            t0 = time.monotonic()
            try:
                conn.request("GET", paths[k % len(paths)])
                response = conn.getresponse()
                response.read()
                failed = int(response.status != 200)
                seconds.append(time.monotonic() - t0)
            except (OSError, http.client.HTTPException):
                conn.close()  # reconnects on the next request
                failed = 1
            with counts.get_lock():
                counts[failed] += 1
            k += 1
            stop.wait(max(0.0, period_s - (time.monotonic() - t0)))
        conn.close()
        out.put(seconds)

    run_threads(clients, client, ready)


class _LoadClients(LoadProcess):
    """`_load_clients` in a process of its own; they send only while `active` is set (the load
    windows)."""

    def __init__(self, port: int, clients: int, rate_hz: float, priority: str):
        self.counts = multiprocessing.get_context("spawn").Array("q", 2)  # ok, failed
        super().__init__("api-load-clients", _load_clients, (port, clients, rate_hz, priority, self.counts))
        self.clients = clients
        self.response_ms: list[float] = []

    def _collect(self) -> None:
        for _ in range(self.clients):
            try:
                self.response_ms += [x * 1e3 for x in self._out.get(timeout=10)]
            except queue.Empty:  # a client is stuck: its times are lost, the counts are not
                break


class _ApiLoad:
    """The session's API, served as `mode` says, plus a separate process of load clients.

    mode "process": `server.process.ApiProcess`, as `dpmhw session start` runs it;
    mode "thread": uvicorn on a thread of the session's own process (for comparison).
    The clients never share the session's process, like real ones.
    """

    def __init__(self, loop, mode: str, clients: int, rate_hz: float = 10.0, client_priority: str = "normal"):
        self.loop = loop
        self.api = self.server = None
        if mode == "process":
            from server.process import ApiProcess

            self.api = ApiProcess(host="127.0.0.1", port=0, token="bench", priority=loop.config.api.priority)
            self.port = self.api.port
        elif mode == "thread":
            import uvicorn

            from server.app import build_app

            self.sock = socket.create_server(("127.0.0.1", 0))
            self.port = self.sock.getsockname()[1]
            self.server = uvicorn.Server(uvicorn.Config(build_app(runtime=loop, token="bench"), log_level="warning"))
            self.server_thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)
        else:
            raise ValueError(f"api mode must be 'process' or 'thread', not {mode!r}")
        self.clients = _LoadClients(self.port, clients, rate_hz, client_priority)
        self.active = self.clients.active
        self.cpu_s: dict[str, float | None] = {}

    @property
    def requests(self) -> int:
        return int(self.clients.counts[0])

    @property
    def errors(self) -> int:
        return int(self.clients.counts[1])

    @property
    def response_ms(self) -> list[float]:
        return self.clients.response_ms

    def __enter__(self) -> "_ApiLoad":
        if self.api is not None:
            self.api.start(self.loop)
        else:
            self.server_thread.start()
            if not wait_for(lambda: self.server.started, 10):
                raise RuntimeError("bench: the API server did not start on 127.0.0.1")
        self.clients.__enter__()
        time.sleep(0.5)  # let start-up work (imports, JIT) settle before the first window
        self._cpu0 = self._cpu()
        return self

    def _cpu(self) -> dict[str, float | None]:
        return {"clients": _cpu_seconds(self.clients.process.pid),
                "api": _cpu_seconds(self.api.process.pid) if self.api is not None else None}

    def __exit__(self, *exc) -> None:
        cpu = self._cpu()  # spent during the windows (start-up excluded)
        self.cpu_s = {k: None if v is None or self._cpu0[k] is None else v - self._cpu0[k] for k, v in cpu.items()}
        self.clients.close()
        if self.api is not None:
            self.api.close()
        else:
            self.server.should_exit = True
            self.server_thread.join(10)
            self.sock.close()


STAGE_KEYS = ("gbuffer", "render", "reuse", "filter", "upsample", "adaptive", "lod", "mesh_lod", "post", "capture", "frame",
              "reproject", "reproject_cpu", "present")


MEASURED_POSE_EVERY = 4  # the measured-pose comparison on every 4th evaluated window (a reference, not the goal)
EXPOSURES_PER_S_MAX = 3 * int(REFRESH_HZ_MAX)  # lit (sub-)frames a second at most: 3 sub-frames a refresh


def _slowed_presents(reprojector, factor: float) -> None:
    """Each kernel call of this reprojector's presents (`Reprojector._splats`, on the present
    thread or its helper) spends `factor` times its own CPU time on its thread, the extra in
    work that releases the GIL as the kernel does: the present of a CPU `factor` times slower
    (only the present's kernels: the renders run at this machine's speed)."""
    splats, block = reprojector._splats, bytes(32768)

    def slowed(*args):
        cpu0 = time.thread_time_ns()
        splats(*args)
        end = time.thread_time_ns() + int((time.thread_time_ns() - cpu0) * (factor - 1.0))
        while time.thread_time_ns() < end:
            hashlib.sha256(block)  # ~20 µs each, without the GIL (hashlib releases it over large buffers)

    reprojector._splats = slowed


def run_case(case: BenchCase, *, seconds: float = 4.0, warmup_s: float = 1.5, width: int = 0, height: int = 0,
             spp: int = 1, max_eval_windows: int = 1000, overrides: tuple[str, ...] = (), present_cpu_factor: float = 1.0,
             progress=None) -> dict:
    """Run one mocked session and measure it (see module doc). width/height: the output size
    (0: the projector's native size); the shading scale and filter come from `overrides`.

    The row is flat (docs/session.md, "Session benchmark JSON"): scene, method, shading_scale,
    filter, alpha, display, reprojection, output_width, output_height, fps (presents/s),
    fps_median (1 / median present interval), render_fps, latency_ms_p50/p95/p99 (sample exposure →
    photon mid), frame_ms_p50/p95/p99 (rendered frames), registration_px_p50/p99 at photon time over
    every photon window (up to `max_eval_windows`, else evenly spaced ones; the measured-pose variant on every
    `MEASURED_POSE_EVERY`th of them) (and _max_, measured-pose and vertex variants; registration_px_p99_window<k>
    per sub-frame in pattern mode), <stage>_ms_p50 for every
    loop stage, late_presents, shared_pose_presents and split_presents (while measured), new_windows_per_s and repeated_windows (the emulated
    projector's), frame counts, present_cpu_factor. `present_cpu_factor` > 1: every kernel call
    of a present spends that many times its CPU time, as on a slower CPU (`_slowed_presents`).
    `progress(text)` hears how the analysis goes."""
    from dpmhw.render.cameras import PinholeCamera
    from dpmhw.session.factory import build_session, prepare_scene
    from dpmhw.session.registration import registration_error

    rows = min(MOCK_EXPOSURE_ROWS_MAX, 4096 + math.ceil((warmup_s + seconds) * EXPOSURES_PER_S_MAX))  # the whole measurement
    cfg = load_session_config(overrides=[
        f"mock.trajectory={case.trajectory}", f"prediction.enabled={str(case.prediction).lower()}",
        f"prediction.late_reprojection={str(case.reprojection).lower()}", f"render.width={width}", f"render.height={height}", f"render.spp={spp}",
        "api.enabled=false", f"mock.exposure_rows={rows}", *overrides])
    loop = build_session(cfg, mock=True, frame_log=100_000)
    if present_cpu_factor != 1.0 and loop.reprojector is not None:
        _slowed_presents(loop.reprojector, present_cpu_factor)
    try:
        loop.start()
        if not wait_for(lambda: loop.status()["state"] == "running", 60):
            raise RuntimeError(f"bench {case.label}: the session did not start: {loop.status()['reason']}")
        time.sleep(warmup_s)
        before = loop.status()
        first, cpu0 = before["frame_number"], time.process_time()
        ticks0 = cpu_ticks()
        time.sleep(seconds)
        status, cpu_s, steal = loop.status(), time.process_time() - cpu0, cpu_steal(ticks0, cpu_ticks())
        records = [r for r in list(loop.frame_log) if r.number > first and r.number <= status["frame_number"]]
        world = loop.parts.mock.world
        video = list(loop.parts.mock.video.exposures) if getattr(loop.parts.mock, "video", None) is not None else None
    finally:
        loop.stop()
    if len(records) < 2:
        raise RuntimeError(f"bench {case.label}: only {len(records)} frames in {seconds} s")
    # ground truth at native projector resolution: errors in the projector's own pixels
    native_cfg = load_session_config(overrides=[*overrides, "render.width=0", "render.height=0"])
    scene = prepare_scene(native_cfg)
    camera = PinholeCamera(scene.camera.K, scene.camera.dist, scene.render.width, scene.render.height, scene.camera.pose)
    (index, body), = loop.parts.bindings.items()
    mesh = scene.objects[index].mesh
    shown = _photon_windows(records, video)
    step = max(1, len(shown) // max_eval_windows)
    if len(records[0].windows) > 1 and step % len(records[0].windows) == 0:
        step += 1  # every sub-frame in turn, not always the same one
    evaluated = shown[::step]
    errors, measured = [], []
    for k, (t_photon, r, pose, _) in enumerate(evaluated):
        if progress is not None and k % 50 == 0:
            progress(f"{case.label}: registration of photon window {k + 1}/{len(evaluated)}")
        truth = Pose(*world.pose(body, t_photon / 1e9))
        errors.append(registration_error(camera, mesh.vertices, mesh.faces, pose[body], truth))
        if k % MEASURED_POSE_EVERY == 0:  # had it shown the measured pose: paired on identical timing
            measured.append(registration_error(camera, mesh.vertices, mesh.faces, r.measured[body], truth))
    rendered = {r.rendered: r for r in records}  # a frame presented more than once counts once
    frame_ms = [r.stages_s["frame"] * 1e3 for r in rendered.values()]
    latency_ms = [(sum(t for t, _ in r.windows) / len(r.windows) - r.sample_t_ns[body]) / 1e6 for r in records]
    span_s = (records[-1].t_present_ns - records[0].t_present_ns) / 1e9
    intervals_s = np.diff([r.t_present_ns for r in records]) / 1e9
    out = {
        "case": case.label, "present_cpu_factor": present_cpu_factor, "scene": cfg.scene.source, "method": _method(cfg), "trajectory": case.trajectory,
        "prediction": case.prediction, "shading_scale": cfg.render.shading_scale, "filter": cfg.render.filter,
        "alpha": cfg.reuse.alpha, "reuse_mode": cfg.reuse.mode, "spp": spp, "reprojection": case.reprojection,
        "display": getattr(getattr(cfg, "display", None), "mode", "video"), "photon_windows": len(records[0].windows),
        "output_width": status["output_size"][0], "output_height": status["output_size"][1],
        "shading_width": status["render_size"][0], "shading_height": status["render_size"][1],
        "frames": len(records), "fps": round((len(records) - 1) / span_s, 2) if span_s > 0 else 0.0,
        "fps_median": round(1.0 / float(np.median(intervals_s)), 2) if len(intervals_s) and np.median(intervals_s) > 0 else 0.0,
        "render_fps": round((len(rendered) - 1) / span_s, 2) if span_s > 0 else 0.0,
        # the session process's CPU (frame, present, tracker and mock threads) per rendered frame
        "cpu_ms_per_rendered_frame": round(cpu_s * 1e3 / max(1, status["frames_rendered"] - before["frames_rendered"]), 3),
        # while measured: presents that missed their refresh, and pattern presents whose sub-frames shared a pose
        **{k: status["counters"].get(k, 0) - before["counters"].get(k, 0) for k in ("late_presents", "shared_pose_presents", "split_presents")},
        "cpu_steal": steal,  # of the machine's CPU time while measured, the host gave to other guests (None: no /proc/stat)
        **_light_counts(video, records),
        # the quality governor's levels over the measured frames (0: the configured settings) and its last reason
        "governor_level_min": min(r.governor_level for r in records),
        "governor_level_max": max(r.governor_level for r in records),
        "governor_reason": status["governor"]["reason"],
    }
    for prefix, values, qs in (("latency_ms", latency_ms, (50, 95, 99)), ("frame_ms", frame_ms, (50, 95, 99)),
                               ("registration_px", [e.mean_px for e in errors], (50, 99)),
                               ("registration_max_px", [e.max_px for e in errors], (50, 99)),
                               ("registration_measured_pose_px", [e.mean_px for e in measured], (50, 99)),
                               ("vertex_px", [e.vertex_px for e in errors], (50, 99))):
        out.update({f"{prefix}_p{q}": v for q, v in zip(qs, _pct(values, qs))})
    for stage in STAGE_KEYS:
        out[f"{stage}_ms_p50"] = _pct([r.stages_s.get(stage, np.nan) * 1e3 for r in records], (50,))[0]
    out["reproject_cpu_ms_p99"] = _pct([r.stages_s.get("reproject_cpu", np.nan) * 1e3 for r in records], (99,))[0]
    out.update({"horizon_ms_mean": status["prediction_horizon_ms"]["mean"], "evaluated_windows": len(errors),
                "projector_width": scene.render.width, "projector_height": scene.render.height})
    for w in range(len(records[0].windows) if len(records[0].windows) > 1 else 0):  # per sub-frame
        out[f"registration_px_p99_window{w}"] = _pct([e.mean_px for e, (*_, k) in zip(errors, evaluated) if k == w], (99,))[0]
    out["series"] = bench_series(records, latency_ms, [t for t, *_ in evaluated], errors)  # for the plots; not a JSON row
    return out


def _light_counts(exposures, records) -> dict:
    """From the emulated projector, over the measured presents' span (the part of it its log
    still holds): (sub-)frames lit per second with a new picture (`new_windows_per_s`: 180 in
    pattern mode at 60 Hz when every present makes its refresh) and those lit again for want of
    one (`repeated_windows`: each shows its picture a period after the instant it was predicted
    for). None without it."""
    if exposures is None:
        return {"new_windows_per_s": None, "repeated_windows": None}
    t0, t1 = records[0].t_present_ns, records[-1].t_present_ns
    if exposures:
        t0 = max(t0, exposures[0].scanout_ns)  # the log keeps the newest rows only
    inside = [e for e in exposures if t0 <= e.scanout_ns < t1]
    fresh = sum(not e.repeat for e in inside)
    return {"new_windows_per_s": round(fresh / ((t1 - t0) / 1e9), 2) if t1 > t0 else 0.0,
            "repeated_windows": len(inside) - fresh}


def _photon_windows(records, exposures) -> list[tuple[int, object, dict, int]]:
    """(photon mid ns, record, {body: pose shown}, window index) for every photon window the presents lit.

    With the emulated projector's exposures (`exposures`), the truth is what it lit and when:
    each exposure belongs to the last present scanned out at or before it (a refresh with no new
    frame shows the previous one again, at other poses than it was made for), and its channel
    names the window. Without them, the presents' own windows."""
    if exposures is None:
        return [(t, r, pose, k) for r in records for k, (t, pose) in enumerate(r.windows)]
    at = np.array([r.t_present_ns for r in records])
    shown_by = np.searchsorted(at, [e.scanout_ns for e in exposures], side="right") - 1
    out = []
    for e, i in zip(exposures, shown_by):
        if i < 0 or e.scanout_ns > at[-1]:
            continue  # before the measured presents, or after them
        r = records[i]
        k = e.channel if len(r.windows) > 1 and e.channel is not None else 0
        out.append(((e.t_start_ns + e.t_end_ns) // 2, r, r.windows[k][1], k))
    return out


def _method(cfg) -> str:
    """Short name of the reconstruction a session ran, e.g. "1/4 + reuse 0.2 + lobe"."""
    scale = {1.0: "native", 0.5: "1/2", 0.25: "1/4"}[cfg.render.shading_scale]
    reuse = "" if cfg.reuse.mode == "off" else f" + reuse {cfg.reuse.alpha:g}"
    return f"{scale}{reuse} + {cfg.render.filter}"


def run_load_case(trajectory: str = "rotate-oscillate", *, modes: tuple[str, ...] = ("process", "thread"),
                  clients: int = 4, rate_hz: float = 10.0, client_priority: str = "normal", windows: int = 6,
                  window_s: float = 3.0, warmup_s: float = 1.5, width: int = 0, height: int = 0, spp: int = 1,
                  overrides: tuple[str, ...] = ()) -> list[dict]:
    """Frame time with and without API load, in alternating windows of one session (the same
    machine conditions for both), for each way of serving the API (`_ApiLoad`)."""
    from dpmhw.session.factory import build_session

    cfg = load_session_config(overrides=[
        f"mock.trajectory={trajectory}", f"render.width={width}", f"render.height={height}", f"render.spp={spp}",
        "api.enabled=false", *overrides])
    loop = build_session(cfg, mock=True, frame_log=100_000)
    spans = {(m, loaded): [] for m in modes for loaded in (False, True)}
    counts = {}
    try:
        loop.start()
        if not wait_for(lambda: loop.status()["state"] == "running", 60):
            raise RuntimeError(f"bench load: the session did not start: {loop.status()['reason']}")
        time.sleep(warmup_s)
        for mode in modes:
            with _ApiLoad(loop, mode, clients, rate_hz, client_priority) as load:
                for w in range(2 * windows):
                    loaded = w % 2 == 1
                    if loaded:
                        load.active.set()
                    t0 = time.monotonic_ns()
                    time.sleep(window_s)
                    spans[mode, loaded].append((t0, time.monotonic_ns()))
                    load.active.clear()
            counts[mode] = (load.requests, load.errors, load.cpu_s, load.response_ms)
        records = list(loop.frame_log)
    finally:
        loop.stop()

    def frame_ms(a: int, b: int) -> np.ndarray:
        return np.array([r.stages_s["frame"] * 1e3 for r in records if a <= r.t_start_ns and r.t_present_ns <= b])

    def p99_ratio(quiet: list[np.ndarray], busy: list[np.ndarray]) -> float | None:
        q, b = np.concatenate([[], *quiet]), np.concatenate([[], *busy])
        return None if not (len(q) and len(b)) else round(float(np.percentile(b, 99) / np.percentile(q, 99)), 3)

    def ratio_interval(quiet: list[np.ndarray], busy: list[np.ndarray], draws: int = 2000) -> list[float] | None:
        """90 % interval of the p99 ratio, resampling whole windows (frames in one window are
        correlated; windows are the independent units)."""
        if not all(len(x) for x in quiet + busy):
            return None
        rng = np.random.default_rng(0)
        ratios = [p99_ratio([quiet[i] for i in rng.integers(0, len(quiet), len(quiet))],
                            [busy[i] for i in rng.integers(0, len(busy), len(busy))]) for _ in range(draws)]
        return [round(float(x), 3) for x in np.percentile(ratios, [5, 95])]

    def per_request_ms(cpu_s: float | None, requests: int) -> float | None:
        return None if cpu_s is None or not requests else round(cpu_s * 1e3 / requests, 3)

    out = []
    for mode in modes:
        quiet_w = [frame_ms(*w) for w in spans[mode, False]]  # frame times per window
        busy_w = [frame_ms(*w) for w in spans[mode, True]]
        quiet, busy = np.concatenate([[], *quiet_w]), np.concatenate([[], *busy_w])
        requests, errors, cpu, response_ms = counts[mode]
        out.append({"case": f"{trajectory} API load", "api_mode": mode, "clients": clients, "rate_hz": rate_hz,
                    "client_priority": client_priority,
                    "response_ms": dict(zip(("p50", "p95", "p99"), _pct(response_ms))),
                    "api_cpu_ms_per_request": per_request_ms(cpu["api"], requests),
                    "client_cpu_ms_per_request": per_request_ms(cpu["clients"], requests),
                    "windows": windows, "window_s": window_s, "requests": requests, "errors": errors,
                    "unloaded_frames": len(quiet), "loaded_frames": len(busy),
                    "unloaded_frame_ms": dict(zip(("p50", "p95", "p99"), _pct(quiet))),
                    "loaded_frame_ms": dict(zip(("p50", "p95", "p99"), _pct(busy))),
                    "p99_ratio": p99_ratio(quiet_w, busy_w),
                    "p99_ratio_90ci": ratio_interval(quiet_w, busy_w),
                    # the noise floor: the same ratio between the odd and even unloaded windows
                    "unloaded_split_p99_ratio": p99_ratio(quiet_w[0::2], quiet_w[1::2])})
    return out


CASES = ((True, True), (True, False), (False, False))  # (prediction, late reprojection) per trajectory


def run_bench(trajectories=("linear", "rotate-oscillate"), *, api_clients: int = 4, api_rate_hz: float = 10.0,
              api_modes: tuple[str, ...] = ("process", "thread"), api_windows: int = 6, api_window_s: float = 3.0,
              api_client_priority: str = "normal", cases: bool = True, mitsuba: bool = True, progress=None, note=None,
              **kw) -> dict:
    """Every trajectory with prediction and late reprojection on, prediction alone, and neither
    (unless not `cases`), each row with its CPU-ms per rendered frame against Mitsuba's 1-spp
    frame (`mitsuba_yardstick`, if `mitsuba`), then (if `api_clients`) the API-load comparison for
    each of `api_modes`. `progress(label)` hears each case begin, `note(text)` how its analysis goes."""
    results = []
    for case in [BenchCase(t, p, r) for t in trajectories for p, r in CASES] if cases else []:
        if progress is not None:
            progress(case.label)
        results.append(run_case(case, progress=note, **kw))
    if results and mitsuba:
        if progress is not None:
            progress("Mitsuba's 1-spp frame of the same scene")
        yardstick = mitsuba_yardstick(kw.get("width", 0), kw.get("height", 0), kw.get("overrides", ()))
        for row in results:
            ratio = None if yardstick["mitsuba_cpu_ms"] is None else round(row["cpu_ms_per_rendered_frame"] / yardstick["mitsuba_cpu_ms"], 4)
            row.update(yardstick, cpu_over_mitsuba=ratio)
    load = []
    if api_clients:
        if progress is not None:
            progress(f"API load: {api_clients} clients × {api_rate_hz:g} req/s, API served by {' then '.join(api_modes)}")
        size = {k: kw[k] for k in ("width", "height", "spp", "overrides") if k in kw}
        load = run_load_case(trajectories[-1], modes=api_modes, clients=api_clients, rate_hz=api_rate_hz,
                             client_priority=api_client_priority, windows=api_windows, window_s=api_window_s, **size)
    return {"cases": results, "api_load": load}


def mitsuba_yardstick(width: int = 0, height: int = 0, overrides: tuple[str, ...] = ()) -> dict:
    """Mitsuba 3's 1-spp frame of the session's scene at its output size and camera
    (`benchmarks.mitsuba.one_spp_frame`), as row keys; without mitsuba (or a scene it cannot
    take) the figures are None and `mitsuba_note` says why."""
    from dpmhw.benchmarks.mitsuba import MitsubaUnavailable, one_spp_frame
    from dpmhw.errors import SceneError
    from dpmhw.session.factory import prepare_scene

    cfg = load_session_config(overrides=[f"render.width={width}", f"render.height={height}", *overrides])
    try:
        return one_spp_frame(prepare_scene(cfg), threads=cfg.render.threads)
    except (MitsubaUnavailable, SceneError) as exc:
        return {"mitsuba_variant": None, "mitsuba_threads": None, "mitsuba_frames": 0, "mitsuba_cpu_ms": None,
                "mitsuba_wall_ms": None, "mitsuba_version": None, "mitsuba_note": f"skipped: {exc}"}


def format_table(bench: dict) -> str:
    results = bench["cases"]
    head = (f"{'case':<52} {'fps':>6} {'render':>6} {'late':>5} {'new/s':>6} {'lat p50':>8} {'p95':>7} {'p99':>7} {'frame p99':>9} "
            f"{'reg p50':>8} {'reg p99':>8} {'vert p50':>8} {'unpred p50':>10} {'p99':>7} {'steal':>6}")
    lines = [head, "-" * len(head)] if results else []
    for r in results:
        new = "-" if r.get("new_windows_per_s") is None else f"{r['new_windows_per_s']:.0f}"
        lines.append(f"{r['case']:<52} {r['fps']:>6.1f} {r['render_fps']:>6.1f} {r['late_presents']:>5} {new:>6} "
                     f"{r['latency_ms_p50']:>8.1f} "
                     f"{r['latency_ms_p95']:>7.1f} {r['latency_ms_p99']:>7.1f} "
                     f"{r['frame_ms_p99']:>9.1f} {r['registration_px_p50']:>8.2f} {r['registration_px_p99']:>8.2f} "
                     f"{r['vertex_px_p50']:>8.2f} {r['registration_measured_pose_px_p50']:>10.2f} "
                     f"{r['registration_measured_pose_px_p99']:>7.2f} {steal_percent(r.get('cpu_steal')):>6}")
    if results:
        lines.append("per-stage p50 ms (" + ", ".join(STAGE_KEYS) + "):")
        for r in results:
            lines.append(f"  {r['case']:<50} {r['method']:<24} " + " ".join(
                f"{r[f'{k}_ms_p50']:.2f}" if r[f"{k}_ms_p50"] is not None else "-" for k in STAGE_KEYS))
    if results:
        r0, head = results[0], "CPU-ms per rendered frame (the session process)"
        if r0.get("mitsuba_cpu_ms") is not None:
            head += (f", and × Mitsuba {r0['mitsuba_version']} {r0['mitsuba_variant']}'s 1-spp frame of the same scene, size "
                     f"and camera: {r0['mitsuba_cpu_ms']:.1f} CPU-ms ({r0['mitsuba_wall_ms']:.1f} ms wall, {r0['mitsuba_threads']} "
                     f"threads, median of {r0['mitsuba_frames']}{'; ' + r0['mitsuba_note'] if r0['mitsuba_note'] else ''})")
        elif r0.get("mitsuba_note"):
            head += f" (Mitsuba: {r0['mitsuba_note']})"
        lines.append(head + ":")
        for r in results:
            ratio = f" = {r['cpu_over_mitsuba']:.3f}×" if r.get("cpu_over_mitsuba") is not None else ""
            lines.append(f"  {r['case']:<50} {r['cpu_ms_per_rendered_frame']:.1f}{ratio}")
    for load in bench.get("api_load") or []:
        u, b = load["unloaded_frame_ms"], load["loaded_frame_ms"]
        where = "own process" if load["api_mode"] == "process" else "thread of the session process"
        lines.append(f"API in its {where}: {load['clients']} clients ({load['client_priority']} priority) × "
                     f"≤{load['rate_hz']:g} req/s on /status, /metrics, "
                     f"/frame.png ({load['requests']} requests, {load['errors']} errors; {load['windows']}+{load['windows']} "
                     f"alternating {load['window_s']:g} s windows; response p50/p99 {load['response_ms']['p50']}/"
                     f"{load['response_ms']['p99']} ms): frame time p50/p99 {b['p50']}/{b['p99']} ms loaded vs "
                     f"{u['p50']}/{u['p99']} ms unloaded, p99 ratio {load['p99_ratio']} (90 % interval "
                     f"{load['p99_ratio_90ci']}; unloaded vs unloaded: "
                     f"{load['unloaded_split_p99_ratio']})")
    if not results:
        return "\n".join(lines)
    lines.append(f"display {results[0]['display']} ({results[0]['photon_windows']} photon windows per present); fps: presents/s, "
                 "render: rendered frames/s; late: presents that missed their refresh; new/s: (sub-)frames lit with a new "
                 "picture per second; latency: tracker mid-exposure → photons; reg: symmetric outline distance "
                 "between the silhouette shown and the true one at each photon window's middle, in projector pixels "
                 f"({results[0]['projector_width']}×{results[0]['projector_height']}; output "
                 f"{results[0]['output_width']}×{results[0]['output_height']}); vert: mean vertex displacement; "
                 "unpred: reg of the same frames had they shown the measured (unpredicted) pose; steal: of the "
                 "machine's CPU time while measured, what the host gave to other guests (a virtual machine's "
                 "refreshes are missed when it is high)")
    return "\n".join(lines)
