"""Build a session's parts from its config: scene, renderer, tracker, projector, sink, mock rig.

The only place in `dpmhw` that reaches into `drivers/` and `firmware_mocks/`, always inside a
function, by the names a config gives (the core never imports them at module level).

`mock=True` starts the firmware mocks on loopback — a NatNet server streaming a simulated world
(the bound bodies move around their scene positions), an emulated DLPC900 behind pyusb and the
video cable into it (`firmware_mocks.video_link`, the window sink's stand-in) — then connects
the *real* drivers to them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from dpmhw.errors import DpmhwError
from dpmhw.scene_file import Scene, load_scene
from dpmhw.session.config import MAX_BODY_ID, SessionConfig, SessionConfigError
from dpmhw.session.loop import SessionLoop, SessionParts

__all__ = ["DLPC900Control", "MockRig", "build_session", "check_devices", "idle_projector", "memory_problem",
           "open_black_window", "open_session_parts", "output_size", "prepare_scene", "resolve_bindings",
           "start_usb_emulator"]

log = logging.getLogger(__name__)


def _scene_source(config: SessionConfig) -> str:
    from dpmhw.scene_file import BUILTIN_SCENES

    source = config.scene.source
    return source if source in BUILTIN_SCENES else str(config.resolve(source))


def _calibration(config: SessionConfig):
    from dpmhw.projector_calibration import load_projector_calibration

    path = config.resolve(config.scene.calibration)
    try:
        return path, load_projector_calibration(path)
    except Exception as exc:
        raise SessionConfigError(f"scene.calibration: cannot load {path}: {exc}") from None


def output_size(config: SessionConfig) -> tuple[int, int]:
    """The output (native) size `prepare_scene` gives, read without loading a mesh: render.width ×
    render.height, else the calibration's, else the scene's [render] size."""
    from dpmhw.scene_file import scene_size

    r = config.render
    if r.width:
        return r.width, r.height
    if config.scene.calibration:
        calib = _calibration(config)[1]
        return calib.width, calib.height
    return scene_size(_scene_source(config))


def memory_problem(config: SessionConfig, size: tuple[int, int]) -> str | None:
    """Why a session at output `size` would allocate more than the limit (naming the fields), or None."""
    from dpmhw.limits import session_memory_problem

    try:
        problem = session_memory_problem(*size, config.render.shading_scale)
    except ValueError as exc:  # the limit's environment variable is malformed
        return str(exc)
    if problem is None:
        return None
    where = "render.width, render.height" if config.render.width else (
        f"render.width, render.height (0: {'scene.calibration' if config.scene.calibration else 'scene.source'}'s size)")
    return f"{where}: {problem}"


def prepare_scene(config: SessionConfig) -> Scene:
    """Load the scene, apply the calibration file and the output-size override: the scene's
    camera is the projector at its native (output) size."""
    sc = config.scene
    scene = load_scene(_scene_source(config), mesh_override=config.resolve(sc.mesh) if sc.mesh else None)
    if sc.calibration:
        from dpmhw.scene_file import CameraSpec
        from dpmhw.transforms import Pose

        path, calib = _calibration(config)
        if calib.frame != "tracker":
            raise SessionConfigError(
                f"scene.calibration: {path} gives the projector pose in the {calib.frame!r} frame, but tracked poses are "
                "in the tracker's frame; calibrate with the tracker step so that world_from_projector.frame = 'tracker'")
        dist = np.zeros(5)
        coeffs = np.asarray(calib.dist, float).reshape(-1)[:5]
        dist[: coeffs.size] = coeffs
        camera = CameraSpec(np.asarray(calib.K, float), dist, Pose(np.asarray(calib.R, float), np.asarray(calib.t, float)))
        scene = dataclasses.replace(scene, camera=camera,
                                    render=dataclasses.replace(scene.render, width=calib.width, height=calib.height))
    r = config.render
    if r.width and r.height:
        scene = scene.at_size(r.width, r.height)
    return scene


def resolve_bindings(config: SessionConfig, scene: Scene) -> dict[int, int]:
    """scene object index -> rigid body id; the config's list, else each object's `rigid_body`."""
    names = [o.name for o in scene.objects]
    if config.bindings:
        out = {}
        for i, b in enumerate(config.bindings):
            if b.object not in names:
                raise SessionConfigError(f"bindings[{i}].object: no object named {b.object!r} in scene "
                                         f"{scene.source} (objects: {', '.join(names)})")
            out[names.index(b.object)] = b.rigid_body
        return out
    out = {i: o.rigid_body for i, o in enumerate(scene.objects) if o.rigid_body is not None}
    for i, body in out.items():
        if body > MAX_BODY_ID:  # the scene file allows more than NatNet carries
            raise SessionConfigError(f"bindings: scene {scene.source} objects[{i}].rigid_body = {body}: a tracker "
                                     f"body id is at most {MAX_BODY_ID}; bind the object with [[bindings]]")
    if not out:
        raise SessionConfigError(f"bindings: scene {scene.source} has no object with a rigid_body; "
                                 "add [[bindings]] rigid_body = N, object = \"name\"")
    return out


class DLPC900Control:
    """`ProjectorControl` over the DLPC900 driver: the display mode `display.mode` names (video,
    or video pattern mode for pattern-8bit), dark = idle (read back)."""

    def __init__(self, dlp: Any):
        self.dlp = dlp

    @classmethod
    def open(cls, config: SessionConfig, settle_s: float = 0.3) -> "DLPC900Control":
        from drivers.dlpc900 import DLPC900, DisplayMode

        p = config.projector
        dlp = DLPC900.open(p.serial or None, timeout_ms=p.timeout_ms, settle_s=settle_s,
                           reconnect_attempts=p.reconnect_attempts, reconnect_backoff_s=0.05)
        try:
            if dlp.in_standby():
                dlp.wake()
            dlp.set_display_mode(DisplayMode.VIDEO)
            if config.display.mode == "pattern-8bit":  # started when lit (`unblank`)
                dlp.set_video_pattern_mode(config.display.refresh_hz, start=False)
            dlp.blank()
        except Exception:
            dlp.close()
            raise
        return cls(dlp)

    def blank(self) -> str:
        return self.dlp.blank().method

    def unblank(self) -> None:
        if self.dlp.in_standby():
            self.dlp.wake()
        self.dlp.set_idle(False)
        if self.dlp.configured.video_pattern_hz is not None:  # blanking stopped the sequence
            self.dlp.start()

    def health(self) -> dict:
        status = self.dlp.status()
        if status.get("hardware_faults"):
            raise DpmhwError(f"DLPC900 {status.get('serial')} reports hardware faults: {', '.join(status['hardware_faults'])}")
        return status

    def reconnect(self) -> None:
        self.dlp.reconnect(restore=True)

    def close(self) -> None:
        self.dlp.close()


@dataclass
class MockRig:
    """The firmware mocks a `--mock` session runs against, for tests and benchmarks."""

    world: Any  # firmware_mocks.world.World (ground truth)
    natnet: Any  # firmware_mocks.natnet_server.NatNetServer (tracker.kind = "natnet")
    serial: Any  # firmware_mocks.serial_tracker.PolhemusEmulator (tracker.kind = "serial")
    projector: Any  # firmware_mocks.dlpc900_usb.EmulatedDLPC900, or the SocketBackend to an out-of-process one
    stack: contextlib.ExitStack
    video: Any = None  # firmware_mocks.video_link.VideoLink into `projector`'s model (in-process only)


def mock_trajectory(name: str, base_t: np.ndarray, speed: float):
    """A world trajectory around an object's scene position (so it stays in the projector's view)."""
    from firmware_mocks.world import Linear, RotateWhileOscillating, Static

    if name == "static":
        return Static(translation=tuple(base_t))
    if name == "linear":
        # starts 0.2 m left of the base and crosses it at 0.08 m/s: in view for about 5 s at speed 1
        return Linear(start=tuple(base_t - np.array([0.2, 0.0, 0.0])), velocity=(0.08 * speed, 0.0, 0.0))
    return RotateWhileOscillating(center=tuple(base_t), amplitude_m=0.08, oscillation_hz=0.5 * speed,
                                  spin_rad_s=np.pi / 2 * speed)


def start_mock_rig(config: SessionConfig, scene: Scene, bindings: dict[int, int],
                   usb: tuple[str, bytes] | None = None) -> tuple[MockRig, dict]:
    """Start the mocks; returns the rig and config overrides pointing the drivers at them
    (`command_port` of the NatNet server, or `port`: the serial emulator's pty). With `usb`
    (address, key of a `start_usb_emulator()` process) the DLPC900 is that out-of-process one."""
    from firmware_mocks.dlpc900_socket import socket_usb
    from firmware_mocks.dlpc900_usb import usb_emulation
    from firmware_mocks.natnet_server import NatNetServer, NatNetServerConfig
    from firmware_mocks.serial_tracker import PolhemusEmulator
    from firmware_mocks.world import World

    stack = contextlib.ExitStack()
    try:
        world = World(epoch_s=time.monotonic())
        for index, body in bindings.items():
            base = scene.objects[index].pose.t
            world.add(body, scene.objects[index].name, mock_trajectory(config.mock.trajectory, base, config.mock.speed))
        m = config.mock
        server = serial = None
        if config.tracker.kind == "serial":
            stations = list(range(1, len(world.objects) + 1))
            if sorted(world.objects) != stations:
                raise SessionConfigError(f"bindings: the mock serial tracker numbers its stations 1…{len(stations)}; "
                                         f"bind rigid_body = {stations} (got {sorted(world.objects)})")
            # a Liberty streams at most 240 Hz
            serial = PolhemusEmulator(world, rate_hz=min(m.rate_hz, 240.0), latency_ms=m.latency_ms)
            stack.callback(serial.close)
            serial.start()
            over = {"port": serial.port}
        else:
            server = NatNetServer(world, NatNetServerConfig(
                unicast=True, command_port=0, interface="127.0.0.1", rate_hz=m.rate_hz, latency_ms=m.latency_ms,
                software_latency_ms=min(0.9, m.latency_ms), marker_noise_m=m.marker_noise_mm / 1e3,
                solve_from_markers=True))
            stack.callback(server.stop)
            server.start()
            over = {"command_port": server.command_port}
        device = video = None
        if usb is None:
            from firmware_mocks.video_link import VideoLink

            device = stack.enter_context(usb_emulation())
            # the cable into the emulated projector, in before the driver opens it (video pattern
            # mode needs its sync); the loop closes it as its sink, the stack again on error
            video = VideoLink(device.model, timing=config.display_timing(),
                              shape=(scene.render.height, scene.render.width), max_rows=config.mock.exposure_rows)
            stack.callback(video.close)
        else:
            device = stack.enter_context(socket_usb(*usb))
    except BaseException:
        stack.close()
        raise
    return MockRig(world, server, serial, device, stack, video), over


def open_tracker(config: SessionConfig, command_port: int | None = None, port: str | None = None):
    from dpmhw.plausibility import PlausibilityLimits

    t = config.tracker
    stale_s = config.safety.stale_after_ms / 1e3
    common = dict(stale_after_s=stale_s, lost_after_s=max(1.0, stale_s),
                  plausibility=PlausibilityLimits(t.max_speed_m_s, t.workspace_min, t.workspace_max))
    if t.kind == "natnet":
        from drivers.natnet import NatNetClient

        return NatNetClient(t.server, command_port=command_port or t.command_port, local_interface=t.local_interface,
                            **common)
    from drivers.serial_tracker import SerialTracker

    return SerialTracker(_serial_port(config, port), baudrate=t.baudrate, **common)


def _serial_port(config: SessionConfig, port: str | None = None) -> str:
    port = port or config.tracker.port
    if not port:
        raise SessionConfigError("tracker.port: a serial tracker needs a port (e.g. /dev/ttyUSB0)")
    return port


def describe_tracker(config: SessionConfig, command_port: int | None = None, port: str | None = None) -> tuple[str, str]:
    """Where the tracker reads from, and the `dpmhw tracker watch` command that checks it (for
    messages; the arguments are `open_tracker`'s mock overrides)."""
    t = config.tracker
    if t.kind == "natnet":
        command_port = command_port or t.command_port
        return (f"NatNet server {t.server}:{command_port}",
                f"dpmhw tracker watch --natnet {t.server} --command-port {command_port} --local-interface {t.local_interface}")
    port = port or t.port
    return f"serial port {port}", f"dpmhw tracker watch --serial {port} --baudrate {t.baudrate}"


def open_sink(config: SessionConfig, mock: bool, shape: tuple[int, int], rig: MockRig | None = None):
    """The sink `sink.kind` names, with the display's timing. In a mock session the window is the
    emulated projector's video input (`rig.video`); where that projector runs in another
    process, a recording sink paced to the refresh stands in for it."""
    from drivers.frame_sinks import make_sink

    kind, timing = config.sink.kind, config.display_timing()
    if mock and kind == "window":
        if rig is not None and rig.video is not None:
            return rig.video
        return make_sink("recording", shape=shape, timing=timing, pace=True, max_frames=8)
    if kind == "none" or kind == "recording":
        return make_sink("recording", shape=shape, timing=timing, max_frames=8)
    if kind == "file":
        try:
            return make_sink("file", path=str(config.resolve(config.sink.path)), fps=config.render.target_fps,
                             timing=timing)
        except (ValueError, OSError) as exc:  # e.g. its folder does not exist
            raise SessionConfigError(f"sink.path: {exc}") from None
    try:
        return make_sink("window", display=config.sink.display, size=(shape[1], shape[0]), timing=timing)
    except ValueError as exc:  # e.g. the display's mode is not the projector's native size
        raise SessionConfigError(f"sink: {exc}") from None


def check_devices(config: SessionConfig, scene: Scene) -> None:
    """Reach every device a start would open, changing none of them (`session config`): the
    projector over USB, the tracker's serial port or NatNet server address, the sink's display
    and its mode. Raises SessionConfigError naming the section of the first one missing."""
    if config.projector.kind == "dlpc900":
        from drivers.dlpc900 import DLPC900

        try:
            DLPC900.open(config.projector.serial or None, timeout_ms=config.projector.timeout_ms, settle_s=0.0).close()
        except Exception as exc:
            raise SessionConfigError(f"projector: {exc}") from None
    t = config.tracker
    if t.kind == "serial":
        port = _serial_port(config)
        if "://" not in port and not os.path.exists(port):  # pyserial URLs (socket://…) are not files
            raise SessionConfigError(f"tracker.port: {port} does not exist")
    else:
        import socket

        try:
            socket.getaddrinfo(t.server, None)
        except OSError as exc:
            raise SessionConfigError(f"tracker.server: cannot resolve {t.server!r}: {exc}") from None
    if config.sink.kind == "window":
        from drivers.frame_sinks import check_display

        try:
            check_display(config.sink.display, (scene.render.width, scene.render.height))
        except Exception as exc:
            raise SessionConfigError(f"sink: {exc}") from None


def shading_scene(scene: Scene, scale: float) -> Scene:
    """The scene at the shading resolution: `scale` of the native size per axis (at least 1 px)."""
    r = scene.render
    return scene.at_size(max(1, round(r.width * scale)), max(1, round(r.height * scale)))


def build_renderer(config: SessionConfig, scene: Scene, gbuffer: bool = True):
    """The path tracer at the shading size and, when that differs from the native (output) size
    and `gbuffer`, the native G-buffer (else None)."""
    from dpmhw.render.integrator import PathIntegrator

    renderer = PathIntegrator(shading_scene(scene, config.render.shading_scale), threads=config.render.threads,
                              pixel_sampling=config.render.pixel_sampling)
    if not gbuffer or (renderer.width, renderer.height) == (scene.render.width, scene.render.height):
        return renderer, None
    from dpmhw.render.gbuffer import NativeGBuffer

    try:
        return renderer, NativeGBuffer(scene, renderer.geometry, scene.render.width, scene.render.height,
                                       threads=config.render.threads)
    except BaseException:
        renderer.close()
        raise


def open_session_parts(config: SessionConfig, *, mock: bool = False, renderer: Any = None,
                       usb: tuple[str, bytes] | None = None) -> SessionParts:
    """Open every part the config names (mocks first with `mock`); closes what it opened on error.
    The projector is opened before the renderer, a real one before the scene, so that a missing
    one is reported at once, not after seconds of scene loading and kernel compiling."""
    closers: list = []
    rig = projector = None
    try:
        if config.projector.kind == "dlpc900" and not mock:
            projector = DLPC900Control.open(config)
            closers.append(projector.close)
        scene = prepare_scene(config)
        problem = memory_problem(config, (scene.render.width, scene.render.height))
        if problem is not None:  # before anything allocates at that size
            raise SessionConfigError(problem)
        bindings = resolve_bindings(config, scene)
        over: dict = {}
        if mock:
            rig, over = start_mock_rig(config, scene, bindings, usb)
            closers.append(rig.stack.close)
            if config.projector.kind == "dlpc900":  # the rig's emulated one
                projector = DLPC900Control.open(config)
                closers.append(projector.close)
        gbuffer = None
        if renderer is None:
            renderer, gbuffer = build_renderer(config, scene)
            if gbuffer is not None:
                closers.append(gbuffer.close)
        if hasattr(renderer, "close"):
            closers.append(renderer.close)
        sink = open_sink(config, mock, (scene.render.height, scene.render.width), rig)
        closers.append(sink.close)
        tracker = open_tracker(config, **over)
        tracker.start()
        closers.append(tracker.stop)
        recorder = None
        if config.recording.enabled:
            from dpmhw.session.recording import SessionRecorder

            try:
                recorder = SessionRecorder.create(config.resolve(config.recording.path), config, tracker)
            except OSError as exc:
                raise SessionConfigError(f"recording.path: cannot create a session folder in {exc.filename or ''}: "
                                         f"{exc.strerror or exc}") from None
            closers.append(recorder.close)
    except BaseException:
        for close in reversed(closers):
            try:
                close()
            except Exception:
                log.exception("cleanup after a failed start")
        raise
    # the loop closes tracker, sink, renderer and projector itself; the rig last
    address, watch = describe_tracker(config, **over)
    return SessionParts(scene, renderer, tracker, sink, bindings, projector, recorder, rig, gbuffer,
                        closers=([gbuffer.close] if gbuffer is not None else []) + ([rig.stack.close] if rig is not None else []),
                        tracker_address=address, tracker_watch=watch)


def build_session(config: SessionConfig, *, mock: bool = False, renderer: Any = None, frame_log: int = 0,
                  usb: tuple[str, bytes] | None = None, heartbeat: Any = None) -> SessionLoop:
    """A ready-to-start loop over freshly opened parts, every per-frame kernel ready (compiled
    now if the cache lacks it: `warmup.compile_kernels` fills it ahead, in parallel).
    `heartbeat`: see dpmhw.session.heartbeat."""
    loop = SessionLoop(config, open_session_parts(config, mock=mock, renderer=renderer, usb=usb), frame_log=frame_log,
                       heartbeat=heartbeat)
    if renderer is None:
        try:
            loop.warm()
        except BaseException:
            loop.stop("the render kernels could not be readied")
            raise
    return loop


# ---- for the supervisor (dpmhw.session.supervisor), which outlives the loop's process -------------
def start_usb_emulator(config: SessionConfig):
    """The mock DLPC900 in its own process (`firmware_mocks.dlpc900_socket.EmulatorProcess`), so
    that it outlives a loop process, as a real projector does; pass (.address, .authkey) as `usb`."""
    from firmware_mocks.dlpc900_socket import EmulatorProcess

    return EmulatorProcess.start(config.projector.serial or "EMU0001", video_hz=config.display.refresh_hz)


def idle_projector(config: SessionConfig, usb: tuple[str, bytes] | None = None) -> str:
    """Open the projector, idle it, confirm by read-back, release it; returns how ("idle", …).
    Raises when it cannot be reached or darkness is not confirmed."""
    if config.projector.kind != "dlpc900":
        return "no projector"
    from drivers.dlpc900 import DLPC900

    with contextlib.ExitStack() as stack:
        backend = None  # pyusb's default (libusb)
        if usb is not None:  # the emulator, passed in (not put on the default bus: callers may be concurrent)
            from firmware_mocks.dlpc900_socket import SocketBackend

            backend = SocketBackend(*usb)
            stack.callback(backend.close)
        dlp = DLPC900.open(config.projector.serial or None, backend=backend, timeout_ms=config.projector.timeout_ms,
                           settle_s=0.0)
        stack.callback(dlp.close)
        return dlp.blank().method


def open_black_window(config: SessionConfig, mock: bool):
    """A black full-screen window on the projector's display, if the session used one (else None)."""
    if mock or config.sink.kind != "window":
        return None
    from drivers.frame_sinks import make_sink

    sink = make_sink("window", display=config.sink.display)
    sink.present(np.zeros((*sink.shape, 3), np.uint8), time.monotonic_ns())
    return sink
