"""Per-tile native refinement in the loop's reconstruction: off is bit-exact, the ray budget
holds, moving objects get native paths, the reprojected history and the blend."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from dpmhw.lod.refine import RefineSettings, TileRefiner, _fetch, _fill, _merge, _select, tile_refiner
from dpmhw.lod.visibility import LodSettingsError
from dpmhw.reconstruct.adaptive import AdaptiveSampler
from dpmhw.reconstruct.stage import ReconstructStage
from dpmhw.render.gbuffer import NativeGBuffer
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene
from dpmhw.session.config import LodSection, load_session_config
from dpmhw.session.factory import shading_scene

W, H = 128, 96


@pytest.fixture(scope="module")
def rig():
    native = load_scene("paper-dynamic").at_size(W, H)
    r = PathIntegrator(shading_scene(native, 0.25), threads=2)
    g = NativeGBuffer(native, r.geometry, W, H, threads=2)
    yield native, r, g
    g.close()
    r.close()


def _stage(native, r, g, lod, adaptive=True):
    return ReconstructStage((W, H), (r.width, r.height), background=native.render.background,
                            viewer=native.viewer_position, gbuffer=g,
                            adaptive=AdaptiveSampler(r, g, 2048) if adaptive else None, lod=lod)


def _run(native, r, stages, frames=4):
    outs = {k: [] for k in stages}
    for k in range(frames):
        t = 0.1 + k / 60
        poses = native.object_poses(t)
        frame = r.render(time=t, seed=k, spp=1, poses=poses)
        for name, st in stages.items():
            outs[name].append(st.apply(frame, mode="motion", alpha=0.2, filter="lobe", poses=poses, camera=r.camera))
    return outs


def test_off_is_no_refiner_and_the_stage_is_unchanged(rig):
    native, r, g = rig
    assert tile_refiner(r, g, LodSection(rays=0)) is None
    assert tile_refiner(r, g, LodSection(moving=False, visible=False)) is None
    assert tile_refiner(r, None, LodSection()) is None  # shading_scale 1: no native G-buffer, nothing to refine
    assert load_session_config(overrides=["lod.rays=0"]).lod.rays == 0


def test_a_refiner_with_nothing_to_refine_leaves_the_output_bit_for_bit(rig):
    """Moving objects held still is not 'nothing moves': use moving=False and visible=False
    through the class directly (tile_refiner would return None): the hook runs, changes nothing."""
    native, r, g = rig
    quiet = TileRefiner(r, g, RefineSettings(rays=10**6, moving=False, visible=False))
    outs = _run(native, r, {"plain": _stage(native, r, g, None), "hooked": _stage(native, r, g, quiet)})
    for a, b in zip(outs["plain"], outs["hooked"]):
        assert np.array_equal(a.image, b.image)
    assert quiet.last_rays == 0


def test_moving_objects_get_native_paths_within_the_budget_and_the_rest_is_untouched(rig):
    native, r, g = rig
    ref = TileRefiner(r, g, RefineSettings(rays=10**6))
    # adaptive sampling off: it skips refined pixels, so its budget would go to others
    outs = _run(native, r, {"plain": _stage(native, r, g, None, False), "lod": _stage(native, r, g, ref, False)})
    assert 0 < ref.last_rays <= 10**6
    a, b = outs["plain"][-1].image, outs["lod"][-1].image
    moving = np.isin(g.id.reshape(H, W), [i for i, o in enumerate(native.objects) if o.is_dynamic])
    changed = np.any(a != b, axis=2)
    assert changed[moving].mean() > 0.5  # the moving objects' pixels are re-shaded natively
    assert not changed[~moving].any()  # nothing else (visible=False): only moving pixels are traced
    assert np.isfinite(outs["lod"][-1].image).all()


@pytest.mark.parametrize("every", [1, 2, 4])
@pytest.mark.parametrize("budget", [0, 500, 5_000, 40_000])
def test_the_ray_budget_is_never_exceeded(rig, budget, every):
    native, r, g = rig
    ref = TileRefiner(r, g, RefineSettings(rays=max(budget, 1), visible=True, adaptive_spp=True, alpha_v=50.0,
                                           moving_every=every))
    st = _stage(native, r, g, ref)
    for k in range(5):
        t = 0.2 + k / 60
        poses = native.object_poses(t)
        st.apply(r.render(time=t, seed=k, spp=1, poses=poses), mode="motion", alpha=0.2, filter="lobe", poses=poses,
                 camera=r.camera)
        assert ref.last_rays <= max(budget, 1)
        assert ref.decisions.ray_bound <= max(budget, 1)
        # paths traced within the planned bound (moving tiles: one phase of the every-N pattern)
        assert ref.last_pixels <= (ref.decisions.spp.astype(np.int64) * ref.decisions.shaded_pixels).sum()


def test_visible_tiles_are_refined_from_the_previous_output(rig):
    """α_v high enough makes every lit tile visible: all lit pixels of the frame get paths."""
    native, r, g = rig
    ref = TileRefiner(r, g, RefineSettings(rays=10**7, moving=False, visible=True, shading_rate=False, alpha_v=1e4))
    _run(native, r, {"lod": _stage(native, r, g, ref)}, frames=3)
    lit = int((g.id >= 0).sum())
    assert ref.last_pixels == lit


def test_fetch_reprojects_bilinearly_over_matching_taps_only():
    Wf, Hf = 4, 3
    n = Wf * Hf
    h_rad = np.zeros((n, 3), np.float32)
    h_rad[:, 0] = np.arange(n)
    h_id = np.zeros(n, np.int32)
    h_frame = np.full(n, 6, np.int64)
    h_id[6] = 9  # another object: never fetched for id 0
    gid = np.zeros(n, np.int32)
    pixels = np.array([0, 1, 2, 3, 4], np.int64)
    xy = np.array([[1.0, 1.0], [1.5, 1.0], [1.9, 1.0], [7.0, 1.0], [1.0, 1.0]])
    ok = np.array([True, True, True, True, False])
    out = np.zeros((5, 3), np.float32)
    valid = np.zeros(5, np.bool_)
    _fetch(pixels, gid, xy, ok, Wf, Hf, h_rad, h_id, h_frame, 7, out, valid)
    assert list(valid) == [True, True, True, False, False]  # outside the frame, behind the camera: none
    assert out[0, 0] == 5.0  # exactly on pixel (1, 1)
    assert out[1, 0] == 5.0  # halfway to (2, 1), which shows another object: renormalised to (1, 1)
    h_frame[:] = 5  # history from two frames ago: stale
    _fetch(pixels, gid, xy, ok, Wf, Hf, h_rad, h_id, h_frame, 7, out, valid)
    assert not valid.any()


def test_merge_blends_path_history_and_base_and_skips_non_finite_samples():
    radiance = np.full((4, 3), 2.0, np.float32)
    wsum = np.ones(4, np.float32)
    unresolved = np.ones(4, np.bool_)
    gid = np.zeros(4, np.int32)
    samples = np.array([[4, 4, 4], [4, 4, 4], [np.nan, 1, 1], [0, 0, 0]], np.float32)
    spp = np.array([1, 1, 1, 0], np.uint8)
    hist = np.full((4, 3), 1.0, np.float32)
    valid = np.array([True, False, False, True])
    h = (np.zeros((4, 3), np.float32), np.full(4, -1, np.int32), np.full(4, -2, np.int64))
    _merge(np.arange(4), spp, samples, hist, valid, np.float32(0.5), np.float32(0.0), radiance, wsum, unresolved, gid, *h, 3)
    assert np.allclose(radiance[:, 0], [2.5, 3.0, 2.0, 1.0])  # path+history, path+base, untouched, history only
    assert list(unresolved) == [False, False, True, False] and np.isinf(wsum[[0, 1, 3]]).all()
    assert list(h[2]) == [3, 3, -2, 3]
    radiance[:] = 2.0
    _merge(np.arange(1), spp, samples, hist, valid, np.float32(0.5), np.float32(0.5), radiance, wsum, unresolved, gid, *h, 4)
    assert radiance[0, 0] == pytest.approx(0.5 * 2.5 + 0.5 * 2.0)  # output leans on the base
    assert h[0][0, 0] == pytest.approx(2.5)  # the history stays native


def test_settings_errors_name_the_field():
    with pytest.raises(LodSettingsError, match="rays"):
        RefineSettings(rays=-1)
    with pytest.raises(LodSettingsError, match="base_weight"):
        RefineSettings(rays=1, base_weight=2.0)
    with pytest.raises(ValidationError, match="rays"):
        LodSection(rays=-5)
    with pytest.raises(LodSettingsError, match="moving_every"):
        RefineSettings(rays=1, moving_every=3)
    with pytest.raises(ValidationError, match="moving_every"):
        LodSection(moving_every=3)
    assert load_session_config(overrides=["lod.moving_every=2"]).lod.moving_every == 2


@pytest.mark.parametrize("every", [1, 2, 4])
def test_moving_every_traces_each_moving_pixel_once_per_cycle(every):
    """In a tile refined only for a moving object, every pixel is traced exactly once in any
    `every` consecutive frames (2: a checkerboard; 4: each 2×2 block's pixels in turn)."""
    Wt, Ht, tile = 32, 16, 16
    rate = np.ones((1, 2), np.uint8)
    spp = np.ones((1, 2), np.uint8)
    only = np.array([[True, False]])  # left tile: moving only; right tile: full rate by visibility
    gid = np.zeros(Wt * Ht, np.int32)
    gid[5] = -1  # background: never selected
    dynamic = np.array([True, False])
    traced = np.zeros(Wt * Ht, np.int64)
    for frame in range(1, 1 + every):
        pix, s = _select(rate, spp, only, gid, dynamic, Wt, 0, Ht, 0, Wt, tile, frame % 4, frame, every)
        assert 5 not in pix
        traced[pix[s > 0]] += 1
        per_frame = (s[pix % Wt < 16] > 0).sum()
        assert abs(per_frame - 255 / every) <= 1  # 1/every of the tile's 255 lit pixels
    left = (np.arange(Wt * Ht) % Wt < 16) & (gid >= 0)
    assert (traced[left] == 1).all()  # once per cycle in the moving-only tile
    assert (traced[~left & (gid >= 0)] == every).all()  # every frame elsewhere


def test_fill_gives_untraced_moving_pixels_their_same_object_neighbours_mean():
    Wt, Ht = 4, 3
    gid = np.array([0, 0, 0, 1,
                    0, 0, 0, 1,
                    0, 0, 0, 1], np.int32)
    normal = np.tile(np.array([0, 0, 1], np.float32), (Wt * Ht, 1))
    normal[2] = (1, 0, 0)  # a crease: pixel 2 is not a neighbour of pixel 6
    pixels = np.arange(Wt * Ht, dtype=np.int64)
    spp = np.array([1, 0, 1, 0, 0, 1, 0, 1, 1, 0, 1, 0], np.uint8)
    samples = np.full((Wt * Ht, 3), np.nan, np.float32)
    samples[spp > 0] = np.arange(1, 7, dtype=np.float32)[:, None]  # pixels 0, 2, 5, 7, 8, 10 → 1 … 6
    stamp, fresh = np.full(Wt * Ht, -1, np.int64), np.zeros((Wt * Ht, 3), np.float32)
    _fill(pixels, spp, samples, np.array([[True]]), 16, gid, normal, Wt, Ht, stamp, fresh, 7)
    assert spp[1] == 1 and samples[1, 0] == pytest.approx((1 + 2 + 3) / 3)  # 0, 2, 5 (same object)
    assert samples[6, 0] == pytest.approx((3 + 6) / 2)  # 5 and 10; not 2 (crease), not 7 (object 1)
    assert samples[3, 0] == 4.0  # object 1: only pixel 7
    assert np.isfinite(samples).all() and (spp == 1).all()
    spp2 = np.array([0, 0], np.uint8)  # a frame with nothing traced near them: they keep their history
    samples2 = np.full((2, 3), np.nan, np.float32)
    _fill(np.array([0, 1]), spp2, samples2, np.array([[True]]), 16, gid, normal, Wt, Ht, stamp, fresh, 8)
    assert (spp2 == 0).all() and np.isnan(samples2).all()


def test_live_budgets_reach_the_samplers(rig):
    """The session's live `lod_rays` and `adaptive_rays` (the quality governor's rungs): a new
    budget holds from the next frame, 0 traces nothing, and raising it again traces again."""
    native, r, g = rig
    ref = TileRefiner(r, g, RefineSettings(rays=10**6))
    st = _stage(native, r, g, ref)
    traced = []
    for k, (lod_rays, adaptive_rays) in enumerate([(10**6, 2048), (0, 0), (5_000, 2048)]):
        st.set_budgets(adaptive_rays, lod_rays)
        t = 0.2 + k / 60
        poses = native.object_poses(t)
        st.apply(r.render(time=t, seed=k, spp=1, poses=poses), mode="motion", alpha=0.2, filter="lobe", poses=poses,
                 camera=r.camera)
        assert ref.last_rays <= lod_rays and ref.policy.settings.ray_budget == lod_rays
        assert st.adaptive.last_rays <= adaptive_rays
        traced.append((ref.last_rays, st.adaptive.last_pixels))
    assert traced[0][0] > 0 and traced[1] == (0, 0) and traced[2][0] > 0
