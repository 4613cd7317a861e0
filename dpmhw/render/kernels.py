"""The per-frame shading kernels, fused with numba (serial and GIL-free, cached on disk).

Chained numpy temporaries cost several times the arithmetic here, so each wavefront stage is one
kernel over the active paths: surface interaction, emission with MIS, next-event estimation,
BSDF sampling and Russian roulette. Numpy arrays stay the interface between stages and Embree.
The first vertex is split in two (first_surface, per camera pose when nothing moves, and
sample_first, per pass and vectorised); the deeper ones are shaded by `shade`, scalar.

BSDF: Lambert diffuse scaled by (1 − specular) plus a GGX lobe (Smith G, visible-normal
sampling), so reflectance never exceeds max(albedo, specular) ≤ 1. Randomness is a counter-based
hash of (pass key, pixel, dimension): the same seed gives the same image bit for bit whatever the
thread count or scheduling.
"""

from __future__ import annotations

import math
from types import FunctionType

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.core.extending import intrinsic

from dpmhw.render import static_raster
from dpmhw.render.embree import traversal
from dpmhw.render.prefetch import prefetch_row

INV_PI = 1.0 / math.pi
DIMS_PER_BOUNCE = 8
MIN_ALPHA = 1e-3  # GGX α floor: mirror-like lobes stay finite
RR_START_DEPTH = 3
RR_MAX_SURVIVAL = 0.95
PREFETCH_AHEAD = 8  # vertices: the triangle row of vertex k + 8 is fetched while vertex k is shaded
SHADOW_SHORTEN = 1e-4  # relative: stop shadow rays just before the sampled light point
OFFSET_REL = 3e-5  # origin offset along the geometric normal, relative to coordinate magnitude

