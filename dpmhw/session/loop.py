"""The real-time loop: latest pose → prediction → render (shading resolution) → reuse → filter /
upsample (native) → post → present, with safety.

Pipelining (`render.pipeline`, on by default): while frame n is reconstructed at native size,
frame n+1 is predicted and rendered on a render thread. The reconstruction leaves a core idle
for much of its time (serial steps of the native G-buffer, the tail after the upsampling) and
the shading-resolution render fills it, so the frame period falls towards the reconstruction's
time instead of render + reconstruction. Each frame keeps its own prediction, settings and
checks: a frame rendered ahead is dropped unseen if the output went dark meanwhile, staleness
is checked again before present as always, and its pose is predicted to its own present time
(the measured pipeline, one frame longer). The renderer is shared with adaptive sampling, so
its calls take turns (`OneCallAtATime`).

One thread runs the frames; a watchdog thread blanks the projector if that thread stalls; a
deadline thread makes the output dark the moment the newest tracking sample turns stale, whatever
the frame thread is doing (dark within `stale_after_ms`, not one frame's work later); a
health thread reads device status (USB reads can block) so the loop never waits on them. The
loop publishes immutable snapshots (status, latest frame); readers (the HTTP service) only swap
references under a short lock, and setting changes are validated by the caller and queued for
the next frame — nothing a reader does can slow a frame down.

Safety (see `safety.py`): tracking invalid or older than `stale_after_ms`, a tracker link lost,
a projector or sink error, a render exception or a stalled loop make the output dark — a black
frame to the sink and the projector idled (read back) — and the status says why.
"""

from __future__ import annotations

import gc
import logging
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Callable, Protocol

import numpy as np

from dpmhw.display import DisplayTiming
from dpmhw.frame_sink import FrameSink
from dpmhw.postprocess import NonFiniteFrameError
from dpmhw.lod.mesh_pipeline import mesh_lod
from dpmhw.lod.refine import tile_refiner
from dpmhw.reconstruct.adaptive import AdaptiveSampler
from dpmhw.reconstruct.settings import FILTER_MODES, REUSE_MODES
from dpmhw.reconstruct.stage import ReconstructStage
from dpmhw.scene_file import Scene
from dpmhw.session.config import LiveSettings, SessionConfig
from dpmhw.session.governor import Governor
from dpmhw.session.heartbeat import Heartbeat
from dpmhw.session.metrics import LoopMetrics
from dpmhw.session.prediction import PosePredictor
from dpmhw.session.present_lead import HANDOFF_NS, PresentLead
from dpmhw.session.safety import SafetyMonitor, SessionState
from dpmhw.stage_runner import Fault, Stage, StageFailed, run_timed
from dpmhw.thread_priority import PRESENT, raise_thread_priority
from dpmhw.tracking import Tracker, TrackerState
from dpmhw.transforms import Pose

__all__ = ["FrameRecord", "LatestFrame", "ProjectorControl", "Renderer", "SessionLoop", "SessionParts", "SettingsError"]

log = logging.getLogger(__name__)

SWITCH_INTERVAL_S = 0.001  # the interpreter's thread switch interval while a session runs (a pattern-mode session
# on a 2-core Zen 1 missed 10-16 refreshes in 10 s at 0.2 ms against 1-2 at 1 ms; 3 ms was no better)
FREEZE_AFTER_FRAMES = 30  # frames presented before what they made is frozen too (gc.freeze; see _freeze_long_lived)


class SettingsError(ValueError):
    """A live-settings change was refused; the message says which setting and why."""


class Renderer(Protocol):
    width: int
    height: int

    def render(self, time: float = 0.0, seed: int = 0, spp: int = 1, poses: list[Pose] | None = None, **kw) -> Any: ...


class ProjectorControl(Protocol):
    """The loop's view of a projector's control link (the DLPC900 over USB, or nothing)."""

    def blank(self) -> str:
        """Make it dark and verify by read-back; returns how (e.g. "idle"). Raises on failure."""

    def unblank(self) -> None:
        """Let the video input reach the mirrors again."""

    def health(self) -> dict:
        """Status flags as plain data; raises when the device is unreachable or reports faults."""

    def reconnect(self) -> None: ...

    def close(self) -> None: ...


@dataclass
class SessionParts:
    """Everything the loop drives, already opened; `closers` run last, in reverse order."""

    scene: Scene
    renderer: Renderer
    tracker: Tracker
    sink: FrameSink
    bindings: dict[int, int]  # scene object index -> rigid body id
    projector: ProjectorControl | None = None
    recorder: Any = None  # dpmhw.session.recording.SessionRecorder
    mock: Any = None  # the mock rig (world, servers, emulated devices) in --mock sessions
    gbuffer: Any = None  # dpmhw.render.gbuffer.NativeGBuffer when the renderer shades below the native size
    closers: list[Callable[[], None]] = field(default_factory=list)
    tracker_address: str = ""  # where the tracker reads from, for messages: "NatNet server 10.0.0.5:1510"
    tracker_watch: str = ""  # the `dpmhw tracker watch …` command that checks the same tracker


@dataclass(frozen=True)
class FrameRecord:
    """What one present showed and what it was made from (for tests, the benchmark and recording)."""

    number: int  # presents so far
    t_start_ns: int  # when the frame it shows began (its tracking check)
    t_present_ns: int  # the refresh it was scanned out at (the sink's answer)
    t_target_ns: int  # the photon time its middle window was predicted to
    poses: dict  # rigid body id -> Pose shown in the middle window (predicted or measured)
    sample_t_ns: dict  # rigid body id -> t_exposure_ns of the newest sample used
    measured: dict  # rigid body id -> Pose of that sample (what it shows without prediction)
    sample_age_s: float  # oldest sample's age when the frame started
    settings: LiveSettings
    stages_s: dict
    windows: tuple = ()  # per photon window: (photon mid ns, {rigid body id: Pose shown})
    rendered: int = 0  # the number of the rendered frame it shows (several presents may show one)
    governor_level: int = 0  # the quality governor's level when it was presented (0: the configured settings)


@dataclass(frozen=True)
class LatestFrame:
    """The newest present (what `/frame.png` serves): its number among the presents, its refresh,
    and the rendered frame it showed (before the late reprojection moved it), or the black one."""

    number: int
    t_present_ns: int
    image: np.ndarray  # (H, W, 3) uint8, read-only
    settings: LiveSettings
    blank: bool


