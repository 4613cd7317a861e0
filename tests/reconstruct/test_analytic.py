"""Analytic direct-lighting demodulation: closed forms against numerical integrals, hard cases, the stage."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dpmhw.reconstruct.analytic import (DEFAULT_FLOORS, AnalyticDirect, _theta_over_sin, emitter_polygons, floor_from, polygon_rows,
                                        terms_at_points)
from dpmhw.reconstruct.guides import Guides
from dpmhw.reconstruct.stage import ReconstructStage
from dpmhw.reconstruct.upsample import upsample
from dpmhw.render.gbuffer import NativeGBuffer
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene
from dpmhw.session.config import SessionConfig
from dpmhw.session.factory import shading_scene

# a 0.5 m square emitter at y = 1, emitting downwards (corners wound so that their normal is −y)
CORNERS = np.array([[-0.25, 1.0, -0.25], [0.25, 1.0, -0.25], [0.25, 1.0, 0.25], [-0.25, 1.0, 0.25]])
VIEWER = np.array([0.0, 0.3, 2.0])


def _light(emission=(1.0, 1.0, 1.0)):
    row, lum = polygon_rows(CORNERS, emission)
    return row[None], np.array([lum])


def _quadrature(p, n, m=600):
    """∫ cos_p dω over the emitter by the midpoint rule over its area (cos_l cos_p / r² dA),
    clipped to n's hemisphere and to the emitter's front."""
    u = (np.arange(m) + 0.5) / m
    a, b = np.meshgrid(u, u)
    q = CORNERS[0] + a[..., None] * (CORNERS[3] - CORNERS[0]) + b[..., None] * (CORNERS[1] - CORNERS[0])
    d = q - p
    r2 = (d * d).sum(-1)
    w = d / np.sqrt(r2)[..., None]
    cos_l = np.maximum(-(w @ np.array([0.0, -1.0, 0.0])), 0.0)
    cos_p = np.maximum(w @ n, 0.0)
    return float((cos_l * cos_p / r2).mean() * 0.25)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("p, n, case", [
    ([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], "parallel, below the centre"),
    ([0.6, 0.2, 0.3], [0.0, 1.0, 0.0], "parallel, off axis"),
    ([0.0, 0.4, 0.0], [1.0, 1.0, 0.0], "tilted 45°"),
    ([0.1, 0.5, -0.2], [-0.3, 0.8, 0.6], "tilted, off axis"),
    ([0.0, 0.7, 0.0], [1.0, 0.15, 0.0], "partly below the horizon (clipped)"),
    ([0.05, 0.8, 0.1], [0.2, -0.05, 1.0], "mostly below the horizon (clipped)"),
])
def test_closed_form_irradiance_matches_a_numerical_integral(p, n, case):
    poly, lum = _light()
    p, n = np.asarray(p, float), _unit(n)
    e, _ = terms_at_points(p[None], n[None], VIEWER, np.array([0.5]), poly, lum)
    ref = _quadrature(p, n)
    assert ref > 1e-3, case
    assert e[0] == pytest.approx(ref, rel=2e-3), case


def test_random_points_clipped_or_not_match_the_numerical_integral():
    """The vectorised kernel selects between the clipped and unclipped cases per point: random
    points and normals, many of them with the light partly below their horizon."""
    poly, lum = _light()
    rng = np.random.default_rng(7)
    pts = rng.uniform([-0.6, 0.0, -0.6], [0.6, 0.8, 0.6], (40, 3))
    nrm = rng.normal(size=(40, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    e, _ = terms_at_points(pts, nrm, VIEWER, np.full(40, 0.5), poly, lum)
    heights = np.einsum("pkc,pc->pk", CORNERS[None] - pts[:, None], nrm)
    clipped = ((heights < 0).any(1) & (heights >= 0).any(1)).sum()
    assert clipped >= 10  # the hard case is exercised
    ref = np.array([_quadrature(p, n, m=400) for p, n in zip(pts, nrm)])
    assert np.allclose(e, ref, rtol=5e-3, atol=2e-4)


def test_a_triangle_emitter_and_a_quad_split_in_two_give_the_same_terms():
    quad, lum = _light()
    t1, l1 = polygon_rows(CORNERS[[0, 1, 2]], (1.0, 1.0, 1.0))
    t2, l2 = polygon_rows(CORNERS[[0, 2, 3]], (1.0, 1.0, 1.0))
    rng = np.random.default_rng(3)
    pts = rng.uniform([-0.6, 0.0, -0.6], [0.6, 0.8, 0.6], (300, 3))
    nrm = rng.normal(size=(300, 3))
    e_q, _ = terms_at_points(pts, nrm, VIEWER, np.full(300, 0.5), quad, lum)
    e_t, _ = terms_at_points(pts, nrm, VIEWER, np.full(300, 0.5), np.stack([t1, t2]), np.array([l1, l2]))
    assert np.allclose(e_q, e_t, rtol=1e-5, atol=1e-6)  # the shared diagonal cancels (up to rounding)


def test_masked_updates_over_many_blocks_equal_a_full_evaluation():
    """More points than one parallel block, an odd box and a mask: the masked pixels get exactly
    the full evaluation's values, the others keep theirs."""
    poly, lum = _light((3.0, 3.0, 3.0))
    W, H = 97, 61  # 5917 pixels: three blocks
    g, pos, nrm = _plane_guides(W, H)
    nrm = nrm.copy()
    nrm[::3] = np.float32([0.6, 0.0, 0.8])  # rows with the light half below the horizon
    gid = g.id.reshape(H, W).copy()
    gid[:, 80:] = -1  # background
    spec = np.full((W * H, 3), 0.3, np.float32)
    rough = np.full(W * H, 0.4, np.float32)
    full = AnalyticDirect(W, H, poly, lum, VIEWER)
    part = AnalyticDirect(W, H, poly, lum, VIEWER)
    for a in (full, part):
        a.set_floors(0.1, 0.1)
    full.update(gid, pos, nrm, rough, g.albedo, spec, (0, H, 0, W))
    mask = np.random.default_rng(0).random(W * H) < 0.5
    part.update(gid, pos, nrm, rough, g.albedo, spec, (3, 58, 5, 90), mask)
    inside = np.zeros((H, W), bool)
    inside[3:58, 5:90] = True
    sel = inside.reshape(-1) & mask
    for name in ("irradiance", "specular", "diffuse_products", "specular_products"):
        a, b = getattr(full, name), getattr(part, name)
        assert np.array_equal(a[sel], b[sel]), name
    assert (part.irradiance[~sel] == 0).all() and (part.diffuse_products[~sel] == 1).all()
    assert (full.irradiance.reshape(H, W)[:, :80] > 0).mean() > 0.5 and (full.irradiance.reshape(H, W)[:, 80:] == 0).all()


