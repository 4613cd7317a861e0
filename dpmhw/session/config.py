"""Session configuration: one TOML file, validated with pydantic, every field overridable.

A lab operator edits the file and overrides single fields from the command line
(`--set render.spp=2`). Any mistake raises `SessionConfigError` naming the file, the dotted
field path, what was expected and what was given; unknown fields are errors too (a typo must
not pass silently as a default).

Each field's bounds are what its consumer can honour: the wire format's integer width (NatNet
packs a body id into a marker's int32 id), the device's limits (the baud rates pyserial
offers), a finite normal float, text without control characters. The memory the output size
needs is checked where that size is known (`dpmhw.session.factory.memory_problem`). Values
that are legal but cost much are accepted and named, with what they cost
(`SessionConfig.warnings`).

`LiveSettings` is the subset the operator may change while the loop runs (over HTTP): the loop
applies a validated change on its next frame. It is derived from the section fields named in
`LIVE_FIELDS`, and the API's models, the operator page and the recording derive from it, so a
live setting is declared (type, bounds, default, description) once.
"""

from __future__ import annotations

import copy
import os
import sys
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, field_validator, model_validator
from serial import SerialBase

from dpmhw.display import DISPLAY_MODES, DisplayTiming
from dpmhw.errors import DpmhwError
from dpmhw.limits import check_file_size, max_scene_bytes
from dpmhw.reconstruct.settings import ALPHA_MAX, ALPHA_MIN, FILTER_MODES, REUSE_MODES
from dpmhw.session.metrics import STAGES, WINDOWS

__all__ = [
    "LIVE_FIELDS",
    "SessionConfig",
    "SessionConfigError",
    "LiveSettings",
    "load_session_config",
    "parse_overrides",
    "format_validation_error",
]


INT32_MAX = (1 << 31) - 1  # a C int: SDL's display index, counters
MAX_BODY_ID = (1 << 15) - 1  # NatNet sends a labeled marker's id as the int32 (body id << 16 | marker index)
MAX_TEXT = 4096  # characters in any text field (PATH_MAX on Linux)
MAX_SET_DEPTH = 32  # brackets and braces a `--set` value may nest (a config needs 2)
BAUDRATES = SerialBase.BAUDRATES  # the rates pyserial sets on every platform it supports
MAX_STATIONS = 16  # a Polhemus tracker numbers its stations 1…16 (docs/protocols.md)
WORKSPACE_LIMIT_M = 1e4  # no capture volume reaches 10 km from its origin
NS_PER_RAY = 250  # wall time per native ray on the bunny's 69k triangles, 2 render threads (docs/lod.md)
METRICS_WINDOW_COSTLY = 16384  # frames: a status update's percentiles over more take milliseconds of the loop
REFRESH_HZ_MAX = 240.0  # the fastest video link a display section may name
MOCK_EXPOSURE_ROWS_MAX = 1_000_000  # the emulated projector's log of lit (sub-)frames at most (about 320 bytes a row)


class SessionConfigError(DpmhwError, ValueError):
    """The session configuration is invalid; the message lists every bad field."""


