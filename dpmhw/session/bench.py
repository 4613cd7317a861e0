"""`dpmhw bench session`: the whole system on the firmware mocks, measured against ground truth.

Each case runs a `--mock` session (NatNet mock at 360 Hz → real NatNet driver → loop → emulated
DLPC900 + in-memory sink) for a few seconds and reports fps, motion-to-photon latency and the
frame-time percentiles from the loop's own metrics, plus the registration error of the presented
frames against the simulated world's true pose at the moment each frame was presented.

The API-load case serves one session with uvicorn on 127.0.0.1 and alternates windows without
and with `clients` threads polling /status, /metrics and /frame.png (each at most `rate_hz`
requests/s: bounded), so loaded and unloaded frame times come from the same session under the
same machine conditions.
"""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from dpmhw.session.config import load_session_config
from dpmhw.tracking import wait_for
from dpmhw.transforms import Pose

__all__ = ["BenchCase", "format_table", "run_bench", "run_case"]


@dataclass(frozen=True)
class BenchCase:
    trajectory: str
    prediction: bool

    @property
    def label(self) -> str:
        return f"{self.trajectory} prediction={'on' if self.prediction else 'off'}"


def _pct(values, qs=(50, 95, 99)):
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return [None if not len(v) else round(float(x), 3) for x in (np.percentile(v, qs) if len(v) else [0] * len(qs))]


class _ApiLoad:
    """uvicorn on a loopback socket + client threads hammering the read endpoints (bounded)."""

    def __init__(self, loop, clients: int, rate_hz: float = 10.0):
        import uvicorn

        from server.app import build_app

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.server = uvicorn.Server(uvicorn.Config(build_app(runtime=loop, token="bench"), log_level="warning",
                                                    lifespan="on"))
        self.server_thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)
        self.stop_event = threading.Event()
        self.active = threading.Event()  # clients send only while set (load windows)
        self.period_s = 1.0 / rate_hz if rate_hz > 0 else 0.0
        self.requests = 0
        self.errors = 0
        self.clients = [threading.Thread(target=self._client, daemon=True) for _ in range(clients)]

    def _client(self) -> None:
        import httpx

        paths = ("/status", "/metrics", "/frame.png")
        with httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=5.0) as c:
            k = 0
            while not self.stop_event.is_set():
                if not self.active.wait(0.05):
                    continue
                t0 = time.monotonic()
                try:
                    c.get(paths[k % len(paths)]).raise_for_status()
                    self.requests += 1
                except Exception:
                    self.errors += 1
                k += 1
                self.stop_event.wait(max(0.0, self.period_s - (time.monotonic() - t0)))

    def __enter__(self) -> "_ApiLoad":
        self.server_thread.start()
        if not wait_for(lambda: self.server.started, 10):
            raise RuntimeError("bench: the API server did not start on 127.0.0.1")
        for t in self.clients:
            t.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop_event.set()
        for t in self.clients:
            t.join(10)
        self.server.should_exit = True
        self.server_thread.join(10)
        self.sock.close()


