"""Camera hits on the static objects by rasterisation: a z-buffer instead of one ray per pixel.

A pinhole camera's ray through pixel (x, y) is r = ((x − cx)/fx, (y − cy)/fy, 1) in camera
space (`cameras.PinholeCamera`: pixel (0, 0)'s centre at (0, 0)). For a triangle with camera-space
vertices V0, V1, V2, each edge function E_ij = r · (V_i × V_j) is linear in (x, y), and the ray
hits the triangle in front of the camera exactly when all three have the sign of
det = V0 · (V1 × V2) (homogeneous rasterisation: no clipping, so triangles crossing the camera
plane need no special case). 1/z of the hit is r · n / det, also linear in (x, y): the depth
test. Neighbours compute their shared edge's coefficients from the same vertices in the other
order, which negates them exactly, and the tests are inclusive: no pixel falls between them.

Then the closest triangle's t, u, v come from a float32 ray–triangle intersection with the
pixel's own camera ray (`PinholeCamera.rays_into`) and the world-space float32 vertices Embree
was given (`embree.accel.RtcAccel`), factored as Embree's Moeller test is. On paper-static at
1024×768 (five poses) they agree with Embree's within 1.3e-6 in t/t; u and v within 1e-6 on the
room and 7e-4 on the bunny, whose 3 mm triangles seen from 1.5 m leave both intersectors' float32
barycentrics that uncertain. The triangle differs from Embree's in 0-1 pixel per frame, on an
edge two triangles share (the same t); where an edge passes exactly through pixel centres, the
inclusive edge tests hit where Embree, without its robust flag, lets a few rays through.
A frame costs 15 CPU-ms there against 35 for the traced tiles (README, "Where a frame's time goes").

Cameras with lens distortion are declined (`CameraHitsUnsupported`): their pixel rays are not
the images of straight lines, so the integrator keeps ray tracing them.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from dpmhw.render.embree.accel import Hits, empty_hits
from dpmhw.render.zbuffer import BAND_ROWS, NEAR_Z

BOX_MARGIN = 1e-3  # pixels
SPAN_WIDTH = 16  # boxes wider than this get each row's span from the edges' crossings


class CameraHitsUnsupported(ValueError):
    """This camera's hits cannot be rasterised (lens distortion): trace its rays instead."""


@nb.njit(nogil=True, cache=True, parallel=True)
def _to_camera(vw, R, t, vc):
    """World vertices (float32) → camera space, Rᵀ (x − t), in float64."""
    for i in nb.prange(vw.shape[0]):
        p0, p1, p2 = vw[i, 0] - t[0], vw[i, 1] - t[1], vw[i, 2] - t[2]
        for a in range(3):
            vc[i, a] = R[0, a] * p0 + R[1, a] * p1 + R[2, a] * p2


@nb.njit(inline="always", nogil=True, cache=True)
def _project(X, Y, Z, fx, fy, cx, cy, box):
    """Grow box (xmin, xmax, ymin, ymax) by the pixel position of camera-space point X, Y, Z."""
    px, py = fx * X / Z + cx, fy * Y / Z + cy
    return min(box[0], px), max(box[1], px), min(box[2], py), max(box[3], py)


