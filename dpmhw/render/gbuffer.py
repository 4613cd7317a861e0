"""The projector-native G-buffer, kept up to date at a cost proportional to what moves.

The projector does not move during a session, so camera rays never change: primary hits on
static objects are traced once (`intersect_static`, 4×4-pixel packets) and their attributes kept.
Each frame only the region of interest of the moving objects is re-traced: the bounding box of
each object's convex hull projected with the current pose, plus `ROI_MARGIN_PX` (for the bunny
about half the box of its projected bounding sphere). Pixels that left the region get their
static attributes back. Pixels that show nothing cost nothing after the first frame.

Inside the region, `update(poses, shading=frame)` (mode "edges", the loop's default) traces only
the pixels near a discontinuity of the shading-resolution frame just rendered for the same
poses: a native pixel whose 2×2 shading taps all show the same moving object at depths within
`EDGE_DEPTH_REL` of each other takes its attributes bilinearly from those taps; one whose taps
all show the same static object (or all nothing) and whose cached static hit agrees keeps the
cached attributes; every other pixel (silhouettes, depth steps, other objects) is traced. Mode
"trace" traces every pixel of the region (exact; the reference the "edges" mode is measured
against in docs/temporal-reuse.md).

Mode "raster" z-buffers the moving objects' model-space meshes into the region instead (`_raster_moving`:
coverage is tested at each pixel ray's ideal image-plane point, so the hits equal ray casting's
except on shared edges, with or without lens distortion) and needs no shading frame. Measured
on dpm-bunny at 1024×768 (69k triangles, 40–55k covered pixels, 2 threads, CPU time per update,
median of 12 poses on the shared machine): raster 13.5 ms, edges 5.7 ms, trace 15.1 ms. Raster
is exact where "edges" interpolates (normals a few degrees off inside, about 1 wrong-id pixel a
frame), but it pays for every covered pixel's attributes and for scattered z-buffer writes, so
"edges" stays the default; "raster" is the choice when the G-buffer must not wait for the
shading frame (e.g. to run beside the renderer).

Attributes follow `render.frame.Frame`: object id (−1 background), world position, shading
normal facing the viewer, camera depth, albedo, specular albedo, roughness (√α of the GGX α).
The pixels to re-trace are listed in 4×4 tile order and traced as 16-wide packets from inside
a numba kernel (`traversal.closest16` on the moving objects' BVHs only, starting from the
cached static hits) when the accelerator is the C-API `RtcAccel`; with embreex's fallback they
are gathered and traced one by one. Work follows the region: only its pixels are classified,
traced and written, and only the part of the last region outside the current one is restored.
`changed` flags the region's pixels whose attributes may differ from the last update's (in mode
"edges" all but those that kept their cached static attributes), so that users of the region
(`reconstruct.stage`'s native guides) recompute only those.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numba as nb
import numpy as np

from dpmhw.parallel_kernels import PixelKernel
from dpmhw.render import kernels
from dpmhw.render.cameras import PinholeCamera
from dpmhw.render.distortion import distort_inline
from dpmhw.render.embree import traversal
from dpmhw.render.embree.accel import RtcAccel, empty_hits
from dpmhw.render.geometry import SceneGeometry
from dpmhw.render.zbuffer import BAND_ROWS, NEAR_Z
from dpmhw.scene_file import Scene
from dpmhw.transforms import Pose

ROI_MARGIN_PX = 4  # plus 1 % of the box size: lens distortion between the hull's projected corners
EDGE_DEPTH_REL = 0.02  # 2×2 shading taps further apart in depth than this: trace the native pixel
MODES = ("raster", "edges", "trace")
ATTRIBUTES = ("id", "position", "normal", "depth", "albedo", "spec_albedo", "roughness")  # a pixel's, as NativeGBuffer's arrays


# The renderer's first-vertex helpers for `_attributes_py`, compiled with its flags (none: IEEE),
# so the arithmetic is the one numba's IR inlining gave, but typed once instead of again inside
# the parallel loop, whose body numba types and lowers twice (the loop, then its gufunc).
_geometric_normal, _hit_point, _face_normals, _albedo_at = (
    kernels.inline_copy(f, "_ieee", cache=True)
    for f in (kernels.geometric_normal, kernels.hit_point, kernels.face_normals, kernels.albedo_at))


def _attributes_py(index, d, hits, scene, view, out):
    """G-buffer attributes of pixels `index` from their camera rays' directions `d` and `hits`
    (t, obj, prim, u, v), all indexed by pixel; the renderer's first-vertex helpers (`kernels.shade`
    at depth 0). scene : (tri, R, T, albedo, textures, specular, alpha), the geometry's tables at the
    current poses; view : (viewer, use_viewer, cam_fwd); out : the G-buffer's (id, position,
    normal, depth, albedo, spec_albedo, roughness), written at `index`."""
    t, obj, prim, u, v = hits
    tri, R, T, alb, tex, spec, alpha = scene
    viewer, use_viewer, cam_fwd = view
    g_id, g_pos, g_normal, g_depth, g_alb, g_spec, g_rough = out
    for k in nb.prange(index.shape[0]):
        p = index[k]
        ob = obj[p]
        if ob < 0:
            g_id[p] = -1
            g_depth[p] = np.inf
            for c in range(3):
                g_pos[p, c] = 0.0
                g_normal[p, c] = 0.0
                g_alb[p, c] = 0.0
                g_spec[p, c] = 0.0
            g_rough[p] = 0.0
            continue
        i = prim[p]
        d0, d1, d2 = d[p, 0], d[p, 1], d[p, 2]
        g0, g1, g2 = _geometric_normal(tri, R, ob, i)
        pm0, pm1, pm2, p0, p1, p2, s0, s1, s2 = _hit_point(tri, R, T, ob, i, u[p], v[p])
        g0, g1, g2, s0, s1, s2, wo0, wo1, wo2, front = _face_normals(p0, p1, p2, g0, g1, g2, s0, s1, s2, d0, d1, d2,
                                                                     viewer[0], viewer[1], viewer[2], use_viewer)
        g_id[p] = ob
        g_pos[p, 0], g_pos[p, 1], g_pos[p, 2] = p0, p1, p2
        g_normal[p, 0], g_normal[p, 1], g_normal[p, 2] = s0, s1, s2
        g_depth[p] = t[p] * (d0 * cam_fwd[0] + d1 * cam_fwd[1] + d2 * cam_fwd[2])
        g_alb[p, 0], g_alb[p, 1], g_alb[p, 2] = _albedo_at(alb, tex, ob, i, u[p], v[p])
        for c in range(3):
            g_spec[p, c] = spec[ob, c]
        g_rough[p] = math.sqrt(tri[i, kernels.TRI_ALPHA] if tri[i, kernels.TRI_ALPHA] > 0.0 else alpha[ob])  # per-triangle α: a roughness map


_attribute_kernel = PixelKernel(_attributes_py)


@nb.njit(nogil=True, cache=True)
def _trace_pixels(acc, R, T, o, d, index, first, end, s_t, s_obj, s_prim, s_u, s_v, t, obj, prim, u, v):
    """Closest hits of the camera rays of pixels index[first:end], 16 consecutive entries per
    packet (`index` is in 4×4 tile order: one packet ≈ one tile), starting from the pixels'
    cached static hits and testing only the moving objects (`acc` = RtcAccel.acc_moving).
    Hits are written to the pixels' rows of t, obj, prim, u, v."""
    f, iv, valid = traversal.scratch16()
    rows = np.empty(16, np.int64)
    for a in range(first, end, 16):
        n = min(16, end - a)
        for i in range(n):
            p = index[a + i]
            rows[i] = p
            t[p], obj[p], prim[p], u[p], v[p] = s_t[p], s_obj[p], s_prim[p], s_u[p], s_v[p]
        traversal.closest16(acc, R, T, f, iv, valid, o, d, rows, n, t, obj, prim, u, v, bool(True))


