"""The reconstruction stage: exact path equals the old pipeline; native output end to end."""

from __future__ import annotations

from concurrent.futures import Future

import numpy as np
import pytest

from dpmhw.postprocess import NonFiniteFrameError, encode_srgb8, srgb8_table, to_srgb8
from dpmhw.reconstruct.reuse import TemporalReuse
from dpmhw.reconstruct.stage import ReconstructStage
from dpmhw.render.gbuffer import NativeGBuffer
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene
from dpmhw.session.factory import shading_scene


@pytest.mark.parametrize("exposure", [1.0, 0.6, 3.0])
def test_table_srgb_equals_to_srgb8_bit_for_bit(exposure):
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.random(300_000, dtype=np.float32), rng.random(300_000, dtype=np.float32) ** 8,
                        rng.uniform(-1, 4, 300_000).astype(np.float32)])
    base, thr = srgb8_table(exposure)
    steps = thr[thr != 0xFFFFFFFF].astype(np.int64)  # every code step and its neighbours
    near = np.concatenate([steps + d for d in range(-2, 3)]).astype(np.uint32).view(np.float32)
    x = np.concatenate([x, near, np.float32([0.0, -0.0, 1.0, 1e-45, 1e30])])
    x = np.ascontiguousarray(np.repeat(x[:, None], 3, axis=1))
    assert np.array_equal(encode_srgb8(x, 1, exposure), to_srgb8(x[:, None, :], exposure)[:, 0, :])
    x[5, 1] = np.nan
    with pytest.raises(NonFiniteFrameError):
        encode_srgb8(x, 1, exposure)


def _frames(scene, n):
    r = PathIntegrator(scene, threads=1)
    try:
        return [(r.render(time=i / 30, seed=i, poses=scene.object_poses(i / 30)), scene.object_poses(i / 30), r.camera)
                for i in range(n)]
    finally:
        r.close()


@pytest.mark.parametrize("mode", ["same-pixel", "motion"])
def test_scale_one_with_the_filter_off_equals_the_old_pipeline_bit_for_bit(mode):
    scene = load_scene("dpm-bunny").at_size(64, 48)
    stage = ReconstructStage((64, 48), (64, 48), background=scene.render.background, viewer=scene.viewer_position)
    old = TemporalReuse(64, 48, alpha=0.2, mode=mode)
    for frame, poses, camera in _frames(scene, 4):
        expected = to_srgb8(old.update_frame(frame, poses=poses, camera=camera))
        got = stage.apply(frame, mode=mode, alpha=0.2, filter="off", poses=poses, camera=camera).image
        assert got.shape == (48, 64, 3) and np.array_equal(got, expected)


@pytest.mark.parametrize("filt", ["off", "normal", "lobe"])
def test_quarter_shading_gives_native_frames_that_follow_the_object(filt):
    native = load_scene("dpm-bunny").at_size(128, 96)
    low = shading_scene(native, 0.25)
    r = PathIntegrator(low, threads=1)
    g = NativeGBuffer(native, r.geometry, 128, 96, threads=1)
    try:
        stage = ReconstructStage((128, 96), (32, 24), background=native.render.background,
                                 viewer=native.viewer_position, gbuffer=g)
        for i in range(3):
            poses = native.object_poses(i / 10)
            frame = r.render(time=i / 10, seed=i, poses=poses)
            out = stage.apply(frame, mode="motion", alpha=0.2, filter=filt, poses=poses, camera=r.camera)
        lit = out.image.sum(axis=2) > 0
        obj = g.id.reshape(96, 128) >= 0
        assert out.image.shape == (96, 128, 3)
        assert not (lit & ~obj).any()  # light only where the native G-buffer sees the object
        assert lit[obj].mean() > 0.8
        y0, y1, x0, x1 = out.lit_box
        assert obj[:y0].sum() == obj[y1:].sum() == obj[:, :x0].sum() == obj[:, x1:].sum() == 0
    finally:
        g.close()
        r.close()


