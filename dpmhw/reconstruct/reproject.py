"""Late reprojection: the last rendered native frame, moved to newer object poses right before a present.

The frame thread calls `Reprojector.capture` once per rendered frame: the moving objects' lit
pixels are compacted into a list (pixel, object, model-space point, colour), so that a present
costs in proportion to them, not to the frame. The present thread calls `Reprojector.present`
with each photon window's predicted poses; it draws into the reprojector's own frames in turn
and copies from the capture only the boxes that changed since a frame's last present
(`Reprojector.reproject` and `reproject_windows` draw into the caller's frame instead):

1. `out` = the captured image, with the captured moving pixels replaced by the *plate*: the last
   colour each pixel showed while it showed a static object or the background (black where it
   never did: the projector's dark);
2. every compacted point is moved by its object's pose change, projected with the lens
   distortion, and splatted to the nearest pixel centre with a z-test (against the other points
   and against the static surfaces' last depth: a static object in front hides it);
3. runs of up to `GAP_MAX_PX` pixels that no point reached, between two covered pixels whose
   points were neighbours at capture, are filled along rows, then along columns: where the two
   ends lie at the same depth (within `DEPTH_STEP_REL`) the run is a crack of magnification and
   takes the colours interpolated between them; across a depth step the run is surface the
   nearer end hid at capture (a disocclusion) and takes the farther end's colour, which
   continues that surface.

Model-space points come from the G-buffer's depth (camera z, as `render.gbuffer` and
`reconstruct.guides` define it) along each pixel's ray through its centre, lens distortion
inverted (`PinholeCamera.ideal_points`): camera point = z·(x, y, 1), model point = pose⁻¹ ·
world point. Only geometry moves: shading, highlights and shadows stay as they were rendered.

Poses equal to the capture's give the captured image bit for bit (nothing moves, nothing is
splatted). Every per-pixel step is a serial numba kernel that releases the GIL: the present
thread runs beside the frame thread's parallel kernels and must not wait for their threads.
The projection of the points is one branch-free loop over contiguous arrays (it vectorises at
whatever SIMD width the CPU has); the splat and the fills are scattered writes.
"""

from __future__ import annotations

import math
import threading
import time
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Sequence

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core.extending import intrinsic

from dpmhw.render.distortion import distort_inline
from dpmhw.transforms import Pose

__all__ = ["Capture", "ReprojectStats", "Reprojector", "GAP_MAX_PX", "DEPTH_STEP_REL", "PRESENT_FRAMES"]

GAP_MAX_PX = 8  # longest run of unreached pixels filled between two splats (a rotation of a few degrees opens ~5)
DEPTH_STEP_REL = 0.02  # ends of a run further apart in depth than this: a disocclusion, not a crack
STATIC_Z_REL = 1e-3  # a static surface nearer than a moved point by more than this fraction hides it
NEAR_Z = 1e-4  # a point this close to the projector's plane (metres) or behind it is dropped
PRESENT_FRAMES = 3  # `present`'s frames, used in turn: one is shown, the one before may still be read by a sink


@dataclass(frozen=True)
class Capture:
    """One rendered frame, ready to be moved: the image, the poses it was rendered at, and the
    moving objects' lit pixels as flat arrays (n = `lit`), each object's points one run
    (`segments[o]:segments[o + 1]`)."""

    image: np.ndarray  # (H, W, 3) uint8, the caller's (not copied: it must not change afterwards)
    R: np.ndarray  # (objects, 3, 3) rotations the image was rendered at
    t: np.ndarray  # (objects, 3) translations
    segments: np.ndarray  # (objects + 1,) int64 each object's run of points
    pixel: np.ndarray  # (n,) int32 flat pixel index
    point: np.ndarray  # (3, n) float32 model-space points (x, y, z rows: contiguous for the projection)
    colour: np.ndarray  # (n, 3) uint8 its colour in the image
    plate: np.ndarray  # (n, 3) uint8 the plate's colour at its pixel (what shows when it leaves)
    box: tuple[int, int, int, int]  # (y0, y1, x0, x1) the lit box it was compacted from
    background: np.ndarray | None = None  # what `image` shows outside `box` (see Reprojector.capture)

    @property
    def lit(self) -> int:
        return int(self.pixel.shape[0])


@dataclass(frozen=True)
class ReprojectStats:
    """What one reprojection did, in pixels (points: the capture's compacted lit pixels)."""

    lit: int  # points in the capture
    moved: int  # pixels a point landed on (after the z-test)
    dropped: int  # points off the frame, behind the projector, or behind a static surface
    holes: int  # crack pixels filled by interpolation (magnification)
    disoccluded: int  # pixels of newly visible surface, filled from the farther side
    vacated: int  # captured moving pixels no point or fill covers now: they show the plate
    box: tuple[int, int, int, int] | None  # (y0, y1, x0, x1) the points landed in (None: none did)


@intrinsic
def _trailing_zeros(typingctx, x):
    """The number of trailing zero bits of x ≠ 0 (one instruction: tzcnt)."""
    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], ir.Constant(ir.IntType(1), 1))
    return x(x), codegen


@nb.njit(_nrt=False)
def _shift_right(r, out):
    """out[i] = r[i − 1] for 1 ≤ i < len(r), out[0] = r[0]."""
    out[0] = r[0]
    for i in range(1, r.shape[0]):
        out[i] = r[i - 1]


# ---- kernels ---------------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _count(ids, depth, dynamic, W, y0, y1, x0, x1, counts):
    """Moving lit pixels of the box per object into `counts`; returns −1 − p for the first pixel
    p whose id names no object, else 0."""
    n_obj = dynamic.shape[0]
    for y in range(y0, y1):
        row = np.uint64(y * W + x0)
        for i in range(x1 - x0):
            p = row + np.uint64(i)
            o = ids[p]
            if o >= n_obj:
                return -1 - np.int64(p)
            if o >= 0 and dynamic[o] and math.isfinite(depth[p]) and depth[p] > 0.0:
                counts[o] += 1
    return 0