def test_theta_over_sin_fit_is_within_1e3_relative_everywhere():
    x = np.linspace(-0.999, 0.9999, 20001)
    exact = np.arccos(x) / np.sqrt(1 - x * x)
    fit = np.array([_theta_over_sin(v) for v in x])
    assert np.max(np.abs(fit / exact - 1)) < 1e-3


def test_emitter_behind_the_surface_or_seen_from_behind_gives_zero():
    poly, lum = _light()
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 1.0, 0.0], [0.1, 0.5, 0.0]])
    nrm = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    e, s = terms_at_points(pts, nrm, VIEWER, np.full(4, 0.3), poly, lum)
    # facing away from the light; above the one-sided emitter; in its plane; facing away again
    assert np.all(e == 0.0) and np.all(s == 0.0)


def test_hard_cases_stay_finite_and_bounded():
    poly, lum = _light((8.0, 8.0, 8.0))
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1, 1.2, (2000, 3))
    nrm = rng.normal(size=(2000, 3))
    pts[:10] = np.nan  # NaN G-buffer pixels
    nrm[10:20] = 0.0  # zero normals
    nrm[20:30] = np.inf
    pts[30:40] = CORNERS[0]  # on an emitter corner
    pts[40:50, 1] = 1.0  # in the emitter's plane
    rough = rng.uniform(0, 1, 2000)
    rough[50:60] = np.nan
    rough[60:70] = 0.0  # mirror: the α floor
    e, s = terms_at_points(pts, nrm, VIEWER, rough, poly, lum)
    assert np.isfinite(e).all() and np.isfinite(s).all()
    assert (e >= 0).all() and (s >= 0).all()
    assert (e[:30] == 0).all() and (s[:30] == 0).all() and (s[50:60] == 0).all()
    assert e.max() <= math.pi * lum[0] + 1e-9  # ∫ cos dω ≤ π
    # grazing: the normal in the plane of the emitter's centre direction, half the light below the horizon
    g, _ = terms_at_points(np.array([[0.0, 0.5, 0.0]]), np.array([[1.0, 0.0, 0.0]]), VIEWER, np.array([0.3]), poly, lum)
    assert 0.0 <= g[0] < terms_at_points(np.array([[0.0, 0.5, 0.0]]), np.array([[0.0, 1.0, 0.0]]), VIEWER,
                                         np.array([0.3]), poly, lum)[0][0]