def test_native_gbuffer_matches_the_renderers_and_retraces_only_the_roi():
    native = load_scene("dpm-bunny").at_size(160, 120)
    r = PathIntegrator(native, threads=1)
    g = NativeGBuffer(native, r.geometry, 160, 120, threads=1)
    try:
        for t in (0.0, 0.7, 1.4):
            poses = native.object_poses(t)
            g.update(poses)
            f = r.render(time=t, poses=poses)
            assert np.array_equal(f.object_id.reshape(-1), g.id)
            hit = g.id >= 0
            assert np.allclose(f.normal.reshape(-1, 3)[hit], g.normal[hit], atol=1e-6)
            assert np.array_equal(f.depth.reshape(-1)[hit], g.depth[hit])
            assert 0 < g.rays_traced < 160 * 120
    finally:
        g.close()
        r.close()


def test_edges_mode_traces_only_near_discontinuities_and_agrees_with_full_tracing():
    native = load_scene("dpm-bunny").at_size(256, 192)
    r = PathIntegrator(shading_scene(native, 0.25), threads=1)
    edges = NativeGBuffer(native, r.geometry, 256, 192, threads=1)
    full = NativeGBuffer(native, r.geometry, 256, 192, threads=1)
    try:
        for t in (0.0, 0.4, 0.8):
            poses = native.object_poses(t)
            frame = r.render(time=t, poses=poses)
            edges.update(poses, shading=frame)
            full.update(poses, mode="trace")
            lit = int((full.id >= 0).sum())
            assert edges.rays_traced < 0.5 * full.rays_traced
            assert (edges.id != full.id).sum() <= 0.01 * lit
            both = (full.id >= 0) & (edges.id == full.id)
            cos = (edges.normal[both] * full.normal[both]).sum(axis=1)
            assert np.median(cos) > np.cos(np.radians(10))  # interpolated inside: a few degrees
            rel = np.abs(edges.depth[both] / full.depth[both] - 1)
            assert np.median(rel) < 0.002 and np.percentile(rel, 99) < 0.03
    finally:
        edges.close()
        full.close()
        r.close()


def test_stages_sharing_one_native_gbuffer_each_see_the_static_scene():
    """The session warms up with throw-away stages on the loop's G-buffer; the loop's own stage
    must still see every static pixel (a static scene has no moving region to refresh)."""
    native = load_scene("paper-static").at_size(64, 48)
    r = PathIntegrator(shading_scene(native, 0.5), threads=1)
    g = NativeGBuffer(native, r.geometry, 64, 48, threads=1)
    try:
        frame = r.render(time=0.0, seed=0)
        images = []
        for _ in range(2):
            stage = ReconstructStage((64, 48), (32, 24), background=native.render.background,
                                     viewer=native.viewer_position, gbuffer=g)
            images.append(stage.apply(frame, mode="same-pixel", alpha=0.2, filter="lobe", poses=native.object_poses(0.0),
                                      camera=r.camera).image)
        assert np.array_equal(images[0], images[1]) and (images[1].sum(axis=2) > 0).mean() > 0.9
    finally:
        g.close()
        r.close()


def test_switching_the_filter_live_restarts_the_history_of_the_other_path():
    scene = load_scene("dpm-bunny").at_size(64, 48)
    stage = ReconstructStage((64, 48), (64, 48), background=scene.render.background, viewer=scene.viewer_position)
    frames = _frames(scene, 3)
    for (frame, poses, camera), filt in zip(frames, ("off", "lobe", "off")):
        out = stage.apply(frame, mode="same-pixel", alpha=0.2, filter=filt, poses=poses, camera=camera)
    fresh = TemporalReuse(64, 48, alpha=0.2, mode="same-pixel")
    frame, poses, camera = frames[2]
    assert np.array_equal(out.image, to_srgb8(fresh.update_frame(frame, poses=poses, camera=camera)))