@nb.njit(cache=True, nogil=True)
def _compact(image, ids, depth, ideal, dynamic, A, b, W, y0, y1, x0, x1, plate, plate_z, cursor,
             pixel, point, colour, back):
    """Moving lit pixels → the capture's arrays, each object's from its `cursor` on (so each
    object's points are one run); every other pixel of the box → the plate."""
    for y in range(y0, y1):
        row = np.uint64(y * W + x0)
        for j in range(x1 - x0):
            p = row + np.uint64(j)
            o = ids[p]
            z = depth[p]
            if o >= 0 and dynamic[o]:
                if not (math.isfinite(z) and z > 0.0):
                    continue
                k = np.uint64(cursor[o])
                cursor[o] = k + np.uint64(1)
                cx, cy = z * ideal[p, 0], z * ideal[p, 1]
                for i in range(3):
                    point[i, k] = A[o, i, 0] * cx + A[o, i, 1] * cy + A[o, i, 2] * z + b[o, i]
                    colour[k, i] = image[p, i]
                    back[k, i] = plate[p, i]
                pixel[k] = p
            else:
                for i in range(3):
                    plate[p, i] = image[p, i]
                plate_z[p] = z if o >= 0 and math.isfinite(z) and z > 0.0 else np.inf


@nb.njit(cache=True, nogil=True)
def _project(px, py, pz, M, fx, fy, cx, cy, dist, W, H, dest, zout, col):
    """Points of one object moved by its model→camera matrix `M` ((12,) float32, row-major
    3×4) and projected: `dest` the nearest pixel (−1: off the frame or behind the projector),
    `col` its column (−1 likewise), `zout` the camera depth. float32 throughout, no branch, no
    scattered write, no reduction (a min/max in this loop stops LLVM from vectorising it:
    `_bounds` takes them after), contiguous arrays: the loop vectorises at the CPU's SIMD width."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    a0, a1, a2, a3, a4, a5 = M[0], M[1], M[2], M[3], M[4], M[5]
    a6, a7, a8, a9, a10, a11 = M[6], M[7], M[8], M[9], M[10], M[11]
    one, two, zero, half = np.float32(1.0), np.float32(2.0), np.float32(0.0), np.float32(0.5)
    near, Wf, Hf, Wi = np.float32(NEAR_Z), np.float32(W), np.float32(H), np.int32(W)
    for k in range(px.shape[0]):
        m0, m1, m2 = px[k], py[k], pz[k]
        X = a0 * m0 + a1 * m1 + a2 * m2 + a3
        Y = a4 * m0 + a5 * m1 + a6 * m2 + a7
        Z = a8 * m0 + a9 * m1 + a10 * m2 + a11
        iz = one / max(Z, near)
        xd, yd = distort_inline(X * iz, Y * iz, k1, k2, p1, p2, k3, one, two)
        u = fx * xd + cx + half  # pixel (0, 0) covers [−0.5, 0.5)²: the nearest centre is ⌊u⌋
        v = fy * yd + cy + half
        inside = (Z > near) & (u >= zero) & (u < Wf) & (v >= zero) & (v < Hf)
        ui = np.int32(u) if inside else np.int32(-1)  # u ≥ 0: truncation is ⌊u⌋
        vi = np.int32(v) if inside else np.int32(0)
        dest[k] = vi * Wi + ui if inside else np.int32(-1)
        col[k] = ui
        zout[k] = Z


@nb.njit(cache=True, nogil=True)
def _bounds(dest, col, W, H):
    """The box (y0, y1, x0, x1) of the projected points' pixels (`_project`'s dest and col),
    empty (H, 0, W, 0) when none is on the frame: rows from the least and greatest pixel index,
    columns from `col`."""
    big = np.int32(2**31 - 1)
    d0, d1, x0, x1 = big, np.int32(-1), big, np.int32(-1)
    for k in range(dest.shape[0]):
        d, x = dest[k], col[k]
        dm = d if d >= 0 else big
        xm = x if x >= 0 else big
        d0 = dm if dm < d0 else d0
        d1 = d if d > d1 else d1
        x0 = xm if xm < x0 else x0
        x1 = x if x > x1 else x1
    if d1 < 0:
        return np.int64(H), np.int64(0), np.int64(W), np.int64(0)
    return np.int64(d0 // W), np.int64(d1 // W + 1), np.int64(x0), np.int64(x1 + 1)


# The fill helpers below are compiled without numba's reference counting (`_nrt=False`: they
# allocate nothing and outlive none of their arrays). With it, each call from the sweep counted
# its six or seven arrays' references up and down, atomically: at a 40-ms horizon (a thousand
# and more runs a window) that was 8 % of a pattern present.
@nb.njit(_nrt=False)
def _put(out, q, r, g, b, ch0, ch1):
    """Channels ch0 to ch1 − 1 of pixel q = those of (r, g, b); the others are not touched."""
    for c in range(ch0, ch1):
        out[q, c] = r if c == 0 else (g if c == 1 else b)


@nb.njit(_nrt=False)
def _fill_run(qa, qb, step, g, pixel, src, zbuf, cover, s2, plate_z, W, ch0, ch1, out):
    """Fill the g pixels between covered pixels qa and qb (q = qa + i·step) that nothing covers
    yet, if the points they show were neighbours at capture; returns (cracks, disoccluded).
    Channels ch0 to ch1 − 1 are written; the ends' colours are read back from `out`. A filled
    pixel gets a depth and a point (the nearer end's), so that it can end a run along the other
    axis. `cover`: s2 splatted, s2 + 1 filled in this reprojection."""
    ka, kb = np.uint64(src[qa]), np.uint64(src[qb])
    d = abs(pixel[kb] - pixel[ka])
    if d > 1 and abs(d - np.int64(W)) > 1:  # (at the frame's side edges a row's end and the next row's start pass too)
        return 0, 0  # something lay between them at capture too: a real gap
    za, zb = zbuf[qa], zbuf[qb]
    crack = abs(za - zb) <= DEPTH_STEP_REL * min(za, zb)
    qf, kf, zf = (qa, ka, za) if za > zb else (qb, kb, zb)
    holes = 0
    dis = 0
    for i in range(1, g + 1):
        q = qa + np.uint64(i) * step
        if cover[q] >> 1 == s2 >> 1:
            continue
        if crack:
            t = i / (g + 1.0)
            z = za + t * (zb - za)
            if plate_z[q] < z * (1.0 - STATIC_Z_REL):
                continue
            r = np.uint8(out[qa, 0] + t * (np.float32(out[qb, 0]) - out[qa, 0]) + 0.5)
            gg = np.uint8(out[qa, 1] + t * (np.float32(out[qb, 1]) - out[qa, 1]) + 0.5)
            bb = np.uint8(out[qa, 2] + t * (np.float32(out[qb, 2]) - out[qa, 2]) + 0.5)
            _put(out, q, r, gg, bb, ch0, ch1)
            src[q] = ka if t < 0.5 else kb
            holes += 1
        else:
            z = zf
            if plate_z[q] < z * (1.0 - STATIC_Z_REL):
                continue
            _put(out, q, out[qf, 0], out[qf, 1], out[qf, 2], ch0, ch1)
            src[q] = kf
            dis += 1
        zbuf[q] = z
        cover[q] = s2 + 1
    return holes, dis


@nb.njit(_nrt=False)
def _gap_above(cover, q, rows_above, W, s2):
    """g ≥ 2 for the covered pixel q − g·W nearest above a gap over q (at most GAP_MAX_PX rows,
    none of them above the box), else 0."""
    for g in range(2, min(GAP_MAX_PX + 1, rows_above) + 1):
        if cover[q - np.uint64(g) * W] >> 1 == s2 >> 1:
            return g
    return 0


@nb.njit(nogil=True, cache=True, _nrt=False)
def _row_run(q, g, rows_above, pixel, src, zbuf, cover, s2, plate_z, W, ch0, ch1, out):
    """Fill the row run between splats q − g and q, then the column run above each pixel it
    filled; returns (cracks, disoccluded). Called only where a gap was found: a call passes
    its arrays' references (atomic reference counts), too dear for every pixel."""
    holes, dis = _fill_run(q - np.uint64(g), q, np.uint64(1), g - 1, pixel, src, zbuf, cover, s2, plate_z, W, ch0, ch1, out)
    for j in range(1, g):
        a = q - np.uint64(g) + np.uint64(j)
        if rows_above > 0 and cover[a] == s2 + 1 and cover[a - W] >> 1 != s2 >> 1:
            ga = _gap_above(cover, a, rows_above, W, s2)
            if ga:
                h, d = _fill_run(a - np.uint64(ga) * W, a, W, ga - 1, pixel, src, zbuf, cover, s2, plate_z, W, ch0, ch1, out)
                holes += h
                dis += d
    return holes, dis


@nb.njit(cache=True, nogil=True)
def _base(image, ch, out, W, box):
    """out = image inside `box` (y0, y1, x0, x1), flat uint8 arrays (H*W*3); only channel `ch`
    of each pixel when ch ≥ 0. Plain loops over contiguous bytes (numba's slice assignment
    copies element by element, a stride-3 loop does not vectorise): the channel is blended in
    with a per-channel byte mask, so the other channels are read and stored back unchanged."""
    y0, y1, x0, x1 = box
    rows, a, e = y1 - y0, 3 * (y0 * W + x0), 3 * (y0 * W + x1)  # the first row's bytes
    if x0 == 0 and x1 == W:  # whole rows: one run
        rows, e = 1, 3 * y1 * W
    m0 = np.uint8(255 if ch == 0 else 0)
    m1 = np.uint8(255 if ch == 1 else 0)
    m2 = np.uint8(255 if ch == 2 else 0)
    for r in range(rows):
        o = 3 * r * W
        src, dst = image[a + o:e + o], out[a + o:e + o]  # indices from 0: no wrap-around test a byte
        if ch < 0:
            for i in range(dst.shape[0]):
                dst[i] = src[i]
            continue
        for p in range(dst.shape[0] // 3):
            i = 3 * p
            dst[i] = dst[i] ^ ((dst[i] ^ src[i]) & m0)
            dst[i + 1] = dst[i + 1] ^ ((dst[i + 1] ^ src[i + 1]) & m1)
            dst[i + 2] = dst[i + 2] ^ ((dst[i + 2] ^ src[i + 2]) & m2)


@nb.njit(cache=True, nogil=True)
def _splat(pixel, back, colour, dest, zout, plate_z, W, y0, y1, x0, x1, ch0, ch1, zbuf, src, cover, s2, flags, shift, out,
           stats):
    """Splat the points with a z-test into channels ch0 to ch1 − 1 of `out`; then, in one
    row-major sweep of the splats' box (y0, y1, x0, x1), fill the runs between splats along the
    row, and along the column above each splat and each pixel a row run filled (a crack row
    crossing a crack column closes too); then give the captured moving pixels that nothing
    covers the plate. When a pixel looks up its column, every pixel above it is final: rows
    above are done, and only this pixel's run fills its column. The fills read only covered
    pixels, so the plate can go in last. `cover`: s2 where a point landed, s2 + 1 where a run
    was filled (older values: neither). `flags` (W + 8 bytes) and `shift` (W stamps): the
    sweep's scratch rows. stats: moved, dropped, holes, disoccluded, vacated."""
    n = pixel.shape[0]
    Wu = np.uint64(W)
    flat, colf, backf = out.reshape(-1), colour.reshape(-1), back.reshape(-1)  # constant strides: no multiply a store
    three = np.uint64(3)
    moved = dropped = 0
    for k in range(n):
        if dest[k] < 0:
            dropped += 1
            continue
        q = np.uint64(dest[k])
        z = zout[k]
        if plate_z[q] < z * (1.0 - STATIC_Z_REL):
            dropped += 1
            continue
        if cover[q] != s2:
            cover[q] = s2
            moved += 1
        elif zbuf[q] <= z:
            continue
        zbuf[q] = z
        src[q] = k
        for c in range(ch0, ch1):  # one byte store a channel: no read-modify-write of the others
            flat[three * q + np.uint64(c)] = colf[np.uint64(3 * k + c)]
    holes = dis = 0
    sid = s2 >> 1
    nx = max(x1 - x0, 0)  # (no point landed: an empty box)
    one = np.uint64(1)
    s, s1, bit = np.int32(s2), np.int32(s2 + 1), np.int32(1)  # int32, not numba's int64: twice the lanes a vector
    words = flags[:(nx + 7) // 8 * 8].view(np.uint64)
    for i in range(nx, words.shape[0] * 8):
        flags[i] = 0
    for y in range(y0, y1):
        p = y * W + x0
        row = np.uint64(p)
        up = y > y0
        r = cover[p:p + nx]
        if p == 0:  # the box starts at the frame's first pixel: nothing before it
            _shift_right(r, shift)
        left = cover[p - 1:p - 1 + nx] if p > 0 else shift[:nx]  # left[i]: the pixel before r[i]
        above = cover[p - W:p - W + nx] if up else r
        fill_up = np.int32(-1) if up else np.int32(0)
        # the pixels with work: a splat that starts a run of the row, or with neither splat nor fill
        # above it; one branch-free pass over the row (it vectorises), then only the flagged pixels,
        # eight flags a word (nearly all words are 0)
        for i in range(nx):
            flags[i] = np.uint8((r[i] == s) & ((left[i] != s) | (((above[i] | bit) != s1) & (fill_up != 0))))
        flags[0] = r[0] == s  # the box's first column has no run to its left
        for k in range(words.shape[0]):
            m = words[k]
            while m:
                i = 8 * k + np.int64(_trailing_zeros(m) >> np.uint64(3))
                m &= m - np.uint64(1)
                q = row + np.uint64(i)  # unsigned indices: no negative-index wrap on every access
                if not (i > 0 and cover[q - one] == s2):  # a splat after a gap in the row: look back for the splat before it
                    for g in range(2, min(GAP_MAX_PX + 1, i) + 1):
                        if cover[q - np.uint64(g)] == s2:
                            h, d = _row_run(q, g, y - y0, pixel, src, zbuf, cover, s2, plate_z, Wu, ch0, ch1, out)
                            holes += h
                            dis += d
                            break
                if up and cover[q - Wu] >> 1 != sid:
                    g = _gap_above(cover, q, y - y0, Wu, s2)
                    if g:
                        h, d = _fill_run(q - np.uint64(g) * Wu, q, Wu, g - 1, pixel, src, zbuf, cover, s2, plate_z, Wu, ch0,
                                         ch1, out)
                        holes += h
                        dis += d
    vacated = 0
    for k in range(n):
        q = np.uint64(pixel[k])
        if cover[q] >> 1 != sid:
            vacated += 1
            for c in range(ch0, ch1):
                flat[three * q + np.uint64(c)] = backf[np.uint64(3 * k + c)]
    stats[0], stats[1], stats[2], stats[3], stats[4] = moved, dropped, holes, dis, vacated


@nb.njit(cache=True, nogil=True)
def _reproject_windows(img, dst, base_box, M, M_bits, R, t, cap_R, cap_t, channels, full_base, segments, moving, px, py, pz, fx,
                       fy, cx, cy, dist, W, H, arrays, plate_z, sid, moves, same, groups, stats, boxes, scratch, plan, g_first,
                       g_end):
    """The photon windows of one present. With `plan`: which windows move and which splats they
    make (written to moves, same, groups), and `dst` = the captured image inside `base_box` (all
    channels at once when `full_base`, else each window's own channel; outside it `dst` holds
    the same already). Then the splats groups[g_first:g_end] (of those planned), each on this
    call's `scratch`; splats of distinct groups are independent, so two threads may make them
    at once, each on its own scratch.

    Window w moves (`moves[w]`) when its poses (R[w], t[w]) differ from the capture's (cap_R,
    cap_t) for an object of `moving`; its points are then moved by `M[w]` and splatted into its
    channel (`channels[w]`, −1: all). A window whose matrices are the previous window's bit for
    bit (`M_bits`, M's bytes as uint32) and whose channel follows its channel joins its splat,
    which writes both channels: the bits each window's own splat would give. A group is (first
    window, end); (−1, −1) after the last. `arrays`: the capture's (pixel, plate, colour);
    `scratch`: (zbuf, src, cover, dest, zout, col, flags, shift); window w stamps `cover` with
    2·(sid + w). stats[w]: moved, dropped, holes, disoccluded, vacated; boxes[w]: the splats'
    (y0, y1, x0, x1)."""
    pixel, plate, colour = arrays
    zbuf, src, cover, dest, zout, col, flags, shift = scratch
    out = dst.reshape(-1, 3)
    n_win = channels.shape[0]
    if plan:
        for w in range(n_win):
            moves[w] = False
            same[w] = w > 0
            for o in moving:
                for i in range(3):
                    moves[w] |= t[w, o, i] != cap_t[o, i]
                    for j in range(3):
                        moves[w] |= R[w, o, i, j] != cap_R[o, i, j]
                if w > 0:
                    for i in range(12):
                        same[w] &= M_bits[w, o, i] == M_bits[w - 1, o, i]
        if full_base:
            _base(img, np.int64(-1), dst, W, base_box)  # not a literal: numba would compile _base once more for it
        else:  # each window's channel (a splat writes only its own channels: the order does not matter)
            for w in range(n_win):
                _base(img, channels[w], dst, W, base_box)
        n, w = 0, 0
        while w < n_win:
            if not moves[w]:
                w += 1
                continue
            e = w + 1  # windows w to e − 1: one pose, consecutive channels
            while e < n_win and moves[e] and same[e] and channels[e] == channels[e - 1] + 1:
                e += 1
            groups[n, 0], groups[n, 1] = w, e
            n += 1
            w = e
        for g in range(n, n_win):
            groups[g, 0], groups[g, 1] = -1, -1
    for g in range(g_first, min(g_end, n_win)):
        w, e = groups[g, 0], groups[g, 1]
        if w < 0:
            break
        ch = channels[w]
        for o in moving:
            a, b = segments[o], segments[o + 1]
            _project(px[a:b], py[a:b], pz[a:b], M[w, o], fx, fy, cx, cy, dist, W, H, dest[a:b], zout[a:b], col[a:b])
        y0, y1, x0, x1 = _bounds(dest, col, W, H)
        ch0, ch1 = (0, 3) if ch < 0 else (ch, channels[e - 1] + 1)  # the channels written
        _splat(pixel, plate, colour, dest, zout, plate_z, W, y0, y1, x0, x1, ch0, ch1, zbuf, src, cover, 2 * (sid + w),
               flags, shift, out, stats[w])
        for v in range(w, e):
            for i in range(5):
                stats[v, i] = stats[w, i]
            boxes[v, 0], boxes[v, 1], boxes[v, 2], boxes[v, 3] = y0, y1, x0, x1


class _Scratch:
    """One thread's buffers for a splat: per pixel, the z-buffer, the point each pixel shows and
    the stamp of the splat that covered it; per point (grown to the largest capture), where it
    lands; the sweep's two scratch rows."""

    def __init__(self, W: int, H: int):
        n = W * H
        self.zbuf = np.zeros(n, np.float32)  # per splat, valid where `cover` holds its stamp
        self.src = np.zeros(n, np.int32)  # the point a splatted pixel shows
        self.cover = np.zeros(n, np.int32)  # 2·id of the window that splatted the pixel, + 1: filled it
        self.flags = np.zeros(W + 8, np.uint8)  # a row's pixels with work (the splat's sweep), in whole words
        self.shift = np.zeros(W, np.int32)  # a row shifted by one pixel, for a box at the frame's first pixel
        self.dest, self.zout, self.col = np.empty(0, np.int32), np.empty(0, np.float32), np.empty(0, np.int32)

    def arrays(self, n: int) -> tuple:
        """The kernel's `scratch` for a capture of n points."""
        if self.dest.shape[0] < n:
            self.dest, self.zout, self.col = np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.int32)
        return self.zbuf, self.src, self.cover, self.dest[:n], self.zout[:n], self.col[:n], self.flags, self.shift


class _SplatHelper:
    """A second thread for a present's splats: a one-thread pool, as `ReconstructStage` keeps
    its helpers. The caller and the pool's thread take the splats in turn from one counter, each
    on its own scratch; a helper that has not begun when the caller has taken the last splat is
    cancelled, so a present never waits for it to be scheduled, only for a splat it has begun.
    Made by the first present that splits, whose thread starts the pool's thread here: it
    shares that thread's scheduling (on Linux a thread inherits its creator's policy and
    priority: the session's present thread is raised).

    The splats write distinct channels of one frame, a byte store per channel; a fill reads the
    other channels of its run's ends too, but uses only its own."""

    def __init__(self):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="reproject-helper")
        self._thread = self._pool.submit(threading.current_thread).result()  # started from this thread, now

    def share(self, fn, count: int) -> int:
        """fn(k, slot) for every k < count: on this thread (slot 0) and the helper's (slot 1).
        Returns the helper's CPU time in them (ns); re-raises its error."""
        lock, taken = threading.Lock(), [0]

        def take() -> int | None:
            with lock:
                k = taken[0]
                taken[0] = k + 1
            return k if k < count else None

        def helper() -> int:
            cpu_ns = 0
            while (k := take()) is not None:
                t0 = time.thread_time_ns()
                fn(k, 1)
                cpu_ns += time.thread_time_ns() - t0
            return cpu_ns

        begun = self._pool.submit(helper)
        try:
            while (k := take()) is not None:
                fn(k, 0)
        finally:
            with lock:
                taken[0] = count  # after an error here the helper takes nothing more
            helper_ns = 0 if begun.cancel() else begun.result()
        return helper_ns

    def close(self) -> None:
        self._pool.shutdown(wait=threading.current_thread() is not self._thread)


@dataclass
class _Frame:
    """One of `present`'s frames: the image, the background its last capture shared, and the box
    outside which it shows that background."""

    image: np.ndarray
    background: np.ndarray | None = None
    written: tuple[int, int, int, int] = (0, 0, 0, 0)


def _union(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """The bounding box of two (y0, y1, x0, x1) boxes; an empty one (y1 ≤ y0 or x1 ≤ x0) adds nothing."""
    if a[1] <= a[0] or a[3] <= a[2]:
        return tuple(b)
    if b[1] <= b[0] or b[3] <= b[2]:
        return tuple(a)
    return min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])


