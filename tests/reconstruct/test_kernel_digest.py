"""The reconstruction kernels' outputs, pinned bit for bit on a small synthetic frame sequence.

A sphere moving in front of a wall, G-buffers in closed form at the shading (48×36) and native
(192×144) sizes, through the stage's kernels in the stage's order: guides, analytic terms,
demodulation, motion reuse of both histories, lobe filter, upsampling with re-modulation, sRGB.
No renderer and no Embree: the inputs are the same on every machine. The kernels compute per
pixel with no sum across lanes, so the digest is the same for numba's AVX-512 and AVX2 code
built for a Zen 4, an Intel Rocket Lake or a Zen 2 target (`NUMBA_CPU_NAME=znver2
NUMBA_CPU_FEATURES=…`, docs/first-run.md); a change of any kernel's arithmetic, or a vector width that changes it,
changes the digest. Zen 1 and Zen 3 hosts (numba targets `znver1`, `znver3`; no AVX-512) give
other bits, the same on both, pinned apart: numpy's own AVX-512 paths in the inputs, not the
kernels (on an AVX-512 host, the AVX2 build with numpy's AVX-512 dispatch off,
`NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL AVX512_SPR"`, gives the Zen 1 / Zen 3 digest). A
target with no digest pinned is skipped, saying so.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from dpmhw.machine import machine_info
from dpmhw.postprocess import encode_srgb8
from dpmhw.reconstruct.analytic import AnalyticDirect, polygon_rows
from dpmhw.reconstruct.filter import cross_bilateral
from dpmhw.reconstruct.guides import Guides
from dpmhw.reconstruct.reuse import TemporalReuse
from dpmhw.reconstruct.upsample import upsample
from dpmhw.render.cameras import PinholeCamera
from dpmhw.transforms import Pose

SHADING, NATIVE = (48, 36), (192, 144)
FRAMES = 4
RADIUS = 0.3
VIEWER = np.zeros(3)
# numba's target CPU → the digest its code gives (checked on those hosts: a Zen 4 (LLVM: znver5), it building for
# znver2 without AVX-512, an AVX-512 Intel Xeon (rocketlake) and it building for znver2, a Zen 1 and a Zen 3)
PINNED = {"znver5": "90d312de38a68ef6", "znver2": "90d312de38a68ef6", "rocketlake": "90d312de38a68ef6",
          "znver1": "11584b25539b410b", "znver3": "11584b25539b410b"}


def _camera(w, h) -> PinholeCamera:
    f = 1.1 * w
    return PinholeCamera(np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]]), np.zeros(5), w, h, Pose.identity())


def _gbuffer(w, h, centre):
    """Object 0: a sphere of RADIUS at `centre`; object 1: the wall z = 3; camera at the origin
    looking down +z. Returns id, model position, position, normal, depth, albedo, spec albedo,
    roughness, each (h, w, …)."""
    cam = _camera(w, h)
    d = cam._dirs_cam.astype(np.float64).reshape(h, w, 3)
    oc = -np.asarray(centre, np.float64)
    b = d @ oc
    disc = b * b - (oc @ oc - RADIUS * RADIUS)
    t_s = -b - np.sqrt(np.maximum(disc, 0.0))
    hit_s = (disc > 0) & (t_s > 0)
    t = np.where(hit_s, t_s, 3.0 / d[..., 2])
    pos = d * t[..., None]
    ids = np.where(hit_s, 0, 1).astype(np.int32)
    nrm = np.where(hit_s[..., None], (pos - centre) / RADIUS, np.array([0.0, 0.0, -1.0]))
    model = np.where(hit_s[..., None], pos - centre, pos)
    alb = np.where(hit_s[..., None], np.array([0.7, 0.4, 0.2]), np.array([0.5, 0.5, 0.5]))
    spec = np.where(hit_s[..., None], 0.04, 0.0) * np.ones(3)
    rough = np.where(hit_s, 0.3, 0.9)
    f32 = np.float32
    return (ids, model.astype(f32), pos.astype(f32), nrm.astype(f32), (pos[..., 2]).astype(f32), alb.astype(f32),
            spec.astype(f32), rough.astype(f32))


def _light(gb, k):
    """A smooth, noisy shading-resolution signal: (radiance, diffuse, specular), (h*w, 3) each."""
    ids, _, pos, nrm, *_ = gb
    rng = np.random.default_rng(k)
    lam = np.clip(nrm[..., 1:2] * -0.5 + 0.6, 0.05, None)
    diffuse = (lam * gb[5] * (1.0 + 0.3 * rng.standard_normal(lam.shape))).astype(np.float32)
    specular = (gb[6] * (0.2 + 0.1 * rng.random(lam.shape))).astype(np.float32)
    return ((diffuse + specular).reshape(-1, 3), diffuse.reshape(-1, 3), specular.reshape(-1, 3))


def stage_digest() -> str:
    (w, h), (W, H) = SHADING, NATIVE
    light, lum = polygon_rows([[-0.5, -1.5, 1.5], [0.5, -1.5, 1.5], [0.5, -1.5, 2.5], [-0.5, -1.5, 2.5]], [4.0, 4.0, 4.0])
    poly, lums = light[None], np.array([lum])
    an_low, an_nat = AnalyticDirect(w, h, poly, lums, VIEWER), AnalyticDirect(W, H, poly, lums, VIEWER)
    for a in (an_low, an_nat):
        a.set_floors(0.05, 0.01)
    low, nat = Guides.empty(w, h), Guides.empty(W, H)
    reuse_d, reuse_s = (TemporalReuse(w, h, alpha=0.2, mode="motion") for _ in range(2))
    camera = _camera(w, h)
    digest = hashlib.sha256()
    image = np.zeros((W * H, 3), np.uint8)
    for k in range(FRAMES):
        centre = np.array([-0.2 + 0.1 * k, 0.05 * k, 2.0])
        poses = [Pose(np.eye(3), centre), Pose.identity()]
        gl, gn = _gbuffer(w, h, centre), _gbuffer(W, H, centre)
        ids, model, pos, nrm, dep, alb, spec, rough = gl
        low.update(ids, pos, nrm, dep, alb, spec, rough, VIEWER, (0, h, 0, w))
        nat.update(gn[0], gn[2], gn[3], gn[4], gn[5], gn[6], gn[7], VIEWER, (0, H, 0, W))
        an_low.update(ids, pos, nrm, rough, low.albedo, low.spec_albedo, (0, h, 0, w))
        an_nat.update(gn[0], gn[2], gn[3], gn[7], nat.albedo, nat.spec_albedo, (0, H, 0, W))
        radiance, diffuse, specular = _light(gl, k)
        emitted = radiance - diffuse - specular
        d_in = (diffuse / an_low.diffuse_products).reshape(h, w, 3)
        s_in = (specular / an_low.specular_products).reshape(h, w, 3)
        d = reuse_d.update(d_in, ids, model, poses, camera)
        s = reuse_s.update(s_in, ids, model, poses, camera)
        d, s, wsum = cross_bilateral(d, s, low, "lobe")
        native = Guides(W, H, nat.id, nat.depth, nat.normal, nat.axis, nat.sharp, an_nat.diffuse_products,
                        an_nat.specular_products)
        out, wsum_n, unresolved = upsample(low, d, s, emitted, native, "lobe", (0, H, 0, W))
        encode_srgb8(out, W, 1.0, (0, H, 0, W), image)
        for a in (low.axis, low.sharp, nat.axis, an_low.irradiance, an_nat.specular, reuse_d.history, reuse_s.history,
                  reuse_d.history_length, d, s, wsum, out, wsum_n, unresolved, image):
            digest.update(np.ascontiguousarray(a).tobytes())
    return digest.hexdigest()[:16]


def test_the_reconstruction_kernels_give_the_pinned_digest():
    target = machine_info()["numba_cpu"]
    if target not in PINNED:
        pytest.skip(f"no digest pinned for numba's target {target!r}: run this file's stage_digest() there and pin it")
    assert stage_digest() == PINNED[target]