@nb.njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def _setup(vc, faces, fx, fy, cx, cy, width, height, coef, box):
    """Per triangle: edge-function and depth-plane coefficients in pixel coordinates (coef rows:
    A, B, C of the three edges, signed so that inside is ≥ 0, then the 1/z plane), and its pixel
    box (x0, x1, y0, y1; empty if x0 > x1) clipped to the image. Float64 throughout."""
    for f in nb.prange(faces.shape[0]):
        box[f, 0], box[f, 1], box[f, 2], box[f, 3] = 1, 0, 1, 0
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        x0, y0, z0 = vc[i0, 0], vc[i0, 1], vc[i0, 2]
        x1, y1, z1 = vc[i1, 0], vc[i1, 1], vc[i1, 2]
        x2, y2, z2 = vc[i2, 0], vc[i2, 1], vc[i2, 2]
        if z0 < NEAR_Z and z1 < NEAR_Z and z2 < NEAR_Z:
            continue  # wholly behind the camera
        # edge normals V_i × V_j: a shared edge's, computed by its neighbour in the other order, is
        # the exact negation (so its coefficients and edge values are too)
        n0x, n0y, n0z = y0 * z1 - z0 * y1, z0 * x1 - x0 * z1, x0 * y1 - y0 * x1
        n1x, n1y, n1z = y1 * z2 - z1 * y2, z1 * x2 - x1 * z2, x1 * y2 - y1 * x2
        n2x, n2y, n2z = y2 * z0 - z2 * y0, z2 * x0 - x2 * z0, x2 * y0 - y2 * x0
        det = x2 * n0x + y2 * n0y + z2 * n0z  # V0 · (V1 × V2)
        if det == 0.0 or np.isnan(det):  # degenerate, or its plane through the camera centre (edge-on)
            continue
        s = 1.0 if det > 0.0 else -1.0
        a0, b0 = n0x / fx, n0y / fy
        a1, b1 = n1x / fx, n1y / fy
        a2, b2 = n2x / fx, n2y / fy
        c0, c1, c2 = n0z - cx * a0 - cy * b0, n1z - cx * a1 - cy * b1, n2z - cx * a2 - cy * b2
        coef[f, 0], coef[f, 1], coef[f, 2] = s * a0, s * b0, s * c0
        coef[f, 3], coef[f, 4], coef[f, 5] = s * a1, s * b1, s * c1
        coef[f, 6], coef[f, 7], coef[f, 8] = s * a2, s * b2, s * c2
        coef[f, 9], coef[f, 10], coef[f, 11] = (a0 + a1 + a2) / det, (b0 + b1 + b2) / det, (c0 + c1 + c2) / det
        # pixel box of the part in front of the camera (the polygon clipped to z ≥ NEAR_Z)
        bb = (np.inf, -np.inf, np.inf, -np.inf)
        for e in range(3):
            if e == 0:
                xa, ya, za, xb, yb, zb = x0, y0, z0, x1, y1, z1
            elif e == 1:
                xa, ya, za, xb, yb, zb = x1, y1, z1, x2, y2, z2
            else:
                xa, ya, za, xb, yb, zb = x2, y2, z2, x0, y0, z0
            if za >= NEAR_Z:
                bb = _project(xa, ya, za, fx, fy, cx, cy, bb)
            if (za < NEAR_Z) != (zb < NEAR_Z):
                h = (NEAR_Z - za) / (zb - za)
                bb = _project(xa + h * (xb - xa), ya + h * (yb - ya), NEAR_Z, fx, fy, cx, cy, bb)
        # the pixel centres (integer coordinates) within it, widened by BOX_MARGIN for the rounding
        # of the projection (a pixel the exact edge test accepts must not be left out)
        bx0 = max(0.0, np.ceil(bb[0] - BOX_MARGIN))
        bx1 = min(width - 1.0, np.floor(bb[1] + BOX_MARGIN))
        by0 = max(0.0, np.ceil(bb[2] - BOX_MARGIN))
        by1 = min(height - 1.0, np.floor(bb[3] + BOX_MARGIN))
        if bx0 <= bx1 and by0 <= by1:
            box[f, 0], box[f, 1], box[f, 2], box[f, 3] = int(bx0), int(bx1), int(by0), int(by1)


