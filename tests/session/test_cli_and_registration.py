"""`dpmhw session …` / `dpmhw bench session` on the mocks, and the registration-error measure."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from dpmhw.cli import _register, app
from dpmhw.render.cameras import PinholeCamera
from dpmhw.scene_file import load_scene
from dpmhw.session.registration import registration_error, silhouette
from dpmhw.transforms import Pose

SMALL = ["--set", "render.width=32", "--set", "render.height=24"]


@pytest.fixture(scope="module")
def runner():
    _register()
    return CliRunner()


def test_config_command_validates_and_masks_the_token(runner, tmp_path):
    r = runner.invoke(app, ["session", "config", "--offline", "--set", "api.token=abc", "--set", "render.spp=3"])
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)  # the memory estimate and warnings go to stderr
    assert data["render"]["spp"] == 3 and data["api"]["token"] == "***"
    bad = tmp_path / "s.toml"
    bad.write_text("[reuse]\nalpha = 2\n")
    r = runner.invoke(app, ["session", "config", "--config", str(bad)])
    assert r.exit_code == 2 and "reuse.alpha" in r.output and str(bad) in r.output


def test_config_command_checks_what_a_start_would(runner, tmp_path):
    """The scene's files and the devices: a mesh given as the calibration and an absent projector
    are refused here, not at start; --offline skips the devices only."""
    (tmp_path / "box.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "lab.toml").write_text('[scene]\ncalibration = "box.obj"\n')
    r = runner.invoke(app, ["session", "config", "--offline", "--config", str(tmp_path / "lab.toml")])
    assert r.exit_code == 2 and "scene.calibration: cannot load" in r.output and "box.obj" in r.output
    no_projector = ["--set", 'projector.serial="NO-SUCH-SERIAL"']  # absent on any machine
    r = runner.invoke(app, ["session", "config", *no_projector])
    errors = [line for line in r.output.splitlines() if line.startswith("error:")]  # after the memory estimate
    assert r.exit_code == 2 and len(errors) == 1 and errors[0].startswith("error: projector: "), r.output
    assert runner.invoke(app, ["session", "config", "--offline", *no_projector]).exit_code == 0


def test_device_checks_name_the_missing_device(monkeypatch, tmp_path):
    from dpmhw.session.config import SessionConfigError, load_session_config
    from dpmhw.session.factory import check_devices, prepare_scene

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    cfg = load_session_config(overrides=["projector.kind=\"none\"", "tracker.kind=\"serial\"",
                                         f"tracker.port={json.dumps(str(tmp_path / 'ttyUSB9'))}"])
    scene = prepare_scene(cfg)
    with pytest.raises(SessionConfigError, match=r"^tracker\.port: .*ttyUSB9 does not exist$"):
        check_devices(cfg, scene)
    cfg = load_session_config(overrides=["projector.kind=\"none\"", "tracker.server=\"no-such-host.invalid\""])
    with pytest.raises(SessionConfigError, match=r"^tracker\.server: cannot resolve 'no-such-host\.invalid'"):
        check_devices(cfg, scene)
    cfg = load_session_config(overrides=["projector.kind=\"none\"", "sink.display=7"])
    with pytest.raises(SessionConfigError, match=r"^sink: display: 7 does not exist"):
        check_devices(cfg, scene)


def test_a_missing_projector_is_reported_before_the_scene_loads(monkeypatch):
    from drivers.dlpc900_wire import DLPC900NotFound
    from dpmhw.session import factory
    from dpmhw.session.config import load_session_config

    def no_scene_yet(config):
        raise AssertionError("the scene was loaded before the projector was opened")

    monkeypatch.setattr(factory, "prepare_scene", no_scene_yet)
    cfg = load_session_config(overrides=['projector.serial="NO-SUCH-SERIAL"', 'sink.kind="none"'])
    with pytest.raises(DLPC900NotFound):
        factory.open_session_parts(cfg)


@pytest.mark.realtime
def test_start_mock_without_api_runs_records_and_ends_dark(runner, tmp_path):
    # one recorded frame is the claim; 6 s leave a loaded 2-core machine time to light one (3 s and
    # two frames did not: issue 14, finding 10)
    # stale_after_ms=2000: at 50 ms a loaded machine's late tracker samples kept it dark the whole
    # 6 s (seen with a CPU hog at load average 10+); what is tested is the recording and the dark end
    r = runner.invoke(app, ["session", "start", "--mock", "--no-api", "--duration", "6", "--status-every", "0", *SMALL,
                            "--record", "--set", f"recording.path={json.dumps(str(tmp_path))}", "--set", "recording.frame_every=1",
                            "--set", "safety.stale_after_ms=2000"])
    assert r.exit_code == 0, r.output
    assert "session started (mock devices)" in r.output and "projector dark (idle)" in r.output
    folder, = tmp_path.glob("session-*")
    poses = (folder / "poses.csv").read_text().splitlines()
    assert len(poses) > 100 and poses[0].startswith("body,t_exposure_ns")  # the real NatNet stream, 360 Hz
    assert len((folder / "frames.csv").read_text().splitlines()) >= 2 and any((folder / "frames").glob("*.png"))


def test_start_mock_with_api_on_loopback(runner, monkeypatch):
    monkeypatch.setenv("DPMHW_API_TOKEN", "cli-token")
    r = runner.invoke(app, ["session", "start", "--mock", "--port", "0", "--duration", "4", "--status-every", "0", *SMALL])
    assert r.exit_code == 0, r.output
    assert "API on http://127.0.0.1:" in r.output and "projector dark (idle)" in r.output
    assert "this session's token" not in r.output  # the env token is used, not a generated one


def test_start_names_a_busy_operator_port(runner, monkeypatch):
    import socket

    monkeypatch.setenv("DPMHW_API_TOKEN", "cli-token")
    with socket.create_server(("127.0.0.1", 0)) as taken:
        busy = taken.getsockname()[1]
        r = runner.invoke(app, ["session", "start", "--mock", "--port", "0", "--operator-port", str(busy),
                                "--duration", "1", "--status-every", "0", *SMALL])
    assert r.exit_code == 2 and f"api.operator_port: cannot listen on 127.0.0.1:{busy}" in r.output, r.output
    assert "loop process" not in r.output  # refused before anything started


def test_start_reports_bad_bindings_as_an_error(runner):
    r = runner.invoke(app, ["session", "start", "--mock", "--no-api", "--duration", "1", *SMALL,
                            "--set", 'bindings=[{rigid_body = 1, object = "teapot"}]'])
    assert r.exit_code == 2 and "bindings[0].object" in r.output and "teapot" in r.output


def test_registration_error_of_a_known_shift():
    scene = load_scene("dpm-bunny")
    cam = PinholeCamera(scene.camera.K, scene.camera.dist, scene.render.width, scene.render.height, scene.camera.pose)
    obj = scene.objects[0]
    v, f = obj.mesh.vertices, obj.mesh.faces
    base = obj.pose
    mask = silhouette(cam, v, f, base)
    assert 0.01 < mask.mean() < 0.5
    same = registration_error(cam, v, f, base, base)
    assert same.mean_px == 0 and same.max_px == 0 and same.vertex_px == 0
    # 1 cm sideways at ~1 m with fx = 1500 px is ~15 px on the projector
    shifted = Pose(base.R, base.t + np.array([0.01, 0.0, 0.0]))
    err = registration_error(cam, v, f, shifted, base)
    assert err.vertex_px == pytest.approx(15.0, rel=0.12)
    assert err.max_px == pytest.approx(15.0, abs=2.0)
    assert 2.0 < err.mean_px < err.max_px


@pytest.mark.parametrize("shift", [(0.0, 0.0, 0.0), (0.004, -0.002, 0.0), (0.3, 0.0, 0.0)])
def test_registration_over_the_silhouettes_window_equals_the_whole_image(shift):
    """The error is measured in the image part both silhouettes lie in: the same numbers as over
    the whole image, also for a mesh partly outside it (0.3 m sideways)."""
    import cv2

    from dpmhw.session import registration

    scene = load_scene("dpm-bunny")
    cam = PinholeCamera(scene.camera.K, scene.camera.dist, scene.render.width, scene.render.height, scene.camera.pose)
    obj = scene.objects[0]
    v, f = obj.mesh.vertices, obj.mesh.faces
    true = Pose(obj.pose.R, obj.pose.t + np.array(shift))
    shown = Pose(obj.pose.R, true.t + np.array([0.003, 0.001, 0.0]))
    a = registration._outline(silhouette(cam, v, f, shown))
    b = registration._outline(silhouette(cam, v, f, true))
    d = np.concatenate([cv2.distanceTransform((~b).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[a],
                        cv2.distanceTransform((~a).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[b]])
    err = registration_error(cam, v, f, shown, true)
    assert (err.mean_px, err.max_px) == pytest.approx((float(d.mean()), float(d.max())), rel=1e-6)


@pytest.mark.slow
def test_bench_session_command(runner, tmp_path):
    out = tmp_path / "bench.json"
    r = runner.invoke(app, ["bench", "session", "--seconds", "1", "--trajectory", "linear", "--api-clients", "2",
                            "--api-windows", "1", "--api-window-s", "1", "--width", "64", "--height", "48",
                            "--json", str(out), "--plot", str(tmp_path / "bench.png")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "bench.png").stat().st_size > 10_000
    results = json.loads(out.read_text())
    assert not any("series" in x for x in results["cases"])  # plotted, not written as rows
    assert [(x["prediction"], x["reprojection"]) for x in results["cases"]] == [(True, True), (True, False), (False, False)]
    assert all(x["frames"] > 2 and x["registration_px_p50"] is not None for x in results["cases"])
    for x in results["cases"]:  # the flat row docs/session.md documents
        assert (x["output_width"], x["output_height"]) == (64, 48)
        assert {"scene", "method", "shading_scale", "filter", "alpha", "fps_median", "latency_ms_p99",
                "registration_px_p99", "gbuffer_ms_p50", "upsample_ms_p50", "late_presents", "new_windows_per_s",
                "repeated_windows"} <= set(x)
        assert x["new_windows_per_s"] > 0  # the emulated projector lit new pictures
        assert not any(isinstance(v, (dict, list)) for v in x.values())
        assert x["cpu_ms_per_rendered_frame"] > 0 and x["mitsuba_note"] is not None  # skipped (with why) without mitsuba
        assert x["cpu_steal"] is None or 0.0 <= x["cpu_steal"] <= 1.0
        assert (x["cpu_over_mitsuba"] is None) == (x["mitsuba_cpu_ms"] is None)
    assert [x["api_mode"] for x in results["api_load"]] == ["process", "thread"]
    for load in results["api_load"]:
        assert load["requests"] > 0 and load["errors"] == 0 and load["loaded_frames"] > 0 and load["unloaded_frames"] > 0
    assert "API in its own process: 2 clients" in r.output and "API in its thread of the session process" in r.output


def test_the_bench_counts_lit_sub_frames_over_the_span_the_projectors_log_holds():
    """A measurement longer than the emulated projector's log (the newest rows only) gives the
    rate of new sub-frames over the part it holds, not the whole span's count spread thin."""
    from types import SimpleNamespace as NS

    from dpmhw.benchmarks.session import _light_counts

    s = 1_000_000_000
    records = [NS(t_present_ns=k * s // 60) for k in range(60 * 10 + 1)]  # 10 s of presents
    held = [NS(scanout_ns=5 * s + (k // 3) * s // 60, repeat=(k // 3) % 60 == 0) for k in range(180 * 5)]  # its last 5 s
    counts = _light_counts(held, records)
    assert counts["repeated_windows"] == 15  # one refresh of three in every second held
    assert counts["new_windows_per_s"] == pytest.approx(180 * 59 / 60, rel=0.01)


def test_the_emulated_projectors_log_is_as_long_as_the_config_says():
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import build_session

    cfg = load_session_config(overrides=["render.width=64", "render.height=48", "api.enabled=false",
                                         "display.mode=pattern-8bit", "mock.exposure_rows=100"])
    loop = build_session(cfg, mock=True)
    try:
        assert loop.parts.mock.video.exposures.maxlen == 100
    finally:
        loop.stop()


def test_bench_session_mitsuba_yardstick_is_skipped_with_a_note(monkeypatch):
    from dpmhw.benchmarks import mitsuba as mb
    from dpmhw.benchmarks.session import mitsuba_yardstick

    def absent(*args, **kwargs):
        raise mb.MitsubaUnavailable("mitsuba is not installed: pip install -e '.[mitsuba]'")

    monkeypatch.setattr(mb, "one_spp_frame", absent)
    row = mitsuba_yardstick(64, 48)
    assert row["mitsuba_cpu_ms"] is None and row["mitsuba_variant"] is None
    assert row["mitsuba_note"] == "skipped: mitsuba is not installed: pip install -e '.[mitsuba]'"


def test_the_tracker_hint_is_a_command_the_cli_accepts(runner):
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import describe_tracker

    for overrides, address in (([], "NatNet server 127.0.0.1:1510"),
                               (['tracker.kind="serial"', 'tracker.port="/dev/null"'], "serial port /dev/null")):
        got, watch = describe_tracker(load_session_config(overrides=overrides))
        assert got == address and watch.startswith("dpmhw tracker watch ")
        r = runner.invoke(app, [*watch.split()[1:], "--seconds", "0.2", "--every", "0.1"])
        assert r.exit_code == 1 and "Usage" not in r.output, r.output  # 1: no frame arrived (not 2: bad options)


def test_the_bench_can_make_each_present_cost_what_a_slower_cpu_would():
    """`--present-cpu-factor F`: each kernel call of a present spends F times its own CPU time
    on its own thread (the thread's CPU, so a busy machine beside does not change it)."""
    import time
    from types import SimpleNamespace as NS

    from dpmhw.benchmarks.session import _slowed_presents

    made = []

    def splats(common, scratch, plan, g_first, g_end):  # 20 ms of this thread's CPU
        end = time.thread_time_ns() + 20_000_000
        while time.thread_time_ns() < end:
            pass
        made.append((common, scratch, plan, g_first, g_end))

    reprojector = NS(_splats=splats)
    _slowed_presents(reprojector, 3.0)
    cpu0 = time.thread_time_ns()
    reprojector._splats("common", "scratch", False, 1, 2)
    assert 60e6 <= time.thread_time_ns() - cpu0 < 75e6
    assert made == [("common", "scratch", False, 1, 2)]