class _Section(BaseModel):
    """Every number finite (pydantic's allow_inf_nan) and none subnormal, every text short and
    without control characters: no consumer means one (a NUL is no path, a newline no header)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    @field_validator("*")
    @classmethod
    def _plain(cls, value: Any) -> Any:
        if any(isinstance(x, float) and 0.0 < abs(x) < sys.float_info.min
               for x in (value if isinstance(value, tuple) else (value,))):
            raise ValueError(f"subnormal number: expected 0 or at least {sys.float_info.min:.3g} in magnitude")
        if isinstance(value, str):
            if len(value) > MAX_TEXT:
                raise ValueError(f"text of {len(value)} characters: expected at most {MAX_TEXT}")
            bad = next((i for i, c in enumerate(value) if c < " " or c == "\x7f"), None)
            if bad is not None:
                raise ValueError(f"control character U+{ord(value[bad]):04X} at position {bad}")
        return value


class SceneSection(_Section):
    source: str = Field("dpm-bunny", description="built-in scene name or a scene TOML path (relative to the config)")
    mesh: str = Field("", description="optional mesh file replacing builtin:bunny")
    calibration: str = Field("", description="projector calibration file; replaces the scene's camera")


SHADING_SCALES = (1.0, 0.5, 0.25)


class RenderSection(_Section):
    width: int = Field(0, ge=0, le=16384, description="output width in pixels; 0 = the projector's native width "
                                                      "(calibration or scene camera). Only for a virtual projector "
                                                      "on the mocks: a real display must match it")
    height: int = Field(0, ge=0, le=16384, description="output height in pixels; 0 = the projector's native height")
    shading_scale: float = Field(0.25, description="shading resolution per axis relative to the output: 1, 0.5 or 0.25; "
                                                   "the frame is upsampled to the output size (dpmhw.reconstruct)")
    filter: Literal[FILTER_MODES] = Field("lobe", description="cross-bilateral filter of the reconstruction: off, "
                                                              "normal-aware or specular-lobe-aware")
    adaptive_rays: int = Field(2048, ge=0, le=1 << 24, description="adaptive sampling: most rays per frame for extra "
                               "native-resolution paths where the upsampling lacks support (0 = off; only below "
                               "shading_scale 1)")
    adaptive_threshold: float = Field(0.0, ge=0.0, le=1.0, description="adaptive sampling: a pixel whose upsampling "
                                      "weight sum is below this gets a native path too (0 = only unresolved pixels, "
                                      "the ones no shading sample supports; 0.05 samples the weak silhouette band as "
                                      "well: ≤ 0.1 dB for ~1.8 CPU-ms a frame on dpm-bunny, docs/temporal-reuse.md)")
    analytic: bool = Field(True, description="demodulate the diffuse and specular light by analytic, noise-free "
                           "direct-lighting terms of each G-buffer pixel before reuse, filter and upsampling, and "
                           "re-modulate with the native ones (dpmhw.reconstruct.analytic; off: the stage before it, "
                           "bit for bit). Only below shading_scale 1")
    analytic_floor: float = Field(1.0, gt=0.0, le=100.0, description="analytic demodulation: the diffuse term's floor, "
                                  "a fraction of its mean over the first frame's lit pixels (keeps the ratio stable "
                                  "where the direct light is ≈ 0)")
    analytic_specular_floor: float = Field(4.0, gt=0.0, le=100.0, description="analytic demodulation: the specular "
                                           "term's floor, a fraction of its mean (larger: the term is an approximation)")
    pipeline: bool = Field(True, description="render frame n+1 on its own thread while frame n is reconstructed "
                                             "(throughput; the next frame's pose is predicted one frame further)")
    pixel_sampling: Literal["centre", "jitter"] = Field("centre", description="shading rays through pixel centres "
                                                         "(static primary hits cached) or jittered per frame (reuse "
                                                         "then antialiases; camera rays traced every frame)")
    spp: int = Field(1, ge=1, le=64, description="samples per pixel per frame")
    threads: int = Field(2, ge=1, le=256, description="threads of each render pool (renderer, G-buffer, ray tracer)")
    exposure: float = Field(1.0, gt=0.0, le=1e4)
    seed: int = Field(0, ge=0, le=(1 << 32) - 1, description="added to the frame number to seed each frame's "
                      "random numbers (a 32-bit unsigned seed)")
    target_fps: float = Field(30.0, ge=1e-3, le=10000.0, description="a frame slower than 1/target_fps is a deadline "
                              "miss")

    @field_validator("shading_scale")
    @classmethod
    def _scale(cls, v: float) -> float:
        if v not in SHADING_SCALES:
            raise ValueError(f"expected one of {', '.join(f'{s:g}' for s in SHADING_SCALES)}")
        return v

    @model_validator(mode="after")
    def _both_or_neither(self) -> "RenderSection":
        if (self.width == 0) != (self.height == 0):
            raise ValueError("render.width and render.height must both be 0 (the scene's size) or both be set")
        return self


class ReuseSection(_Section):
    mode: Literal[REUSE_MODES] = Field("motion", description="temporal reuse: off, same-pixel, or motion (reproject "
                                                              "through the object's motion)")
    alpha: float = Field(0.2, ge=ALPHA_MIN, le=ALPHA_MAX, description="weight of the new frame, in (0, 1]; 1 = no reuse "
                         f"(at least {ALPHA_MIN:.3g}: 1/the longest history the reuse keeps)")
    split_screen: bool = Field(False, description="left half plain, right half with reuse (for comparison)")
    warmup: bool = Field(False, description="running mean for the first 1/alpha frames after a reset")


# --- contrast-driven level of detail in the reconstruction (dpmhw.lod.refine) ---
class LodSection(_Section):
    """Per-tile native paths on top of the shading-resolution frame (docs/lod.md). Off (rays = 0,
    or neither moving nor visible): the reconstruction is exactly what it is without it."""

    rays: int = Field(400_000, ge=0, le=1 << 30, description="most native rays per frame for the refined tiles "
                      "(worst case per path; 0 = off; only below shading_scale 1)")
    moving: bool = Field(False, description="the pixels of moving objects get native paths (every moving_every frames; the ¼ "
                         "shading loses their detail; ≈ 28 CPU-ms a frame on dpm-bunny at moving_every 2, docs/lod.md)")
    visible: bool = Field(False, description="tiles the visibility map of the previous output calls visible get "
                          "native paths at ½ or full rate")
    shading_rate: bool = Field(True, description="visible tiles: ½ or full rate by visibility (off: all full rate)")
    adaptive_spp: bool = Field(False, description="visible tiles: 1, 2 or 4 paths per pixel by visibility")
    base_weight: float = Field(0.3, ge=0.0, le=1.0, description="share of the upsampled frame in a refined pixel")
    moving_every: Literal[1, 2, 4] = Field(2, description="with moving: each of a moving object's pixels gets a native "
                                           "path every 1, 2 or 4 frames (1/every of the paths; between, its history)")
    viewer_distance_m: float = Field(1.5, gt=0.0, le=1e4, description="the audience's distance to the surface")
    alpha_v: float = Field(0.0, ge=-1e4, le=1e4, description="added to the visibility (higher refines more)")
    mesh: bool = Field(False, description="mesh level of detail per moving object per frame (dpmhw.lod.mesh_pipeline; "
                       "off: the renderer's meshes as loaded, bit for bit; at lab distances a visible object keeps "
                       "level 0, docs/mesh-lod.md)")


class GovernorSection(_Section):
    """The quality governor (dpmhw.session.governor, docs/session.md): steps the live settings down a
    ladder of cheaper rungs while the render rate misses its target, and back up when there is room."""

    enabled: bool = Field(True, description="hold the render rate by trading quality for speed (off: the settings "
                          "stay as configured and set)")
    target_fps: float | None = Field(None, ge=1.0, le=1000.0, description="render rate to hold; unset: the display's "
                                     "refresh rate (the sink's timing)")
    latency_budget_ms: float = Field(40.0, gt=0.0, le=10000.0, description="a frame's own time (start to present), "
                                     "90th percentile over the short window, above this also steps down")
    down_window_s: float = Field(0.5, ge=0.05, le=60.0, description="seconds of frames the rate is measured over "
                                 "before stepping down (a CPU hog is answered within about twice this)")
    down_margin: float = Field(0.1, ge=0.0, le=0.9, description="step down when the rate is below target by more "
                               "than this fraction")
    up_window_s: float = Field(3.0, ge=0.1, le=600.0, description="seconds at one level, measured, before a step up "
                               "is considered, at least down_window_s (doubles after each step up that had to be "
                               "undone, up to 16×)")
    headroom: float = Field(0.15, ge=0.0, le=4.0, description="step up only if the rate predicted for the better rung "
                            "(from the measured one and the rungs' measured costs) beats the target by this fraction")


class PredictionSection(_Section):
    enabled: bool = Field(True, description="extrapolate tracked poses to the display time")
    model: Literal["velocity", "acceleration"] = Field("acceleration", description="constant linear acceleration, or "
                                                      "constant velocity (docs/session.md compares them by marker noise)")
    history: int = Field(24, ge=2, le=64, description="recent samples used to estimate the derivatives (24: 67 ms at 360 Hz)")
    late_reprojection: bool = Field(True, description="at each present, move the newest rendered frame to the poses "
                                    "predicted for its photon windows from the newest tracker sample (dpmhw.reconstruct.reproject)")
    max_horizon_ms: float = Field(150.0, gt=0.0, le=2000.0, description="never extrapolate further than this")


class Binding(_Section):
    rigid_body: int = Field(ge=0, le=MAX_BODY_ID, description=f"NatNet's rigid body id (0…{MAX_BODY_ID}: its markers' "
                            f"ids carry it in their upper 16 bits), or the serial tracker's station (1…{MAX_STATIONS})")
    object: str = Field(min_length=1, description="scene object name")


class TrackerSection(_Section):
    kind: Literal["natnet", "serial"] = "natnet"
    server: str = "127.0.0.1"
    command_port: int = Field(1510, ge=1, le=65535)
    local_interface: str = "127.0.0.1"
    port: str = Field("", description="serial port (kind = serial): a device path or a pyserial URL")
    baudrate: Literal[BAUDRATES] = Field(115200, description="serial line rate (kind = serial): one of pyserial's standard rates")
    # the plausibility gate (dpmhw.plausibility): samples breaking these are dropped, never projected
    max_speed_m_s: float = Field(20.0, gt=0.0, le=1000.0, description="fastest a tracked body can move")
    workspace_min: tuple[float, float, float] = Field((-20.0, -20.0, -20.0), description="capture volume, metres")
    workspace_max: tuple[float, float, float] = Field((20.0, 20.0, 20.0), description="capture volume, metres")

    @field_validator("workspace_min", "workspace_max")
    @classmethod
    def _in_reach(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if any(abs(x) > WORKSPACE_LIMIT_M for x in v):
            raise ValueError(f"expected coordinates within ±{WORKSPACE_LIMIT_M:g} m")
        return v

    @model_validator(mode="after")
    def _workspace_is_a_box(self) -> "TrackerSection":
        if any(lo >= hi for lo, hi in zip(self.workspace_min, self.workspace_max)):
            raise ValueError(f"tracker.workspace_min {list(self.workspace_min)} must be below tracker.workspace_max "
                             f"{list(self.workspace_max)} on every axis")
        return self


class ProjectorSection(_Section):
    kind: Literal["dlpc900", "none"] = "dlpc900"
    serial: str = ""
    timeout_ms: int = Field(500, ge=10, le=60000)
    poll_interval_s: float = Field(0.25, gt=0.0, le=60.0, description="how often device health is read")
    reconnect_attempts: int = Field(2, ge=1, le=100)


class DisplaySection(_Section):
    mode: Literal[DISPLAY_MODES] = Field("video", description="video: the DLPC900 shows each 24-bit frame for one "
                                         "refresh; pattern-8bit: video-pattern mode, the frame's R, G and B bit planes "
                                         "as three 8-bit sub-frames (180 Hz at 60 Hz), each lit by its own LED")
    refresh_hz: float = Field(60.0, ge=1.0, le=REFRESH_HZ_MAX, description="the video link's refresh rate")
    controller_delay_ms: float | None = Field(None, ge=0.0, le=1000.0, description="scan-out start to first photon; "
                                              "unset: one refresh period (an assumption: the programmer's guide gives "
                                              "no figure; the controller buffers a whole frame before showing it)")
    shared_pose: Literal["auto", "never"] = Field("auto", description="pattern-8bit, auto: while presents at each "
                                                  "sub-frame's own pose would need more than ¾ of a period, the three "
                                                  "sub-frames share the middle one's pose (one splat, not three; the "
                                                  "outer ones then lag a third of a period's motion); never: always own "
                                                  "poses, and a present that is not ready misses its refresh")
    present_threads: int = Field(2, ge=1, le=2, description="pattern-8bit, 2: once the present lead nears ¾ of a period, a "
                                 "present's splats at its sub-frames' own poses are shared with a helper thread at the "
                                 "present thread's priority (less wall time for more CPU); 1: the present thread alone")

    def timing(self) -> DisplayTiming:
        # DLPU018 states no frame latency for video or video-pattern mode. The controller stores an
        # incoming frame's bit planes in its embedded DRAM and sends them to the DMD from there (the
        # DLPC900 datasheet's display description), so it can show a frame only once the whole
        # frame has arrived: the default assumes one refresh period (docs/session.md).
        delay = 1e3 / self.refresh_hz if self.controller_delay_ms is None else self.controller_delay_ms
        return DisplayTiming(self.mode, self.refresh_hz, round(delay * 1e6))


class SinkSection(_Section):
    kind: Literal["window", "file", "recording", "none"] = "window"
    path: str = Field("", description="output path (kind = file)")
    display: int = Field(0, ge=0, le=INT32_MAX, description="display index (kind = window)")

    @model_validator(mode="after")
    def _file_has_a_path(self) -> "SinkSection":
        if self.kind == "file" and not self.path:
            raise ValueError("sink.path: a file sink needs a path (a folder for PNGs or a video file)")
        return self


class SafetySection(_Section):
    stale_after_ms: float = Field(50.0, gt=0.0, le=10000.0, description="tracking older than this blanks the output")
    holdoff_s: float = Field(0.5, ge=0.0, le=600.0, description="a cause must be gone this long before projection resumes")
    resume: Literal["auto", "manual"] = Field("auto", description="manual: resume only on an explicit request")
    watchdog_s: float = Field(1.0, gt=0.0, le=600.0, description="a loop iteration longer than this is a stall")
    dark_render_interval_s: float = Field(
        0.25, ge=0.0, le=60.0, description="while dark, render only this often (enough to see a render fault clear)")
    restart: Literal["never", "on-crash"] = Field(
        "never", description="on-crash: the supervisor restarts a loop process that died (else it stays dark and reports)")
    restart_limit: int = Field(3, ge=0, le=1000, description="at most this many restarts within restart_window_s; then dark")
    restart_window_s: float = Field(600.0, gt=0.0, le=86400.0, description="crashes older than this no longer count")
    restart_backoff_s: float = Field(1.0, ge=0.0, le=600.0, description="wait before a restart; doubles with each crash in the window")


class MetricsSection(_Section):
    window: int = Field(512, ge=8, le=1_000_000, description="frames kept in each rolling window")


class ApiSection(_Section):
    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = Field(8765, ge=0, le=65535)
    operator_port: int = Field(8766, ge=0, le=65535, description="the operator's reserved port on the same address: "
                               "POST /session/blank and GET /status only, served by the session process, out of "
                               "reach of the main port's load (0 picks a free one)")
    token: str = Field("", pattern=r"^([A-Za-z0-9._~+/-]+=*)?$", description="bearer token for mutating endpoints "
                       "(RFC 6750 token characters); DPMHW_API_TOKEN overrides")
    priority: Literal["idle", "low", "normal"] = Field(
        "idle", description="CPU priority of the API process: idle (Linux SCHED_IDLE: runs only on otherwise idle "
                            "CPU time, so the loop always goes first), low (nice 10), normal")

    @field_validator("operator_port")
    @classmethod
    def _two_ports(cls, operator_port: int, info) -> int:
        port = info.data.get("port")
        if operator_port and operator_port == port:
            raise ValueError(f"must differ from api.port ({port})")
        return operator_port


class RecordingSection(_Section):
    enabled: bool = False
    path: str = Field("sessions", description="parent folder; each session gets its own subfolder")
    frame_every: int = Field(30, ge=1, le=INT32_MAX, description="keep every Nth presented frame as PNG")


class MockSection(_Section):
    trajectory: Literal["static", "linear", "rotate-oscillate"] = "rotate-oscillate"
    rate_hz: float = Field(360.0, ge=1.0, le=10000.0, description="samples per second (below 1 Hz every pose is "
                           "stale)")
    latency_ms: float = Field(4.5, ge=0.0, le=1000.0)
    speed: float = Field(1.0, gt=0.0, le=100.0, description="scales every velocity of the trajectory")
    marker_noise_mm: float = Field(0.0, ge=0.0, le=10.0, description="Gaussian noise (standard deviation) on each "
                                   "marker of the NatNet mock; the pose it streams is then fitted to the noisy markers")
    exposure_rows: int = Field(4096, ge=1, le=MOCK_EXPOSURE_ROWS_MAX, description="(sub-)frames of light the emulated projector "
                               "keeps in its log, the newest (4096: 22 s of pattern-8bit at 60 Hz); `dpmhw bench session` "
                               "sizes it to its measurement")


class SessionConfig(_Section):
    """Everything one projection session needs; see docs/session.md for each field."""

    scene: SceneSection = SceneSection()
    render: RenderSection = RenderSection()
    reuse: ReuseSection = ReuseSection()
    lod: LodSection = LodSection()  # docs/lod.md
    governor: GovernorSection = GovernorSection()
    prediction: PredictionSection = PredictionSection()
    bindings: list[Binding] = Field(default_factory=list, description="empty: every scene object with a rigid_body")
    tracker: TrackerSection = TrackerSection()
    projector: ProjectorSection = ProjectorSection()
    display: DisplaySection = DisplaySection()  # docs/session.md, "Display timing"
    sink: SinkSection = SinkSection()
    safety: SafetySection = SafetySection()
    metrics: MetricsSection = MetricsSection()
    api: ApiSection = ApiSection()
    recording: RecordingSection = RecordingSection()
    mock: MockSection = MockSection()
    base_dir: str = Field("", description="folder relative paths are resolved against (the config's folder)")

    @field_validator("bindings")
    @classmethod
    def _unique_bodies(cls, bindings: list[Binding]) -> list[Binding]:
        seen: set[str] = set()
        for b in bindings:
            if b.object in seen:
                raise ValueError(f"object {b.object!r} is bound twice")
            seen.add(b.object)
        return bindings

    @model_validator(mode="after")
    def _stations(self) -> "SessionConfig":
        if self.tracker.kind == "serial":
            for i, b in enumerate(self.bindings):
                if not 1 <= b.rigid_body <= MAX_STATIONS:
                    raise ValueError(f"bindings[{i}].rigid_body: a serial tracker's stations are 1…{MAX_STATIONS} "
                                     f"(got {b.rigid_body})")
        return self

    def warnings(self) -> list[str]:
        """Legal values that cost much, one line each saying what they cost (the caller prints them)."""
        r, out = self.render, []
        period_s = 1.0 / r.target_fps
        if r.target_fps < 1.0:
            out.append(f"render.target_fps={r.target_fps:g}: a frame counts as a deadline miss only after "
                       f"{period_s:.3g} s, so the deadline-miss counter says almost nothing")
        if period_s > self.safety.watchdog_s:
            out.append(f"render.target_fps={r.target_fps:g}: a frame that misses its deadline ({period_s:.3g} s) "
                       f"has already been a stall (safety.watchdog_s={self.safety.watchdog_s:g}) and blanked the output")
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        if r.threads > cpus:
            out.append(f"render.threads={r.threads} on {cpus} CPU(s): each render pool starts {r.threads} threads; "
                       "beyond the CPU count they add switching and memory, not speed")
        window = self.metrics.window
        if window > METRICS_WINDOW_COSTLY:
            out.append(f"metrics.window={window}: keeps {WINDOWS * 8 * window / 2**20:.0f} MiB of timings, and every "
                       f"status update (each 50 ms, on the loop thread) takes percentiles over up to "
                       f"{(len(STAGES) + 1) * window} values; once the windows fill, that can take longer than a frame")
        budgets = [("render.adaptive_rays", r.adaptive_rays, r.shading_scale < 1)]
        budgets.append(("lod.rays", self.lod.rays, r.shading_scale < 1 and (self.lod.moving or self.lod.visible)))
        for name, rays, active in budgets:
            cost_s = rays * NS_PER_RAY * 1e-9
            if active and cost_s > self.safety.watchdog_s:
                out.append(f"{name}={rays}: at about {NS_PER_RAY} ns a ray the budget allows {cost_s:.3g} s of rays in "
                           f"one frame ({period_s * 1e3:.0f} ms at render.target_fps={r.target_fps:g}); a frame that "
                           f"spends it is a stall (safety.watchdog_s={self.safety.watchdog_s:g}) and blanks the output")
        return out

    def display_timing(self) -> DisplayTiming:
        """When what the sink presents becomes light (`dpmhw.display`)."""
        return self.display.timing()

    def resolve(self, path: str) -> Path:
        p = Path(path).expanduser()
        return p if p.is_absolute() or not self.base_dir else Path(self.base_dir) / p

    def api_token(self) -> str:
        """The bearer token: DPMHW_API_TOKEN wins over the file (keeps secrets out of files)."""
        return os.environ.get("DPMHW_API_TOKEN", "") or self.api.token

    def live_settings(self) -> "LiveSettings":
        return LiveSettings(**{name: getattr(getattr(self, section), field) for name, (section, field) in LIVE_FIELDS.items()})


# The live settings: name → (section, field) of SessionConfig that declares it and gives its start value.
LIVE_FIELDS: dict[str, tuple[str, str]] = {
    "alpha": ("reuse", "alpha"),
    "reuse_mode": ("reuse", "mode"),
    "spp": ("render", "spp"),
    "split_screen": ("reuse", "split_screen"),
    "prediction": ("prediction", "enabled"),
    "filter": ("render", "filter"),
    "adaptive_rays": ("render", "adaptive_rays"),
    "lod_rays": ("lod", "rays"),
}


def _live_field(section: str, field: str) -> tuple[Any, Any]:
    info = SessionConfig.model_fields[section].annotation.model_fields[field]
    return info.annotation, copy.copy(info)


LiveSettings = create_model(
    "LiveSettings",
    __config__=ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False),
    __doc__="What the operator may change while the loop runs; immutable, so a snapshot is safe to share. "
            "Each field is the section field `LIVE_FIELDS` names: the same type, bounds, default and description.",
    __module__=__name__,
    **{name: _live_field(*where) for name, where in LIVE_FIELDS.items()},
)


def _short(text: str, most: int = 80) -> str:
    return text if len(text) <= most else f"{text[:most]}…"


def format_validation_error(source: str, exc: ValidationError) -> str:
    """One line per bad field: `source: a.b[0].c: what was expected (got value)`."""
    lines = []
    for err in exc.errors():
        path = ""
        for part in err["loc"]:
            path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
        got = err.get("input")
        shown = "" if isinstance(got, (dict, list)) or got is None else f" (got {_short(repr(got))})"
        lines.append(f"{source}: {path or '(top level)'}: {err['msg']}{shown}")
    return "\n".join(lines)


def _nesting(text: str) -> int:
    """How deep the brackets and braces of a TOML value nest, outside its strings."""
    depth = deepest = 0
    quote = ""
    escaped = False
    for c in text:
        if quote:
            if escaped:
                escaped = False
            elif c == "\\" and quote == '"':
                escaped = True
            elif c == quote:
                quote = ""
        elif c in "\"'":
            quote = c
        elif c in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "]}":
            depth -= 1
    return deepest


def _parse_value(key: str, text: str) -> Any:
    """A command-line value as TOML (numbers, booleans, strings in quotes, lists); bare words are strings.
    Nesting is bounded before the (recursive) parser sees it."""
    if _nesting(text) > MAX_SET_DEPTH:
        raise SessionConfigError(f"--set {key}: the value nests deeper than {MAX_SET_DEPTH} levels of [ ] and {{ }}")
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_overrides(items: list[str]) -> dict:
    """`["render.spp=2", "api.port=0"]` → nested dict. Raises SessionConfigError on a malformed item."""
    out: dict = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key or any(not part for part in key.split(".")):
            raise SessionConfigError(f"--set {item!r}: expected section.field=value, e.g. render.spp=2")
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise SessionConfigError(f"--set {item!r}: {part} is set both as a value and as a section")
        node[parts[-1]] = _parse_value(key, value.strip())
    return out


def _merge(base: dict, over: dict) -> dict:
    merged = dict(base)
    for k, v in over.items():
        merged[k] = _merge(merged[k], v) if isinstance(v, dict) and isinstance(merged.get(k), dict) else v
    return merged


def load_session_config(path: str | Path | None = None, overrides: list[str] | dict | None = None) -> SessionConfig:
    """Read a session TOML file (None: all defaults) and apply command-line overrides.

    Raises SessionConfigError naming the file and every bad field.
    """
    data: dict = {}
    source = "(defaults)"
    base_dir = ""
    if path is not None:
        p = Path(path)
        source = str(p)
        if not p.is_file():
            raise SessionConfigError(f"{p}: no such session config file")
        try:
            check_file_size(p, max_scene_bytes(), "session config file", "DPMHW_MAX_SCENE_KB")  # hand-written, as a scene
            data = tomllib.loads(p.read_bytes().decode("utf-8"))
        except tomllib.TOMLDecodeError as exc:
            raise SessionConfigError(f"{p}: not valid TOML: {exc}") from None
        except (OSError, ValueError) as exc:  # too large, unreadable, not UTF-8
            raise SessionConfigError(f"{p}: {exc}") from None
        except RecursionError:
            raise SessionConfigError(f"{p}: arrays or tables nested too deeply to be a session config") from None
        base_dir = str(p.parent.resolve())
    if overrides:
        over = parse_overrides(overrides) if isinstance(overrides, list) else overrides
        data = _merge(data, over)
        source = f"{source} + command line" if path is not None else "command line"
    data.setdefault("base_dir", base_dir)
    try:
        return SessionConfig.model_validate(data)
    except ValidationError as exc:
        raise SessionConfigError(format_validation_error(source, exc)) from None
