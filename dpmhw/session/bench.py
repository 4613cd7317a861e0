"""`dpmhw bench session`: the whole system on the firmware mocks, measured against ground truth.

Each case runs a `--mock` session (NatNet mock at 360 Hz → real NatNet driver → loop → emulated
DLPC900 + in-memory sink) for a few seconds and reports fps, motion-to-photon latency and the
frame-time percentiles from the loop's own metrics, plus the registration error of the presented
frames against the simulated world's true pose at the moment each frame was presented.

With `api_clients > 0` a uvicorn server on 127.0.0.1 serves the session while that many client
threads poll /status, /metrics and /frame.png as fast as they can, so the frame-time p99 can be
compared with the unloaded run of the same case.
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
    api_clients: int = 0

    @property
    def label(self) -> str:
        return f"{self.trajectory} prediction={'on' if self.prediction else 'off'}" + (
            f" +{self.api_clients} API clients" if self.api_clients else "")


def _pct(values, qs=(50, 95, 99)):
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return [None if not len(v) else round(float(x), 3) for x in (np.percentile(v, qs) if len(v) else [0] * len(qs))]


class _ApiLoad:
    """uvicorn on a loopback socket + client threads hammering the read endpoints (bounded)."""

    def __init__(self, loop, clients: int):
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
        self.requests = 0
        self.errors = 0
        self.clients = [threading.Thread(target=self._client, daemon=True) for _ in range(clients)]

    def _client(self) -> None:
        import httpx

        paths = ("/status", "/metrics", "/frame.png")
        with httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=5.0) as c:
            k = 0
            while not self.stop_event.is_set():
                try:
                    c.get(paths[k % len(paths)]).raise_for_status()
                    self.requests += 1
                except Exception:
                    self.errors += 1
                    time.sleep(0.05)
                k += 1

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
        load = _ApiLoad(loop, case.api_clients) if case.api_clients else None
        if load is not None:
            load.__enter__()
        try:
            time.sleep(seconds)
            status = loop.status()
        finally:
            if load is not None:
                load.__exit__(None, None, None)
        records = [r for r in list(loop.frame_log) if r.number > first and r.number <= status["frame_number"]]
        world = loop.parts.mock.world
    finally:
        loop.stop()
    if len(records) < 2:
        raise RuntimeError(f"bench {case.label}: only {len(records)} frames in {seconds} s")
    # ground truth at native projector resolution: errors in the projector's own pixels
    native_cfg = load_session_config(overrides=["render.width=0", "render.height=0"])
    scene = prepare_scene(native_cfg)
    camera = PinholeCamera(scene.camera.K, scene.camera.dist, scene.render.width, scene.render.height, scene.camera.pose)
    (index, body), = loop.parts.bindings.items()
    mesh = scene.objects[index].mesh
    display_ns = int(cfg.prediction.display_latency_ms * 1e6)
    step = max(1, len(records) // max_eval_frames)
    errors = []
    for r in records[::step]:
        R, t = world.pose(body, (r.t_present_ns + display_ns) / 1e9)
        errors.append(registration_error(camera, mesh.vertices, mesh.faces, r.poses[body], Pose(R, t)))
    frame_ms = [r.stages_s["frame"] * 1e3 for r in records]
    latency_ms = [(r.t_present_ns + display_ns - r.sample_t_ns[body]) / 1e6 for r in records]
    span_s = (records[-1].t_present_ns - records[0].t_present_ns) / 1e9
    out = {
        "case": case.label, "trajectory": case.trajectory, "prediction": case.prediction, "api_clients": case.api_clients,
        "frames": len(records), "fps": round((len(records) - 1) / span_s, 2) if span_s > 0 else 0.0,
        "latency_ms": dict(zip(("p50", "p95", "p99"), _pct(latency_ms))),
        "frame_ms": dict(zip(("p50", "p95", "p99"), _pct(frame_ms))),
        "render_ms_p50": status["stages_ms"]["render"]["p50_ms"],
        "horizon_ms_mean": status["prediction_horizon_ms"]["mean"],
        "registration_px": dict(zip(("p50", "p99"), _pct([e.mean_px for e in errors], (50, 99)))),
        "registration_max_px": dict(zip(("p50", "p99"), _pct([e.max_px for e in errors], (50, 99)))),
        "vertex_px": dict(zip(("p50", "p99"), _pct([e.vertex_px for e in errors], (50, 99)))),
        "evaluated_frames": len(errors), "render_size": [width, height], "spp": spp,
        "projector_size": [scene.render.width, scene.render.height],
    }
    if load is not None:
        out["api_requests"] = load.requests
        out["api_errors"] = load.errors
    return out


def run_bench(trajectories=("linear", "rotate-oscillate"), *, api_clients: int = 8, progress=None, **kw) -> list[dict]:
    """Every trajectory with prediction on and off, then (if `api_clients`) the first one under load."""
    cases = [BenchCase(t, p) for t in trajectories for p in (True, False)]
    if api_clients:
        cases.append(BenchCase(trajectories[0], True, api_clients))
    results = []
    for case in cases:
        if progress is not None:
            progress(case.label)
        results.append(run_case(case, **kw))
    return results


def format_table(results: list[dict]) -> str:
    head = (f"{'case':<44} {'fps':>6} {'lat p50':>8} {'p95':>7} {'p99':>7} {'frame p99':>9} "
            f"{'reg p50':>8} {'reg p99':>8} {'vert p50':>8}")
    lines = [head, "-" * len(head)]
    for r in results:
        lat, fr, reg, vert = r["latency_ms"], r["frame_ms"], r["registration_px"], r["vertex_px"]
        lines.append(f"{r['case']:<44} {r['fps']:>6.1f} {lat['p50']:>8.1f} {lat['p95']:>7.1f} {lat['p99']:>7.1f} "
                     f"{fr['p99']:>9.1f} {reg['p50']:>8.2f} {reg['p99']:>8.2f} {vert['p50']:>8.2f}")
    loaded = [r for r in results if r["api_clients"]]
    for r in loaded:
        base = next((b for b in results if not b["api_clients"] and b["trajectory"] == r["trajectory"]
                     and b["prediction"] == r["prediction"]), None)
        if base:
            ratio = r["frame_ms"]["p99"] / base["frame_ms"]["p99"]
            lines.append(f"frame-time p99 under {r['api_clients']} API clients ({r.get('api_requests', 0)} requests, "
                         f"{r.get('api_errors', 0)} errors): {r['frame_ms']['p99']:.1f} ms vs {base['frame_ms']['p99']:.1f} ms "
                         f"unloaded ({(ratio - 1) * 100:+.0f} %)")
    lines.append("latency: tracker mid-exposure → frame presented; reg: symmetric outline distance between the "
                 "silhouette shown and the true one at present time, in projector pixels "
                 f"({results[0]['projector_size'][0]}×{results[0]['projector_size'][1]}); vert: mean vertex displacement")
    return "\n".join(lines)