def test_no_emitter_makes_the_products_the_floored_albedos_and_finite():
    a = AnalyticDirect(8, 4, np.zeros((0, 20)), np.zeros(0), VIEWER)
    with pytest.raises(RuntimeError):
        a.update(np.zeros(32, np.int32), np.zeros((32, 3)), np.ones((32, 3)), np.ones(32), np.ones((32, 3)),
                 np.ones((32, 3)), (0, 4, 0, 8))
    a.set_floors(floor_from(np.zeros(32), np.zeros(32), 0.15), 1.0)
    assert a.floors == (1.0, 1.0)  # no lit pixel with E > 0: a floor of 1 (the ratio is the signal itself)
    alb = np.full((32, 3), 0.5, np.float32)
    a.update(np.zeros(32, np.int32), np.zeros((32, 3)), np.ones((32, 3)), np.ones(32), alb, alb, (0, 4, 0, 8))
    assert np.array_equal(a.diffuse_products, alb) and np.array_equal(a.specular_products, alb)
    with pytest.raises(ValueError, match="diffuse floor"):
        a.set_floors(0.0, 1.0)
    with pytest.raises(ValueError, match="specular floor"):
        a.set_floors(1.0, math.nan)


def test_specular_term_is_largest_where_the_reflection_points_at_the_light():
    poly, lum = _light()
    viewer = np.array([0.0, 0.0, 1.0])
    xs = np.linspace(-0.4, 0.4, 81)
    pts = np.stack([np.zeros_like(xs), np.zeros_like(xs), xs], axis=1)  # along z on the floor y = 0
    nrm = np.tile([0.0, 1.0, 0.0], (len(xs), 1))
    # the mirror point of the viewer (0, 0, 1) about the floor toward the light's centre (0, 1, 0) is z = 0.5
    # for a viewer at height 0 … use a viewer above: reflection hits the centre at z where (z-0)/1 = (1-z)/h
    viewer = np.array([0.0, 1.0, 0.6])
    _, s = terms_at_points(pts, nrm, viewer, np.full(len(xs), 0.35), poly, lum)
    assert np.isfinite(s).all() and s.max() > 0
    assert abs(xs[np.argmax(s)] - 0.3) <= 0.02  # the mirror point between (0, 1, 0.6) and the centre (0, 1, 0)


def _plane_guides(W, H, z0=0.4):
    """A floor at y = 0 seen from above (pixel (x, y) ↦ world (x/W − ½, 0, y/H − ½)), normal +y."""
    xs = (np.arange(W) + 0.5) / W - 0.5
    ys = (np.arange(H) + 0.5) / H - 0.5
    X, Y = np.meshgrid(xs, ys)
    pos = np.stack([X, np.zeros_like(X), Y], -1).astype(np.float32)
    nrm = np.tile(np.float32([0, 1, 0]), (H, W, 1))
    g = Guides.from_gbuffer(np.zeros((H, W), np.int32), pos, nrm, np.full((H, W), z0, np.float32),
                            np.full((H, W, 3), 0.6, np.float32), np.zeros((H, W, 3), np.float32),
                            np.full((H, W), 1.0, np.float32), np.array([0.0, 5.0, 0.0], np.float32))
    return g, pos, nrm


def test_a_flat_lit_plane_upsampled_through_the_ratio_reproduces_the_analytic_native_shading():
    poly, lum = _light((3.0, 3.0, 3.0))
    W, H, w, h = 64, 48, 16, 12
    nat, npos, nnrm = _plane_guides(W, H)
    low, lpos, lnrm = _plane_guides(w, h)
    lo = AnalyticDirect(w, h, poly, lum, VIEWER)
    hi = AnalyticDirect(W, H, poly, lum, VIEWER)
    rough = np.ones(W * H, np.float32)
    lo.set_floors(1.0, 1.0)
    lo.update(low.id, lpos, lnrm, rough[: w * h], low.albedo, low.spec_albedo, (0, h, 0, w))
    f = floor_from(lo.irradiance, low.id, 0.15)
    for a in (lo, hi):
        a.set_floors(f, 1.0)
    lo.update(low.id, lpos, lnrm, rough[: w * h], low.albedo, low.spec_albedo, (0, h, 0, w))
    hi.update(nat.id, npos, nnrm, rough, nat.albedo, nat.spec_albedo, (0, H, 0, W))
    k = 1.0 / math.pi
    # shading = albedo/π · (E + F): the floor stands for a constant ambient, so the ratio is flat
    diffuse_low = low.albedo * k * (lo.irradiance[:, None] + f)
    expected = nat.albedo * k * (hi.irradiance[:, None] + f)
    zeros = np.zeros((w * h, 3), np.float32)
    ratio = diffuse_low / lo.diffuse_products
    out, _, unresolved = upsample(low, ratio, zeros, zeros, _with_albedo(nat, hi.diffuse_products), "normal")
    assert not unresolved.any()
    assert np.allclose(out, expected, rtol=1e-5, atol=1e-7)
    # without the ratio, the same upsampling blurs the native shading (the light is close: E varies fast)
    plain, _, _ = upsample(low, diffuse_low / low.albedo, zeros, zeros, nat, "normal")
    assert np.abs(plain - expected).max() > 100 * np.abs(out - expected).max()