def run_case(case: BenchCase, *, seconds: float = 4.0, warmup_s: float = 1.5, width: int = 256, height: int = 192,
             spp: int = 1, max_eval_frames: int = 120, overrides: tuple[str, ...] = ()) -> dict:
    """Run one mocked session and measure it (see module doc)."""
    from dpmhw.render.cameras import PinholeCamera
    from dpmhw.session.factory import build_session, prepare_scene
    from dpmhw.session.registration import registration_error

    cfg = load_session_config(overrides=[
        f"mock.trajectory={case.trajectory}", f"prediction.enabled={str(case.prediction).lower()}",
        f"render.width={width}", f"render.height={height}", f"render.spp={spp}", "sink.kind=recording",
        "api.enabled=false", *overrides])
    loop = build_session(cfg, mock=True, frame_log=100_000)
    try:
        loop.start()
        if not wait_for(lambda: loop.status()["state"] == "running", 60):
            raise RuntimeError(f"bench {case.label}: the session did not start: {loop.status()['reason']}")
        time.sleep(warmup_s)
        first = loop.status()["frame_number"]
        time.sleep(seconds)
        status = loop.status()
        records = [r for r in list(loop.frame_log) if r.number > first and r.number <= status["frame_number"]]
        world = loop.parts.mock.world
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
    display_ns = int(cfg.prediction.display_latency_ms * 1e6)
    step = max(1, len(records) // max_eval_frames)
    errors, measured = [], []
    for r in records[::step]:
        R, t = world.pose(body, (r.t_present_ns + display_ns) / 1e9)
        truth = Pose(R, t)
        errors.append(registration_error(camera, mesh.vertices, mesh.faces, r.poses[body], truth))
        # the same frame had it shown the measured pose: prediction on/off paired on identical timing
        measured.append(registration_error(camera, mesh.vertices, mesh.faces, r.measured[body], truth))
    frame_ms = [r.stages_s["frame"] * 1e3 for r in records]
    latency_ms = [(r.t_present_ns + display_ns - r.sample_t_ns[body]) / 1e6 for r in records]
    span_s = (records[-1].t_present_ns - records[0].t_present_ns) / 1e9
    out = {
        "case": case.label, "trajectory": case.trajectory, "prediction": case.prediction,
        "frames": len(records), "fps": round((len(records) - 1) / span_s, 2) if span_s > 0 else 0.0,
        "latency_ms": dict(zip(("p50", "p95", "p99"), _pct(latency_ms))),
        "frame_ms": dict(zip(("p50", "p95", "p99"), _pct(frame_ms))),
        "render_ms_p50": status["stages_ms"]["render"]["p50_ms"],
        "horizon_ms_mean": status["prediction_horizon_ms"]["mean"],
        "registration_px": dict(zip(("p50", "p99"), _pct([e.mean_px for e in errors], (50, 99)))),
        "registration_max_px": dict(zip(("p50", "p99"), _pct([e.max_px for e in errors], (50, 99)))),
        "registration_measured_pose_px": dict(zip(("p50", "p99"), _pct([e.mean_px for e in measured], (50, 99)))),
        "vertex_px": dict(zip(("p50", "p99"), _pct([e.vertex_px for e in errors], (50, 99)))),
        "evaluated_frames": len(errors), "render_size": [width, height], "spp": spp,
        "projector_size": [scene.render.width, scene.render.height],
    }
    return out


def run_load_case(trajectory: str = "rotate-oscillate", *, clients: int = 4, rate_hz: float = 10.0, windows: int = 4,
                  window_s: float = 2.0, warmup_s: float = 1.5, width: int = 256, height: int = 192, spp: int = 1,
                  overrides: tuple[str, ...] = ()) -> dict:
    """Frame time with and without API load in one session, in alternating windows (same
    machine conditions for both): `clients` threads, each at most `rate_hz` requests/s."""
    from dpmhw.session.factory import build_session

    cfg = load_session_config(overrides=[
        f"mock.trajectory={trajectory}", f"render.width={width}", f"render.height={height}", f"render.spp={spp}",
        "sink.kind=recording", "api.enabled=false", *overrides])
    loop = build_session(cfg, mock=True, frame_log=100_000)
    spans: dict[bool, list[tuple[int, int]]] = {False: [], True: []}
    try:
        loop.start()
        if not wait_for(lambda: loop.status()["state"] == "running", 60):
            raise RuntimeError(f"bench load: the session did not start: {loop.status()['reason']}")
        time.sleep(warmup_s)
        with _ApiLoad(loop, clients, rate_hz) as load:
            for w in range(2 * windows):
                loaded = w % 2 == 1
                if loaded:
                    load.active.set()
                t0 = time.monotonic_ns()
                time.sleep(window_s)
                spans[loaded].append((t0, time.monotonic_ns()))
                load.active.clear()
        records = list(loop.frame_log)
    finally:
        loop.stop()

    def frame_ms(loaded: bool) -> list[float]:
        return [r.stages_s["frame"] * 1e3 for r in records
                if any(a <= r.t_start_ns and r.t_present_ns <= b for a, b in spans[loaded])]

    quiet, busy = frame_ms(False), frame_ms(True)
    q, b = _pct(quiet), _pct(busy)
    return {"case": f"{trajectory} API load", "clients": clients, "rate_hz": rate_hz, "windows": windows,
            "window_s": window_s, "requests": load.requests, "errors": load.errors,
            "unloaded_frames": len(quiet), "loaded_frames": len(busy),
            "unloaded_frame_ms": dict(zip(("p50", "p95", "p99"), q)),
            "loaded_frame_ms": dict(zip(("p50", "p95", "p99"), b)),
            "p99_ratio": None if not (q[2] and b[2]) else round(b[2] / q[2], 3)}


def run_bench(trajectories=("linear", "rotate-oscillate"), *, api_clients: int = 4, api_rate_hz: float = 10.0,
              progress=None, **kw) -> dict:
    """Every trajectory with prediction on and off, then (if `api_clients`) the API-load comparison."""
    results = []
    for case in [BenchCase(t, p) for t in trajectories for p in (True, False)]:
        if progress is not None:
            progress(case.label)
        results.append(run_case(case, **kw))
    load = None
    if api_clients:
        if progress is not None:
            progress(f"API load: {api_clients} clients × {api_rate_hz:g} req/s, alternating windows")
        size = {k: kw[k] for k in ("width", "height", "spp", "overrides") if k in kw}
        load = run_load_case(trajectories[-1], clients=api_clients, rate_hz=api_rate_hz, **size)
    return {"cases": results, "api_load": load}


def format_table(bench: dict) -> str:
    results = bench["cases"]
    head = (f"{'case':<34} {'fps':>6} {'lat p50':>8} {'p95':>7} {'p99':>7} {'frame p99':>9} "
            f"{'reg p50':>8} {'reg p99':>8} {'vert p50':>8} {'unpred p50':>10} {'p99':>7}")
    lines = [head, "-" * len(head)]
    for r in results:
        lat, fr, reg, vert = r["latency_ms"], r["frame_ms"], r["registration_px"], r["vertex_px"]
        meas = r["registration_measured_pose_px"]
        lines.append(f"{r['case']:<34} {r['fps']:>6.1f} {lat['p50']:>8.1f} {lat['p95']:>7.1f} {lat['p99']:>7.1f} "
                     f"{fr['p99']:>9.1f} {reg['p50']:>8.2f} {reg['p99']:>8.2f} {vert['p50']:>8.2f} "
                     f"{meas['p50']:>10.2f} {meas['p99']:>7.2f}")
    load = bench.get("api_load")
    if load:
        u, b = load["unloaded_frame_ms"], load["loaded_frame_ms"]
        lines.append(f"API load ({load['clients']} clients × ≤{load['rate_hz']:g} req/s on /status, /metrics, /frame.png; "
                     f"{load['requests']} requests, {load['errors']} errors; {load['windows']} alternating "
                     f"{load['window_s']:g} s windows): frame time p50/p99 {b['p50']}/{b['p99']} ms loaded vs "
                     f"{u['p50']}/{u['p99']} ms unloaded (p99 ratio {load['p99_ratio']})")
    lines.append("latency: tracker mid-exposure → frame presented; reg: symmetric outline distance between the "
                 "silhouette shown and the true one at present time, in projector pixels "
                 f"({results[0]['projector_size'][0]}×{results[0]['projector_size'][1]}); vert: mean vertex displacement; "
                 "unpred: reg of the same frames had they shown the measured (unpredicted) pose")
    return "\n".join(lines)