def test_native_gbuffer_packet_path_equals_the_embreex_path():
    """The C-API packet re-trace (tile order, from the cached static hits) and embreex's
    gathered one-ray path give the same G-buffer bit for bit."""
    from dpmhw.render.embree.accel import EmbreeAccel, RtcAccel

    native = load_scene("dpm-bunny").at_size(96, 72)
    r = PathIntegrator(native, threads=1)
    if not isinstance(r.geometry.accel, RtcAccel):
        r.close()
        pytest.skip("libembree4 not loadable: only the embreex path exists")
    packets = NativeGBuffer(native, r.geometry, 96, 72, threads=2)
    rtc = r.geometry.accel
    r.geometry.accel = EmbreeAccel(native.objects, r.geometry.tri_offsets, threads=1)
    single = None
    try:
        single = NativeGBuffer(native, r.geometry, 96, 72, threads=2)
        for t in (0.0, 0.5, 1.0):
            poses = native.object_poses(t)
            packets.update(poses, mode="trace")
            single.update(poses, mode="trace")
            assert packets.rays_traced == single.rays_traced > 0
            for name in ("id", "position", "normal", "depth", "albedo", "roughness"):
                assert np.array_equal(getattr(packets, name), getattr(single, name)), name
    finally:
        r.geometry.accel.close()
        r.geometry.accel = rtc
        packets.close()
        if single is not None:
            single.close()
        r.close()


@pytest.mark.parametrize("dist", [(0.0, 0.0, 0.0, 0.0, 0.0), (-0.12, 0.05, 0.002, -0.003, 0.0)])
def test_raster_mode_gives_the_ray_cast_gbuffer_except_at_ties(dist):
    """Rasterising the moving objects (z-buffer of their model-space meshes, coverage tested
    at each pixel ray's ideal image-plane point) finds the hits ray casting finds; only pixel
    centres on a shared edge or a silhouette may differ. With and without lens distortion."""
    from dataclasses import replace

    base = load_scene("dpm-bunny").at_size(256, 192)
    native = replace(base, camera=replace(base.camera, dist=np.array(dist)))
    r = PathIntegrator(shading_scene(native, 0.25), threads=1)
    ras = NativeGBuffer(native, r.geometry, 256, 192, threads=2)
    full = NativeGBuffer(native, r.geometry, 256, 192, threads=2)
    try:
        for t in (0.0, 0.4, 0.8, 1.3):
            poses = native.object_poses(t)
            ras.update(poses, mode="raster")
            full.update(poses, mode="trace")
            lit = int((full.id >= 0).sum())
            assert lit > 500 and ras.rays_traced == 0 and ras.pixels_rasterised > 0
            assert (ras.id != full.id).sum() <= max(2, 0.002 * lit)
            same = (full.id >= 0) & (ras.id == full.id)
            assert np.allclose(ras.depth[same], full.depth[same], rtol=1e-4)
            assert np.allclose(ras.position[same], full.position[same], atol=1e-4)
            cos = (ras.normal[same] * full.normal[same]).sum(axis=1)
            assert (cos > 0.9999).mean() > 0.999
            for name in ("albedo", "spec_albedo", "roughness"):
                assert np.array_equal(getattr(ras, name)[same], getattr(full, name)[same]), name
        # the region moves away: its old pixels get the static scene back
        ras.update(native.object_poses(0.0), mode="raster")
        full.update(native.object_poses(0.0), mode="trace")
        assert (ras.id != full.id).sum() <= max(2, 0.002 * int((full.id >= 0).sum()))
    finally:
        ras.close()
        full.close()
        r.close()


def test_the_shading_branch_on_the_helper_thread_gives_the_same_frames_as_in_line():
    """The shading-resolution branch runs beside the native G-buffer on a helper thread; the
    frames equal those of running it in line, bit for bit, and close() stops the helper."""

    class _InLine:  # an executor that runs the branch at submit, on the calling thread
        def submit(self, fn, *args):
            value = fn(*args)
            return type("Done", (), {"result": lambda self: value})()

        def shutdown(self, wait=True):
            pass

    native = load_scene("dpm-bunny").at_size(256, 192)
    r = PathIntegrator(shading_scene(native, 0.25), threads=2)
    gs = [NativeGBuffer(native, r.geometry, 256, 192, threads=2) for _ in range(2)]
    stages = [ReconstructStage((256, 192), (64, 48), background=native.render.background, viewer=native.viewer_position,
                               gbuffer=g) for g in gs]
    stages[1]._helper = _InLine()
    try:
        for i in range(5):
            poses = native.object_poses(i / 10)
            frame = r.render(time=i / 10, seed=i, poses=poses)
            a, b = (s.apply(frame, mode="motion", alpha=0.2, filter="lobe", poses=poses, camera=r.camera) for s in stages)
            assert np.array_equal(a.image, b.image) and a.image.sum() > 0
            assert set(a.stages_s) == {"gbuffer", "reuse", "filter", "upsample", "adaptive", "post"}
        assert stages[0]._helper is not None
        stages[0].close()
        assert stages[0]._helper is None
    finally:
        for g in gs:
            g.close()
        r.close()