class OneCallAtATime:
    """The renderer as the loop's threads see it: with pipelining, `render` (render thread) and
    `render_pixels` (adaptive sampling, lod; loop thread) may be called at once, and they share
    the renderer's work buffers, so calls take turns. `counts` is that of this view's last
    `render_pixels` call (the one its caller asks about); anything else is the renderer's."""

    def __init__(self, renderer):
        self._r = renderer
        self._lock = threading.Lock()
        self.counts = None

    def render(self, *args, **kw):
        with self._lock:
            return self._r.render(*args, **kw)

    def render_pixels(self, *args, **kw):
        with self._lock:
            out = self._r.render_pixels(*args, **kw)
            self.counts = self._r.counts
            return out

    def __getattr__(self, name):
        return getattr(self._r, name)


@dataclass(frozen=True)
class _Capture:
    """A rendered native frame kept for the presents: the image, the poses it was rendered at, and
    the reprojection's capture of its moving pixels (None: presented as rendered)."""

    number: int
    job: "_Job"
    image: np.ndarray  # (H, W, 3) uint8, read-only
    reprojection: Any


@dataclass
class _Job:
    """One frame between its prediction and its present (`frame`: the rendered `Frame`, or the
    future of a render started ahead)."""

    settings: LiveSettings
    t_start: int
    stages: dict
    samples: dict
    age_s: float
    scene_time: float
    poses: list
    used: dict
    horizon_ns: int
    t_target: int
    resume_at: int | None
    seed: int
    frame: Any = None


@dataclass
class _Made:
    """What one iteration's stages made of its job."""

    job: _Job
    frame: Any = None  # the rendered `Frame`
    output: Any = None  # the reconstruction's `StageOutput`
    capture: _Capture | None = None


# what a failure of the frame thread's stages means (any other exception is a fault of the loop itself)
_RENDER_FAULTS = (Fault(Exception, "render", "render_errors", "render failed: {type}: {exc}"),)
_RECONSTRUCT_FAULTS = (Fault(NonFiniteFrameError, "render", None, "post-processing refused the frame: {exc}"),
                       Fault(Exception, "render", "reuse_errors", "reconstruction failed: {type}: {exc}"))


def reconstruct_stage(config: SessionConfig, scene, renderer, gbuffer, clock) -> ReconstructStage:
    """The session's reconstruction from its config: `renderer` at the shading size (it also
    serves the adaptive and LOD paths), `gbuffer` the native one (None at equal sizes)."""
    r = config.render
    return ReconstructStage((scene.render.width, scene.render.height), (renderer.width, renderer.height),
                            background=scene.render.background, viewer=scene.viewer_position,
                            warmup=config.reuse.warmup, gbuffer=gbuffer, clock=clock,
                            adaptive=AdaptiveSampler(renderer, gbuffer, r.adaptive_rays, r.adaptive_threshold)
                            if gbuffer is not None else None,  # budget 0 samples nothing; a live setting may raise it
                            lod=tile_refiner(renderer, gbuffer, config.lod),
                            analytic=(r.analytic_floor, r.analytic_specular_floor) if r.analytic else None)


def exercise_stage(stage: ReconstructStage, frames, camera):
    """Every reuse mode and filter an operator can switch to, each over `frames` ((poses, Frame)
    at two poses: the second takes the history and the moved region), then a clean history:
    what a stage calls, called once (numba compiles or loads it now, not in a frame). Returns
    the last output."""
    for mode in REUSE_MODES:
        for filt in FILTER_MODES:
            for poses, frame in frames:
                out = stage.apply(frame, mode=mode, alpha=0.2, filter=filt, poses=poses, camera=camera)
    stage.reset()
    return out


def exercise_reprojection(reprojector, scene, size: tuple[int, int]) -> None:
    """Capture a synthetic frame (the first moving object everywhere) and reproject it after a
    move: what a present calls, with the loop's types (a frame is read-only once made),
    compiled before presents need it."""
    W, H = size
    moving = next((k for k, o in enumerate(scene.objects) if o.is_dynamic), 0)
    image = np.zeros((H, W, 3), np.uint8)
    image.setflags(write=False)
    cap = reprojector.capture(image, np.full(H * W, moving, np.int32), np.ones(H * W, np.float32),
                              scene.object_poses(0.0), (0, H, 0, W))
    reprojector.reproject(cap, scene.object_poses(0.25), np.zeros_like(image))