# ---- checks ----------------------------------------------------------------------------------------
def _poses(poses, n: int, name: str = "poses") -> tuple[np.ndarray, np.ndarray]:
    """`n` finite rigid poses as stacked R (n, 3, 3) and t (n, 3), or a ValueError naming the
    argument and the entry."""
    try:
        items = list(poses)
    except TypeError:
        raise ValueError(f"{name}: expected a sequence of {n} Pose, got {type(poses).__name__}") from None
    if len(items) != n:
        raise ValueError(f"{name}: expected one Pose per scene object ({n}), got {len(items)}")
    try:
        R = np.array([p.R for p in items], np.float64)
        t = np.array([p.t for p in items], np.float64)
        ok = R.shape == (n, 3, 3) and t.shape == (n, 3)
    except (AttributeError, TypeError, ValueError):
        ok = False
    if not ok:
        for i, p in enumerate(items):
            shapes = (np.shape(getattr(p, "R", None)), np.shape(getattr(p, "t", None)))
            if shapes != ((3, 3), (3,)):
                raise ValueError(f"{name}[{i}]: expected a Pose with R (3, 3) and t (3,), got {type(p).__name__}")
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        bad = ~(np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1))
        raise ValueError(f"{name}[{int(np.flatnonzero(bad)[0])}]: not finite")
    return R, t