def test_native_guides_recomputed_only_where_the_gbuffer_changed_equal_guides_from_scratch():
    """Inside the moving objects' region the stage recomputes the guides of only the pixels the
    G-buffer changed (`NativeGBuffer.changed`); after every frame they must equal the guides of
    the whole native G-buffer computed afresh."""
    from dpmhw.reconstruct.guides import Guides

    native = load_scene("dpm-bunny").at_size(256, 192)
    r = PathIntegrator(shading_scene(native, 0.25), threads=1)
    g = NativeGBuffer(native, r.geometry, 256, 192, threads=1)
    stage = ReconstructStage((256, 192), (64, 48), background=native.render.background, viewer=native.viewer_position,
                             gbuffer=g)
    try:
        unchanged = []
        for k, t in enumerate((0.0, 0.05, 0.1, 0.6, 0.65, 1.4, 1.45)):
            poses = native.object_poses(t)
            frame = r.render(time=t, seed=k, poses=poses)
            stage.apply(frame, mode="motion", alpha=0.2, filter="lobe", poses=poses, camera=r.camera)
            H, W = g.height, g.width
            fresh = Guides.from_gbuffer(g.id.reshape(H, W), g.position.reshape(H, W, 3), g.normal.reshape(H, W, 3),
                                        g.depth.reshape(H, W), g.albedo.reshape(H, W, 3), g.spec_albedo.reshape(H, W, 3),
                                        g.roughness.reshape(H, W), stage.viewer)
            for name in ("id", "depth", "normal", "axis", "sharp", "albedo", "spec_albedo"):
                assert np.array_equal(getattr(stage.native, name), getattr(fresh, name)), (t, name)
            if g.roi_box is not None:
                y0, y1, x0, x1 = g.roi_box
                unchanged.append(int((~g.changed.reshape(H, W)[y0:y1, x0:x1]).sum()))
        assert max(unchanged) > 0  # the mask did skip pixels (else this test checks nothing new)
    finally:
        stage.close()
        g.close()
        r.close()


def test_two_stages_sharing_a_moving_native_gbuffer_each_keep_guides_equal_to_fresh_ones():
    """A benchmark runs several stages on one native G-buffer, each updating it per frame: a
    stage that did not see the previous update must not trust `changed` (it recomputes the region)."""
    from dpmhw.reconstruct.guides import Guides

    native = load_scene("dpm-bunny").at_size(256, 192)
    r = PathIntegrator(shading_scene(native, 0.25), threads=1)
    g = NativeGBuffer(native, r.geometry, 256, 192, threads=1)
    stages = [ReconstructStage((256, 192), (64, 48), background=native.render.background,
                               viewer=native.viewer_position, gbuffer=g) for _ in range(2)]
    try:
        for k, t in enumerate((0.0, 0.05, 0.6, 0.65, 1.4)):
            poses = native.object_poses(t)
            frame = r.render(time=t, seed=k, poses=poses)
            for stage in stages:
                stage.apply(frame, mode="motion", alpha=0.2, filter="lobe", poses=poses, camera=r.camera)
            H, W = g.height, g.width
            fresh = Guides.from_gbuffer(g.id.reshape(H, W), g.position.reshape(H, W, 3), g.normal.reshape(H, W, 3),
                                        g.depth.reshape(H, W), g.albedo.reshape(H, W, 3), g.spec_albedo.reshape(H, W, 3),
                                        g.roughness.reshape(H, W), stages[0].viewer)
            for stage in stages:
                for name in ("id", "depth", "normal", "axis", "sharp"):
                    assert np.array_equal(getattr(stage.native, name), getattr(fresh, name)), (t, name)
    finally:
        for stage in stages:
            stage.close()
        g.close()
        r.close()