@nb.njit
def _static_back(p, s_id, s_pos, s_nrm, s_dep, s_alb, s_spec, s_rough, g_id, g_pos, g_normal, g_depth, g_alb, g_spec,
                 g_rough):
    """Pixel p shows its cached static attributes again."""
    g_id[p] = s_id[p]
    g_depth[p] = s_dep[p]
    g_rough[p] = s_rough[p]
    for c in range(3):
        g_pos[p, c] = s_pos[p, c]
        g_normal[p, c] = s_nrm[p, c]
        g_alb[p, c] = s_alb[p, c]
        g_spec[p, c] = s_spec[p, c]


@nb.njit(parallel=True, cache=True, nogil=True)
def _classify(W, H, box, w, h, low, dynamic, static, gbuf, static_px, trace, changed):
    """Per native pixel of `box` (y0, y1, x0, x1): interpolate (1), keep static (2) or trace (0,
    flag in `trace`). `low`: the shading frame's attributes (w × h), `static` the cached static
    ones, `gbuf` the G-buffer's, each flat and in `ATTRIBUTES` order. `changed`: whether the
    pixel's attributes may differ from the last update's (False only for a pixel that kept its
    cached static attributes and held them already)."""
    y0, y1, x0, x1 = box
    lid, lpos, lnrm, ldep, lalb, lspec, lrough = low
    s_id, s_pos, s_nrm, s_dep, s_alb, s_spec, s_rough = static
    g_id, g_pos, g_normal, g_depth, g_alb, g_spec, g_rough = gbuf
    sx = w / W
    sy = h / H
    for y in nb.prange(y0, y1):
        v = (y + 0.5) * sy - 0.5
        ty = min(max(int(np.floor(v)), 0), h - 2) if h > 1 else 0
        fy = min(max(v - ty, 0.0), 1.0)
        for x in range(x0, x1):
            p = y * W + x
            u = (x + 0.5) * sx - 0.5
            tx = min(max(int(np.floor(u)), 0), w - 2) if w > 1 else 0
            fx = min(max(u - tx, 0.0), 1.0)
            j00 = ty * w + tx
            j01 = j00 + (1 if w > 1 else 0)
            j10 = j00 + (w if h > 1 else 0)
            j11 = j10 + (1 if w > 1 else 0)
            o = lid[j00]
            same = lid[j01] == o and lid[j10] == o and lid[j11] == o
            trace[p] = False
            changed[p] = True
            if same and (o < 0 or not dynamic[o]):
                if s_id[p] == o:  # static or empty, and the cache agrees: keep it
                    if static_px[p]:
                        changed[p] = False
                        continue
                    static_px[p] = True
                    _static_back(p, s_id, s_pos, s_nrm, s_dep, s_alb, s_spec, s_rough,
                                 g_id, g_pos, g_normal, g_depth, g_alb, g_spec, g_rough)
                    continue
            elif same:
                z0, z1, z2, z3 = ldep[j00], ldep[j01], ldep[j10], ldep[j11]
                zmin = min(min(z0, z1), min(z2, z3))
                zmax = max(max(z0, z1), max(z2, z3))
                if zmax - zmin <= EDGE_DEPTH_REL * zmin:
                    w00 = (1 - fx) * (1 - fy)
                    w01 = fx * (1 - fy)
                    w10 = (1 - fx) * fy
                    w11 = fx * fy
                    static_px[p] = False
                    g_id[p] = o
                    g_depth[p] = w00 * z0 + w01 * z1 + w10 * z2 + w11 * z3
                    g_rough[p] = lrough[j00]
                    for c in range(3):
                        g_pos[p, c] = w00 * lpos[j00, c] + w01 * lpos[j01, c] + w10 * lpos[j10, c] + w11 * lpos[j11, c]
                        nc = w00 * lnrm[j00, c] + w01 * lnrm[j01, c] + w10 * lnrm[j10, c] + w11 * lnrm[j11, c]
                        g_normal[p, c] = nc
                        g_alb[p, c] = lalb[j00, c]
                        g_spec[p, c] = lspec[j00, c]
                    nl = np.sqrt(g_normal[p, 0] ** 2 + g_normal[p, 1] ** 2 + g_normal[p, 2] ** 2)
                    if nl > 1e-12:
                        for c in range(3):
                            g_normal[p, c] /= nl
                        continue
            trace[p] = True