def _array(a, name: str, dtype, size: int, shape: str) -> np.ndarray:
    if not isinstance(a, np.ndarray) or a.dtype != dtype or a.size != size:
        got = f"{a.dtype} {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
        raise ValueError(f"{name}: expected {shape} {np.dtype(dtype).name}, got {got}")
    return np.ascontiguousarray(a).reshape(-1)


class Reprojector:
    """Late reprojection for one projector (see the module docstring).

    camera : the native `PinholeCamera` (with its lens distortion)
    dynamic : per scene object, whether it moves (only those are reprojected)

    threads : 2: a present whose windows make two or three splats (a pattern-8bit present at
        each sub-frame's own poses) makes them on the calling thread and a helper thread at once
        (`_SplatHelper`): less wall time for more CPU (docs/reprojection.md); the same bits.

    `capture` belongs to one thread (the frame thread), `reproject` to one other (the present
    thread); each holds its own lock, so a second caller waits instead of corrupting state.
    `close` ends the helper thread (so does the Reprojector's collection).
    """

    def __init__(self, camera, dynamic: Sequence[bool], threads: int = 1):
        try:
            K = np.asarray(camera.K, np.float64)
            dist = np.asarray(camera.dist, np.float64).reshape(-1)
            W, H = int(camera.width), int(camera.height)
            cam_R, cam_t = np.asarray(camera.pose.R, np.float64), np.asarray(camera.pose.t, np.float64)
            ideal = camera.ideal_points()
        except (AttributeError, TypeError, ValueError):
            raise ValueError(f"camera: expected a PinholeCamera, got {type(camera).__name__}") from None
        if K.shape != (3, 3) or dist.shape != (5,) or W < 1 or H < 1 or cam_R.shape != (3, 3) or cam_t.shape != (3,) \
                or not all(np.isfinite(a).all() for a in (K, dist, cam_R, cam_t)):
            raise ValueError("camera: expected finite K (3, 3), dist (5,), pose and a size ≥ 1×1")
        if threads not in (1, 2):
            raise ValueError(f"threads: expected 1 or 2, got {threads!r}")
        flags = np.asarray(list(dynamic))
        if flags.ndim != 1 or flags.size == 0 or flags.dtype != np.bool_:
            raise ValueError(f"dynamic: expected one bool per scene object, got {list(dynamic)!r}")
        self.width, self.height = W, H
        self.dynamic = flags.copy()
        self.K, self.dist, self.cam_R, self.cam_t = K, dist, cam_R, cam_t
        self._ideal = ideal
        n = W * H
        self._plate = np.zeros((n, 3), np.uint8)  # last colour without a moving object in front
        self._plate_z = np.full(n, np.inf, np.float32)  # depth of the static surface there (inf: none seen)
        self._scratch = [_Scratch(W, H) for _ in range(threads)]  # a splat's buffers, one set per thread
        self._sid = 0
        self._helper: _SplatHelper | None = None  # started by the first present that splits
        self.last_helper_cpu_ns = 0  # the helper thread's CPU time in the last reprojection
        k = len(flags)  # per window of a present (at most 3): poses, matrices, channel, results
        self._R, self._t, self._M = np.empty((3, k, 3, 3)), np.empty((3, k, 3)), np.empty((3, k, 3, 4), np.float32)
        self._channels, self._moves, self._same = np.empty(3, np.int64), np.empty(3, np.bool_), np.empty(3, np.bool_)
        self._stats, self._boxes, self._groups = np.empty((3, 5), np.int64), np.empty((3, 4), np.int64), np.empty((3, 2), np.int64)
        self._intrinsics = (np.float32(K[0, 0]), np.float32(K[1, 1]), np.float32(K[0, 2]), np.float32(K[1, 2]),
                            dist.astype(np.float32))
        self._frames: list[_Frame | None] = [None] * PRESENT_FRAMES  # `present`'s own, made at first use
        self._turn = 0
        self._capture_lock = threading.Lock()
        self._present_lock = threading.Lock()

    def capture(self, image: np.ndarray, object_id: np.ndarray, depth: np.ndarray, poses: Sequence[Pose],
                box: tuple[int, int, int, int] | None = None, background: np.ndarray | None = None) -> Capture:
        """Compact the moving objects' lit pixels of `box` (the lit box; None: the whole frame)
        and update the plate there. `object_id`, `depth`: the native G-buffer's (H*W values).
        The capture keeps `image` itself: hand over a frame that is not written again.
        `background`: a frame (H*W*3 bytes, not written again either) that `image` equals
        outside `box`; captures that share it (the same object) let `present` copy only their
        boxes into its frames, not the whole frame."""
        W, H = self.width, self.height
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != (H, W, 3) \
                or not image.flags.c_contiguous:
            got = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
            raise ValueError(f"image: expected a C-contiguous ({H}, {W}, 3) uint8 array, got {got}")
        ids = _array(object_id, "object_id", np.int32, H * W, f"({H * W},)")
        z = _array(depth, "depth", np.float32, H * W, f"({H * W},)")
        R, t = _poses(poses, len(self.dynamic))
        y0, y1, x0, x1 = self._box(box)
        if background is not None and (not isinstance(background, np.ndarray) or background.dtype != np.uint8
                                       or background.size != H * W * 3):
            got = f"{background.dtype} {background.shape}" if isinstance(background, np.ndarray) else type(background).__name__
            raise ValueError(f"background: expected None or {H * W * 3} uint8 values, got {got}")
        A = np.einsum("kji,jl->kil", R, self.cam_R)  # camera → model: R_kᵀ (R_cam·c + t_cam − t_k)
        b = np.einsum("kji,kj->ki", R, self.cam_t - t)
        with self._capture_lock:
            counts = np.zeros(len(self.dynamic), np.int64)
            err = _count(ids, z, self.dynamic, W, y0, y1, x0, x1, counts)
            if err < 0:
                p = -1 - err
                raise ValueError(f"object_id: pixel {p} names object {ids[p]}, the scene has {len(self.dynamic)}")
            segments = np.concatenate([[0], np.cumsum(counts)])
            n = int(segments[-1])
            pixel, point = np.empty(n, np.int32), np.empty((3, n), np.float32)
            colour, back = np.empty((n, 3), np.uint8), np.empty((n, 3), np.uint8)
            _compact(image.reshape(-1, 3), ids, z, self._ideal, self.dynamic, A, b, W, y0, y1, x0, x1, self._plate,
                     self._plate_z, segments[:-1].copy(), pixel, point, colour, back)
        return Capture(image, R, t, segments, pixel, point, colour, back, (y0, y1, x0, x1), background)

    def reproject(self, capture: Capture, poses: Sequence[Pose], out: np.ndarray, channel: int | None = None) -> ReprojectStats:
        """`out` = the capture moved to `poses` (only channel `channel` of it when given)."""
        return self.reproject_windows(capture, [(poses, channel)], out)[0]

    def reproject_windows(self, capture: Capture, windows: Sequence[tuple[Sequence[Pose], int | None]],
                          out: np.ndarray) -> list[ReprojectStats]:
        """`out` = the capture moved to each window's poses, in the window's channel: one window
        of all channels (channel None), or windows of distinct channels 0–2 (a present's
        sub-frames). On one thread, one kernel call for all of them, so the present thread
        releases the GIL once; with `threads` 2 and two or three splats, one call to plan them and
        one per splat, shared with the helper thread. Each window gives the same bits as its own
        `reproject`."""
        W, H = self.width, self.height
        self._check(capture)
        if not isinstance(out, np.ndarray) or out.dtype != np.uint8 or out.shape != (H, W, 3) or not out.flags.c_contiguous \
                or not out.flags.writeable:
            got = f"{out.dtype} {out.shape}" if isinstance(out, np.ndarray) else type(out).__name__
            raise ValueError(f"out: expected a writable C-contiguous ({H}, {W}, 3) uint8 array, got {got}")
        if np.may_share_memory(out, capture.image):
            raise ValueError("out: is the capture's own image (the capture must stay as it was rendered)")
        windows, channels = self._windows(windows)
        with self._present_lock:
            return self._reproject(capture, windows, channels, out, (0, H, 0, W))[0]

    def present(self, capture: Capture, windows: Sequence[tuple[Sequence[Pose], int | None]], helper: bool = True
                ) -> tuple[np.ndarray, list[ReprojectStats]]:
        """The capture moved to each window's poses (as `reproject_windows`), in the next of
        `PRESENT_FRAMES` frames of this Reprojector's own: (frame, stats). A frame stays as it is
        until `PRESENT_FRAMES` − 1 more presents (a sink may still read it). The windows cover
        every channel: one window of all channels, or three of channels 0, 1 and 2. `helper`:
        whether the splats may be shared with the helper thread (with `threads` 2).

        Only what differs from what the frame held is copied from the capture: with a
        `background` both captures share, the bounding box of this capture's box, the last
        one's and what the last reprojection into the frame wrote (a present's cost then
        follows the lit pixels, not the frame); otherwise the whole frame."""
        W, H = self.width, self.height
        self._check(capture)
        windows, channels = self._windows(windows)
        if sorted(channels) not in ([-1], [0, 1, 2]):
            raise ValueError(f"windows: a present covers every channel: one window of all (None) or three of 0, 1 and 2, "
                             f"got channels {[None if c < 0 else c for c in channels]}")
        with self._present_lock:
            self._turn = (self._turn + 1) % PRESENT_FRAMES
            frame = self._frames[self._turn]
            if frame is None:
                frame = self._frames[self._turn] = _Frame(np.zeros((H, W, 3), np.uint8))
            same = capture.background is not None and frame.background is capture.background
            base_box = _union(frame.written, capture.box) if same else (0, H, 0, W)
            frame.background = None  # (what the frame holds is unknown until the reprojection is done)
            stats, splats = self._reproject(capture, windows, channels, frame.image, base_box, helper)
            frame.background, frame.written = capture.background, _union(capture.box, splats)
        return frame.image, stats

    def _check(self, capture) -> None:
        W, H = self.width, self.height
        if not isinstance(capture, Capture) or capture.image.shape != (H, W, 3) or len(capture.R) != len(self.dynamic):
            raise ValueError(f"capture: expected a Capture of this Reprojector ({W}×{H}), got {type(capture).__name__}")

    def _windows(self, windows) -> tuple[list, list[int]]:
        """The windows as a list and their channels (−1: all), or a ValueError: one window of all
        channels, or windows of distinct channels 0–2."""
        windows = list(windows)
        channels = [self._channel(c, k) for k, (_, c) in enumerate(windows)]
        if not windows or (len(windows) > 1 and (-1 in channels or len(set(channels)) < len(windows))):
            raise ValueError(f"windows: expected one window of all channels or windows of distinct channels 0–2, "
                             f"got channels {[None if c < 0 else c for c in channels]}")
        return windows, channels

    def _reproject(self, capture: Capture, windows: list, channels: list[int], out: np.ndarray,
                   base_box: tuple[int, int, int, int], helper: bool = True
                   ) -> tuple[list[ReprojectStats], tuple[int, int, int, int]]:
        """`reproject_windows` of checked windows into `out`, which equals the capture outside
        `base_box`, its splats shared with the helper thread if `helper` (and `threads` is 2);
        holding the present lock. Returns the stats and the bounding box of every window's splats."""
        W, H = self.width, self.height
        nw, n_obj = len(windows), len(self.dynamic)
        n, seg = capture.lit, capture.segments
        px, py, pz = capture.point
        moving = np.flatnonzero(self.dynamic & (seg[1:] > seg[:-1]))  # the moving objects with points
        # the buffers below are the present thread's, reused every call
        R, t, M = self._R[:nw], self._t[:nw], self._M[:nw]
        for w, (poses, _) in enumerate(windows):
            R[w], t[w] = _poses(poses, n_obj, f"windows[{w}] poses" if nw > 1 else "poses")
        M[..., :3] = np.einsum("ji,wkjl->wkil", self.cam_R, R)  # model → camera: R_camᵀ (R_k·m + t_k − t_cam)
        M[..., 3] = (t - self.cam_t) @ self.cam_R
        M12 = M.reshape(nw, n_obj, 12)
        self._channels[:nw] = channels
        if self._sid + nw >= 2**30 - 1:  # the stamps wrap only after 2³⁰ windows; then start over
            for sc in self._scratch:
                sc.cover[:] = 0
            self._sid = 0
        sid = self._sid + 1
        self._sid += nw
        common = (capture.image.reshape(-1), out.reshape(-1), base_box, M12, M12.view(np.uint32), R, t, capture.R, capture.t,
                  self._channels[:nw], channels[0] < 0 or nw == 3, seg, moving, px, py, pz, *self._intrinsics, W, H,
                  (capture.pixel, capture.plate, capture.colour), self._plate_z, sid, self._moves[:nw], self._same[:nw],
                  self._groups[:nw], self._stats[:nw], self._boxes[:nw])
        mine = self._scratch[0].arrays(n)
        self.last_helper_cpu_ns = 0
        if len(self._scratch) == 1 or nw == 1 or not helper:
            self._splats(common, mine, True, 0, nw)
        else:
            self._splats(common, mine, True, 0, 0)  # plan, and the captured image under the splats
            splats = int(np.count_nonzero(self._groups[:nw, 0] >= 0))
            if splats == 1:
                self._splats(common, mine, False, 0, 1)
            elif splats > 1:
                scratch = (mine, self._scratch[1].arrays(n))
                helper = self._helper  # (`close` may clear the attribute meanwhile)
                if helper is None:
                    helper = self._helper = _SplatHelper()
                    weakref.finalize(self, helper.close)
                self.last_helper_cpu_ns = helper.share(
                    lambda g, slot: self._splats(common, scratch[slot], False, g, g + 1), splats)
        moves, stats, boxes = self._moves[:nw].tolist(), self._stats[:nw].tolist(), self._boxes[:nw].tolist()
        result, splats = [], (0, 0, 0, 0)
        for w in range(nw):
            if not moves[w]:  # nothing moves: the captured image itself
                result.append(ReprojectStats(n, n, 0, 0, 0, 0, capture.box if n else None))
                continue
            y0, y1, x0, x1 = boxes[w]
            result.append(ReprojectStats(n, *stats[w], (y0, y1, x0, x1) if y1 > y0 else None))
            splats = _union(splats, (y0, y1, x0, x1))
        return result, splats

    def _splats(self, common: tuple, scratch: tuple, plan: bool, g_first: int, g_end: int) -> None:
        """One kernel call on one thread's scratch (`_reproject_windows`): the plan when `plan`, then
        the splats g_first to g_end − 1."""
        _reproject_windows(*common, scratch, plan, g_first, g_end)

    def close(self) -> None:
        """End the helper thread, if one started (a later present starts another)."""
        helper, self._helper = self._helper, None
        if helper is not None:
            helper.close()

    @staticmethod
    def _channel(channel, w: int) -> int:
        if channel is None:
            return -1
        if not isinstance(channel, (int, np.integer)) or isinstance(channel, bool) or not 0 <= channel <= 2:
            raise ValueError(f"channel: expected None, 0, 1 or 2, got {channel!r}" if w == 0 else
                             f"windows[{w}] channel: expected None, 0, 1 or 2, got {channel!r}")
        return int(channel)

    def _box(self, box) -> tuple[int, int, int, int]:
        if box is None:
            return (0, self.height, 0, self.width)
        try:
            y0, y1, x0, x1 = (int(v) for v in box)
            if any(int(v) != v for v in box):
                raise ValueError
        except (TypeError, ValueError):
            raise ValueError(f"box: expected (y0, y1, x0, x1) integers, got {box!r}") from None
        if not (0 <= y0 <= y1 <= self.height and 0 <= x0 <= x1 <= self.width):
            raise ValueError(f"box: expected 0 ≤ y0 ≤ y1 ≤ {self.height} and 0 ≤ x0 ≤ x1 ≤ {self.width}, got {box!r}")
        return y0, y1, x0, x1
