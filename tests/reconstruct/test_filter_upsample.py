"""Cross-bilateral filter and joint bilateral upsampling on synthetic G-buffers."""

from __future__ import annotations

import numpy as np
import pytest

from dpmhw.reconstruct.filter import cross_bilateral
from dpmhw.reconstruct.guides import Guides
from dpmhw.reconstruct.upsample import upsample

MODES = ("off", "normal", "lobe")


def gbuffer(w, h, ids=None, depth=None, normal=None, roughness=0.3, albedo=0.5):
    """A flat G-buffer (plane facing the viewer at depth 1) unless overridden; returns Guides."""
    ids = np.zeros((h, w), np.int32) if ids is None else ids
    depth = np.ones((h, w), np.float32) if depth is None else depth
    pos = np.zeros((h, w, 3), np.float32)
    pos[..., 2] = depth
    if normal is None:
        normal = np.zeros((h, w, 3), np.float32)
        normal[..., 2] = -1.0
    alb = np.full((h, w, 3), albedo, np.float32)
    return Guides.from_gbuffer(ids, pos, normal, depth, alb, alb * 0.5, np.full((h, w), roughness, np.float32), (0, 0, -1.0))


def native_coords(W, w):
    """Shading-resolution coordinate of each native column centre."""
    return (np.arange(W) + 0.5) * (w / W) - 0.5


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("size", [(16, 12, 64, 48), (20, 15, 40, 30), (13, 9, 50, 37)])
def test_constant_and_linear_ramp_are_reproduced(mode, size):
    w, h, W, H = size
    low, native = gbuffer(w, h), gbuffer(W, H)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    for ramp, field in ((False, np.full((h, w), 0.7, np.float32)), (True, 0.1 + 0.05 * xs + 0.03 * ys)):
        d = np.repeat(field[..., None], 3, axis=2).reshape(-1, 3)
        out, wsum, unresolved = upsample(low, d, np.zeros_like(d), np.zeros_like(d), native, mode)
        out = out.reshape(H, W, 3)[..., 0] / 0.5  # re-modulated with albedo 0.5
        u, v = native_coords(W, w), native_coords(H, h)
        expect = 0.1 + 0.05 * u[None, :] + 0.03 * v[:, None] if ramp else np.full((H, W), 0.7)
        inside = (v[:, None] >= 0) & (v[:, None] <= h - 1) & (u[None, :] >= 0) & (u[None, :] <= w - 1)
        np.testing.assert_allclose(out[inside], expect[inside], rtol=1e-5, atol=1e-6)
        assert not unresolved.any()


@pytest.mark.parametrize("mode", MODES)
def test_no_bleeding_across_object_id_or_depth_edges(mode):
    """Two objects (ids 0/1) and, within object 0, a depth step: light never crosses either edge."""
    w, h, W, H = 16, 12, 64, 48
    def scene(w, h):
        x = (np.arange(w) + 0.5) / w
        ids = np.broadcast_to(np.where(x < 0.43, 0, 1), (h, w)).astype(np.int32).copy()
        y = (np.arange(h) + 0.5) / h
        depth = np.broadcast_to(np.where(y < 0.37, 1.0, 2.0)[:, None], (h, w)).astype(np.float32).copy()
        return ids, depth
    lid, lz = scene(w, h)
    nid, nz = scene(W, H)
    low, native = gbuffer(w, h, lid, lz), gbuffer(W, H, nid, nz)
    # light: object 1 → 0; object 0 near (depth 1) → 1; object 0 far (depth 2) → 4
    value = np.where(lid == 1, 0.0, np.where(lz == 1.0, 1.0, 4.0)).astype(np.float32)
    d = np.repeat(value[..., None], 3, axis=2).reshape(-1, 3)
    fd, fs, _ = cross_bilateral(d, d, low, mode)
    for buf in (fd, fs):  # the filter: pixel for pixel
        np.testing.assert_allclose(buf[:, 0].reshape(h, w), value, rtol=1e-6, atol=0)
    flat = np.repeat(value[..., None], 3, axis=2).reshape(-1, 3)
    out, _, unresolved = upsample(low, flat, flat, np.zeros_like(flat), native, mode)
    got = out[:, 0].reshape(H, W) / (0.5 + 0.25)  # albedo 0.5, specular albedo 0.25
    expect = np.where(nid == 1, 0.0, np.where(nz == 1.0, 1.0, 4.0))
    assert not unresolved.any()
    np.testing.assert_allclose(got, expect, rtol=1e-6)  # pixel for pixel, across both edges