def _done(value) -> Future:
    f = Future()
    f.set_result(value)
    return f


def test_the_next_frames_gbuffer_brought_ahead_gives_the_same_frames():
    """With `next_frame` the native G-buffer moves to the next frame on its own thread while this
    frame is upsampled and adaptively sampled: the frames equal those of a stage without it, bit
    for bit, also when a frame announced ahead never comes (a dropped prefetch)."""
    from dpmhw.reconstruct.adaptive import AdaptiveSampler

    native = load_scene("dpm-bunny").at_size(256, 192)
    r = PathIntegrator(shading_scene(native, 0.25), threads=2)
    gs = [NativeGBuffer(native, r.geometry, 256, 192, threads=2) for _ in range(2)]
    stages = [ReconstructStage((256, 192), (64, 48), background=native.render.background, viewer=native.viewer_position,
                               gbuffer=g, adaptive=AdaptiveSampler(r, g, 4096, threshold=0.05)) for g in gs]
    try:
        times = [i / 10 for i in range(7)]
        poses = [native.object_poses(t) for t in times]
        frames = [r.render(time=t, seed=i, poses=p) for i, (t, p) in enumerate(zip(times, poses))]
        dropped = r.render(time=0.35, seed=99, poses=native.object_poses(0.35))  # announced, never applied
        for i, frame in enumerate(frames):
            if i == 3:
                nxt = (native.object_poses(0.35), _done(dropped))
            else:
                nxt = (poses[i + 1], _done(frames[i + 1])) if i + 1 < len(frames) else None
            a = stages[0].apply(frame, mode="motion", alpha=0.2, filter="lobe", poses=poses[i], camera=r.camera,
                                next_frame=nxt)
            b = stages[1].apply(frame, mode="motion", alpha=0.2, filter="lobe", poses=poses[i], camera=r.camera)
            assert np.array_equal(a.image, b.image) and a.lit_box == b.lit_box and a.image.sum() > 0
            assert stages[1]._ahead is None and (stages[0]._ahead is not None) == (nxt is not None)
        assert stages[0].adaptive.last_pixels > 0  # the sampler ran on the guides' ids
        stages[0].close()
        assert stages[0]._ahead is None and stages[0]._ahead_thread is None
    finally:
        for s in stages:
            s.close()
        for g in gs:
            g.close()
        r.close()


def test_a_failure_of_the_early_gbuffer_update_is_the_next_frames_and_the_stage_recovers():
    native = load_scene("dpm-bunny").at_size(128, 96)
    r = PathIntegrator(shading_scene(native, 0.25), threads=1)
    g = NativeGBuffer(native, r.geometry, 128, 96, threads=1)
    stage = ReconstructStage((128, 96), (32, 24), background=native.render.background, viewer=native.viewer_position,
                             gbuffer=g)
    try:
        poses = [native.object_poses(i / 10) for i in range(4)]
        frames = [r.render(time=i / 10, seed=i, poses=p) for i, p in enumerate(poses)]
        real = g.update
        calls = []

        def flaky(*a, **k):
            calls.append(1)
            if len(calls) == 2:  # the early update for frame 1
                raise RuntimeError("trace failed")
            return real(*a, **k)

        g.update = flaky
        kw = dict(mode="motion", alpha=0.2, filter="lobe", camera=r.camera)
        stage.apply(frames[0], poses=poses[0], next_frame=(poses[1], _done(frames[1])), **kw)
        with pytest.raises(RuntimeError, match="trace failed"):
            stage.apply(frames[1], poses=poses[1], next_frame=(poses[2], _done(frames[2])), **kw)
        assert stage._ahead is None  # nothing left running for a frame that failed
        out = stage.apply(frames[2], poses=poses[2], **kw)  # its own update: the stage goes on
        assert out.image.sum() > 0
    finally:
        stage.close()
        g.close()
        r.close()
