"""Sessions output the projector's native size, end to end on the mocks, whatever the shading scale."""

from __future__ import annotations

import pytest

from dpmhw.session.config import SessionConfigError, load_session_config
from dpmhw.session.factory import build_session
from dpmhw.session.testing import wait_for


@pytest.mark.parametrize("scale, filt", [(0.25, "lobe"), (0.5, "normal"), (1, "off")])
def test_mocked_session_frames_have_the_native_shape(scale, filt):
    cfg = load_session_config(overrides=[
        "render.width=128", "render.height=96", f"render.shading_scale={scale}", f"render.filter={filt}",
        "mock.speed=0.3", "safety.stale_after_ms=200", "safety.watchdog_s=5", "sink.kind=recording",
        "projector.poll_interval_s=0.05"])
    loop = build_session(cfg, mock=True).start()
    try:
        assert wait_for(lambda: loop.status()["frame_number"] >= 5, timeout_s=60)
        loop.update_settings({"filter": "normal" if filt != "normal" else "lobe"})  # live, like alpha
        start = loop.status()["frame_number"]
        assert wait_for(lambda: loop.status()["frame_number"] >= start + 3, timeout_s=60)
        status = loop.status()
    finally:
        loop.stop()
    frames = loop.parts.sink.frames
    assert frames and all(f.frame.shape == (96, 128, 3) for f in frames)
    assert status["output_size"] == [128, 96]
    assert status["render_size"] == [round(128 * scale), round(96 * scale)]
    assert status["settings_applied"]["filter"] in ("normal", "lobe")
    for stage in ("render", "gbuffer", "reuse", "filter", "upsample", "post", "present"):
        assert status["stages_ms"][stage]["p50_ms"] is not None


def test_a_live_filter_setting_outside_the_modes_is_refused():
    from dpmhw.session.loop import SettingsError
    from dpmhw.session.testing import fake_session

    loop = fake_session()
    with pytest.raises(SettingsError, match="filter"):
        loop.update_settings({"filter": "bilateral"})


def test_shading_scale_must_be_one_of_the_supported_ones():
    with pytest.raises(SessionConfigError, match="render.shading_scale"):
        load_session_config(overrides=["render.shading_scale=0.3"])


def test_a_jittered_session_renders_native_frames_with_jittered_camera_rays():
    """Both pixel-sampling modes stay available to a session (issue 12)."""
    cfg = load_session_config(overrides=[
        "render.width=128", "render.height=96", "render.pixel_sampling=jitter", "mock.speed=0.3",
        "safety.stale_after_ms=200", "safety.watchdog_s=5", "sink.kind=recording", "projector.poll_interval_s=0.05"])
    loop = build_session(cfg, mock=True).start()
    try:
        assert wait_for(lambda: loop.status()["frame_number"] >= 3, timeout_s=60)
    finally:
        loop.stop()
    renderer = loop.parts.renderer
    assert renderer.pixel_sampling == "jitter"  # what it does with it: tests/render/test_pixel_jitter.py
    assert all(f.frame.shape == (96, 128, 3) for f in loop.parts.sink.frames)


def test_pixel_sampling_must_be_centre_or_jitter():
    assert load_session_config().render.pixel_sampling == "centre"
    with pytest.raises(SessionConfigError, match="render.pixel_sampling"):
        load_session_config(overrides=["render.pixel_sampling=random"])