def test_a_pixel_whose_object_no_tap_shows_uses_the_wider_window_or_is_unresolved():
    w, h, W, H = 8, 8, 32, 32
    lid = np.zeros((h, w), np.int32)
    lid[5, 5] = 1  # object 1 covers one shading pixel (native centre 21.5, 21.5)
    nid = np.zeros((H, W), np.int32)
    nid[27, 27] = 1  # its 2×2 taps are (6..7, 6..7): none shows object 1, the 5×5 window does
    nid[10, 10] = 1  # too far from any shading pixel of object 1
    nid[2, 30] = 2  # an object the shading image never saw
    low, native = gbuffer(w, h, lid), gbuffer(W, H, nid)
    d = np.where(lid == 1, 3.0, 1.0).astype(np.float32)
    d = np.repeat(d[..., None], 3, axis=2).reshape(-1, 3)
    out, _, unresolved = upsample(low, d, np.zeros_like(d), np.zeros_like(d), native, "lobe")
    got = out[:, 0].reshape(H, W) / 0.5
    assert got[27, 27] == pytest.approx(3.0)
    unresolved = unresolved.reshape(H, W)
    assert unresolved[10, 10] and unresolved[2, 30] and unresolved.sum() == 2
    assert got[10, 10] == 0.0 and got[2, 30] == 0.0  # never light from another object


def test_nan_gbuffer_and_empty_regions_stay_finite():
    w, h, W, H = 16, 12, 64, 48
    lid = np.zeros((h, w), np.int32)
    lid[:, :4] = -1  # nothing there
    nid = np.zeros((H, W), np.int32)
    nid[:, :16] = -1
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = -1
    normal[20:30, 20:30] = np.nan
    depth = np.ones((H, W), np.float32)
    depth[5:9, 40:50] = np.nan
    lnormal = np.zeros((h, w, 3), np.float32)
    lnormal[..., 2] = -1
    lnormal[3:5, 6:8] = np.nan
    low = gbuffer(w, h, lid, normal=lnormal)
    native = gbuffer(W, H, nid, depth, normal)
    d = np.random.default_rng(2).random((h * w, 3)).astype(np.float32)
    d[7] = np.nan
    d[30] = np.inf
    for mode in MODES:
        fd, fs, wsum = cross_bilateral(d, d, low, mode)
        assert np.isfinite(fd).all() and np.isfinite(fs).all() and (wsum > 0).all()
        out, _, _ = upsample(low, fd, fs, np.zeros_like(fd), native, mode, background=(0.1, 0.2, 0.3))
        assert np.isfinite(out).all()
        assert np.all(out.reshape(H, W, 3)[:, :16] == np.float32([0.1, 0.2, 0.3]))


def test_lobe_aware_keeps_a_roughness_edge_the_normal_aware_filter_blurs():
    """Glossy (roughness 0.1) next to rough (0.6) on one flat object: the specular light differs;
    the normal-aware weight sees one surface and mixes them, the lobe-aware weight does not."""
    w, h = 24, 16
    rough = np.where(np.arange(w) < 12, 0.1, 0.6).astype(np.float32)
    g = gbuffer(w, h, roughness=np.broadcast_to(rough, (h, w)).copy())
    truth = np.where(np.arange(w) < 12, 5.0, 0.5).astype(np.float32)
    s = np.repeat(np.broadcast_to(truth, (h, w))[..., None], 3, axis=2).reshape(-1, 3).copy()
    err = {}
    for mode in ("normal", "lobe"):
        _, fs, _ = cross_bilateral(s, s, g, mode)
        err[mode] = np.abs(fs[:, 0].reshape(h, w) - truth).max()
    assert err["normal"] > 1.0 and err["lobe"] < 0.2 * err["normal"]