# fastmath without nnan/ninf: the kernels test for non-finite samples and must keep doing so
_jit = dict(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
# The shading kernels without reassociation: a vectorised loop and its scalar remainder must round
# alike (which pixels fall in the remainder depends on the segmentation), and so must their copies
# inlined into trace_segment, where constants fold into the arithmetic, and the staged path's own
_jit_shading = dict(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn"})
# ... and the vectorised ones without contraction into FMAs either: LLVM fused their vector
# multiply-adds differently in the code it caches on disk than in the code it runs after compiling
# (the same kernel gave other last bits in the next process)
_jit_vector = dict(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "afn"})

M1 = np.uint64(0xBF58476D1CE4E5B9)
M2 = np.uint64(0x94D049BB133111EB)
GOLDEN = np.uint64(0x9E3779B97F4A7C15)
S30, S27, S31, S40 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(40)

# float32 constants: a Python float literal beside a float32 value makes numba compute in float64
# (wider, slower square roots and divisions, and conversions back and forth, and a loop that does
# not vectorise to 16 lanes). The shading kernels, GGX lobe included, stay in float32 with these.
F0, F1 = np.float32(0.0), np.float32(1.0)
INV_PI32 = np.float32(INV_PI)
OFFSET_REL32, TINY32 = np.float32(OFFSET_REL), np.float32(1e-20)
TINY_LEN32, MIN_COS32 = np.float32(1e-12), np.float32(1e-6)
LUM_R, LUM_G, LUM_B = np.float32(0.2126), np.float32(0.7152), np.float32(0.0722)

# Columns of `SceneGeometry.tri`, (F, TRI_COLS) float32 rows in each object's model space (one hit
# touches two cache lines): the first vertex, the edges v1 − v0 and v2 − v0, the unit geometric
# normal, the three corners' shading normals, and the triangle's GGX α where its object has a
# roughness map (else 0: the object's α applies).
TRI_V0, TRI_E1, TRI_E2, TRI_NG, TRI_N0, TRI_N1, TRI_N2, TRI_ALPHA = 0, 3, 6, 9, 12, 15, 18, 21
TRI_COLS = 24


@nb.njit(inline="always", **_jit)
def _mix64(x):
    x = (x ^ (x >> S30)) * M1
    x = (x ^ (x >> S27)) * M2
    return x ^ (x >> S31)


@nb.njit(inline="always", **_jit)
def rand(key, pixel, dim):
    """Uniform float in [0, 1) from (pass key, pixel index, dimension)."""
    x = _mix64(key ^ (np.uint64(pixel) * GOLDEN + np.uint64(dim)))
    return np.float32(x >> S40) * np.float32(1.0 / 16777216.0)


JITTER_SALT = 0x6A09E667F3BCC908  # the pixel-jitter stream: independent of the path dimensions


def jitter_key(seed: int, pass_index: int) -> np.uint64:
    """The per-pass key of the pixel-jitter random numbers."""
    return np.uint64(int(pass_key(seed, pass_index)) ^ JITTER_SALT)


def pass_key(seed: int, pass_index: int) -> np.uint64:
    """The per-pass hash key (Python side, same mixing as the kernels)."""
    mask = (1 << 64) - 1

    def mix(x):
        x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & mask
        x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & mask
        return x ^ (x >> 31)

    return np.uint64(mix((mix(seed & mask) + pass_index * 0x9E3779B97F4A7C15) & mask))


HALF_PI32 = np.float32(0.5 * math.pi)
PI32 = np.float32(math.pi)
_S3, _S5, _S7, _S9 = (np.float32(c) for c in (-1 / 6, 1 / 120, -1 / 5040, 1 / 362880))
_C2, _C4, _C6, _C8 = (np.float32(c) for c in (-1 / 2, 1 / 24, -1 / 720, 1 / 40320))


@nb.njit(inline="always", **_jit)
def _cos_sin_turn(u):
    """cos(2πu), sin(2πu) for u in [0, 1], float32, within a few ulp of libm's. Branch-free and
    inline: libm's sincosf is a call in the middle of the shading loop, which makes LLVM spill
    the loop's live registers around it. Quadrant q = round(4u), then Taylor series of degree 9
    (sin) and 8 (cos) on |x| ≤ π/4, whose truncation errors (≤ 2e-9, 3e-8) are below float32's ulp."""
    q4 = u * np.float32(4.0)
    q = np.floor(q4 + np.float32(0.5))
    x = (q4 - q) * HALF_PI32
    x2 = x * x
    sn = x * (F1 + x2 * (_S3 + x2 * (_S5 + x2 * (_S7 + x2 * _S9))))
    cs = F1 + x2 * (_C2 + x2 * (_C4 + x2 * (_C6 + x2 * _C8)))
    quad = np.int32(q) & 3
    c = sn if quad & 1 else cs  # quadrants 1 and 3 swap cos and sin
    s = cs if quad & 1 else sn
    c = -c if quad == 1 or quad == 2 else c
    s = -s if quad >= 2 else s
    return c, s


@nb.njit(inline="always", **_jit)
def _dot(a0, a1, a2, b0, b1, b2):
    return a0 * b0 + a1 * b1 + a2 * b2


@nb.njit(inline="always", **_jit)
def _lum(r, g, b):
    return LUM_R * r + LUM_G * g + LUM_B * b


@nb.njit(inline="always", **_jit)
def _basis(n0, n1, n2):
    """Orthonormal tangents of a unit normal (Duff et al. 2017)."""
    sign = F1 if n2 >= 0.0 else -F1
    a = -F1 / (sign + n2)
    b = n0 * n1 * a
    return F1 + sign * n0 * n0 * a, sign * b, -sign * n0, b, sign + n1 * n1 * a, -n1


@nb.njit(inline="always", **_jit)
def _cosine_local(u1, u2):
    """A cosine-distributed direction about +z from two uniforms (Malley's method: a uniform point
    (x, y) of the unit disk, radius √u1 and angle 2π·u2, lifted to the hemisphere); its pdf is
    z/π. The GGX sample takes the same disk point."""
    r = math.sqrt(u1)
    cphi, sphi = _cos_sin_turn(u2)
    return r * cphi, r * sphi, math.sqrt(max(F0, F1 - u1))


@nb.njit(inline="always", **_jit)
def _to_world(x, y, z, t0, t1, t2, c0, c1, c2, s0, s1, s2):
    """Local coordinates in the frame (t, c, s) → world."""
    return x * t0 + y * c0 + z * s0, x * t1 + y * c1 + z * s1, x * t2 + y * c2 + z * s2


@nb.njit(inline="always", **_jit)
def _ggx_d(cos_h, a2):
    denom = cos_h * cos_h * (a2 - F1) + F1
    return a2 / (PI32 * denom * denom)


@nb.njit(inline="always", **_jit)
def _ggx_g1(cos_v, a2):
    return np.float32(2.0) * cos_v / (cos_v + math.sqrt(max(F0, a2 + (F1 - a2) * cos_v * cos_v)))


@nb.njit(inline="always", **_jit)
def _max_abs3(x, y, z):
    return max(abs(x), max(abs(y), abs(z)))


@nb.njit(inline="always", **_jit)
def _eval_bsdf(wo0, wo1, wo2, wi0, wi1, wi2, n0, n1, n2, ar, ag, ab, sr, sg, sb, alpha, p_spec, glossy):
    """Diffuse and specular BSDF values (fd0..2, fs0..2) and the lobe-mixture pdf of wi, in
    float32 and branch-free (selects), so it vectorises. `glossy` False (a constant in the
    vectorised kernels): the Lambert lobe alone."""
    cos_i = _dot(wi0, wi1, wi2, n0, n1, n2)
    fd0 = ar * (F1 - sr) * INV_PI32
    fd1 = ag * (F1 - sg) * INV_PI32
    fd2 = ab * (F1 - sb) * INV_PI32
    fs0 = fs1 = fs2 = F0
    pdf = (F1 - p_spec) * cos_i * INV_PI32
    if glossy:
        cos_o = _dot(wo0, wo1, wo2, n0, n1, n2)
        h0, h1, h2 = wo0 + wi0, wo1 + wi1, wo2 + wi2
        hl = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
        cos_h = _dot(h0, h1, h2, n0, n1, n2) / hl
        a2 = alpha * alpha
        d = _ggx_d(cos_h, a2)
        g1o = _ggx_g1(cos_o, a2)
        ok = (p_spec > F0) & (hl > TINY_LEN32) & (cos_h > F0)
        common = d * g1o * _ggx_g1(cos_i, a2) / (np.float32(4.0) * cos_o * cos_i) if ok else F0
        fs0, fs1, fs2 = sr * common, sg * common, sb * common
        pdf += p_spec * g1o * d / (np.float32(4.0) * cos_o) if ok else F0
    return fd0, fd1, fd2, fs0, fs1, fs2, pdf


@nb.njit(inline="always", **_jit)
def _ggx_sample(wo0, wo1, wo2, t0, t1, t2, c0, c1, c2, s0, s1, s2, alpha, x, y):
    """A GGX reflection direction by visible-normal sampling (Heitz 2018) in the frame (t, c, s),
    from the disk point (x, y) (radius √u1, angle 2π·u2). Branch-free, float32."""
    lx = _dot(wo0, wo1, wo2, t0, t1, t2)
    ly = _dot(wo0, wo1, wo2, c0, c1, c2)
    lz = _dot(wo0, wo1, wo2, s0, s1, s2)
    vx, vy, vz = alpha * lx, alpha * ly, lz
    ivl = F1 / math.sqrt(vx * vx + vy * vy + vz * vz)
    vx, vy, vz = vx * ivl, vy * ivl, vz * ivl
    lensq = vx * vx + vy * vy
    tilted = lensq > np.float32(1e-14)
    il = F1 / math.sqrt(lensq) if tilted else F0
    a0 = -vy * il if tilted else F1
    a1 = vx * il if tilted else F0
    e0, e1, e2 = -vz * a1, vz * a0, vx * a1 - vy * a0
    sv = np.float32(0.5) * (F1 + vz)
    q2 = (F1 - sv) * math.sqrt(max(F0, F1 - x * x)) + sv * y
    q3 = math.sqrt(max(F0, F1 - x * x - q2 * q2))
    hx = x * a0 + q2 * e0 + q3 * vx
    hy = x * a1 + q2 * e1 + q3 * vy
    hz = max(np.float32(1e-6), q3 * vz + q2 * e2)
    hx, hy = alpha * hx, alpha * hy
    ihl = F1 / math.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx * ihl, hy * ihl, hz * ihl
    h0, h1, h2 = _to_world(hx, hy, hz, t0, t1, t2, c0, c1, c2, s0, s1, s2)
    dh = np.float32(2.0) * _dot(wo0, wo1, wo2, h0, h1, h2)
    return dh * h0 - wo0, dh * h1 - wo1, dh * h2 - wo2


def inline_copy(dispatcher, suffix: str, **jit):
    """A copy of a helper that numba inlines in its IR (`inline="always"`), compiled on its own
    with the flags `jit` (the caller's: inlined in numba's IR, a helper takes its caller's
    fast-math flags), once per signature and literal argument value, instead of being parsed and
    typed again at each call site; LLVM always inlines it (`forceinline`), so loops still
    vectorise through it and constant arguments still fold. Renamed (`suffix`), so that it never
    shares an on-disk cache entry with the original."""
    f = dispatcher.py_func
    copy = FunctionType(f.__code__, f.__globals__, f.__name__ + suffix)
    copy.__qualname__ = f.__qualname__ + suffix
    return nb.njit(forceinline=True, **jit)(copy)


# The vectorised kernels' (`_sample_block`) copies, with their flags (`_jit_vector`: neither
# contraction nor reassociation, so the arithmetic rounds as written, wherever LLVM puts it). The
# shading kernels keep inlining the originals in numba's IR: compiled on their own with
# `contract`, then inlined, they change the FMAs LLVM forms (the renders' last bits).
_cosine_local_v, _eval_bsdf_v, _ggx_sample_v = (inline_copy(f, "_vector", **_jit_vector)
                                                 for f in (_cosine_local, _eval_bsdf, _ggx_sample))


@nb.njit(inline="always", **_jit)
def _light_index(light_cdf, ut):
    """The emissive triangle light_cdf picks for ut: the first whose cumulative weight exceeds it."""
    lo, hi = 0, light_cdf.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if light_cdf[mid] <= ut:
            lo = mid + 1
        else:
            hi = mid
    return lo


@nb.njit(inline="always", **_jit)
def geometric_normal(tri, R, ob, i):
    """World-space unit geometric normal of triangle i (`tri` rows, see `shade`) of object ob."""
    n0, n1, n2 = tri[i, TRI_NG], tri[i, TRI_NG + 1], tri[i, TRI_NG + 2]
    g0 = R[ob, 0, 0] * n0 + R[ob, 0, 1] * n1 + R[ob, 0, 2] * n2
    g1 = R[ob, 1, 0] * n0 + R[ob, 1, 1] * n1 + R[ob, 1, 2] * n2
    g2 = R[ob, 2, 0] * n0 + R[ob, 2, 1] * n1 + R[ob, 2, 2] * n2
    return g0, g1, g2


@nb.njit(inline="always", **_jit)
def hit_point(tri, R, T, ob, i, u, v):
    """The point at barycentrics (u, v) of triangle i of object ob, in model space and in world
    space, and its interpolated shading normal in world space (not normalised). Straight-line
    code: inlined into a loop, it adds no reference counting (see traversal)."""
    w0 = F1 - u - v  # F1, not 1.0: a float64 literal here made the whole shading frame float64
    pm0 = tri[i, TRI_V0] + u * tri[i, TRI_E1] + v * tri[i, TRI_E2]
    pm1 = tri[i, TRI_V0 + 1] + u * tri[i, TRI_E1 + 1] + v * tri[i, TRI_E2 + 1]
    pm2 = tri[i, TRI_V0 + 2] + u * tri[i, TRI_E1 + 2] + v * tri[i, TRI_E2 + 2]
    p0 = R[ob, 0, 0] * pm0 + R[ob, 0, 1] * pm1 + R[ob, 0, 2] * pm2 + T[ob, 0]
    p1 = R[ob, 1, 0] * pm0 + R[ob, 1, 1] * pm1 + R[ob, 1, 2] * pm2 + T[ob, 1]
    p2 = R[ob, 2, 0] * pm0 + R[ob, 2, 1] * pm1 + R[ob, 2, 2] * pm2 + T[ob, 2]
    sm0 = w0 * tri[i, TRI_N0] + u * tri[i, TRI_N1] + v * tri[i, TRI_N2]
    sm1 = w0 * tri[i, TRI_N0 + 1] + u * tri[i, TRI_N1 + 1] + v * tri[i, TRI_N2 + 1]
    sm2 = w0 * tri[i, TRI_N0 + 2] + u * tri[i, TRI_N1 + 2] + v * tri[i, TRI_N2 + 2]
    s0 = R[ob, 0, 0] * sm0 + R[ob, 0, 1] * sm1 + R[ob, 0, 2] * sm2
    s1 = R[ob, 1, 0] * sm0 + R[ob, 1, 1] * sm1 + R[ob, 1, 2] * sm2
    s2 = R[ob, 2, 0] * sm0 + R[ob, 2, 1] * sm1 + R[ob, 2, 2] * sm2
    return pm0, pm1, pm2, p0, p1, p2, s0, s1, s2


@nb.njit(inline="always", **_jit)
def albedo_at(obj_alb, tex, ob, i, u, v):
    """The diffuse albedo at barycentrics (u, v) of triangle row i of object ob: obj_alb[ob],
    times its texture where it has one. `tex` = (tri_uv, obj_tex, texels) (SceneGeometry.textures):
    the corners' texture coordinates interpolated, then the texels fetched bilinearly with repeat
    wrapping, texel centres at half-integers and v = 1 the image's top row (OBJ and Mitsuba's
    convention)."""
    tri_uv, obj_tex, texels = tex
    a0, a1, a2 = obj_alb[ob, 0], obj_alb[ob, 1], obj_alb[ob, 2]
    width = obj_tex[ob, 1]
    if width == 0:
        return a0, a1, a2
    height = obj_tex[ob, 2]
    w0 = F1 - u - v
    tu = w0 * tri_uv[i, 0] + u * tri_uv[i, 2] + v * tri_uv[i, 4]
    tv = w0 * tri_uv[i, 1] + u * tri_uv[i, 3] + v * tri_uv[i, 5]
    tu -= np.floor(tu)  # repeat: [0, 1) before scaling, so no coordinate overflows an index
    tv -= np.floor(tv)
    x = tu * np.float32(width) - np.float32(0.5)
    y = (F1 - tv) * np.float32(height) - np.float32(0.5)
    fx, fy = np.floor(x), np.floor(y)
    ax, ay = x - fx, y - fy
    x0, y0 = int(fx), int(fy)
    x0 = x0 + width if x0 < 0 else (x0 - width if x0 >= width else x0)
    y0 = y0 + height if y0 < 0 else (y0 - height if y0 >= height else y0)
    x1 = x0 + 1 if x0 + 1 < width else 0
    y1 = y0 + 1 if y0 + 1 < height else 0
    r0, r1 = obj_tex[ob, 0] + y0 * width, obj_tex[ob, 0] + y1 * width
    w00, w01, w10, w11 = (F1 - ax) * (F1 - ay), ax * (F1 - ay), (F1 - ax) * ay, ax * ay
    t0 = w00 * texels[r0 + x0, 0] + w01 * texels[r0 + x1, 0] + w10 * texels[r1 + x0, 0] + w11 * texels[r1 + x1, 0]
    t1 = w00 * texels[r0 + x0, 1] + w01 * texels[r0 + x1, 1] + w10 * texels[r1 + x0, 1] + w11 * texels[r1 + x1, 1]
    t2 = w00 * texels[r0 + x0, 2] + w01 * texels[r0 + x1, 2] + w10 * texels[r1 + x0, 2] + w11 * texels[r1 + x1, 2]
    return a0 * t0, a1 * t1, a2 * t2


@nb.njit(inline="always", **_jit)
def face_normals(p0, p1, p2, g0, g1, g2, s0, s1, s2, d0, d1, d2, v0, v1, v2, use_viewer):
    """Normalise the shading normal s (g where it vanishes), take the outgoing direction wo (−d,
    or towards the viewer at v when `use_viewer`: in DPM the eye, not the projector, sees the
    surface), and face both normals towards wo (two-sided shading; s falls back to g where it
    is not in wo's hemisphere). Scalars only. Returns g, s, wo and whether the ray hit the front."""
    sl = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    if sl > TINY_LEN32:
        s0, s1, s2 = s0 / sl, s1 / sl, s2 / sl
    else:
        s0, s1, s2 = g0, g1, g2
    wo0, wo1, wo2 = -d0, -d1, -d2
    if use_viewer:
        e0, e1, e2 = v0 - p0, v1 - p1, v2 - p2
        el = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        if el > TINY_LEN32:
            wo0, wo1, wo2 = e0 / el, e1 / el, e2 / el
    front = _dot(g0, g1, g2, wo0, wo1, wo2) > 0.0
    if not front:
        g0, g1, g2, s0, s1, s2 = -g0, -g1, -g2, -s0, -s1, -s2
    if _dot(s0, s1, s2, wo0, wo1, wo2) <= MIN_COS32:
        s0, s1, s2 = g0, g1, g2
    return g0, g1, g2, s0, s1, s2, wo0, wo1, wo2, front


@nb.njit(nogil=True, **_jit_shading)
def shade(depth, max_bounces, mis_last, key, first, count, rd, nx_o, nx_d, scn, film, work, split):
    """One wavefront step at a vertex after the first (depth ≥ 1: the first is
    first_surface + sample_first) over the paths in rows [first, first + count) (see module
    doc), compacting as it goes. Serial and without the GIL: the integrator runs one image
    segment per call, on several threads at once.

    `rd`: the paths' ray directions, their hits in `work`'s h_*. `scn`, `film`, `work`: the
    tuples of trace_segment. `tri`: rows of TRI_COLS (TRI_V0 …). `tex`: the albedo textures
    (albedo_at). `light_world` : (L, 12) rows of the emissive triangles in world space (v0, e1,
    e2, normal: SceneGeometry.light_rows), so light sampling transforms nothing per vertex.
    Writes the film at each path's pixel, and, packed from row `first`: the shadow rays (sh_o,
    sh_d, sh_tmax, sh_pix, with their diffuse and specular contributions in sh_c[:, 0:3] and
    sh_c[:, 3:6], added if unoccluded) and the surviving paths (pixel, beta, kd, prev_pdf, prev_env
    compacted in place; their rays in nx_o, nx_d, which must not be `rd`). Compacting in place is
    safe: row j ≤ k is written only after row k has been read. Returns (shadow rays, survivors).

    Per path only what the next vertex needs is kept: the BSDF pdf of its ray (prev_pdf) and the
    environment light's pdf of that direction (prev_env), both for MIS. `split` False (no object
    has a specular lobe): every path is diffuse, so kd, film_spec and sh_c[:, 3:6] are neither
    read nor written."""
    tri, obj_R, obj_t, obj_alb, tex, obj_spec, obj_alpha, obj_emit, obj_pdfA, light_world, light_obj, light_cdf, p_env, background, _, _, _ = scn
    _, film_diff, film_spec, nonfinite = film
    pixel, beta, kd, prev_pdf, prev_env, sh_o, sh_d, sh_tmax, sh_c, sh_pix, _, _, _, _, _, hit_t, hit_obj, hit_prim, hit_u, hit_v = work
    p_env = np.float32(p_env)  # 0, ½ or 1: exact
    p_area = F1 - p_env
    has_bg = background[0] > 0.0 or background[1] > 0.0 or background[2] > 0.0
    last = depth >= max_bounces
    base_dim = depth * DIMS_PER_BOUNCE
    ns = first  # next shadow-ray row
    nc = first  # next surviving-path row
    end = first + count
    for k in range(first, end):
        if k + PREFETCH_AHEAD < end and hit_prim[k + PREFETCH_AHEAD] >= 0:
            prefetch_row(tri, hit_prim[k + PREFETCH_AHEAD])
        pix = pixel[k]
        d0, d1, d2 = rd[k, 0], rd[k, 1], rd[k, 2]
        ob = hit_obj[k]
        kdr, kdg, kdb = F1, F1, F1
        b0, b1, b2 = beta[k, 0], beta[k, 1], beta[k, 2]
        if split:
            kdr, kdg, kdb = kd[k, 0], kd[k, 1], kd[k, 2]
        tri_i = 0
        u = v = F0
        g0 = g1 = g2 = F0
        le0 = le1 = le2 = F0  # radiance arriving along this ray from a light, MIS-weighted
        if ob < 0:  # escaped: the constant environment
            if has_bg:
                r_lb = prev_env[k] / prev_pdf[k]
                w = F1 / (F1 + r_lb * r_lb)
                le0, le1, le2 = background[0] * w, background[1] * w, background[2] * w
        else:
            tri_i = hit_prim[k]
            u, v = hit_u[k], hit_v[k]
            g0, g1, g2 = geometric_normal(tri, obj_R, ob, tri_i)
            if (obj_emit[ob, 0] > 0.0 or obj_emit[ob, 1] > 0.0 or obj_emit[ob, 2] > 0.0) and _dot(g0, g1, g2, d0, d1, d2) < 0.0:
                t = hit_t[k]
                pl = p_area * obj_pdfA[ob] * t * t / max(-_dot(g0, g1, g2, d0, d1, d2), np.float32(1e-12))
                r_lb = pl / prev_pdf[k]
                w = F1 / (F1 + r_lb * r_lb)
                le0, le1, le2 = obj_emit[ob, 0] * w, obj_emit[ob, 1] * w, obj_emit[ob, 2] * w
        if le0 > 0.0 or le1 > 0.0 or le2 > 0.0:
            c0, c1, c2 = b0 * le0, b1 * le1, b2 * le2
            if math.isfinite(c0 + c1 + c2):
                if split:
                    film_diff[pix, 0] += c0 * kdr
                    film_diff[pix, 1] += c1 * kdg
                    film_diff[pix, 2] += c2 * kdb
                    film_spec[pix, 0] += c0 * (F1 - kdr)
                    film_spec[pix, 1] += c1 * (F1 - kdg)
                    film_spec[pix, 2] += c2 * (F1 - kdb)
                else:
                    film_diff[pix, 0] += c0
                    film_diff[pix, 1] += c1
                    film_diff[pix, 2] += c2
            else:
                nonfinite[pix] += 1
        if ob < 0 or depth > max_bounces:
            continue  # escaped, or the extra ray that only looked for emitters (mis_last)
        # ---- surface interaction: hit point from barycentrics in model space, then to world ----
        pm0, pm1, pm2, p0, p1, p2, s0, s1, s2 = hit_point(tri, obj_R, obj_t, ob, tri_i, u, v)
        g0, g1, g2, s0, s1, s2, wo0, wo1, wo2, front = face_normals(p0, p1, p2, g0, g1, g2, s0, s1, s2, d0, d1, d2,
                                                                    F0, F0, F0, False)
        alpha = obj_alpha[ob]
        if tri[tri_i, TRI_ALPHA] > 0.0:  # per-triangle α (a scene's roughness_map)
            alpha = tri[tri_i, TRI_ALPHA]
        ar, ag, ab = albedo_at(obj_alb, tex, ob, tri_i, u, v)
        wd = _lum(ar * (F1 - obj_spec[ob, 0]), ag * (F1 - obj_spec[ob, 1]), ab * (F1 - obj_spec[ob, 2]))
        ws = _lum(obj_spec[ob, 0], obj_spec[ob, 1], obj_spec[ob, 2])
        if wd + ws <= 0.0:
            continue  # black surface: nothing is reflected
        p_spec = ws / (wd + ws)
        eps = OFFSET_REL32 * max(_max_abs3(p0, p1, p2), _max_abs3(pm0, pm1, pm2)) + TINY32
        o0, o1, o2 = p0 + g0 * eps, p1 + g1 * eps, p2 + g2 * eps
        continues = not last
        # ---- next-event estimation: one shadow ray, to the environment or an emissive triangle ----
        u_sel = rand(key, pix, base_dim)
        u1 = rand(key, pix, base_dim + 1)
        u2 = rand(key, pix, base_dim + 2)
        li0 = li1 = li2 = F0
        inv_pl = F0  # 1 / the light sample's solid-angle pdf (0: no sample)
        tmax = F0
        wi0 = wi1 = wi2 = F0
        if u_sel < p_env:
            t0, t1, t2, c0, c1, c2 = _basis(s0, s1, s2)
            x, y, z = _cosine_local(u1, u2)
            wi0, wi1, wi2 = _to_world(x, y, z, t0, t1, t2, c0, c1, c2, s0, s1, s2)
            pdf_l = p_env * z * INV_PI32
            if pdf_l > 0.0:
                inv_pl = F1 / pdf_l
            li0, li1, li2 = background[0], background[1], background[2]
            tmax = np.float32(3.0e38)
        elif p_area > 0.0:
            lo = _light_index(light_cdf, (u_sel - p_env) / p_area)
            lob = light_obj[lo]
            su = math.sqrt(u1)
            bb1, bb2 = u2 * su, F1 - su
            q0 = light_world[lo, 0] + bb1 * light_world[lo, 3] + bb2 * light_world[lo, 6] - o0
            q1 = light_world[lo, 1] + bb1 * light_world[lo, 4] + bb2 * light_world[lo, 7] - o1
            q2 = light_world[lo, 2] + bb1 * light_world[lo, 5] + bb2 * light_world[lo, 8] - o2
            dist2 = q0 * q0 + q1 * q1 + q2 * q2
            dist = math.sqrt(dist2)
            if dist > TINY32:
                wi0, wi1, wi2 = q0 / dist, q1 / dist, q2 / dist
                cos_l = -_dot(light_world[lo, 9], light_world[lo, 10], light_world[lo, 11], wi0, wi1, wi2)
                pa = p_area * obj_pdfA[lob] * dist2  # pdf = pa / cos_l; one division, off the sqrt's path
                if cos_l > 0.0 and pa > 0.0:
                    inv_pl = cos_l / pa
                    li0, li1, li2 = obj_emit[lob, 0], obj_emit[lob, 1], obj_emit[lob, 2]
                    tmax = dist * np.float32(1.0 - SHADOW_SHORTEN)
        cos_i = _dot(wi0, wi1, wi2, s0, s1, s2)
        if inv_pl > 0.0 and cos_i > 0.0 and _dot(wi0, wi1, wi2, g0, g1, g2) > 0.0:
            fd0, fd1, fd2, fs0, fs1, fs2, pdf_b = _eval_bsdf(wo0, wo1, wo2, wi0, wi1, wi2, s0, s1, s2, ar, ag, ab, obj_spec[ob, 0], obj_spec[ob, 1], obj_spec[ob, 2], alpha, p_spec, split)
            w = F1
            if continues or mis_last:
                r_bl = pdf_b * inv_pl
                w = F1 / (F1 + r_bl * r_bl)
            scale = cos_i * w * inv_pl
            cd0, cd1, cd2 = fd0 * li0 * scale * b0, fd1 * li1 * scale * b1, fd2 * li2 * scale * b2
            cs0, cs1, cs2 = fs0 * li0 * scale * b0, fs1 * li1 * scale * b1, fs2 * li2 * scale * b2
            if split:  # deeper vertices inherit the first vertex's diffuse/specular split
                t0 = cd0 + cs0
                t1 = cd1 + cs1
                t2 = cd2 + cs2
                cd0, cd1, cd2 = t0 * kdr, t1 * kdg, t2 * kdb
                cs0, cs1, cs2 = t0 - cd0, t1 - cd1, t2 - cd2
            if math.isfinite(cd0 + cd1 + cd2 + cs0 + cs1 + cs2):
                if cd0 + cd1 + cd2 + cs0 + cs1 + cs2 > 0.0:
                    sh_pix[ns] = pix
                    sh_o[ns, 0], sh_o[ns, 1], sh_o[ns, 2] = o0, o1, o2
                    sh_d[ns, 0], sh_d[ns, 1], sh_d[ns, 2] = wi0, wi1, wi2
                    sh_tmax[ns] = tmax
                    sh_c[ns, 0], sh_c[ns, 1], sh_c[ns, 2] = cd0, cd1, cd2
                    if split:
                        sh_c[ns, 3], sh_c[ns, 4], sh_c[ns, 5] = cs0, cs1, cs2
                    ns += 1
            else:
                nonfinite[pix] += 1
        if not (continues or mis_last):
            continue
        # ---- BSDF sampling: the continuation ray ----
        u_lobe = rand(key, pix, base_dim + 3)
        u1 = rand(key, pix, base_dim + 4)
        u2 = rand(key, pix, base_dim + 5)
        t0, t1, t2, c0, c1, c2 = _basis(s0, s1, s2)
        x, y, z = _cosine_local(u1, u2)
        if u_lobe < p_spec:
            wi0, wi1, wi2 = _ggx_sample(wo0, wo1, wo2, t0, t1, t2, c0, c1, c2, s0, s1, s2, alpha, x, y)
        else:
            wi0, wi1, wi2 = _to_world(x, y, z, t0, t1, t2, c0, c1, c2, s0, s1, s2)
        cos_i = _dot(wi0, wi1, wi2, s0, s1, s2)
        if cos_i <= 0.0 or _dot(wi0, wi1, wi2, g0, g1, g2) <= 0.0:
            continue
        fd0, fd1, fd2, fs0, fs1, fs2, pdf_b = _eval_bsdf(wo0, wo1, wo2, wi0, wi1, wi2, s0, s1, s2, ar, ag, ab, obj_spec[ob, 0], obj_spec[ob, 1], obj_spec[ob, 2], alpha, p_spec, split)
        if not pdf_b > 0.0:
            continue
        f0, f1, f2 = fd0 + fs0, fd1 + fs1, fd2 + fs2
        scale = cos_i / pdf_b
        nb0, nb1, nb2 = b0 * f0 * scale, b1 * f1 * scale, b2 * f2 * scale
        if depth + 1 >= RR_START_DEPTH:
            q = min(np.float32(RR_MAX_SURVIVAL), max(nb0, max(nb1, nb2)))
            if rand(key, pix, base_dim + 6) >= q:
                continue
            nb0, nb1, nb2 = nb0 / q, nb1 / q, nb2 / q
        if not math.isfinite(nb0 + nb1 + nb2):
            nonfinite[pix] += 1
            continue
        if nb0 + nb1 + nb2 <= 0.0:
            continue
        pixel[nc] = pix
        beta[nc, 0], beta[nc, 1], beta[nc, 2] = nb0, nb1, nb2
        if split:
            kd[nc, 0], kd[nc, 1], kd[nc, 2] = kdr, kdg, kdb
        prev_pdf[nc] = pdf_b
        prev_env[nc] = p_env * cos_i * INV_PI32
        nx_o[nc, 0], nx_o[nc, 1], nx_o[nc, 2] = o0, o1, o2
        nx_d[nc, 0], nx_d[nc, 1], nx_d[nc, 2] = wi0, wi1, wi2
        nc += 1
    return ns - first, nc - first


# ---- the first vertex in two passes: its surface (per camera pose), then its samples (per frame) ----
# What a first vertex needs that does not depend on the frame's random numbers (the hit point
# turned into a ray origin, the facing normals, the outgoing direction, the material, what the
# camera sees directly) is written per pixel by `first_surface`, as columns (S_* rows of `surf`).
# With the projector fixed and nothing moving these are the same every frame, and the integrator
# keeps them with the camera hits. `sample_first` then takes a frame's light sample and BSDF
# sample at every pixel in straight-line float32 code over those columns, which LLVM vectorises
# (16 lanes), and writes the shadow and continuation rays out, packed.
S_O, S_G, S_S, S_WO, S_ALB, S_SPEC = 0, 3, 6, 9, 12, 15  # origin (offset), facing normals, wo, albedo, specular
S_ALPHA, S_PSPEC, S_ACTIVE, S_EMIT = 18, 19, 20, 21  # GGX α, lobe probability, 1 = reflects, emission seen (3)
SURF_COLS = 24
# pixels whose light rows are gathered (scalar) before their vectorised samples: few, so a block
# half on an object before an empty background wastes few lanes (128: +5 % on the session's
# 256×192 render)
LIGHT_BLOCK = 32
L_ROW, L_EMIT, L_PA = 0, 12, 15  # gathered light columns: world row (12), emission (3), p_area · pdf per area
LIGHT_COLS = 16
NO_SHADOW = np.float32(-1.0)  # a block table's tmax where no shadow ray is traced


@nb.njit(nogil=True, **_jit_shading)
def first_surface(first, end, rd, primary, scn, surf, gb, split):
    """The frame-independent part of the first vertex of pixels [first, end) (camera rays rd,
    their hits `primary`): surf[S_*, pixel] (see above), and the G-buffer rows when its
    `write_gbuffer` (`primary`, `scn`, `gb`: the tuples of trace_segment).
    Each column is written once, and only what sample_first reads: a pixel that reflects
    nothing gets S_ACTIVE 0 and its S_EMIT (its other columns keep stale, finite values, which
    its vector lane computes with and discards); without specular lobes (`split` False) the
    S_SPEC, S_ALPHA and S_PSPEC columns are not read."""
    hit_t, hit_obj, hit_prim, hit_u, hit_v = primary
    tri, obj_R, obj_t, obj_alb, tex, obj_spec, obj_alpha, obj_emit, _, _, _, _, _, background, viewer, use_viewer, cam_fwd = scn
    gb_id, gb_model, gb_pos, gb_normal, gb_depth, gb_alb, gb_spec, gb_rough, write_gbuffer = gb
    has_bg = background[0] > 0.0 or background[1] > 0.0 or background[2] > 0.0
    for k in range(first, end):
        if k + PREFETCH_AHEAD < end and hit_prim[k + PREFETCH_AHEAD] >= 0:
            prefetch_row(tri, hit_prim[k + PREFETCH_AHEAD])
        ob = hit_obj[k]
        surf[S_ACTIVE, k] = F0
        for c in range(3):
            surf[S_EMIT + c, k] = F0
        if ob < 0:  # escaped: the constant environment
            if write_gbuffer:
                gb_id[k] = -1
                gb_depth[k] = np.inf
                gb_rough[k] = F0
                for c in range(3):
                    gb_model[k, c] = gb_pos[k, c] = gb_normal[k, c] = gb_alb[k, c] = gb_spec[k, c] = F0
            if has_bg:
                for c in range(3):
                    surf[S_EMIT + c, k] = background[c]
            continue
        d0, d1, d2 = rd[k, 0], rd[k, 1], rd[k, 2]
        i = hit_prim[k]
        g0, g1, g2 = geometric_normal(tri, obj_R, ob, i)
        emissive = obj_emit[ob, 0] > 0.0 or obj_emit[ob, 1] > 0.0 or obj_emit[ob, 2] > 0.0
        pm0, pm1, pm2, p0, p1, p2, s0, s1, s2 = hit_point(tri, obj_R, obj_t, ob, i, hit_u[k], hit_v[k])
        g0, g1, g2, s0, s1, s2, wo0, wo1, wo2, front = face_normals(p0, p1, p2, g0, g1, g2, s0, s1, s2, d0, d1, d2,
                                                                    viewer[0], viewer[1], viewer[2], use_viewer)
        # an emitter seen from its front (from the viewer's side when there is one; the
        # geometric normal before facing points against the ray when front is from the camera)
        if emissive and front:
            for c in range(3):
                surf[S_EMIT + c, k] = obj_emit[ob, c]
        alpha = obj_alpha[ob]
        if tri[i, TRI_ALPHA] > 0.0:  # per-triangle α (a scene's roughness_map)
            alpha = tri[i, TRI_ALPHA]
        ar, ag, ab = albedo_at(obj_alb, tex, ob, i, hit_u[k], hit_v[k])
        if write_gbuffer:
            gb_id[k] = ob
            gb_model[k, 0], gb_model[k, 1], gb_model[k, 2] = pm0, pm1, pm2
            gb_pos[k, 0], gb_pos[k, 1], gb_pos[k, 2] = p0, p1, p2
            gb_normal[k, 0], gb_normal[k, 1], gb_normal[k, 2] = s0, s1, s2
            gb_depth[k] = hit_t[k] * _dot(d0, d1, d2, cam_fwd[0], cam_fwd[1], cam_fwd[2])
            gb_alb[k, 0], gb_alb[k, 1], gb_alb[k, 2] = ar, ag, ab
            for c in range(3):
                gb_spec[k, c] = obj_spec[ob, c]
            gb_rough[k] = math.sqrt(alpha)
        wd = _lum(ar * (F1 - obj_spec[ob, 0]), ag * (F1 - obj_spec[ob, 1]), ab * (F1 - obj_spec[ob, 2]))
        ws = _lum(obj_spec[ob, 0], obj_spec[ob, 1], obj_spec[ob, 2])
        if wd + ws <= 0.0:
            continue  # black surface: nothing is reflected
        eps = OFFSET_REL32 * max(_max_abs3(p0, p1, p2), _max_abs3(pm0, pm1, pm2)) + TINY32
        surf[S_O, k], surf[S_O + 1, k], surf[S_O + 2, k] = p0 + g0 * eps, p1 + g1 * eps, p2 + g2 * eps
        surf[S_G, k], surf[S_G + 1, k], surf[S_G + 2, k] = g0, g1, g2
        surf[S_S, k], surf[S_S + 1, k], surf[S_S + 2, k] = s0, s1, s2
        surf[S_WO, k], surf[S_WO + 1, k], surf[S_WO + 2, k] = wo0, wo1, wo2
        surf[S_ALB, k], surf[S_ALB + 1, k], surf[S_ALB + 2, k] = ar, ag, ab
        if split:
            for c in range(3):
                surf[S_SPEC + c, k] = obj_spec[ob, c]
            surf[S_ALPHA, k] = alpha
            surf[S_PSPEC, k] = ws / (wd + ws)
        surf[S_ACTIVE, k] = F1


LSB = LIGHT_BLOCK + 16  # a block column's stride (not a multiple of 512 bytes: columns in different L1 sets)
# columns of a block's samples (`_sample_block` → the scalar writes of `sample_first`)
O_SD, O_TMAX, O_SC, O_ND, O_NB, O_NKD, O_PDF, O_ENV, O_BAD = 0, 3, 4, 10, 13, 16, 19, 20, 21
OUT_COLS = 22


@nb.njit(nogil=True, **_jit_shading)
def _gather_lights(key, a, m, light_world, light_obj, light_cdf, obj_emit, obj_pdfA, p_env, p_area, lblk):
    """The emissive triangle of pixel a + j's light sample (j < m), as columns lblk[L_* · LSB + j]."""
    for j in range(m):
        lo = 0
        if p_area > 0.0:  # (ut < 0: the environment is sampled, this row unused)
            lo = _light_index(light_cdf, (rand(key, a + j, 0) - p_env) / p_area)
        lob = light_obj[lo]
        for c in range(12):
            lblk[(L_ROW + c) * LSB + j] = light_world[lo, c]
        for c in range(3):
            lblk[(L_EMIT + c) * LSB + j] = obj_emit[lob, c]
        lblk[L_PA * LSB + j] = p_area * obj_pdfA[lob]


@nb.njit(inline="always", **_jit_vector)
def _sample_block(key, a, m, surf, lblk, oblk, p_env, background, sample_bsdf, glossy):
    """The light and BSDF samples of pixels [a, a + m), one pixel per vector lane (every branch a
    select): reads their surfaces and gathered lights, writes the block's columns oblk[O_* · LSB
    + j] and nothing else (so LLVM needs no run-time alias checks). `glossy` is a constant:
    False compiles the Lambert lobe alone."""
    bg0, bg1, bg2 = background[0], background[1], background[2]
    ua = np.uint64(a)
    for j in range(np.uint64(m)):
        k = ua + j
        active = surf[S_ACTIVE, k] > F0
        o0, o1, o2 = surf[S_O, k], surf[S_O + 1, k], surf[S_O + 2, k]
        g0, g1, g2 = surf[S_G, k], surf[S_G + 1, k], surf[S_G + 2, k]
        s0, s1, s2 = surf[S_S, k], surf[S_S + 1, k], surf[S_S + 2, k]
        wo0, wo1, wo2 = surf[S_WO, k], surf[S_WO + 1, k], surf[S_WO + 2, k]
        ar, ag, ab = surf[S_ALB, k], surf[S_ALB + 1, k], surf[S_ALB + 2, k]
        sr = sg = sb = F0
        alpha = p_spec = F0
        if glossy:
            sr, sg, sb = surf[S_SPEC, k], surf[S_SPEC + 1, k], surf[S_SPEC + 2, k]
            alpha, p_spec = surf[S_ALPHA, k], surf[S_PSPEC, k]
        # ---- next-event estimation: the environment (cosine-sampled) or the gathered emissive triangle ----
        u_sel = rand(key, k, 0)
        u1 = rand(key, k, 1)
        u2 = rand(key, k, 2)
        t0, t1, t2, c0, c1, c2 = _basis(s0, s1, s2)
        x, y, z = _cosine_local_v(u1, u2)
        pdf_e = p_env * z * INV_PI32
        inv_e = F1 / pdf_e if pdf_e > F0 else F0
        su = math.sqrt(u1)
        bb1, bb2 = u2 * su, F1 - su  # uniform on the triangle
        q0 = lblk[L_ROW * LSB + j] + bb1 * lblk[(L_ROW + 3) * LSB + j] + bb2 * lblk[(L_ROW + 6) * LSB + j] - o0
        q1 = lblk[(L_ROW + 1) * LSB + j] + bb1 * lblk[(L_ROW + 4) * LSB + j] + bb2 * lblk[(L_ROW + 7) * LSB + j] - o1
        q2 = lblk[(L_ROW + 2) * LSB + j] + bb1 * lblk[(L_ROW + 5) * LSB + j] + bb2 * lblk[(L_ROW + 8) * LSB + j] - o2
        dist2 = q0 * q0 + q1 * q1 + q2 * q2
        dist = math.sqrt(dist2)
        idist = F1 / dist
        qa0, qa1, qa2 = q0 * idist, q1 * idist, q2 * idist
        cos_l = -_dot(lblk[(L_ROW + 9) * LSB + j], lblk[(L_ROW + 10) * LSB + j], lblk[(L_ROW + 11) * LSB + j], qa0, qa1, qa2)
        pa = lblk[L_PA * LSB + j] * dist2  # the pdf is pa / cos_l: one division
        area_ok = (dist > TINY32) & (cos_l > F0) & (pa > F0)
        inv_a = cos_l / pa if area_ok else F0
        env = u_sel < p_env
        e0, e1, e2 = _to_world(x, y, z, t0, t1, t2, c0, c1, c2, s0, s1, s2)
        wi0 = e0 if env else qa0
        wi1 = e1 if env else qa1
        wi2 = e2 if env else qa2
        inv_pl = inv_e if env else inv_a
        li0 = bg0 if env else lblk[L_EMIT * LSB + j]
        li1 = bg1 if env else lblk[(L_EMIT + 1) * LSB + j]
        li2 = bg2 if env else lblk[(L_EMIT + 2) * LSB + j]
        cos_i = _dot(wi0, wi1, wi2, s0, s1, s2)
        nee = active & (inv_pl > F0) & (cos_i > F0) & (_dot(wi0, wi1, wi2, g0, g1, g2) > F0)
        fd0, fd1, fd2, fs0, fs1, fs2, pdf_b = _eval_bsdf_v(wo0, wo1, wo2, wi0, wi1, wi2, s0, s1, s2, ar, ag, ab, sr, sg, sb,
                                                           alpha, p_spec, glossy)
        r_bl = pdf_b * inv_pl
        w = F1 / (F1 + r_bl * r_bl) if sample_bsdf else F1
        scale = cos_i * w * inv_pl
        cd0, cd1, cd2 = fd0 * li0 * scale, fd1 * li1 * scale, fd2 * li2 * scale
        cs0, cs1, cs2 = fs0 * li0 * scale, fs1 * li1 * scale, fs2 * li2 * scale
        tot = cd0 + cd1 + cd2 + cs0 + cs1 + cs2
        fin = math.isfinite(tot)
        shadow = nee & fin & (tot > F0)
        oblk[O_SD * LSB + j], oblk[(O_SD + 1) * LSB + j], oblk[(O_SD + 2) * LSB + j] = wi0, wi1, wi2
        tmax = np.float32(3.0e38) if env else dist * np.float32(1.0 - SHADOW_SHORTEN)
        oblk[O_TMAX * LSB + j] = tmax if shadow else NO_SHADOW
        oblk[O_SC * LSB + j] = cd0 if shadow else F0
        oblk[(O_SC + 1) * LSB + j] = cd1 if shadow else F0
        oblk[(O_SC + 2) * LSB + j] = cd2 if shadow else F0
        oblk[(O_SC + 3) * LSB + j] = cs0 if shadow else F0
        oblk[(O_SC + 4) * LSB + j] = cs1 if shadow else F0
        oblk[(O_SC + 5) * LSB + j] = cs2 if shadow else F0
        # ---- BSDF sampling: the continuation ray ----
        u_lobe = rand(key, k, 3)
        u1 = rand(key, k, 4)
        u2 = rand(key, k, 5)
        x, y, z = _cosine_local_v(u1, u2)
        wi0, wi1, wi2 = _to_world(x, y, z, t0, t1, t2, c0, c1, c2, s0, s1, s2)
        if glossy:  # the GGX lobe's direction where u_lobe chooses it
            h0, h1, h2 = _ggx_sample_v(wo0, wo1, wo2, t0, t1, t2, c0, c1, c2, s0, s1, s2, alpha, x, y)
            spec_lobe = u_lobe < p_spec
            wi0 = h0 if spec_lobe else wi0
            wi1 = h1 if spec_lobe else wi1
            wi2 = h2 if spec_lobe else wi2
        cos_i = _dot(wi0, wi1, wi2, s0, s1, s2)
        ok = active & sample_bsdf & (cos_i > F0) & (_dot(wi0, wi1, wi2, g0, g1, g2) > F0)
        fd0, fd1, fd2, fs0, fs1, fs2, pdf_b = _eval_bsdf_v(wo0, wo1, wo2, wi0, wi1, wi2, s0, s1, s2, ar, ag, ab, sr, sg, sb,
                                                           alpha, p_spec, glossy)
        ok = ok & (pdf_b > F0)
        f0, f1, f2 = fd0 + fs0, fd1 + fs1, fd2 + fs2
        scale = cos_i / pdf_b
        nb0, nb1, nb2 = f0 * scale, f1 * scale, f2 * scale
        nsum = nb0 + nb1 + nb2
        fin2 = math.isfinite(nsum)
        alive = ok & fin2 & (nsum > F0)
        oblk[O_BAD * LSB + j] = np.float32(nee & (not fin)) + np.float32(ok & (not fin2))
        oblk[O_ND * LSB + j], oblk[(O_ND + 1) * LSB + j], oblk[(O_ND + 2) * LSB + j] = wi0, wi1, wi2
        oblk[O_NB * LSB + j], oblk[(O_NB + 1) * LSB + j], oblk[(O_NB + 2) * LSB + j] = nb0, nb1, nb2
        if glossy:  # split the path by the lobe weights at the first vertex
            oblk[O_NKD * LSB + j] = fd0 / f0 if f0 > F0 else F1
            oblk[(O_NKD + 1) * LSB + j] = fd1 / f1 if f1 > F0 else F1
            oblk[(O_NKD + 2) * LSB + j] = fd2 / f2 if f2 > F0 else F1
        oblk[O_PDF * LSB + j] = pdf_b if alive else F0  # 0: no continuation
        oblk[O_ENV * LSB + j] = p_env * cos_i * INV_PI32


# The two lobe sets as kernels of their own (the body inlined once into each), which LLVM inlines
# into sample_first: numba types each once instead of re-typing both inside sample_first.
@nb.njit(nogil=True, **_jit_vector)
def _sample_block_glossy(key, a, m, surf, lblk, oblk, p_env, background, sample_bsdf):
    _sample_block(key, a, m, surf, lblk, oblk, p_env, background, sample_bsdf, True)


@nb.njit(nogil=True, **_jit_vector)
def _sample_block_lambert(key, a, m, surf, lblk, oblk, p_env, background, sample_bsdf):
    _sample_block(key, a, m, surf, lblk, oblk, p_env, background, sample_bsdf, False)


@nb.njit(nogil=True, cache=True)
def block_scratch():
    """The per-thread scratch of sample_first (allocated per thread and pass, not per call)."""
    return np.empty(LIGHT_COLS * LSB, np.float32), np.empty(OUT_COLS * LSB, np.float32)


@nb.njit(nogil=True, **_jit_vector)
def sample_first(first, end, key, surf, nx_o, nx_d, scn, film, work, sample_bsdf, split, scratch):
    """The first vertex's samples at pixels [first, end) from their surfaces (first_surface), in
    blocks: the lights gathered (scalar), the samples (vectorised), then written out (scalar):
    the emission seen directly into film_emit, and packed from row `first` the shadow rays
    (sh_*, as `shade` writes them) and the paths that continue (pixel, beta, kd, prev_pdf,
    prev_env, nx_o, nx_d). Packed, not at their pixels' rows: where most pixels see nothing
    (an object in front of an empty background) the queries then cost what the hits cost.
    `scn`, `film`, `work`: the tuples of trace_segment; `scratch` = (lblk, oblk): LIGHT_COLS · LSB
    and OUT_COLS · LSB floats (block_scratch()). Returns (shadow rays, continuation rays)."""
    _, _, _, _, _, _, _, obj_emit, obj_pdfA, light_world, light_obj, light_cdf, p_env, background, _, _, _ = scn
    film_emit, _, _, nonfinite = film
    pixel, beta, kd, prev_pdf, prev_env, sh_o, sh_d, sh_tmax, sh_c, sh_pix = work[:10]
    lblk, oblk = scratch
    p_env = np.float32(p_env)  # 0, ½ or 1: exact
    p_area = F1 - p_env
    ns = nc = first
    for a in range(first, end, LIGHT_BLOCK):
        m = min(LIGHT_BLOCK, end - a)
        for j in range(m):  # the emission seen directly (the environment, emitters)
            e0, e1, e2 = surf[S_EMIT, a + j], surf[S_EMIT + 1, a + j], surf[S_EMIT + 2, a + j]
            if e0 != F0 or e1 != F0 or e2 != F0:  # (most pixels see none: no read-modify-write)
                film_emit[a + j, 0] += e0
                film_emit[a + j, 1] += e1
                film_emit[a + j, 2] += e2
        active = 0
        for j in range(m):
            active += surf[S_ACTIVE, a + j] > F0
        if active == 0:  # nothing here reflects (an empty background): no samples to take
            continue
        _gather_lights(key, a, m, light_world, light_obj, light_cdf, obj_emit, obj_pdfA, p_env, p_area, lblk)
        if split:
            _sample_block_glossy(key, a, m, surf, lblk, oblk, p_env, background, sample_bsdf)
        else:
            _sample_block_lambert(key, a, m, surf, lblk, oblk, p_env, background, sample_bsdf)
        for j in range(m):
            k = a + j
            bad = oblk[O_BAD * LSB + j]
            if bad != F0:
                nonfinite[k] += np.int32(bad)
            tmax = oblk[O_TMAX * LSB + j]
            if tmax >= F0:
                sh_pix[ns] = k
                for c in range(3):
                    sh_o[ns, c] = surf[S_O + c, k]
                    sh_d[ns, c] = oblk[(O_SD + c) * LSB + j]
                    sh_c[ns, c] = oblk[(O_SC + c) * LSB + j]
                if split:
                    for c in range(3, 6):
                        sh_c[ns, c] = oblk[(O_SC + c) * LSB + j]
                sh_tmax[ns] = tmax
                ns += 1
            pdf = oblk[O_PDF * LSB + j]
            if pdf > F0:
                pixel[nc] = k
                prev_pdf[nc], prev_env[nc] = pdf, oblk[O_ENV * LSB + j]
                for c in range(3):
                    beta[nc, c] = oblk[(O_NB + c) * LSB + j]
                    nx_o[nc, c] = surf[S_O + c, k]
                    nx_d[nc, c] = oblk[(O_ND + c) * LSB + j]
                if split:
                    for c in range(3):
                        kd[nc, c] = oblk[(O_NKD + c) * LSB + j]
                nc += 1
    return ns - first, nc - first


@nb.njit(nogil=True, **_jit)
def add_unoccluded(first, count, sh_pix, contrib, blocked, film_diff, film_spec, split):
    """Add the contribution of each shadow ray in rows [first, first + count) that nothing blocked."""
    for k in range(first, first + count):
        if not blocked[k]:
            p = sh_pix[k]
            film_diff[p, 0] += contrib[k, 0]
            film_diff[p, 1] += contrib[k, 1]
            film_diff[p, 2] += contrib[k, 2]
            if split:
                film_spec[p, 0] += contrib[k, 3]
                film_spec[p, 1] += contrib[k, 4]
                film_spec[p, 2] += contrib[k, 5]


@intrinsic
def _fma32(typingctx, a, b, c):
    """a * b + c in float32, rounded once (LLVM's fma)."""
    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return nb.float32(nb.float32, nb.float32, nb.float32), codegen


@nb.njit(nogil=True, cache=True, error_model="numpy")
def camera_rays(dirs_cam, R, t, first, end, o, d):
    """Camera rays through the centres of pixels [first, end) into o, d (n, 3) float32: origin t,
    direction R @ dirs_cam[pixel] (R camera→world, both float32). Each component is the FMA
    chain x·R[j,0] → +y·R[j,1] → +z·R[j,2], as OpenBLAS's sgemm computes `dirs_cam @ R.T`
    on FMA CPUs: the rays `PinholeCamera.generate_rays` made with numpy, bit for bit, on
    such a machine, and the same rays on any machine. Compiled: a pose change costs a pass
    over the buffers, not numpy temporaries."""
    for i in range(first, end):
        x, y, z = dirs_cam[i, 0], dirs_cam[i, 1], dirs_cam[i, 2]
        for j in range(3):
            d[i, j] = _fma32(z, R[j, 2], _fma32(y, R[j, 1], x * R[j, 0]))
            o[i, j] = t[j]


@nb.njit(nogil=True, **_jit)
def jittered_directions(corners, R, width, key, first, end, out):
    """World directions of camera rays through a random point of each pixel in [first, end)
    (row-major pixel index), written to out[pixel]: each pass samples the pixel's footprint
    uniformly, so the passes average to the box-filtered pixel integral. The point is
    (rand(key, pixel, 0), rand(key, pixel, 1)) with the pass's jitter key: it depends only on
    the seed, the pass and the pixel. `corners`: PinholeCamera.pixel_corners(); R camera→world."""
    for pix in range(first, end):
        y, x = pix // width, pix % width
        jx, jy = rand(key, pix, 0), rand(key, pix, 1)
        w00, w01, w10, w11 = (1 - jx) * (1 - jy), jx * (1 - jy), (1 - jx) * jy, jx * jy
        cx = w00 * corners[y, x, 0] + w01 * corners[y, x + 1, 0] + w10 * corners[y + 1, x, 0] + w11 * corners[y + 1, x + 1, 0]
        cy = w00 * corners[y, x, 1] + w01 * corners[y, x + 1, 1] + w10 * corners[y + 1, x, 1] + w11 * corners[y + 1, x + 1, 1]
        d0 = R[0, 0] * cx + R[0, 1] * cy + R[0, 2]
        d1 = R[1, 0] * cx + R[1, 1] * cy + R[1, 2]
        d2 = R[2, 0] * cx + R[2, 1] * cy + R[2, 2]
        inv = 1.0 / np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        out[pix, 0], out[pix, 1], out[pix, 2] = d0 * inv, d1 * inv, d2 * inv


@intrinsic
def _take_next(typingctx, counter):
    """counter[0] += 1, atomically; returns the value before (a shared int64 work counter)."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64 and counter.ndim == 1):
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.atomic_rmw("add", ary.data, ir.Constant(ir.IntType(64), 1), "monotonic")

    return types.int64(counter), codegen


@nb.njit(nogil=True, cache=True)
def clear_rows(film, first, end):
    """Zeros in rows [first, end) of a frame's film. Each image segment clears its own rows in its
    own thread, so the frame's arrays are allocated empty on the main thread (no serial fill
    there) and are in cache when that segment shades. The G-buffer needs none: first_surface
    writes every row of it, a miss's no-hit values included."""
    film_emit, film_diff, film_spec, nonfinite = film
    for i in range(first, end):
        for c in range(3):
            film_emit[i, c] = film_diff[i, c] = film_spec[i, c] = 0.0
        nonfinite[i] = 0


