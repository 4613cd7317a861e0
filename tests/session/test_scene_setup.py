"""Scene preparation for a session: render-size override, calibration file, bindings."""

from __future__ import annotations

import numpy as np
import pytest

from dpmhw.projector_calibration import ProjectorCalibration
from dpmhw.render.cameras import PinholeCamera
from dpmhw.scene_file import load_scene
from dpmhw.session.config import SessionConfigError, load_session_config
from dpmhw.session.factory import prepare_scene, resolve_bindings


def camera(scene):
    return PinholeCamera(scene.camera.K, scene.camera.dist, scene.render.width, scene.render.height, scene.camera.pose)


def test_reduced_size_keeps_points_on_the_same_place_of_the_picture():
    full = prepare_scene(load_session_config(overrides=["render.width=0", "render.height=0"]))
    small = prepare_scene(load_session_config(overrides=["render.width=256", "render.height=192"]))
    assert (small.render.width, small.render.height) == (256, 192)
    pts = full.objects[0].mesh.vertices[:50]
    px_full, _ = camera(full).project(pts)
    px_small, _ = camera(small).project(pts)
    np.testing.assert_allclose((px_small + 0.5) * 4, px_full + 0.5, atol=1e-9)  # lens shift kept


def test_calibration_file_replaces_the_camera(tmp_path):
    scene = load_scene("dpm-bunny")
    K = scene.camera.K.copy()
    K[0, 0] = K[1, 1] = 1400.0
    calib = ProjectorCalibration(1024, 768, K, np.zeros(5), scene.camera.pose.R, scene.camera.pose.t, frame="tracker")
    calib.save(tmp_path / "projector.json")
    (tmp_path / "session.toml").write_text('[scene]\ncalibration = "projector.json"\n[render]\nwidth = 512\nheight = 384\n')
    s = prepare_scene(load_session_config(tmp_path / "session.toml"))
    assert s.camera.K[0, 0] == pytest.approx(700.0) and (s.render.width, s.render.height) == (512, 384)
    calib.frame = "camera"
    calib.save(tmp_path / "projector.json")
    with pytest.raises(SessionConfigError, match="scene.calibration: .*'camera' frame"):
        prepare_scene(load_session_config(tmp_path / "session.toml"))


def test_bindings_default_to_the_scene_and_unknown_objects_are_named():
    cfg = load_session_config()
    scene = prepare_scene(cfg)
    assert resolve_bindings(cfg, scene) == {0: 1}
    cfg = load_session_config(overrides=['bindings=[{rigid_body = 4, object = "bunny"}]'])
    assert resolve_bindings(cfg, scene) == {0: 4}
    cfg = load_session_config(overrides=['bindings=[{rigid_body = 4, object = "teapot"}]'])
    with pytest.raises(SessionConfigError, match=r"bindings\[0\].object: no object named 'teapot'"):
        resolve_bindings(cfg, scene)


def test_real_renderer_is_warmed_up_before_the_loop_starts(monkeypatch):
    """The first kernel calls compile (numba): they must happen while the session is built, not as
    the loop's first frames, which the watchdog would report as a stall (tests/session/test_warmup.py
    checks that no frame compiles anything)."""
    from dpmhw.render.integrator import PathIntegrator
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import build_session

    calls = []
    original = PathIntegrator.render
    monkeypatch.setattr(PathIntegrator, "render", lambda self, *a, **kw: calls.append(kw) or original(self, *a, **kw))
    cfg = load_session_config(overrides=["render.width=32", "render.height=24", "projector.kind=none", "sink.kind=none"])
    loop = build_session(cfg, mock=True)
    try:
        assert not loop.running and len(calls) == 3 and {c["spp"] for c in calls} == {1}
        assert len({c["time"] for c in calls}) == 2  # a pose, then a move
    finally:
        loop.stop()