class SessionLoop:
    """Runs one projection session. `start()`, then `stop()` (idempotent) for a verified dark end."""

    def __init__(self, config: SessionConfig, parts: SessionParts, *, frame_log: int = 0,
                 clock: Callable[[], int] = time.monotonic_ns, wait: Callable[[float], bool] | None = None,
                 heartbeat: Heartbeat | None = None):
        """`clock` (nanoseconds) and `wait` are time as the loop's threads see it: `wait(seconds)`
        sleeps up to that long and returns True once the loop is stopping (default: the stop
        event's wait, which returns early then); a test drives both with a simulated clock."""
        self.config = config
        self.parts = parts
        self.clock = clock
        self.heartbeat = heartbeat  # what the frame thread did, for a supervisor (clock: CLOCK_MONOTONIC)
        s = config.safety
        self.stale_ns = int(s.stale_after_ms * 1e6)
        self.watchdog_ns = int(s.watchdog_s * 1e9)
        self.dark_render_interval_ns = int(s.dark_render_interval_s * 1e9)
        self.safety = SafetyMonitor(s.holdoff_s, s.resume, clock)
        self.metrics = LoopMetrics(config.metrics.window, 1.0 / config.render.target_fps)
        self.predictor = PosePredictor(config.prediction.history, config.prediction.max_horizon_ms / 1e3,
                                       config.prediction.model)
        scene = parts.scene
        self.output_size = (scene.render.width, scene.render.height)  # the projector's native (W, H)
        self._renderer = OneCallAtATime(parts.renderer)  # pipelining renders on a second thread
        self.reconstruct = reconstruct_stage(config, scene, self._renderer, parts.gbuffer, clock)
        self.mesh_lod = mesh_lod(parts.renderer, parts.gbuffer, config.lod)  # mesh levels (None: off)
        # the display: when each present becomes light (refresh grid, controller delay, photon windows)
        self._bodies = tuple(sorted(set(parts.bindings.values())))  # the tracked rigid bodies
        self._switch_interval = sys.getswitchinterval()  # the interpreter's, put back at stop
        self.timing: DisplayTiming = getattr(parts.sink, "timing", None) or DisplayTiming()
        self._vsync_phase = parts.sink.vsync_phase_ns() if hasattr(parts.sink, "vsync_phase_ns") else 0
        self.reprojector = self._reprojector() if config.prediction.late_reprojection else None
        self._capture: _Capture | None = None  # the newest rendered frame, for the present thread
        self._predict_lock = threading.Lock()  # the predictor is fed and read by both threads
        self._first_valid: dict[int, int] = {}  # body -> arrival of its first fresh sample since the frame thread last looked
        # when each present begins, and whether a pattern present's sub-frames share one pose
        pattern = len(self.timing.windows) > 1
        self.lead = PresentLead(self.timing.period_ns, pattern and config.display.shared_pose == "auto",
                                split_splats=pattern and config.display.present_threads == 2)
        self._present_number = 0
        self._present_heartbeat_ns = clock()
        self._present_priority = "not started"
        # render frame n+1 beside frame n's reconstruction; not with mesh LOD, whose level switch must hold for
        # a whole frame (render, G-buffer, refinement)
        self.pipeline = bool(config.render.pipeline) and self.mesh_lod is None
        self._render_thread: ThreadPoolExecutor | None = None
        self._next: _Job | None = None  # the frame whose render was started ahead
        self.frame_log: list[FrameRecord] | None = [] if frame_log else None
        self._frame_log_max = frame_log
        self._settings = config.live_settings()
        self._accepted = self._settings
        self._pending: LiveSettings | None = None
        self._pinned: set[str] = set()  # live settings the operator set: the governor leaves them alone
        self.governor = Governor(config.governor, self.timing.refresh_hz, clock, inert=frozenset(
            name for name, part in (("adaptive_rays", self.reconstruct.adaptive), ("lod_rays", self.reconstruct.lod))
            if part is None))
        self._reset_requested = False
        self._lock = threading.Lock()  # guards the published references and the queue only
        self._output_lock = threading.Lock()  # serialises going dark / going live
        self._output_on = False
        self.first_lit = threading.Event()  # set when the output first goes on (the show's clock starts)
        self.first_lit_at: float | None = None  # time.monotonic() then (one clock for every process here)
        self._stop = threading.Event()
        self._wait = wait if wait is not None else self._stop.wait
        self._threads: list[threading.Thread] = []
        self._heartbeat_ns = clock()
        self._status: MappingProxyType = MappingProxyType({})
        self._published_ns = 0
        self._latest: LatestFrame | None = None
        self._projector_health: MappingProxyType = MappingProxyType({"kind": "none"} if parts.projector is None else {})
        self._last_blank = ""
        self._dark_render_ns = 0  # when the last frame was rendered while the output was dark
        self._frame_number = 0
        self._t0_ns = clock()
        self._samples = None  # tracker subscription (every sample), opened by start()
        self._ever_streamed = False
        self._stopped = False
        self.final_blank: str | None = None
        self._publish(force=True)

    # ---- lifecycle -------------------------------------------------------------------------
    def warm(self) -> float:
        """Run each per-frame path once, on this loop's own renderer and stage, before it goes
        live (a pose twice, its camera hits then kept, and a move); returns the seconds taken.
        With a warm kernel cache this loads code; otherwise it compiles it."""
        t0 = time.monotonic()
        scene, renderer = self.parts.scene, self.parts.renderer
        frames = []
        for k, t in enumerate((0.0, 0.0, 0.25)):
            poses = scene.object_poses(t)
            frames.append((poses, renderer.render(time=t, seed=k, spp=1, poses=poses)))
        out = exercise_stage(self.reconstruct, frames[1:], renderer.camera)
        if self.reprojector is not None:
            exercise_reprojection(self._reprojector(), scene, self.output_size)  # a throwaway: its plate stays clean
        if self.mesh_lod is not None:
            self._observe_mesh_lod(out.image, frames[-1][1])
        took = time.monotonic() - t0
        log.info("render and reconstruction kernels ready in %.1f s", took)
        return took

    def _observe_mesh_lod(self, image: np.ndarray, frame) -> None:
        g = self.parts.gbuffer
        H, W = image.shape[:2]
        refiner = self.reconstruct.lod  # its map of this output, when tiles are refined: one map for both uses
        self.mesh_lod.observe(image, g.depth.reshape(H, W) if g is not None else frame.depth,
                              g.id.reshape(H, W) if g is not None else frame.object_id,
                              visibility=refiner.output_map if refiner is not None else None)

    def start(self) -> "SessionLoop":
        # every tracker sample feeds the predictor, not only the newest one per frame: at 10 fps
        # `history` newest-per-frame samples would span a second instead of a few milliseconds
        subscribe = getattr(self.parts.tracker, "subscribe", None)
        self._samples = subscribe(maxlen=4096) if subscribe is not None else None
        self._go_dark("starting: dark until tracking and devices are ready")
        self._freeze_long_lived()  # the full collection's cost is paid here, while dark
        # a thread that wakes for its refresh waits for the GIL up to the switch interval (5 ms by
        # default: a third of a 60 Hz period); the present thread's lead must cover that
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        for name, target in (("session-loop", self._run), ("session-present", self._present_loop),
                             ("session-watchdog", self._watchdog),
                             ("session-deadline", self._stale_deadline), ("session-health", self._health)):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self, reason: str = "stopped by request", timeout_s: float = 10.0) -> str | None:
        """Stop every thread, leave the projector dark (read back) and close every part.

        Returns how the projector was blanked (None without a projector); safe to call twice.
        """
        if self._stopped:
            return self.final_blank
        self._stopped = True
        self._stop.set()
        for t in self._threads:
            t.join(timeout=timeout_s)
            if t.is_alive():
                log.error("%s did not stop within %.0f s", t.name, timeout_s)
        self._threads.clear()
        if self._render_thread is not None:  # a render started ahead finishes before the renderer closes
            self._render_thread.shutdown(wait=True)
            self._render_thread = None
        self._next = None
        self._go_dark(reason, force=True)
        gc.unfreeze()  # this session's objects may be collected again once it is gone
        sys.setswitchinterval(self._switch_interval)
        self.reconstruct.close()
        if self.reprojector is not None:
            self.reprojector.close()
        self.final_blank = self._last_blank
        if self._samples is not None:
            self._samples.close()
        self.safety.mark_stopped(f"{reason}; projector dark ({self._last_blank or 'no projector'})")
        self._publish(force=True)
        p = self.parts
        for name, close in (("recorder", getattr(p.recorder, "close", None)), ("tracker", p.tracker.stop),
                            ("sink", p.sink.close), ("renderer", getattr(p.renderer, "close", None)),
                            ("projector", getattr(p.projector, "close", None))):
            if close is None:
                continue
            try:
                close()
            except Exception:
                log.exception("closing the %s failed", name)
        for close in reversed(p.closers):
            try:
                close()
            except Exception:
                log.exception("closing a session part failed")
        return self.final_blank

    def __enter__(self) -> "SessionLoop":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return bool(self._threads) and not self._stop.is_set()

    # ---- the API side (any thread; never waits on the loop) --------------------------------
    def status(self) -> dict:
        """Latest published snapshot merged with the current safety state."""
        with self._lock:
            snap = self._status
        view = self.safety.view()
        out = dict(snap)
        out.update(state=view.state.value, reason=view.reason, output_on=view.output_on,
                   causes=[{"name": c.name, "kind": c.kind, "reason": c.reason,
                            "since_s": round((self.clock() - c.since_ns) / 1e9, 3)} for c in view.causes],
                   faults=view.activations, heartbeat_age_s=round((self.clock() - self._heartbeat_ns) / 1e9, 3))
        return out

    def settings(self) -> LiveSettings:
        with self._lock:
            return self._accepted

    def update_settings(self, patch: dict, *, operator: bool = True) -> LiveSettings:
        """Validate `patch` against the accepted settings and queue it for the next frame (a patch
        that changes no value queues nothing: the loop applies only real changes). An operator's
        fields are pinned (the governor works around them); the governor's (`operator=False`)
        skip pinned fields. Under the lock, so neither overwrites the other with a stale base."""
        from pydantic import ValidationError

        with self._lock:
            base = self._accepted
            if not operator:
                patch = {k: v for k, v in patch.items() if k not in self._pinned}
            try:
                new = LiveSettings.model_validate({**base.model_dump(), **patch})
            except ValidationError as exc:
                raise SettingsError("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())) from None
            if operator:
                self._pinned.update(patch)
            if new == base:
                return base
            self._accepted = new
            self._pending = new
        return new

    def blank(self) -> None:
        """The operator's blank: dark on the caller's thread before this returns (black frame,
        projector idled and read back), not at the loop thread's next look at the safety state,
        which may be a render away."""
        self.safety.operator_blank()
        if self._output_on:
            self._go_dark(self.safety.view().reason)

    def resume(self) -> tuple[bool, str]:
        return self.safety.request_resume()

    def reset_history(self) -> None:
        with self._lock:
            self._reset_requested = True

    def latest_frame(self) -> LatestFrame | None:
        with self._lock:
            return self._latest

    def ready(self) -> bool:
        """Serving frames (or deliberately dark) with a live loop thread."""
        return self.running and self.safety.view().state in (SessionState.RUNNING, SessionState.BLANKED)

    # ---- the loop thread -------------------------------------------------------------------
    def _run(self) -> None:
        poll_s = 0.005
        while not self._stop.is_set():
            t_begin = self._heartbeat_ns = self.clock()
            try:
                presented = self._iteration()
                self.safety.update("loop", False)
            except Exception as exc:  # a bug in the loop itself: dark, visible, keep going
                log.exception("session loop iteration failed")
                self.safety.update("loop", True, f"internal error {type(exc).__name__}: {exc}", "fault")
                presented = False
            self._heartbeat_ns = self.clock()
            self._publish()
            if not presented:
                if self._wait(self._idle_wait_s(poll_s)):
                    break
            else:  # no faster than the display shows frames: a newer one would only replace it unseen
                rest = t_begin + self.timing.period_ns - self.clock()
                if rest > 0 and self._wait(rest / 1e9):
                    break

    def _idle_wait_s(self, poll_s: float) -> float:
        """Sleep after a dark turn: `poll_s`, but wake the resume lead before the hold-off ends,
        so the first lit frame is rendered by then and presented on time."""
        resume_at, now = self.safety.resume_at_ns(), self.clock()
        if resume_at is None or resume_at <= now:  # not holding off: nothing to wake for
            return poll_s
        return min(poll_s, max(0.0, (resume_at - now - self._resume_lead_ns()) / 1e9))

    def _resume_lead_ns(self) -> int:
        """How long before the hold-off ends the first lit frame is begun: its expected work twice
        (the first frame after a dark spell runs slower: cold caches and threads) plus the
        interpreter's thread switch interval (a waking thread may wait that long for the GIL).
        With one pipeline's lead only, the first frame could be lit up to a frame late."""
        return int((2 * self.metrics.expected_pipeline_s() + sys.getswitchinterval()) * 1e9)

    def _resume_due(self, now: int) -> int | None:
        """When the hold-off ends, if that is within the resume lead of `now` (the frame begun now
        is then presented at that instant); else None."""
        resume_at = self.safety.resume_at_ns()
        return resume_at if resume_at is not None and resume_at - now <= self._resume_lead_ns() else None

    def _apply_queued(self) -> LiveSettings:
        with self._lock:
            pending, self._pending = self._pending, None
            reset, self._reset_requested = self._reset_requested, False
        if pending is not None:
            self._settings = pending
            self.reconstruct.set_budgets(pending.adaptive_rays, pending.lod_rays)
            self.metrics.count("settings_changes_applied")
        if reset:
            self.reconstruct.reset()
            self.predictor.reset()
            self.metrics.count("history_resets")
        return self._settings

    def _check_tracking(self, now: int) -> tuple[dict, float] | None:
        """Feed the predictor; report tracking causes. Returns (samples, oldest age) or None."""
        tracker = self.parts.tracker
        status = tracker.status()
        bodies = self._bodies
        with self._predict_lock:
            self._drain_samples()
            first_valid, self._first_valid = self._first_valid, {}  # body -> arrival of its first fresh sample since the last turn
        if status.state in (TrackerState.STREAMING, TrackerState.STALE):
            self._ever_streamed = True
            # the link was back when its first sample arrived (the hold-off counts from there)
            self.safety.update("tracker", False, cleared_at_ns=min(first_valid.values(), default=status.last_arrival_ns))
        elif self._ever_streamed and status.state != TrackerState.STOPPED:
            self.safety.update("tracker", True, f"tracker link {status.state.value}: {status.reason}", "fault")
        samples = {}
        problems = []
        for body in bodies:
            s = tracker.latest(body)
            if s is None:
                where = f" from {self.parts.tracker_address}" if self.parts.tracker_address else ""
                hint = f"; check it with `{self.parts.tracker_watch}`" if self.parts.tracker_watch else ""
                problems.append(f"rigid body {body}: no sample yet{where} (tracker {status.state.value}){hint}")
                continue
            with self._predict_lock:
                self.predictor.observe(s)
            age = now - s.t_exposure_ns
            if not s.valid:
                problems.append(f"rigid body {body}: not tracked in tracker frame {s.frame_number}")
            elif age > self.stale_ns:
                problems.append(self._stale_reason(body, age))
                if status.details.get("last_implausible_ns", 0) > s.t_arrival_ns:  # dropped by the plausibility gate
                    problems[-1] += f"; newer samples dropped as implausible: {status.details['last_implausible']}"
            samples[body] = s
        # tracking became good when the last body's first fresh sample arrived: the hold-off counts from there
        good_since = max((first_valid.get(b, s.t_arrival_ns) for b, s in samples.items()), default=None)
        self.safety.update("tracking", bool(problems), "; ".join(problems), "blank", cleared_at_ns=good_since)
        if problems:
            return None
        oldest = min((s.t_exposure_ns for s in samples.values()), default=now)
        return samples, (now - oldest) / 1e9

    def _drain_samples(self) -> None:
        """Every tracker sample since the last drain into the predictor (caller holds `_predict_lock`);
        remembers when each body's first fresh sample arrived, for the frame thread's hold-off."""
        if self._samples is None:
            return
        bodies = self._bodies
        for sample in self._samples.drain():
            if sample.rigid_body_id in bodies:
                self.predictor.observe(sample)
                if sample.valid and sample.t_arrival_ns - sample.t_exposure_ns <= self.stale_ns:  # fresh on arrival
                    self._first_valid.setdefault(sample.rigid_body_id, sample.t_arrival_ns)

    def _photon_target(self, t_ready: int) -> int:
        """The photon time of the first refresh a frame ready at `t_ready` can reach: the middle of
        its photon windows (the late reprojection then moves it to each window's own instant)."""
        vsync = self.timing.next_vsync(t_ready + self.lead.lead_ns, self._vsync_phase)
        mids = self.timing.photon_mid_ns(vsync)
        return mids[len(mids) // 2]

    def _prepare(self, settings: LiveSettings, ahead: bool) -> "_Job | bool":
        """Tracking check, prediction and the dark-state decisions of one frame; returns the job to
        render, or False (nothing to present this turn). `ahead`: prepared while the previous
        frame is still being reconstructed (pipelining); then only a frame that may be lit now is
        prepared (a dark or resuming output renders in line, as without pipelining)."""
        t_start = self.clock()
        stages: dict[str, float] = {}
        tracking = self._check_tracking(t_start)
        if tracking is None:
            self._sync_output()
            return False
        samples, age_s = tracking
        stages["tracker_age"] = age_s
        # predict to the instant this frame will be lit: the photon time of the first refresh after
        # now + the measured pipeline, or, for the first frame after a hold-off (begun ahead of it),
        # after the hold-off's end
        resume_due = self._resume_due(t_start)
        t_target = self._photon_target(max(t_start + int(self.metrics.expected_pipeline_s() * 1e9), resume_due or 0))
        scene_time = (t_start - self._t0_ns) / 1e9
        poses = self.parts.scene.object_poses(scene_time)
        used: dict[int, Pose] = {}
        horizon_ns = 0
        for index, body in self.parts.bindings.items():
            with self._predict_lock:
                predicted = self.predictor.predict(body, t_target, enabled=settings.prediction)
            if predicted is None:  # no valid sample kept yet (only invalid ones arrived)
                if not ahead:
                    self._sync_output()
                return False
            poses[index], horizon_ns = predicted
            used[body] = predicted[0]
        t1 = self.clock()
        stages["predict"] = (t1 - t_start) / 1e9
        resume_at = None
        if not self.safety.output_allowed(t1):
            if ahead:
                return False
            # about to resume (the hold-off ends within the resume lead): render now, present at its end
            resume_at = resume_due
            if resume_at is None and self.safety.resume_at_ns() is not None:
                # holding off, no cause active (so no render fault to watch clear): a dark render now
                # could still be running when the resume render is due, and light it a frame late
                self._sync_output()
                return False
            # dark: nothing is shown, so render only as often as it takes to see a render fault clear
            if resume_at is None and t1 - self._dark_render_ns < self.dark_render_interval_ns:
                self._sync_output()
                return False
            self._dark_render_ns = t1
        return _Job(settings, t_start, stages, samples, age_s, scene_time, poses, used, horizon_ns, t_target, resume_at,
                    self.config.render.seed + self._frame_number + (1 if ahead else 0))

    def _render(self, job: "_Job"):
        """This frame's mesh levels, then its render (on the render thread when started ahead)."""
        made = _Made(job)
        run_timed((Stage("mesh_lod", self._choose_levels) if self.mesh_lod is not None else None,
                   Stage("render", self._shade)), made, self.clock, job.stages)
        return made.frame

    def _choose_levels(self, made: _Made) -> None:
        self.mesh_lod.choose(made.job.poses, self.parts.renderer.camera.pose)

    def _shade(self, made: _Made) -> None:
        job = made.job
        made.frame = self._renderer.render(time=job.scene_time, seed=job.seed, spp=job.settings.spp, poses=job.poses)

    def _prefetch(self) -> None:
        """Pipelining: prepare the next frame and start its render on the render thread now, so it
        runs beside this frame's reconstruction (which leaves a core idle for much of its time)."""
        job = self._prepare(self._apply_queued(), ahead=True)
        if isinstance(job, _Job):
            if self._render_thread is None:
                self._render_thread = ThreadPoolExecutor(1, thread_name_prefix="session-render")
            job.frame = self._render_thread.submit(self._render, job)
            self._next = job

    def _take_next(self) -> "_Job | None":
        """The frame started ahead, if the output may still be lit (else it is dropped unseen: a
        dark output renders only as its probe interval says)."""
        job, self._next = self._next, None
        if job is not None and not self.safety.output_allowed(self.clock()):
            try:
                job.frame.result()
            except Exception:
                pass  # its fault, if any, shows again when a frame is next rendered
            return None
        return job

    def _iteration(self) -> bool:
        job = self._take_next()
        if job is None:
            job = self._prepare(self._apply_queued(), ahead=False)
            if not isinstance(job, _Job):
                return job
        made = _Made(job)
        try:
            made_all = run_timed((
                Stage("render", self._rendered, _RENDER_FAULTS, timed=False),  # timed where it ran
                Stage("prefetch", lambda made: self._prefetch(), timed=False) if self.pipeline else None,
                Stage("reconstruct", self._reconstructed, _RECONSTRUCT_FAULTS, timed=False),  # times its sub-stages
                Stage("mesh_lod", self._observe_levels) if self.mesh_lod is not None else None,
                Stage("capture", self._captured)), made, self.clock, job.stages)
        except StageFailed as failed:
            return self._stage_failed(failed.cause, failed.counter, failed.reason)
        if not made_all:
            return False
        settings, stages, resume_at = job.settings, job.stages, job.resume_at
        t5 = self.clock()
        stages["frame"] = (t5 - job.t_start) / 1e9
        self._frame_number += 1
        if self._frame_number == FREEZE_AFTER_FRAMES:
            self._freeze_long_lived()  # what the first frames made (cheap: the rest is frozen since start)
        self.metrics.record_render(stages, t5)
        with self._lock:
            pinned = frozenset(self._pinned)
        patch = self.governor.observe(t5, stages["frame"], stages, settings, pinned)  # the render rate is its to set
        if patch:
            self.update_settings(patch, operator=False)
        if resume_at is not None and resume_at > t5:
            self._wait((resume_at - t5) / 1e9)  # less than one frame's work
        if not self._sync_output():
            self.metrics.count("frames_withheld")  # rendered while dark (keeps causes observable)
            return False
        with self._output_lock:  # only a frame made for a lit output is ever presented
            if not self._output_on:  # dark again since
                self.metrics.count("frames_withheld")
                return False
            with self._lock:
                self._capture = made.capture
        return True

    def _rendered(self, made: _Made) -> None:
        """The frame, rendered now or started ahead (pipelining)."""
        job = made.job
        made.frame = self._render(job) if job.frame is None else job.frame.result()
        self.safety.update("render", False)

    def _reconstructed(self, made: _Made) -> None:
        settings, nxt = made.job.settings, self._next  # started ahead: the stage brings the native G-buffer to it early
        out = self.reconstruct.apply(made.frame, mode=settings.reuse_mode, alpha=settings.alpha, filter=settings.filter,
                                     split_screen=settings.split_screen, exposure=self.config.render.exposure,
                                     poses=made.job.poses, camera=getattr(self.parts.renderer, "camera", None),
                                     next_frame=(nxt.poses, nxt.frame) if nxt is not None else None)
        out.image.setflags(write=False)
        made.job.stages.update(out.stages_s)
        made.output = out

    def _observe_levels(self, made: _Made) -> None:
        """The output's visibility per object, for the next choice of mesh levels."""
        self._observe_mesh_lod(made.output.image, made.frame)

    def _captured(self, made: _Made) -> bool:
        """Keep the frame for the presents, unless the newest sample went stale while it was made
        (never light it then: dark within stale_after_ms + one frame); takes in what arrived meanwhile."""
        if self._check_tracking(self.clock()) is None:
            self._sync_output()
            self.metrics.count("frames_withheld")
            return False
        out = made.output
        made.capture = self._capture_frame(made.job, out, made.frame)
        return True

    # ---- the present thread: one present per refresh, never waiting for a render ----------
    def _reprojector(self):
        """The late reprojection over the native camera (the native G-buffer's, or the renderer's
        when it renders at the native size)."""
        camera = getattr(self.parts.gbuffer, "camera", None) or getattr(self.parts.renderer, "camera", None)
        if camera is None:
            return None
        from dpmhw.reconstruct.reproject import Reprojector  # numba kernels: not for renderer-less test doubles

        return Reprojector(camera, [o.is_dynamic for o in self.parts.scene.objects], self.config.display.present_threads)

    def _capture_frame(self, job: "_Job", out, frame) -> _Capture:
        """Keep a finished frame (the stage's output) for the presents; with the late
        reprojection, its moving pixels (the native G-buffer's ids and depths of this frame: the
        stage keeps them until its next `apply`) are captured in their objects' own frames."""
        image = out.image
        reprojection = None
        if self.reprojector is not None:
            native = self.reconstruct.native if self.parts.gbuffer is not None else None
            if native is not None:
                ids, depth = native.id, native.depth
            else:
                ids, depth = frame.object_id.reshape(-1), frame.depth.reshape(-1)
            reprojection = self.reprojector.capture(image, ids, depth, list(job.poses), out.lit_box, out.background)
        return _Capture(self._frame_number + 1, job, image, reprojection)

    def _present_loop(self) -> None:
        """Wake `lead.lead_ns` before each refresh and present the newest capture, moved to
        each photon window's predicted poses. A present that misses its refresh widens the lead.
        Woken (or back from the last present) after the planned wake, the thread still presents
        for the refresh after the last one while the median time to a ready frame fits before it:
        skipping that refresh would show the last frame again for certain."""
        self._present_priority = raise_thread_priority(PRESENT, "present")
        period = self.timing.period_ns
        last = None
        while not self._stop.is_set():
            now = self.clock()
            vsync = self.timing.next_vsync(now + self.lead.lead_ns, self._vsync_phase)
            if last is not None:  # never the last refresh again; woke or returned late, the one after it while a present fits
                following = last + period
                if vsync <= last or (vsync > following and following - now >= self.lead.time_ns):
                    vsync = following
            wake = vsync - self.lead.lead_ns
            if wake > now and self._wait((wake - now) / 1e9):
                break
            self._present_heartbeat_ns = self.clock()
            try:
                vsync = self._present(vsync) or vsync
                self.safety.update("present", False)
            except Exception as exc:  # a bug in the present path: dark, visible, keep going
                log.exception("present failed")
                self.safety.update("present", True, f"present failed: {type(exc).__name__}: {exc}", "fault")
                self._go_dark(f"present failed: {exc}")
            last = vsync

    def _present(self, vsync: int) -> int | None:
        """One refresh: the newest capture, if the output is lit and tracking is fresh, reprojected
        per photon window and handed to the sink for `vsync`. A reprojected frame ready too late
        for `vsync` is made again for the refresh after (counted in `retargeted_presents`): the
        refresh it reaches then shows the poses meant for it. Returns the refresh presented for."""
        with self._lock:
            cap = self._capture
        if cap is None or not self._output_on:
            return None
        t0 = self.clock()
        planned_wake = vsync - self.lead.lead_ns
        samples = {}
        for body in self._bodies:
            s = self.parts.tracker.latest(body)
            if s is None or not s.valid or t0 - s.t_exposure_ns > self.stale_ns:
                self.metrics.count("presents_withheld")  # the frame thread or the deadline goes dark
                return None
            samples[body] = s
        settings = cap.job.settings
        cpu_ns = 0  # the present thread's CPU time in the reprojection (the goal's measure; `reproject` is wall time)
        if cap.reprojection is not None:
            made = self._reproject_for(cap, vsync, settings)
            if made is None:
                return None
            ready = self.clock()
            missed = ready > vsync - HANDOFF_NS
            if missed:
                self.metrics.count("retargeted_presents")
                vsync += self.timing.period_ns
                cpu_ns = made[3]
                made = self._reproject_for(cap, vsync, settings)
                if made is None:
                    return None
            image, windows, horizon_ns, cpu = made
            cpu_ns += cpu
            if self.lead.shared:
                self.metrics.count("shared_pose_presents")
            elif self.lead.split:
                self.metrics.count("split_presents")
        else:  # as rendered: every window shows the poses the frame was predicted to
            image, horizon_ns = cap.image, cap.job.horizon_ns
            windows = [(t, cap.job.used) for t in self.timing.photon_mid_ns(vsync)]
            samples = cap.job.samples
            ready = self.clock()
            missed = False
        t1 = self.clock()
        with self._output_lock:  # the deadline thread may have gone dark since: never light after it
            if not self._output_on:
                self.metrics.count("presents_withheld")
                return None
            t_present = self.parts.sink.present(image, vsync)
        t2 = self.clock()
        if self.heartbeat is not None:
            self.heartbeat.presented(t2, self._present_allowance_ns())
        self._adapt_lead(ready - planned_wake, late=missed or t_present > vsync)
        self.safety.mark_started()
        self._present_number += 1
        # lit from the refresh the sink answered; a sink without one answers when it took the frame,
        # which a display would show at its next refresh
        shown = self.timing.photon_mid_ns(self.timing.next_vsync(max(t_present, vsync), self._vsync_phase))
        windows = tuple((t, used) for t, (_, used) in zip(shown, windows))
        oldest = min(s.t_exposure_ns for s in samples.values())
        latency_s = (sum(shown) / len(shown) - oldest) / 1e9
        stages = {"reproject": (t1 - t0) / 1e9, "reproject_cpu": cpu_ns / 1e9, "present": (t2 - t1) / 1e9}
        self.metrics.record_present(stages, t_present, latency_s, horizon_ns / 1e9)
        mid = len(windows) // 2
        record = FrameRecord(self._present_number, cap.job.t_start, t_present, windows[mid][0], windows[mid][1],
                             {b: s.t_exposure_ns for b, s in samples.items()},
                             {b: Pose(np.array(s.rotation), np.array(s.translation)) for b, s in samples.items()},
                             cap.job.age_s, settings, {**cap.job.stages, **stages}, windows, cap.number,
                             self.governor.level)
        with self._lock:
            self._latest = LatestFrame(self._present_number, t_present, cap.image, settings, blank=False)
        if self.frame_log is not None:
            self.frame_log.append(record)
            if len(self.frame_log) > self._frame_log_max:
                del self.frame_log[0]
        if self.parts.recorder is not None:
            self.parts.recorder.frame(record, cap.image)
        return vsync

    def _reproject_for(self, cap: _Capture, vsync: int, settings) -> tuple[np.ndarray, list, int, int] | None:
        """The capture moved to the poses predicted for each photon window of `vsync`: (image,
        [(photon mid, {body: pose shown})], horizon used, the reprojection's thread CPU ns), or None
        before any sample."""
        mids = at = self.timing.photon_mid_ns(vsync)
        if self.lead.shared:  # every sub-frame at the middle one's pose: one projection and splat (PresentLead)
            at = [mids[len(mids) // 2]] * len(mids)
        with self._predict_lock:
            self._drain_samples()
            per_body = {body: self.predictor.predict_many(body, at, enabled=settings.prediction)
                        for body in self._bodies}
        if any(p is None for p in per_body.values()):
            return None
        windows, moves, horizon_ns = [], [], cap.job.horizon_ns
        for k, (w, t) in enumerate(zip(self.timing.windows, mids)):
            poses, used = list(cap.job.poses), {}
            for index, body in self.parts.bindings.items():
                poses[index], horizon_ns = per_body[body][k]
                used[body] = poses[index]
            windows.append((t, used))
            moves.append((poses, w.channel))
        cpu0 = time.thread_time_ns()
        image, _ = self.reprojector.present(cap.reprojection, moves, helper=self.lead.split)  # one of its frames, in turn (a sink may read the last)
        return image, windows, horizon_ns, time.thread_time_ns() - cpu0 + self.reprojector.last_helper_cpu_ns

    def _adapt_lead(self, ready_ns: int, late: bool) -> None:
        """The present's time from its planned wake to a frame ready, to the lead (`PresentLead`)."""
        if late:  # missed its refresh: shown a period late, at other poses than predicted
            self.metrics.count("late_presents")
        change = self.lead.add(ready_ns, late)
        if change is not None:
            log.warning(change)

    @staticmethod
    def _freeze_long_lived() -> None:
        """What exists once the session is built and warm (scene, kernels, buffers, the service) lives
        as long as the session: move it out of the collector's reach, or a full collection walks
        ~160k objects every ~20 frames on the frame thread (73-78 CPU-ms, a late frame; measured with
        perf). Collected first so no garbage is pinned; `stop` unfreezes (a service may run
        many sessions in one process). Once at start, while dark (that first collection took ~75 ms:
        done after frame 30 only, it made a late frame, a stale tracker sample and a dark spell
        right after going live), and again after `FREEZE_AFTER_FRAMES` for what the first frames made."""
        gc.collect()
        gc.freeze()

    # ---- output on / off -------------------------------------------------------------------
    def _stage_failed(self, cause: str, counter: str | None, reason: str) -> bool:
        """A stage of this frame failed: count it, raise the fault cause, go dark; the frame is dropped."""
        if counter is not None:
            self.metrics.count(counter)
        self.safety.update(cause, True, reason, "fault")
        self._sync_output()
        return False

    def _sync_output(self) -> bool:
        """Make the output match the safety decision; returns whether frames may be presented."""
        allowed = self.safety.output_allowed()
        if allowed and not self._output_on:
            self._go_live()
        elif not allowed and self._output_on:
            self._go_dark(self.safety.view().reason)
        return self._output_on

    def _go_live(self) -> None:
        with self._output_lock:
            if self._output_on:
                return
            if self.parts.projector is not None:
                try:
                    self.parts.projector.unblank()
                except Exception as exc:
                    self.safety.update("projector", True, f"cannot light the projector: {type(exc).__name__}: {exc}", "fault")
                    return
            self.reconstruct.reset()  # history from before the dark spell describes another moment
            if self.heartbeat is not None:
                self.heartbeat.presented(self.clock(), self._present_allowance_ns())
            self._output_on = True
            if self.first_lit_at is None:
                self.first_lit_at = time.monotonic()
                self.first_lit.set()
            self.metrics.count("resumes")
            log.warning("projection resumed")

    def _present_allowance_ns(self) -> int:
        """How long a lit frame may stand before a supervisor calls this process hung: the stale
        limit plus twice the expected frame time (a slow but live loop presents within that), never
        more than the watchdog's stall limit."""
        return min(self.stale_ns + int(2e9 * self.metrics.expected_pipeline_s()), self.watchdog_ns)

    def _go_dark(self, reason: str, force: bool = False, from_watchdog: bool = False) -> None:
        """Black frame to the sink (not from the watchdog: the stuck loop may be inside the sink)
        and the projector idled with read-back. Failures become a fault, never an exception."""
        with self._output_lock:
            if not self._output_on and not force and self._last_blank:
                return
            self._output_on = False
            self._capture = None  # nothing from before the dark spell is presented after it
            self.metrics.count("blanks")
            log.warning("projection dark: %s", reason)
            black_shown = False
            if not from_watchdog:
                black = np.zeros((self.output_size[1], self.output_size[0], 3), np.uint8)
                black.setflags(write=False)
                try:
                    t = self.parts.sink.present(black, self.clock())
                    with self._lock:
                        self._latest = LatestFrame(self._present_number, t, black, self._settings, blank=True)
                    black_shown = True
                except Exception as exc:
                    self.safety.update("sink", True, f"cannot present a black frame: {type(exc).__name__}: {exc}", "fault")
            if self.parts.projector is None:
                self._last_blank = "no projector"
                if not black_shown:
                    return  # the sink may still show the last frame: lit as far as a supervisor knows
            else:
                try:
                    self._last_blank = self.parts.projector.blank()
                except Exception as exc:
                    self._last_blank = f"FAILED: {exc}"
                    self.safety.update("projector_blank", True, f"cannot confirm the projector is dark: {exc}", "fault")
                    return  # still lit as far as a supervisor knows
                self.safety.update("projector_blank", False)
            if self.heartbeat is not None:
                self.heartbeat.dark()

    # ---- watchdog and device health ---------------------------------------------------------
    def _watchdog(self) -> None:
        period = min(self.watchdog_ns / 4e9, 0.1)
        while not self._wait(period):
            now = self.clock()
            age = now - self._heartbeat_ns
            if self._output_on:  # a lit output needs its present thread as well
                age = max(age, now - self._present_heartbeat_ns)
            if age > self.watchdog_ns:
                if not self.safety.active("watchdog"):
                    self.metrics.count("watchdog_trips")
                self.safety.update("watchdog", True, f"loop stalled: no iteration finished for {age / 1e9:.1f} s "
                                                     f"(limit {self.watchdog_ns / 1e9:g} s)", "fault")
                if self._output_on:
                    self._go_dark("watchdog: loop stalled", from_watchdog=True)
            else:
                self.safety.update("watchdog", False)

    def _stale_reason(self, body: int, age_ns: int, suffix: str = "") -> str:
        """The tracking cause's reason for a stale body (the frame thread's check and the deadline's)."""
        return f"rigid body {body}: newest sample is {age_ns / 1e6:.0f} ms old (limit {self.stale_ns / 1e6:g} ms){suffix}"

    def _stale_deadline(self) -> None:
        """Go dark at the newest sample's exposure + `stale_after_ms`, not at the frame thread's
        next check (up to a frame's work later, which can push dark past `stale_after_ms` + one
        frame). Sleeps until the earliest body's
        deadline (at most 20 ms, so new samples move it) and only reads `tracker.latest`; the
        frame thread keeps owning the tracking cause and its clearing."""
        bodies = self._bodies
        while not self._stop.is_set():
            if not self._output_on or not bodies:
                if self._wait(0.02):
                    break
                continue
            now = self.clock()
            newest = {b: self.parts.tracker.latest(b) for b in bodies}
            if any(s is None for s in newest.values()):
                if self._wait(0.02):
                    break
                continue
            body, s = min(newest.items(), key=lambda kv: kv[1].t_exposure_ns)
            due = s.t_exposure_ns + self.stale_ns
            if now <= due:
                if self._wait(min(due - now + 1, 20_000_000) / 1e9):
                    break
                continue
            reason = self._stale_reason(body, now - s.t_exposure_ns, " (deadline)")
            self.metrics.count("stale_deadline_trips")
            self.safety.update("tracking", True, reason, "blank")
            self._go_dark(reason)

    def _health(self) -> None:
        projector = self.parts.projector
        interval = self.config.projector.poll_interval_s
        while not self._stop.is_set():
            if projector is not None:
                try:
                    health = projector.health()
                    self._projector_health = MappingProxyType({**health, "error": None})
                    self.safety.update("projector", False)
                    if self.safety.active("projector_blank"):  # a blank failed: retry until it is confirmed
                        self._go_dark("retrying a failed blank", force=True, from_watchdog=True)
                except Exception as exc:
                    reason = f"{type(exc).__name__}: {exc}"
                    self._projector_health = MappingProxyType({"error": reason})
                    self.safety.update("projector", True, reason, "fault")
                    try:
                        projector.reconnect()
                    except Exception as rexc:
                        log.info("projector reconnect failed: %s", rexc)
            if self._wait(interval):
                break

    # ---- snapshots -------------------------------------------------------------------------
    def _publish(self, force: bool = False) -> None:
        """Replace the status snapshot (at most every 50 ms unless forced): the API only reads it."""
        now = self.clock()
        if not force and now - self._published_ns < 50_000_000:
            return
        self._published_ns = now
        tracker_status = self.parts.tracker.status()
        tracker = {
            "kind": getattr(self.parts.tracker, "kind", type(self.parts.tracker).__name__),
            "state": tracker_status.state.value, "reason": tracker_status.reason,
            "frames": tracker_status.frames, "malformed": tracker_status.malformed,
            "implausible": getattr(tracker_status, "implausible", 0),
            "latency_ms": None if tracker_status.latency_ns is None else round(tracker_status.latency_ns / 1e6, 3),
            "stale": self.safety.active("tracking"),
            "thread_priority": tracker_status.details.get("thread_priority"),  # its receiver's (a driver's own)
        }
        with self._lock:
            accepted, applied = self._accepted, self._settings
        snap = {
            "frame_number": self._present_number,  # presents (the display's frames)
            "frames_rendered": self._frame_number,
            "uptime_s": round((now - self._t0_ns) / 1e9, 3),
            **self.metrics.summary(),
            "settings": accepted.model_dump(),
            "settings_applied": applied.model_dump(),
            "devices": {"tracker": tracker, "projector": dict(self._projector_health),
                        "last_blank": self._last_blank},
            "display": {"mode": self.timing.mode, "refresh_hz": self.timing.refresh_hz,
                        "controller_delay_ms": round(self.timing.controller_delay_ns / 1e6, 3),
                        "late_reprojection": self.reprojector is not None,
                        "present_lead_ms": round(self.lead.lead_ns / 1e6, 3),
                        "sub_frame_poses": "shared" if self.lead.shared else "own",
                        "present_threads": 2 if self.lead.split else 1,
                        "present_priority": self._present_priority},
            "render_size": [self.parts.renderer.width, self.parts.renderer.height],  # the shading resolution
            "output_size": list(self.output_size),
            "governor": self.governor.status(),
        }
        with self._lock:
            self._status = MappingProxyType(snap)