def _with_albedo(g: Guides, albedo) -> Guides:
    import dataclasses

    return dataclasses.replace(g, albedo=albedo)


def test_the_quad_light_is_one_polygon_emitting_on_the_renderers_side():
    scene = load_scene("dpm-bunny")
    r = PathIntegrator(scene.at_size(32, 24), threads=1)
    try:
        poly, lum = emitter_polygons(r.geometry, scene.object_poses(0.0))
        assert poly.shape == (1, 20) and poly[0, 15] == 4
        assert poly[0, 19] == pytest.approx(0.25) and lum[0] == pytest.approx(8.0)
        k = next(i for i, o in enumerate(scene.objects) if o.is_emissive)
        R = scene.object_poses(0.0)[k].R
        emit_normal = R @ r.geometry.tri[r.geometry.light_prim[0], 9:12]  # the side the renderer emits on
        assert np.allclose(poly[0, 12:15], emit_normal, atol=1e-6)
    finally:
        r.close()


def _stage_frames(analytic, n=3, size=(128, 96)):
    native = load_scene("dpm-bunny").at_size(*size)
    r = PathIntegrator(shading_scene(native, 0.25), threads=1)
    g = NativeGBuffer(native, r.geometry, *size, threads=1)
    try:
        stage = ReconstructStage(size, (r.width, r.height), background=native.render.background,
                                 viewer=native.viewer_position, gbuffer=g, analytic=analytic)
        outs = []
        for i in range(n):
            poses = native.object_poses(i / 10)
            frame = r.render(time=i / 10, seed=i, poses=poses)
            outs.append(stage.apply(frame, mode="motion", alpha=0.2, filter="lobe", poses=poses, camera=r.camera).image)
        return stage, outs
    finally:
        g.close()
        r.close()


def test_stage_with_the_analytic_demodulation_gives_finite_native_frames_that_differ_from_off():
    stage, on = _stage_frames((0.15, 1.0))
    assert stage.analytic is not None and stage.analytic[1].floors[0] > 0
    _, off = _stage_frames(None)
    assert on[-1].shape == off[-1].shape == (96, 128, 3)
    assert not np.array_equal(on[-1], off[-1])
    lit = off[-1].sum(axis=2) > 0
    assert ((on[-1].sum(axis=2) > 0) == lit).mean() > 0.99  # light where it was, re-shaded


def test_off_passes_the_native_guides_and_albedos_through_unchanged(monkeypatch):
    """Off, the stage runs exactly the code it ran before: the upsampler gets the native Guides
    object itself (albedos, not products) and no analytic state exists."""
    import dpmhw.reconstruct.stage as stage_module

    seen = []
    real = stage_module.upsample

    def spy(low, d, s, e, native, *a, **k):
        seen.append(native)
        return real(low, d, s, e, native, *a, **k)

    monkeypatch.setattr(stage_module, "upsample", spy)
    stage, _ = _stage_frames(None, n=2)
    assert stage.analytic is None and seen and all(g is stage.native for g in seen)
    seen.clear()
    stage, _ = _stage_frames((0.15, 1.0), n=2)
    assert seen and all(g.albedo is stage.analytic[1].diffuse_products for g in seen)


def test_stage_refuses_bad_floors():
    native = load_scene("dpm-bunny").at_size(64, 48)
    r = PathIntegrator(shading_scene(native, 0.25), threads=1)
    g = NativeGBuffer(native, r.geometry, 64, 48, threads=1)
    try:
        for bad in ((0.0, 1.0), (0.1, math.inf), (0.1,)):
            with pytest.raises(ValueError, match="analytic"):
                ReconstructStage((64, 48), (16, 12), gbuffer=g, analytic=bad)
    finally:
        g.close()
        r.close()


def test_session_config_switch_and_floors():
    c = SessionConfig.model_validate({"render": {"analytic": False}})
    assert c.render.analytic is False
    d = SessionConfig.model_validate({})
    assert d.render.analytic is True and (d.render.analytic_floor, d.render.analytic_specular_floor) == DEFAULT_FLOORS
    with pytest.raises(Exception, match="analytic_floor"):
        SessionConfig.model_validate({"render": {"analytic_floor": 0}})


def test_bench_lod_methods_are_checked_and_plain_variants_turn_the_demodulation_off():
    from dpmhw.benchmarks.lod import check_methods

    assert check_methods(["none", "quarter", "quarter-plain", "all-plain"]) == ("none", "quarter", "quarter-plain", "all-plain")
    for bad in (["quarter"], ["none", "none-plain"], ["none", "fast"], ["none", "quarter", "quarter"], []):
        with pytest.raises(ValueError, match="methods"):
            check_methods(bad)