@nb.njit(nogil=True, cache=True)
def _bin(box, bands):
    """Triangles per band of BAND_ROWS rows (CSR: start (bands + 1,), ids), in triangle order."""
    count = np.zeros(bands + 1, np.int64)
    nf = box.shape[0]
    for f in range(nf):
        if box[f, 0] <= box[f, 1]:
            for b in range(box[f, 2] // BAND_ROWS, box[f, 3] // BAND_ROWS + 1):
                count[b + 1] += 1
    start = np.cumsum(count)
    ids = np.empty(start[-1], np.int32)
    fill = start[:-1].copy()
    for f in range(nf):
        if box[f, 0] <= box[f, 1]:
            for b in range(box[f, 2] // BAND_ROWS, box[f, 3] // BAND_ROWS + 1):
                ids[fill[b]] = f
                fill[b] += 1
    return start, ids


@nb.njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def _raster(coef, box, start, ids, width, height, depth, tri):
    """Closest triangle (largest 1/z) per pixel into tri (−1: none), band by band in parallel.
    Every pixel centre in a triangle's box is tested exactly (inclusive); for a wide box, each
    row is first cut to the edges' crossings widened by a pixel (the test decides the rest)."""
    bands = start.shape[0] - 1
    half = (bands + 1) // 2
    for i in nb.prange(2 * half):
        # the threads' static shares of the range interleave bands (0, 2, 4 … then 1, 3, 5 …), so
        # that objects in the middle of the image do not all fall to one thread
        b = 2 * i if i < half else 2 * (i - half) + 1
        if b >= bands:
            continue
        r0, r1 = b * BAND_ROWS, min((b + 1) * BAND_ROWS, height)
        for p in range(r0 * width, r1 * width):
            depth[p], tri[p] = -np.inf, -1
        for q in range(start[b], start[b + 1]):
            f = ids[q]
            a0, b0, c0, a1, b1, c1 = coef[f, 0], coef[f, 1], coef[f, 2], coef[f, 3], coef[f, 4], coef[f, 5]
            a2, b2, c2, da, db, dc = coef[f, 6], coef[f, 7], coef[f, 8], coef[f, 9], coef[f, 10], coef[f, 11]
            x0, x1 = box[f, 0], box[f, 1]
            wide = x1 - x0 >= SPAN_WIDTH
            for y in range(max(box[f, 2], r0), min(box[f, 3] + 1, r1)):
                fy = float(y)
                e0, e1, e2 = b0 * fy + c0, b1 * fy + c1, b2 * fy + c2
                xa, xb = x0, x1
                if wide:
                    lo, hi = _span(a0, e0, float(x0), float(x1))
                    lo, hi = _span(a1, e1, lo, hi)
                    lo, hi = _span(a2, e2, lo, hi)
                    if not lo <= hi:
                        continue
                    xa, xb = int(np.ceil(lo)), int(np.floor(hi))
                row = y * width
                zy = db * fy + dc
                for x in range(xa, xb + 1):  # branch-free: coverage of small triangles is random
                    fx = float(x)
                    z = da * fx + zy
                    old = depth[row + x]
                    win = (a0 * fx + e0 >= 0.0) & (a1 * fx + e1 >= 0.0) & (a2 * fx + e2 >= 0.0) & (z > old)
                    depth[row + x] = z if win else old
                    tri[row + x] = f if win else tri[row + x]
    return 0


@nb.njit(inline="always", nogil=True, cache=True, error_model="numpy")
def _span(a, e, lo, hi):
    """[lo, hi] cut to where a·x + e ≥ 0, a pixel wider on the cut side (empty: lo > hi)."""
    if a > 0.0:
        return max(lo, -e / a - 1.0), hi
    if a < 0.0:
        return lo, min(hi, -e / a + 1.0)
    return (lo, hi) if e >= 0.0 else (1.0, 0.0)


@nb.njit(nogil=True, cache=True, error_model="numpy")
def resolve_range(tri, vw, faces, tri_obj, tri_prim, origin, d, first, end, t, obj, prim, u, v):
    """Pixels [first, end): each one's hit on its triangle `tri[p]` (`CameraHits.triangles`;
    vw, faces, tri_obj, tri_prim: the CameraHits tables), intersected in float32 with the pixel's own camera ray
    (origin the camera's position, unit direction: t is the ray distance), or a miss. The
    Moeller–Trumbore test factored around the origin-relative corner C = v0 − o and the normal
    Ng = (v2 − v0) × (v0 − v1), as Embree's Moeller intersector factors it (u = (C × d)·(v2 − v0)
    / Ng·d, v = (C × d)·(v0 − v1) / Ng·d, t = Ng·C / Ng·d): the same roundings of the inputs. (The
    textbook factoring gave u, v up to 1.5e-3 from Embree's on the bunny; this one 7e-4.)"""
    o0, o1, o2 = origin[0], origin[1], origin[2]
    for p in range(first, end):
        f = tri[p]
        if f < 0:
            t[p], obj[p], prim[p], u[p], v[p] = np.inf, -1, -1, 0.0, 0.0
            continue
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        p0, p1, p2 = vw[i0, 0], vw[i0, 1], vw[i0, 2]
        e10, e11, e12 = p0 - vw[i1, 0], p1 - vw[i1, 1], p2 - vw[i1, 2]  # v0 − v1
        e20, e21, e22 = vw[i2, 0] - p0, vw[i2, 1] - p1, vw[i2, 2] - p2  # v2 − v0
        n0, n1, n2 = e21 * e12 - e22 * e11, e22 * e10 - e20 * e12, e20 * e11 - e21 * e10  # e2 × e1
        d0, d1, d2 = d[p, 0], d[p, 1], d[p, 2]
        c0, c1, c2 = p0 - o0, p1 - o1, p2 - o2
        r0, r1, r2 = c1 * d2 - c2 * d1, c2 * d0 - c0 * d2, c0 * d1 - c1 * d0  # C × d
        inv = np.float32(1.0) / (n0 * d0 + n1 * d1 + n2 * d2)
        t[p] = (n0 * c0 + n1 * c1 + n2 * c2) * inv
        u[p] = (r0 * e20 + r1 * e21 + r2 * e22) * inv
        v[p] = (r0 * e10 + r1 * e11 + r2 * e12) * inv
        obj[p], prim[p] = tri_obj[f], tri_prim[f]


@nb.njit(nogil=True, cache=True, parallel=True)
def _resolve(tri, vw, faces, tri_obj, tri_prim, origin, d, t, obj, prim, u, v):
    """resolve_range over all pixels, in chunks on numba's threads."""
    n = tri.shape[0]
    chunks = (n + 16383) // 16384
    for c in nb.prange(chunks):
        resolve_range(tri, vw, faces, tri_obj, tri_prim, origin, d, c * 16384, min(n, c * 16384 + 16384), t, obj, prim, u, v)


def _morton_order(points: np.ndarray) -> np.ndarray:
    """Indices that sort points along a Z-order curve (10 bits per axis over their bounds)."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    lo, hi = points.min(axis=0), points.max(axis=0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-30) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


class CameraHits:
    """Rasterises a pinhole camera's closest static hits (what `RtcAccel.intersect_static` traces
    for the camera rays). The static triangles are kept in world space (float32, as Embree has
    them) with each one's object and global triangle row; per frame they go to camera space."""

    def __init__(self, objects, tri_offsets: np.ndarray):
        vw, faces, tri_obj, tri_prim = [], [], [], []
        base = 0
        for k, o in enumerate(objects):
            if o.is_dynamic:
                continue
            nf = len(o.mesh.faces)
            vw.append(o.pose.apply(o.mesh.vertices).astype(np.float32))  # Embree's static vertex buffer
            faces.append(np.asarray(o.mesh.faces, np.int64) + base)
            tri_obj.append(np.full(nf, k, np.int32))
            tri_prim.append(int(tri_offsets[k]) + np.arange(nf, dtype=np.int32))
            base += len(o.mesh.vertices)
        vertices = np.concatenate(vw) if vw else np.zeros((0, 3), np.float32)
        faces = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
        # triangles in Morton order of their centroids, vertices in order of first use: whatever the
        # camera, a band's triangles and their vertices are then near each other in memory (in mesh
        # order, reading them was cache misses: 3 of the 7 ms of paper-static's bunnies)
        order = _morton_order(vertices[faces].mean(axis=1))
        faces = faces[order]
        used, first = np.unique(faces.ravel(), return_index=True)
        renumber = np.empty(len(vertices), np.int64)
        renumber[used[np.argsort(first)]] = np.arange(len(used))
        self.vertices = np.ascontiguousarray(vertices[used[np.argsort(first)]])
        self.faces = np.ascontiguousarray(renumber[faces].astype(np.int32))
        self.tri_obj = np.concatenate(tri_obj)[order] if tri_obj else np.zeros(0, np.int32)
        self.tri_prim = np.concatenate(tri_prim)[order] if tri_prim else np.zeros(0, np.int32)
        nf = len(self.faces)
        self._coef = np.empty((nf, 12))
        self._box = np.empty((nf, 4), np.int64)
        self._vc = np.empty((len(self.vertices), 3))
        self._depth = self._tri = None

    @staticmethod
    def check(camera) -> None:
        """Raise CameraHitsUnsupported unless this camera can be rasterised."""
        if np.any(camera.dist != 0):
            raise CameraHitsUnsupported("camera.dist: lens distortion is not rasterised (its pixel rays "
                                        "are not images of straight lines); trace the camera rays instead")

    def triangles(self, camera) -> np.ndarray:
        """(H·W,) int32: the row in `faces` of each pixel's closest static triangle, −1 for none
        (a buffer this object reuses)."""
        self.check(camera)
        K, w, h = camera.K, camera.width, camera.height
        npix = w * h
        if self._tri is None or len(self._tri) != npix:
            self._depth, self._tri = np.empty(npix), np.empty(npix, np.int32)
        _to_camera(self.vertices, np.asarray(camera.pose.R, np.float64), np.asarray(camera.pose.t, np.float64), self._vc)
        _setup(self._vc, self.faces, K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, self._coef, self._box)
        start, ids = _bin(self._box, (h + BAND_ROWS - 1) // BAND_ROWS)
        _raster(self._coef, self._box, start, ids, w, h, self._depth, self._tri)
        return self._tri

    def hits(self, camera, d: np.ndarray, out: Hits | None = None) -> Hits:
        """The static hits of the camera's pixel rays: origin the camera's position in float32,
        directions d ((H·W, 3) float32, row-major, as `PinholeCamera.rays_into` writes them),
        into `out` (or new arrays)."""
        n = camera.width * camera.height
        if d.shape != (n, 3) or d.dtype != np.float32:
            raise ValueError(f"d: expected ({n}, 3) float32 camera ray directions (one per pixel), got {d.shape} {d.dtype}")
        if out is not None and len(out.t) != n:
            raise ValueError(f"out: expected hits for {n} pixels, got {len(out.t)}")
        tri = self.triangles(camera)
        out = out if out is not None else empty_hits(n)
        _resolve(tri, self.vertices, self.faces, self.tri_obj, self.tri_prim, camera.pose.t.astype(np.float32), d, out.t, out.obj, out.prim, out.u, out.v)
        return out