@pytest.mark.parametrize("mode", MODES)
def test_upsampling_weights_equal_the_reference_weights(mode):
    """Each native pixel is the weighted mean of its 2×2 same-object taps with the reference
    (float64, log-space) depth × normal / lobe weights: the kernel folds the exponentials into
    one per weight, which must not change them beyond the fast exponential's error."""
    from dpmhw.reconstruct.filter import DEPTH_GATE, DEPTH_SIGMA
    from dpmhw.reconstruct.weights import BETA, normal_weight

    rng = np.random.default_rng(7)
    w, h, W, H = 12, 9, 48, 36

    def random_gbuffer(w, h):
        ids = (rng.random((h, w)) < 0.15).astype(np.int32)
        depth = (1.0 + 0.04 * rng.random((h, w))).astype(np.float32)
        normal = rng.normal(size=(h, w, 3)) * 0.15
        normal[..., 2] = -1.0
        normal = (normal / np.linalg.norm(normal, axis=2, keepdims=True)).astype(np.float32)
        pos = np.zeros((h, w, 3), np.float32)
        pos[..., 2] = depth
        alb = np.full((h, w, 3), 0.5, np.float32)
        rough = rng.uniform(0.3, 0.9, (h, w)).astype(np.float32)
        return Guides.from_gbuffer(ids, pos, normal, depth, alb, alb, rough, (0, 0, -1.0))

    low, native = random_gbuffer(w, h), random_gbuffer(W, H)
    dif = rng.random((w * h, 3)).astype(np.float32)
    spe = rng.random((w * h, 3)).astype(np.float32)
    out, _, unresolved = upsample(low, dif, spe, np.zeros_like(dif), native, mode)
    checked = 0
    for Y in range(H):
        v = (Y + 0.5) * h / H - 0.5
        for X in range(W):
            u = (X + 0.5) * w / W - 0.5
            i = Y * W + X
            ty0, tx0 = int(np.floor(v)), int(np.floor(u))
            fy, fx = v - ty0, u - tx0
            num_d, num_s, den_d, den_s = np.zeros(3), np.zeros(3), 0.0, 0.0
            for dy in (0, 1):
                for dx in (0, 1):
                    ty, tx = ty0 + dy, tx0 + dx
                    if not (0 <= ty < h and 0 <= tx < w):
                        continue
                    j = ty * w + tx
                    if low.id[j] != native.id[i]:
                        continue
                    zi, zj = float(native.depth[i]), float(low.depth[j])
                    if abs(zi - zj) > DEPTH_GATE * zi:
                        continue
                    b = (fy if dy else 1 - fy) * (fx if dx else 1 - fx)
                    wz = np.exp(-0.5 * (abs(zi - zj) / (DEPTH_SIGMA * zi)) ** 2)
                    wd = ws = wz
                    if mode != "off":
                        wd = ws = wz * normal_weight(native.normal[i], low.normal[j])
                    if mode == "lobe":
                        a_, b_ = float(native.sharp[i]), float(low.sharp[j])  # the guides hold λ̄ (smoothed)
                        cos = min(float(np.dot(native.axis[i].astype(float), low.axis[j].astype(float))), 1.0)
                        ws = wz * np.exp(BETA * (np.log(2 * np.sqrt(a_ * b_) / (a_ + b_)) + a_ * b_ / (a_ + b_) * (cos - 1)))
                    num_d += b * wd * dif[j]
                    num_s += b * ws * spe[j]
                    den_d += b * wd
                    den_s += b * ws
            if native.id[i] < 0 or den_d < 1e-3 or den_s < 1e-3:
                continue  # background, or a weight too small to compare (or the fallback window)
            expect = 0.5 * num_d / den_d + 0.5 * num_s / den_s
            np.testing.assert_allclose(out[i], expect, rtol=0, atol=3e-3)
            checked += 1
    assert checked > 0.4 * int((native.id >= 0).sum())