@nb.njit(parallel=True, cache=True, nogil=True)
def _project_vertices(verts, R, T, cam_R, cam_t, fx, fy, cx, cy, dist, cam, pix):
    """Model-space vertices → camera space (float64, `cam`) and distorted pixel coordinates (`pix`)."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for i in nb.prange(verts.shape[0]):
        m0, m1, m2 = float(verts[i, 0]), float(verts[i, 1]), float(verts[i, 2])
        w0 = R[0, 0] * m0 + R[0, 1] * m1 + R[0, 2] * m2 + T[0] - cam_t[0]
        w1 = R[1, 0] * m0 + R[1, 1] * m1 + R[1, 2] * m2 + T[1] - cam_t[1]
        w2 = R[2, 0] * m0 + R[2, 1] * m1 + R[2, 2] * m2 + T[2] - cam_t[2]
        c0 = cam_R[0, 0] * w0 + cam_R[1, 0] * w1 + cam_R[2, 0] * w2  # x_cam = R_camᵀ (x_world − t_cam)
        c1 = cam_R[0, 1] * w0 + cam_R[1, 1] * w1 + cam_R[2, 1] * w2
        c2 = cam_R[0, 2] * w0 + cam_R[1, 2] * w1 + cam_R[2, 2] * w2
        cam[i, 0], cam[i, 1], cam[i, 2] = c0, c1, c2
        z = c2 if c2 > 1e-12 else 1e-12
        x, y = c0 / z, c1 / z
        xd, yd = distort_inline(x, y, k1, k2, p1, p2, k3)
        pix[i, 0] = fx * xd + cx
        pix[i, 1] = fy * yd + cy


@nb.njit(parallel=True, cache=True, nogil=True)
def _setup_faces(faces, cam, pix, margin_rel, y0, y1, x0, x1, rect):
    """Per face: its clipped pixel box (ya, yb, xa, xb) in `rect` (empty: ya = yb): the pixels
    whose centres (integer pixel coordinates) lie in the box of its corners' distorted pixel
    positions, widened by a rounding margin plus `margin_rel` of its size (under lens distortion
    an edge is a curve between its corners)."""
    for f in nb.prange(faces.shape[0]):
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        rect[f, 0] = rect[f, 1] = 0
        if min(cam[i0, 2], min(cam[i1, 2], cam[i2, 2])) <= NEAR_Z:
            continue
        pxa = min(pix[i0, 0], min(pix[i1, 0], pix[i2, 0]))
        pxb = max(pix[i0, 0], max(pix[i1, 0], pix[i2, 0]))
        pya = min(pix[i0, 1], min(pix[i1, 1], pix[i2, 1]))
        pyb = max(pix[i0, 1], max(pix[i1, 1], pix[i2, 1]))
        m = 1e-3 + margin_rel * max(pxb - pxa, pyb - pya)
        if not (pya - m < y1 and pyb + m >= y0 and pxa - m < x1 and pxb + m >= x0):
            continue
        ya = max(int(math.ceil(pya - m)), y0)
        yb = min(int(math.floor(pyb + m)) + 1, y1)
        xa = max(int(math.ceil(pxa - m)), x0)
        xb = min(int(math.floor(pxb + m)) + 1, x1)
        if ya < yb and xa < xb:
            rect[f, 0], rect[f, 1], rect[f, 2], rect[f, 3] = ya, yb, xa, xb


@nb.njit(parallel=True, cache=True, nogil=True)
def _raster_moving(faces, cam, rect, ideal, qx_col, qy_row, separable, dcz, W, bands, obj, prim0, stamp, sid, s_t, t, o_id, prim,
            u, v):
    """Z-buffer the faces into the pixels' camera-ray hits (t, o_id, prim, u, v): a pixel whose
    `stamp` is `sid` holds a moving object's hit of this frame there, any other its cached static
    hit `s_t` (so nothing is copied first). A pixel's ray passes through its ideal
    (undistorted) image-plane point `ideal`; it meets a face iff that point lies inside the face's
    corners projected to the same plane (every ray starts at the projector's centre), so the
    hits equal ray casting's except on shared edges (ties). Barycentrics are perspective-correct
    and (u, v) weigh the face's second and third corner, as Embree's do; t is the ray parameter
    (camera depth / the ray's depth per unit length `dcz`). Without lens distortion the ideal point
    is separable (`qx_col[x]`, `qy_row[y]`: no per-pixel table read). Threads take interleaved
    row bands."""
    for b in nb.prange(bands):
        for f in range(faces.shape[0]):
            ya, yb = rect[f, 0], rect[f, 1]
            if ya >= yb:
                continue
            ra = ya // BAND_ROWS
            rb = (yb - 1) // BAND_ROWS
            if rb - ra + 1 < bands and (b - ra) % bands > rb - ra:
                continue  # none of its row blocks belongs to this band
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            za, zb, zc = cam[i0, 2], cam[i1, 2], cam[i2, 2]
            ax, ay = cam[i0, 0] / za, cam[i0, 1] / za
            bx, by = cam[i1, 0] / zb, cam[i1, 1] / zb
            cx, cy = cam[i2, 0] / zc, cam[i2, 1] / zc
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            if area == 0.0 or not math.isfinite(area):
                continue
            inv = 1.0 / area
            iza, izb, izc = 1.0 / za, 1.0 / zb, 1.0 / zc
            for y in range(ya, yb):
                if (y // BAND_ROWS) % bands != b:
                    continue
                qy = qy_row[y]
                for x in range(rect[f, 2], rect[f, 3]):
                    p = y * W + x
                    if separable:
                        qx = qx_col[x]
                    else:
                        qx, qy = float(ideal[p, 0]), float(ideal[p, 1])
                    l0 = ((bx - qx) * (cy - qy) - (by - qy) * (cx - qx)) * inv
                    l1 = ((cx - qx) * (ay - qy) - (cy - qy) * (ax - qx)) * inv
                    l2 = ((ax - qx) * (by - qy) - (ay - qy) * (bx - qx)) * inv
                    if l0 < 0.0 or l1 < 0.0 or l2 < 0.0:
                        continue
                    z = 1.0 / (l0 * iza + l1 * izb + l2 * izc)
                    tt = z / dcz[p]
                    if tt < (t[p] if stamp[p] == sid else s_t[p]):
                        stamp[p] = sid
                        t[p] = tt
                        o_id[p] = obj
                        prim[p] = prim0 + f
                        u[p] = l1 * izb * z
                        v[p] = l2 * izc * z


@nb.njit(cache=True, nogil=True)
def _raster_pixels(W, box, stamp, sid, static_px, static, gbuf):
    """Pixels of `box` (y0, y1, x0, x1) a moving object covers (returned, row-major: their
    attributes come from their hits); every other pixel of the box gets its cached `static`
    attributes back into `gbuf` (both in `ATTRIBUTES` order)."""
    y0, y1, x0, x1 = box
    s_id, s_pos, s_nrm, s_dep, s_alb, s_spec, s_rough = static
    g_id, g_pos, g_normal, g_depth, g_alb, g_spec, g_rough = gbuf
    out = np.empty((y1 - y0) * (x1 - x0), np.int64)
    n = 0
    for y in range(y0, y1):
        for p in range(y * W + x0, y * W + x1):
            if stamp[p] == sid:
                out[n] = p
                n += 1
                static_px[p] = False
            elif not static_px[p]:
                static_px[p] = True
                _static_back(p, s_id, s_pos, s_nrm, s_dep, s_alb, s_spec, s_rough,
                             g_id, g_pos, g_normal, g_depth, g_alb, g_spec, g_rough)
    return out[:n]


class NativeGBuffer:
    """The G-buffer at the projector's native size (W, H) for one fixed projector pose.

    `update(poses)` brings it to the given object poses and returns the box (y0, y1, x0, x1) of
    the pixels that may show something (`lit_box`); `changed_box` is the box whose attributes
    changed in that call, `roi_box` the moving objects' box (None: none). A consumer that derives
    data from the attributes recomputes the union of its previous and the current `roi_box`
    (and everything the first time): with several consumers, `changed_box` belongs to the last.
    Arrays are flat, (W*H, ...), row-major.
    """

    def __init__(self, scene: Scene, geometry: SceneGeometry, width: int, height: int, threads: int = 2):
        self.scene = scene
        self.geometry = geometry
        self.width, self.height = int(width), int(height)
        cam = scene.at_size(self.width, self.height).camera
        self.camera = PinholeCamera(cam.K, cam.dist, self.width, self.height, cam.pose)
        self.viewer = np.asarray(scene.viewer_position, np.float32)
        self.use_viewer = not np.allclose(scene.viewer_position, scene.camera.pose.t)
        self.cam_fwd = self.camera.pose.R[:, 2].astype(np.float32)
        self._pool = ThreadPoolExecutor(max(1, threads), thread_name_prefix="gbuffer") if threads > 1 else None
        self.threads = max(1, int(threads))
        n = self.width * self.height
        self.id = np.full(n, -1, np.int32)
        self.position = np.zeros((n, 3), np.float32)
        self.normal = np.zeros((n, 3), np.float32)
        self.depth = np.full(n, np.inf, np.float32)
        self.albedo = np.zeros((n, 3), np.float32)
        self.spec_albedo = np.zeros((n, 3), np.float32)
        self.roughness = np.zeros(n, np.float32)
        self.dynamic = [i for i, o in enumerate(scene.objects) if o.is_dynamic]
        self._hulls = [_hull_vertices(scene.objects[i].mesh.vertices) for i in self.dynamic]
        self._o, self._d = self.camera.generate_rays()
        self._is_dynamic = np.array([o.is_dynamic for o in scene.objects], np.bool_)
        self._trace_flags = np.zeros(self.width * self.height, np.bool_)
        # per pixel of the last update's region: its attributes may have changed (mode "edges";
        # the other modes mark the whole region); what `Guides.update(mask=…)` recomputes
        self.changed = np.ones(self.width * self.height, np.bool_)
        self.updates = 0  # update() calls so far: a user of `changed` must have seen the one before
        self._meshes = None  # the rasteriser's tables, made on its first use (`_raster_setup`)
        self.pixels_rasterised = 0  # pixels a moving object covered in the last "raster" update
        self.rays_traced = 0  # camera rays traced in the last update (for the benchmark)
        self._trace_static()
        self._prev_box: tuple[int, int, int, int] | None = None
        self.changed_box = (0, self.height, 0, self.width)
        self.lit_box = self._static_lit
        self.roi_box: tuple[int, int, int, int] | None = None  # the moving objects' box of the last update
        self._first = True

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _attribute_arrays(self, static: bool = False) -> tuple:
        """The G-buffer's arrays (or its cached static ones) in `ATTRIBUTES` order."""
        return tuple(self._static[k] if static else getattr(self, k) for k in ATTRIBUTES)

    # ---- static part, once -----------------------------------------------------------------
    def _trace_static(self) -> None:
        hits = self.geometry.accel.intersect_static(self._o, self._d, width=self.width)
        self.static_hits = hits
        self._hits = empty_hits(len(hits.t))  # per-frame hits, rows = pixels (only the traced ones are read)
        index = np.arange(self.width * self.height, dtype=np.int64)
        R, T = self.geometry.poses(self.scene.object_poses(0.0))
        self._attributes(index, self._d, hits, R, T)
        self._static = {k: getattr(self, k).copy() for k in ATTRIBUTES}
        self.static_px = np.ones(len(index), np.bool_)  # the pixel holds its cached static attributes
        self._static["static_px"] = self.static_px.copy()
        live = [getattr(self, k) for k in self._static]  # a restore copies these from their static copies, as flat bytes
        self._restore_buffers = (tuple(_bytes(a) for a in live), tuple(_bytes(a) for a in self._static.values()),
                                 np.array([a.nbytes // a.shape[0] for a in live], np.int64))
        self._static_lit = _bbox(self.id.reshape(self.height, self.width) >= 0)
        self.rays_traced = len(index)

    def _attributes(self, index, d, hits, R, T) -> None:
        g = self.geometry
        _attribute_kernel(
            len(index), index, d, (hits.t, hits.obj, hits.prim, hits.u, hits.v),
            (g.tri, R, T, g.obj_albedo, g.textures, g.obj_specular, g.obj_alpha), (self.viewer, self.use_viewer, self.cam_fwd),
            (self.id, self.position, self.normal, self.depth, self.albedo, self.spec_albedo, self.roughness))

    def _raster_setup(self) -> None:
        """What the rasteriser keeps: each pixel's ray as an ideal image-plane point and its depth
        per unit length, and per moving object its model-space mesh and work arrays."""
        d_cam = self._d.astype(np.float64) @ self.camera.pose.R  # camera-space ray directions
        self._ideal = np.ascontiguousarray(d_cam[:, :2] / d_cam[:, 2:3], np.float32)
        self._dcz = np.ascontiguousarray(d_cam[:, 2], np.float32)
        self._meshes = []
        for i in self.dynamic:
            mesh = getattr(self, "_mesh_now", {}).get(i, self.scene.objects[i].mesh)  # `use_mesh`'s level
            v = np.ascontiguousarray(mesh.vertices, np.float32)
            f = np.ascontiguousarray(mesh.faces, np.int64)
            self._meshes.append((i, int(self.geometry.tri_offsets[i]), v, f, np.empty((len(v), 3)), np.empty((len(v), 2)),
                                 np.empty((len(f), 4), np.int32)))
        self._margin_rel = 0.0 if not np.any(self.camera.dist) else 0.05
        K = self.camera.K
        self._qx_col = (np.arange(self.width) - K[0, 2]) / K[0, 0]  # the ideal points without distortion
        self._qy_row = (np.arange(self.height) - K[1, 2]) / K[1, 1]
        self._stamp = np.zeros(len(self._dcz), np.int32)  # see `_raster_moving`
        self._sid = 0

    # ---- hook: mesh level of detail (dpmhw.lod.mesh_pipeline) -----------------------------------
    def use_mesh(self, k: int, mesh, all_levels=None) -> None:
        """Moving object k is drawn with `mesh` from the next update on (its triangle rows and
        BVH already swapped by `SceneGeometry.set_level`). `all_levels` (every mesh it may use,
        given once): the region of interest then holds each of them. The static caches need
        nothing: they hold static objects only, and the region is re-traced every update."""
        j = self.dynamic.index(k)
        self._mesh_now = {**getattr(self, "_mesh_now", {}), k: mesh}
        if all_levels is not None:
            self._hulls[j] = _hull_vertices(np.concatenate([np.asarray(m.vertices) for m in all_levels]))
        if self._meshes is not None:  # the rasteriser's tables of that object
            v = np.ascontiguousarray(mesh.vertices, np.float32)
            f = np.ascontiguousarray(mesh.faces, np.int64)
            self._meshes[j] = (k, int(self.geometry.tri_offsets[k]), v, f, np.empty((len(v), 3)), np.empty((len(v), 2)),
                               np.empty((len(f), 4), np.int32))

    # ---- per frame -------------------------------------------------------------------------
    def _raster_box(self, box, poses) -> None:
        """Mode "raster": z-buffer the moving objects' meshes into the box (see `_raster_moving`); falls
        back to tracing the box when a moving vertex reaches the projector's plane."""
        if self._meshes is None:
            self._raster_setup()
        R, T = self.geometry.poses(poses)
        cam = self.camera
        K, cam_R, cam_t = cam.K, cam.pose.R.astype(np.float64), cam.pose.t.astype(np.float64)
        for i, _, v, _, cpos, pix, _ in self._meshes:
            _project_vertices(v, R[i].astype(np.float64), T[i].astype(np.float64), cam_R, cam_t, K[0, 0], K[1, 1],
                              K[0, 2], K[1, 2], cam.dist, cpos, pix)
            if not cpos[:, 2].min() > NEAR_Z:
                self._trace_box(box, poses)
                return
        s, h = self.static_hits, self._hits
        W = self.width
        self._sid = self._sid % 2_000_000_000 + 1
        bands = max(1, nb.get_num_threads())
        for i, prim0, _, faces, cpos, pix, rect in self._meshes:
            _setup_faces(faces, cpos, pix, self._margin_rel, *box, rect)
            _raster_moving(faces, cpos, rect, self._ideal, self._qx_col, self._qy_row, self._margin_rel == 0.0, self._dcz, W,
                    bands, i, prim0, self._stamp, self._sid, s.t,
                    h.t, h.obj, h.prim, h.u, h.v)
        index = _raster_pixels(W, box, self._stamp, self._sid, self.static_px, self._attribute_arrays(static=True), self._attribute_arrays())
        self._attributes(index, self._d, h, R, T)
        self.pixels_rasterised = len(index)

    def _interpolate(self, box, f) -> np.ndarray:
        """Fill the box from the shading frame where it is smooth; returns the pixels to trace."""
        h, w = f.object_id.shape
        trace = self._trace_flags
        low = (_flat(f.object_id, np.int32, 1), _flat(f.position), _flat(f.normal), _flat(f.depth, np.float32, 1), _flat(f.albedo),
               _flat(f.specular_albedo), _flat(f.roughness, np.float32, 1))
        _classify(self.width, self.height, box, w, h, low, self._is_dynamic, self._attribute_arrays(static=True), self._attribute_arrays(),
                  self.static_px, trace, self.changed)
        return _tile_order(trace, False, self.width, *box)

    def roi(self, poses: list[Pose]) -> tuple[int, int, int, int] | None:
        """Box (y0, y1, x0, x1) holding every moving object's projection (None: none visible):
        the box of its convex hull's corners projected, which holds the projection of every
        vertex (a pinhole maps the hull onto the hull of the projected corners), plus a margin
        (lens distortion curves the edges between corners)."""
        boxes = []
        cam = self.camera
        for k, hull in zip(self.dynamic, self._hulls):
            world = poses[k].apply(hull)
            z = (world - cam.pose.t) @ cam.pose.R[:, 2]
            if z.min() <= 1e-3:  # the object reaches the projector's plane: everything
                return (0, self.height, 0, self.width)
            px, _ = cam.project(world)
            boxes.append((px[:, 1].min(), px[:, 1].max(), px[:, 0].min(), px[:, 0].max()))
        if not boxes:
            return None
        y0, y1 = min(b[0] for b in boxes), max(b[1] for b in boxes)
        x0, x1 = min(b[2] for b in boxes), max(b[3] for b in boxes)
        my = ROI_MARGIN_PX + 0.01 * (y1 - y0)
        mx = ROI_MARGIN_PX + 0.01 * (x1 - x0)
        box = (int(max(math.floor(y0 - my), 0)), int(min(math.ceil(y1 + my) + 1, self.height)),
               int(max(math.floor(x0 - mx), 0)), int(min(math.ceil(x1 + mx) + 1, self.width)))
        if box[0] >= box[1] or box[2] >= box[3]:
            return None
        return box

    def update(self, poses: list[Pose], shading=None, mode: str = "edges") -> tuple[int, int, int, int]:
        """Bring the region of the moving objects to `poses`; returns `lit_box`. `shading`: the
        renderer `Frame` of the same poses at the shading resolution (mode "edges" traces only
        near its discontinuities; without it every pixel of the region is traced)."""
        if mode not in MODES:
            raise ValueError(f"gbuffer mode: expected one of {', '.join(MODES)}, got {mode!r}")
        self.rays_traced = 0
        self.updates += 1
        box = self.roi(poses) if self.dynamic else None
        prev = self._prev_box
        if prev is not None:  # pixels of the last region outside this one: back to static
            for part in box_minus(prev, box):
                _restore_kernel(*self._restore_buffers, self.width, *part)
        self.pixels_rasterised = 0
        if box is not None:
            if mode != "edges" or shading is None:  # every pixel of the region may change
                self.changed.reshape(self.height, self.width)[box[0]:box[1], box[2]:box[3]] = True
            if mode == "raster":
                self._raster_box(box, poses)
            else:
                self._trace_box(box, poses, shading if mode == "edges" else None)
        self._prev_box = box
        self.roi_box = box
        changed = [b for b in (prev, box) if b is not None]
        self.changed_box = (0, self.height, 0, self.width) if self._first else _union(changed)
        self._first = False
        self.lit_box = _union([b for b in (self._static_lit, box) if b is not None])
        return self.lit_box

    def _trace_box(self, box, poses, shading=None) -> None:
        if shading is None:
            index = _tile_order(self._trace_flags, True, self.width, *box)
        else:
            index = self._interpolate(box, shading)
        n = len(index)
        if n == 0:
            return
        R, T = self.geometry.poses(poses)
        accel, s, h = self.geometry.accel, self.static_hits, self._hits
        if isinstance(accel, RtcAccel):  # packets of 16 pixels, queried from the kernel
            k = -(-n // (16 * 2 * self.threads)) * 16
            bounds = [(a, min(a + k, n)) for a in range(0, n, k)]

            def run(ab):
                _trace_pixels(accel.acc_moving, R, T, self._o, self._d, index, ab[0], ab[1], s.t, s.obj, s.prim, s.u, s.v,
                              h.t, h.obj, h.prim, h.u, h.v)
        else:  # embreex: the selected rays gathered, traced, scattered back to their pixels
            d = np.ascontiguousarray(self._d[index])
            o = np.ascontiguousarray(self._o[index])
            c = empty_hits(n)
            for name in ("t", "obj", "prim", "u", "v"):
                getattr(c, name)[:] = getattr(s, name)[index]
            cuts = np.linspace(0, n, 2 * self.threads + 1).astype(np.int64)
            bounds = [(int(a), int(e)) for a, e in zip(cuts[:-1], cuts[1:]) if e > a]

            def run(ab):
                accel.intersect_range(o, d, ab[0], ab[1], R, T, c, static_done=True)
        if self._pool is None or len(bounds) < 2:
            for ab in bounds:
                run(ab)
        else:
            others = [self._pool.submit(run, ab) for ab in bounds[1:]]
            run(bounds[0])  # this thread takes a share instead of waiting idle
            for f in others:
                f.result()
        if not isinstance(accel, RtcAccel):
            for name in ("t", "obj", "prim", "u", "v"):
                getattr(h, name)[index] = getattr(c, name)
        self.static_px[index] = False
        self._attributes(index, self._d, h, R, T)
        self.rays_traced = n


def _bytes(a: np.ndarray) -> np.ndarray:
    """A C-contiguous array's bytes, flat (a view: writes reach the array)."""
    return a.reshape(-1).view(np.uint8)


@nb.njit(cache=True, nogil=True)
def _restore_kernel(dsts, srcs, px, W, y0, y1, x0, x1):
    """Pixels x0 to x1 − 1 of rows y0 to y1 − 1 of each buffer dsts[b] = those of srcs[b]: flat
    bytes, px[b] a pixel, rows of W pixels (one signature and one call for every buffer). A
    loop, not a slice assignment: numba's slice assignment brings the string formatting of its
    shape-mismatch message, seconds of compile. Unsigned indices: numba wraps a signed index that
    may be negative, a select per byte that keeps LLVM from turning the loop into block copies
    (ten times slower)."""
    for b in range(len(dsts)):
        dst, src, n = dsts[b], srcs[b], np.uint64(px[b])
        for y in range(y0, y1):
            for i in range(np.uint64(y * W + x0) * n, np.uint64(y * W + x1) * n):
                dst[i] = src[i]


def _flat(a, dtype=np.float32, cols=3) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype)
    return a.reshape(-1) if cols == 1 else a.reshape(-1, cols)


@nb.njit(cache=True, nogil=True)
def _tile_order(flags, every, W, y0, y1, x0, x1):
    """Pixels of the box (all if `every`, else those flagged) in 4×4 tile order, rows then
    columns inside a tile: 16 consecutive entries of a dense box are one tile (one coherent packet)."""
    out = np.empty((y1 - y0) * (x1 - x0), np.int64)
    n = 0
    for ty in range(y0, y1, 4):
        for tx in range(x0, x1, 4):
            for y in range(ty, min(ty + 4, y1)):
                for x in range(tx, min(tx + 4, x1)):
                    if every or flags[y * W + x]:
                        out[n] = y * W + x
                        n += 1
    return out[:n]


def _hull_vertices(vertices: np.ndarray) -> np.ndarray:
    """The corners of the convex hull of a mesh's vertices (all of them if it has no volume)."""
    from scipy.spatial import ConvexHull, QhullError

    v = np.asarray(vertices, np.float64)
    try:
        return np.ascontiguousarray(v[ConvexHull(v).vertices])
    except (QhullError, ValueError):  # flat or degenerate: every vertex
        return np.ascontiguousarray(v)


def box_minus(a, b) -> list[tuple[int, int, int, int]]:
    """Box a without box b, as up to four boxes."""
    if b is None or b[0] >= a[1] or b[1] <= a[0] or b[2] >= a[3] or b[3] <= a[2]:
        return [a]
    out = []
    if a[0] < b[0]:
        out.append((a[0], b[0], a[2], a[3]))
    if b[1] < a[1]:
        out.append((b[1], a[1], a[2], a[3]))
    y0, y1 = max(a[0], b[0]), min(a[1], b[1])
    if a[2] < b[2]:
        out.append((y0, y1, a[2], b[2]))
    if b[3] < a[3]:
        out.append((y0, y1, b[3], a[3]))
    return out


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)


def _union(boxes) -> tuple[int, int, int, int]:
    boxes = [b for b in boxes if b is not None]
    if not boxes:
        return (0, 0, 0, 0)
    return (min(b[0] for b in boxes), max(b[1] for b in boxes), min(b[2] for b in boxes), max(b[3] for b in boxes))