@nb.njit(nogil=True, cache=True, error_model="numpy")
def trace_segments(counter, starts, counts, clear, radiance, acc, acc_moving, acc_static, packets, split, depth_limit, max_bounces,
                   mis_last, key, primary_dirs, primary, complete_primary, static, camera_o, scn, film, gb, surface, work, jitter):
    """trace_segment over the image segments (first rows `starts`, row counts `counts`) that
    this thread takes from the shared `counter` (counter[0] = next segment, atomically), so each
    render thread makes one call per pass instead of one per segment (each call unboxes some
    60 arrays under the GIL). `clear`: each segment first zeros its film rows (clear_rows). `radiance` (n, 3) or empty: each segment then writes its
    rows of emit + diff + spec (a 1-spp frame's radiance, the same float32 sums as numpy's).
    Returns the (shadow rays, continuation rays) traced, or (−1, −1) if a path outlived 4096 bounces."""
    film_emit, film_diff, film_spec = film[0], film[1], film[2]
    scratch = block_scratch()
    traced_shadow = traced_next = 0
    while True:
        s = _take_next(counter)
        if s >= starts.shape[0]:
            return traced_shadow, traced_next
        first, count = starts[s], counts[s]
        if count <= 0:
            continue
        if clear:
            clear_rows(film, first, first + count)
        n_shadow, n_next = trace_segment(acc, acc_moving, acc_static, packets, split, depth_limit, max_bounces, mis_last, key, first, count,
                                         primary_dirs, primary, complete_primary, static, camera_o, scn, film, gb, surface, work, jitter,
                                         scratch)
        if n_shadow < 0:
            return -1, -1
        traced_shadow += n_shadow
        traced_next += n_next
        if radiance.shape[0] > 0:
            for i in range(first, first + count):
                for c in range(3):
                    radiance[i, c] = film_emit[i, c] + film_diff[i, c] + film_spec[i, c]


# Without fast-math: LLVM inlines the ray queries here, and a fast-math caller would let it fuse
# their float32 transforms into FMAs (moving objects' hits would change in the last bit). Inlined
# by numba into its one caller, trace_segments: as a function of its own, it would have LLVM
# optimise and generate the whole path tracer a second time.
@nb.njit(inline="always", nogil=True, cache=True, error_model="numpy")
def trace_segment(acc, acc_moving, acc_static, packets, split, depth_limit, max_bounces, mis_last, key, first, count, primary_dirs, primary,
                  complete_primary, static, camera_o, scn, film, gb, surface, work, jitter, scratch):
    """All bounces of the paths through pixels [first, first + count) in one call, with Embree
    queried from inside (traversal): shade → shadow rays → continuation rays → shade …, no
    Python between the stages. `primary` = (t, obj, prim, u, v) of the camera rays. `static` =
    (trace, t, obj, prim, u, v, then the rasteriser's per-pixel triangles and tables, see
    static_raster.resolve_range): the camera rays' hits on the static objects (the integrator's
    per-pose cache, which is `primary` itself when nothing moves); with `trace` (a new camera
    pose) this segment's rows of it are made first: resolved on the rasterised triangles, or
    (no triangles given) traced as 4×4-tile packets against the static BVH (`acc_static`), here
    rather than in a separate pass over the image, so the work is spread over the threads with
    everything else and the hits are still in cache when shaded. With `complete_primary` the static hits are copied into `primary`'s rows and the
    moving objects traced (from camera_o along primary_dirs). `packets` = (continuation, shadow): 16-wide
    packets of consecutive rows, or single rays. The tuples, as the integrator builds them:
    scn = (tri, R, T, obj_alb, tex, obj_spec, obj_alpha, obj_emit, obj_pdfA, light_world,
    light_obj, light_cdf, p_env, background, viewer, use_viewer, cam_fwd): the scene's tables
    (SceneGeometry) and the objects' poses; film = (emit, diff, spec, nonfinite); gb = (id, model,
    pos, normal, depth, alb, spec, rough, write_gbuffer): the G-buffer; surface = (ready, surf):
    the first vertices' surfaces (first_surface), computed here unless ready (kept by the
    integrator while the camera and every object stay put); work = (pixel, beta, kd, prev_pdf,
    prev_env, sh_o, sh_d, sh_tmax, sh_c, sh_pix, blocked, ray_o0, ray_d0, ray_o1, ray_d1, h_t,
    h_obj, h_prim, h_u, h_v): per-path arrays, kept between frames; the vertices at depth d
    write their continuation rays into ray_o{d % 2}, ray_d{d % 2}, whose hits the next depth
    reads from h_*. `jitter` = (on, jitter key, pixel corners, camera rotation,
    image width, cam_d): when on, the camera rays are generated through a random point of each
    pixel into cam_d (which `primary_dirs` must then be) and traced here in full. Returns (shadow rays,
    continuation rays), or (−1, −1) if a path outlived 4096 bounces."""
    R, T = scn[1], scn[2]
    _, film_diff, film_spec, _ = film
    surface_ready, surf = surface
    _, _, _, _, _, sh_o, sh_d, sh_tmax, sh_c, sh_pix, blocked, ray_o0, ray_d0, ray_o1, ray_d1, h_t, h_obj, h_prim, h_u, h_v = work
    p_t, p_obj, p_prim, p_u, p_v = primary
    end = first + count
    jitter_on, jkey, corners, cam_R, width, cam_d = jitter
    if jitter_on:
        jittered_directions(corners, cam_R, width, jkey, first, end, cam_d)
        traversal.closest_range(acc, R, T, camera_o, cam_d, first, end, p_t, p_obj, p_prim, p_u, p_v, packets[0], bool(False))
    else:
        trace_static, s_t, s_obj, s_prim, s_u, s_v, r_tri, r_vw, r_faces, r_obj, r_prim, r_origin = static
        if trace_static and r_tri.shape[0] > 0:  # rasterised: each pixel's triangle known, its hit resolved here
            static_raster.resolve_range(r_tri, r_vw, r_faces, r_obj, r_prim, r_origin, primary_dirs, first, end, s_t, s_obj, s_prim, s_u, s_v)
        elif trace_static:
            traversal.closest_tiles(acc_static, R, T, camera_o, primary_dirs, width, first, end, s_t, s_obj, s_prim, s_u, s_v)
        if complete_primary:
            for i in range(first, end):
                p_t[i], p_obj[i], p_prim[i], p_u[i], p_v[i] = s_t[i], s_obj[i], s_prim[i], s_u[i], s_v[i]
            traversal.closest_range(acc_moving, R, T, camera_o, primary_dirs, first, end, p_t, p_obj, p_prim, p_u, p_v, packets[0], bool(True))
    traced_shadow = traced_next = 0
    depth = np.int64(0)  # not a literal 0: shade would be compiled for it too (see traversal's flags)
    while True:
        nx_o, nx_d = (ray_o0, ray_d0) if depth % 2 == 0 else (ray_o1, ray_d1)
        if depth == 0:  # the first vertex: its surface (unless kept), then this pass's samples
            if not surface_ready:
                first_surface(first, end, primary_dirs, primary, scn, surf, gb, split)
            n_shadow, n_next = sample_first(first, end, key, surf, nx_o, nx_d, scn, film, work, max_bounces > 0 or mis_last, split,
                                            scratch)
        else:
            rd = ray_d1 if depth % 2 == 0 else ray_d0
            n_shadow, n_next = shade(depth, max_bounces, mis_last, key, first, count, rd, nx_o, nx_d, scn, film, work, split)
        if n_shadow:
            traversal.occluded_range(acc, R, T, sh_o, sh_d, sh_tmax, first, first + n_shadow, blocked, packets[1])
            add_unoccluded(first, n_shadow, sh_pix, sh_c, blocked, film_diff, film_spec, split)
            traced_shadow += n_shadow
        if depth >= depth_limit or n_next == 0:
            return traced_shadow, traced_next
        traversal.closest_range(acc, R, T, nx_o, nx_d, first, first + n_next, h_t, h_obj, h_prim, h_u, h_v, packets[0], bool(False))
        traced_next += n_next
        count = n_next
        depth += 1
        if depth > 4096:
            return -1, -1
