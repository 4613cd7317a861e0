"""Temporal reuse: an exponential moving average of 1-spp frames, gated by object id.

Per pixel X_i, every frame (methods.md §1, Miyamoto et al.)::

    c̄_i(X_i) = α_eff · c_i(X_i) + (1 − α_eff) · c̄_{i−1}(X_{i−1})   if the history at X_{i−1} matches
    c̄_i(X_i) = c_i(X_i)                                            otherwise (reset)

Modes
-----
``off``
    Pass-through (plain path tracing); no history is kept.
``same-pixel`` (the paper's method 2)
    X_{i−1} = X_i. The history matches when the id stored at the pixel equals the current id.
``motion`` (the paper's method 1)
    X_{i−1} is the current hit point x_m (model coordinates of the object hit through the pixel
    centre) moved with the object's pose of the previous frame and projected with the previous
    frame's camera. The history is *fetched* there:

    1. X_{i−1} outside the image (x ∉ [−0.5, W−0.5) or y ∉ [−0.5, H−0.5), or behind the previous
       camera) → reset.
    2. The four taps around X_{i−1} (pixel centres floor(x), floor(x)+1 × floor(y), floor(y)+1)
       get bilinear weights. A tap *matches* when it lies inside the image, holds history, and
       its stored object id equals the current pixel's id.
    3. If the matching taps' weights sum to at least ``MIN_BILINEAR_WEIGHT`` → the bilinear
       average over the matching taps, renormalised by that sum.
    4. Else, if any tap matches → the nearest matching tap (Euclidean distance to X_{i−1}).
    5. Else → reset.

    Background pixels (id −1) carry no model position: they reuse the same pixel while the
    camera holds still, and reset when it moves. When |X_{i−1} − X_i| < ``SNAP_PX`` (a static
    surface whose float32 model position rounds to within a thousandth of a pixel of its centre)
    the pixel is fetched exactly, so static regions are not blurred by rounding.

Warm-up (beyond the paper, optional): α_eff = max(α, 1/n), n = frames since the last reset
including this one; the first frames after a reset are then a plain running mean instead of
being dominated by the one sample that started the history. Without warm-up α_eff = α (and a
reset outputs the current sample, as in the paper).

Numerics. The history is stored as a pair of float32 arrays (hi, lo) whose sum carries the EMA
to about float64 precision: the blend is evaluated in float64 as h + α(c − h) (whose fixed point
is exactly c whatever the rounding of α) and split back into hi = fl32(h), lo = fl32(h − hi).
The float32 output is therefore the correctly rounded EMA, with no drift and no stagnation over
any number of frames. Non-finite input samples (NaN/Inf) never enter the history: the pixel
keeps its history unchanged (and outputs it); a pixel without history outputs 0. They are
counted in ``nonfinite_last`` / ``nonfinite_total``.

Split screen: the output's left half (columns < W // 2) is the plain 1-spp input, the right half
the reused image, as the paper's comparison videos; the history is updated over the whole frame.

All per-pixel work runs in numba kernels (parallel over rows); no per-pixel Python.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from dpmhw.errors import DpmhwError
from dpmhw.parallel_kernels import PixelKernel, span, spans
from dpmhw.render.distortion import distort_inline
from dpmhw.reconstruct.settings import ALPHA_MAX, ALPHA_MIN, MAX_HISTORY_LENGTH, REUSE_MODES

MIN_BILINEAR_WEIGHT = 1e-6
SNAP_PX = 1e-3


class ReuseError(DpmhwError, ValueError):
    """Invalid temporal-reuse setting or input (names the parameter and what was expected)."""


def validate_alpha(alpha) -> float:
    """α must be a finite number in (0, 1], at least ALPHA_MIN; anything else raises ReuseError."""
    expected = f"expected a number in (0, {ALPHA_MAX:g}], at least {ALPHA_MIN:.3g}"
    try:
        a = float(alpha)
    except (TypeError, ValueError):
        raise ReuseError(f"alpha: {expected}, got {alpha!r}") from None
    if not np.isfinite(a) or not (ALPHA_MIN <= a <= ALPHA_MAX):
        raise ReuseError(f"alpha: {expected} (1 = no reuse, 0.2 = the paper's setting), got {alpha!r}")
    return a


def validate_mode(mode: str) -> str:
    if mode not in REUSE_MODES:
        raise ReuseError(f"mode: expected one of {', '.join(REUSE_MODES)}, got {mode!r}")
    return mode


@dataclass(frozen=True)
class ReuseSettings:
    alpha: float = 0.2
    mode: str = "same-pixel"
    warmup: bool = False
    split_screen: bool = False

    def __post_init__(self):
        object.__setattr__(self, "alpha", validate_alpha(self.alpha))
        validate_mode(self.mode)

    @property
    def label(self) -> str:
        if self.mode == "off":
            return "off"
        return f"{self.mode} α={self.alpha:g}" + (" +warmup" if self.warmup else "")


# ----------------------------------------------------------------------------------------------
# kernels


@nb.njit(cache=True, inline="always")  # typed with its callers' argument types: on its own it took four signatures
def _blend_pixel(p, c0, c1, c2, prev0, prev1, prev2, n_prev, has_prev, alpha, warmup, hi, lo, n_out, out):
    """Blend one pixel. prev* in float64 (the fetched history), n_prev its history length.
    Returns 1 if the input sample was non-finite (and dropped)."""
    finite = np.isfinite(c0) and np.isfinite(c1) and np.isfinite(c2)
    if not finite:
        if has_prev:
            v0, v1, v2, n = prev0, prev1, prev2, n_prev
        else:
            v0, v1, v2, n = 0.0, 0.0, 0.0, 0.0
    elif not has_prev:
        v0, v1, v2, n = np.float64(c0), np.float64(c1), np.float64(c2), 1.0
    else:
        n = min(n_prev + 1.0, MAX_HISTORY_LENGTH)
        a = alpha
        if warmup and 1.0 / n > a:
            a = 1.0 / n
        v0 = prev0 + a * (np.float64(c0) - prev0)
        v1 = prev1 + a * (np.float64(c1) - prev1)
        v2 = prev2 + a * (np.float64(c2) - prev2)
    h0, h1, h2 = np.float32(v0), np.float32(v1), np.float32(v2)
    hi[p, 0], hi[p, 1], hi[p, 2] = h0, h1, h2
    lo[p, 0] = np.float32(v0 - np.float64(h0))
    lo[p, 1] = np.float32(v1 - np.float64(h1))
    lo[p, 2] = np.float32(v2 - np.float64(h2))
    n_out[p] = n
    out[p, 0], out[p, 1], out[p, 2] = h0, h1, h2
    return 0 if finite else 1


def _same_pixel_py(cur, cur_id, hi, lo, hist_n, hist_id, alpha, warmup, out):
    """In place: history at the same pixel, reset where the stored id differs."""
    npix = cur.shape[0]
    bad = np.zeros(npix, np.int32)
    for p in nb.prange(npix):
        has = hist_n[p] > 0.0 and hist_id[p] == cur_id[p]
        prev0 = np.float64(hi[p, 0]) + np.float64(lo[p, 0])
        prev1 = np.float64(hi[p, 1]) + np.float64(lo[p, 1])
        prev2 = np.float64(hi[p, 2]) + np.float64(lo[p, 2])
        bad[p] = _blend_pixel(p, cur[p, 0], cur[p, 1], cur[p, 2], prev0, prev1, prev2, hist_n[p], has, alpha, warmup, hi, lo, hist_n, out)
        hist_id[p] = cur_id[p]
    return bad.sum()


def _motion_py(cur, cur_id, prev_xy, prev_ok, width, height, hi, lo, hist_n, hist_id, alpha, warmup,
                   new_hi, new_lo, new_n, out, fetch_kind):
    """Fetch the history at prev_xy (see the module docstring), blend, write the new history.
    fetch_kind per pixel: 0 reset, 1 bilinear, 2 nearest matching tap, 3 exact (snapped).
    Returns the non-finite inputs dropped."""
    n = cur.shape[0]
    bad = 0
    for s in nb.prange(spans(n)):
        a, e = span(s, n)
        bad += _motion_span(a, e, cur, cur_id, prev_xy, prev_ok, width, height, hi, lo, hist_n, hist_id, alpha, warmup,
                            new_hi, new_lo, new_n, out, fetch_kind)
    return bad


@nb.njit(nogil=True, cache=True, _nrt=False)
def _motion_span(first, end, cur, cur_id, prev_xy, prev_ok, width, height, hi, lo, hist_n, hist_id, alpha, warmup,
                 new_hi, new_lo, new_n, out, fetch_kind):
    bad = 0
    for p in range(first, end):
        ident = cur_id[p]
        x = prev_xy[p, 0]
        y = prev_xy[p, 1]
        has = False
        kind = 0
        prev0 = prev1 = prev2 = 0.0
        n_prev = 0.0
        if prev_ok[p] and x >= -0.5 and x < width - 0.5 and y >= -0.5 and y < height - 0.5:
            px = p % width
            py = p // width
            if abs(x - px) < SNAP_PX and abs(y - py) < SNAP_PX:
                if hist_n[p] > 0.0 and hist_id[p] == ident:
                    has = True
                    kind = 3
                    prev0 = np.float64(hi[p, 0]) + np.float64(lo[p, 0])
                    prev1 = np.float64(hi[p, 1]) + np.float64(lo[p, 1])
                    prev2 = np.float64(hi[p, 2]) + np.float64(lo[p, 2])
                    n_prev = hist_n[p]
            else:
                x0 = int(np.floor(x))
                y0 = int(np.floor(y))
                fx = x - x0
                fy = y - y0
                wsum = 0.0
                s0 = s1 = s2 = sn = 0.0
                best_d = 1e30
                best = -1
                for j in range(2):
                    ty = y0 + j
                    wy = fy if j == 1 else 1.0 - fy
                    for i in range(2):
                        tx = x0 + i
                        wx = fx if i == 1 else 1.0 - fx
                        if tx < 0 or tx >= width or ty < 0 or ty >= height:
                            continue
                        q = ty * width + tx
                        if hist_n[q] <= 0.0 or hist_id[q] != ident:
                            continue
                        w = wx * wy
                        wsum += w
                        s0 += w * (np.float64(hi[q, 0]) + np.float64(lo[q, 0]))
                        s1 += w * (np.float64(hi[q, 1]) + np.float64(lo[q, 1]))
                        s2 += w * (np.float64(hi[q, 2]) + np.float64(lo[q, 2]))
                        sn += w * hist_n[q]
                        d = (tx - x) * (tx - x) + (ty - y) * (ty - y)
                        if d < best_d:
                            best_d = d
                            best = q
                if wsum >= MIN_BILINEAR_WEIGHT:
                    has = True
                    kind = 1
                    prev0, prev1, prev2, n_prev = s0 / wsum, s1 / wsum, s2 / wsum, sn / wsum
                elif best >= 0:
                    has = True
                    kind = 2
                    prev0 = np.float64(hi[best, 0]) + np.float64(lo[best, 0])
                    prev1 = np.float64(hi[best, 1]) + np.float64(lo[best, 1])
                    prev2 = np.float64(hi[best, 2]) + np.float64(lo[best, 2])
                    n_prev = hist_n[best]
        fetch_kind[p] = kind
        bad += _blend_pixel(p, cur[p, 0], cur[p, 1], cur[p, 2], prev0, prev1, prev2, n_prev, has, alpha, warmup,
                            new_hi, new_lo, new_n, out)
    return bad


_same_pixel_kernel = PixelKernel(_same_pixel_py)
_motion_kernel = PixelKernel(_motion_py)


# ----------------------------------------------------------------------------------------------
# reprojection


def _reproject_py(ids, xm, R, T, cam_R, cam_t, K, dist, width, bg_still, xy, ok):
    """world = R[id] @ x_m + T[id]; project with the previous camera (cv2.projectPoints model)."""
    n = ids.shape[0]
    for s in nb.prange(spans(n)):
        a, e = span(s, n)
        _reproject_span(a, e, ids, xm, R, T, cam_R, cam_t, K, dist, width, bg_still, xy, ok)


@nb.njit(nogil=True, cache=True, _nrt=False)
def _reproject_span(first, end, ids, xm, R, T, cam_R, cam_t, K, dist, width, bg_still, xy, ok):
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for p in range(first, end):
        o = ids[p]
        if o < 0:
            xy[p, 0] = p % width
            xy[p, 1] = p // width
            ok[p] = bg_still
            continue
        m0, m1, m2 = np.float64(xm[p, 0]), np.float64(xm[p, 1]), np.float64(xm[p, 2])
        w0 = R[o, 0, 0] * m0 + R[o, 0, 1] * m1 + R[o, 0, 2] * m2 + T[o, 0] - cam_t[0]
        w1 = R[o, 1, 0] * m0 + R[o, 1, 1] * m1 + R[o, 1, 2] * m2 + T[o, 1] - cam_t[1]
        w2 = R[o, 2, 0] * m0 + R[o, 2, 1] * m1 + R[o, 2, 2] * m2 + T[o, 2] - cam_t[2]
        # camera coordinates: cam_R is camera→world, so x_cam = cam_R^T (w − t)
        c0 = cam_R[0, 0] * w0 + cam_R[1, 0] * w1 + cam_R[2, 0] * w2
        c1 = cam_R[0, 1] * w0 + cam_R[1, 1] * w1 + cam_R[2, 1] * w2
        c2 = cam_R[0, 2] * w0 + cam_R[1, 2] * w1 + cam_R[2, 2] * w2
        if not (c2 > 1e-12) or not np.isfinite(c0 + c1 + c2):
            xy[p, 0] = np.nan
            xy[p, 1] = np.nan
            ok[p] = False
            continue
        x = c0 / c2
        y = c1 / c2
        xd, yd = distort_inline(x, y, k1, k2, p1, p2, k3)
        xy[p, 0] = K[0, 0] * xd + K[0, 2]  # no skew, as PinholeCamera.project
        xy[p, 1] = K[1, 1] * yd + K[1, 2]
        ok[p] = True


def reproject(object_id: np.ndarray, model_position: np.ndarray, prev_poses, prev_camera, camera=None) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's surface point was in the previous frame.

    Parameters
    ----------
    object_id : (H, W) int32, −1 for background
    model_position : (H, W, 3) float, hit point in the object's model coordinates
    prev_poses : sequence of Pose (model→world), indexed by object id, at the previous frame
    prev_camera : PinholeCamera of the previous frame (``K``, ``dist``, ``pose`` camera→world)
    camera : PinholeCamera of the current frame; background pixels reuse the same pixel when its
        pose equals the previous one (or when it is None), else they reset.

    Returns
    -------
    prev_xy : (H*W, 2) float64 pixel coordinates X_{i−1} (cv2.projectPoints convention: pixel
        (0, 0) is the centre of the top-left pixel); NaN behind the previous camera
    ok : (H*W,) bool, False where the point is behind the previous camera (or background after
        the camera moved)
    """
    H, W = object_id.shape
    ids = np.ascontiguousarray(np.asarray(object_id).reshape(-1), dtype=np.int32)
    xm = np.ascontiguousarray(np.asarray(model_position).reshape(-1, 3), dtype=np.float32)
    n_obj = len(prev_poses)
    if ids.size and ids.max() >= n_obj:
        raise ReuseError(f"object_id: ids up to {int(ids.max())} but only {n_obj} previous poses were given")
    R = np.ascontiguousarray(np.stack([np.asarray(p.R, np.float64) for p in prev_poses])) if n_obj else np.zeros((1, 3, 3))
    T = np.ascontiguousarray(np.stack([np.asarray(p.t, np.float64) for p in prev_poses])) if n_obj else np.zeros((1, 3))
    still = camera is None or (np.array_equal(camera.pose.R, prev_camera.pose.R) and np.array_equal(camera.pose.t, prev_camera.pose.t))
    xy = np.empty((H * W, 2), np.float64)
    ok = np.empty(H * W, np.bool_)
    _reproject_kernel(H * W, ids, xm, R, T, np.ascontiguousarray(prev_camera.pose.R, dtype=np.float64),
                      np.ascontiguousarray(prev_camera.pose.t, dtype=np.float64), np.ascontiguousarray(prev_camera.K, dtype=np.float64),
                      np.ascontiguousarray(np.asarray(prev_camera.dist, np.float64).reshape(5)), W, bool(still), xy, ok)
    return xy, ok


_reproject_kernel = PixelKernel(_reproject_py)


# ----------------------------------------------------------------------------------------------
# state


class TemporalReuse:
    """Per-pixel EMA history for one image size.

    Parameters
    ----------
    width, height : image size
    alpha : float in (0, 1], at least ALPHA_MIN; 1 = no reuse
    mode : "off" | "same-pixel" | "motion"
    warmup : α_eff = max(α, 1/n) with n frames since the last reset
    split_screen : left half of the output is the plain input

    ``update`` returns the (H, W, 3) float32 output of this frame (linear, before
    post-processing) and keeps its own copy of the history.
    """

    def __init__(self, width: int, height: int, alpha: float = 0.2, mode: str = "same-pixel", warmup: bool = False,
                 split_screen: bool = False):
        if int(width) < 1 or int(height) < 1:
            raise ReuseError(f"image size: expected width, height ≥ 1, got {width}×{height}")
        self.settings = ReuseSettings(alpha, mode, bool(warmup), bool(split_screen))
        self.width, self.height = int(width), int(height)
        n = self.width * self.height
        self._hi = np.zeros((n, 3), np.float32)
        self._lo = np.zeros((n, 3), np.float32)
        self._n = np.zeros(n, np.float32)  # frames since reset (float: a bilinear fetch blends lengths)
        self._id = np.full(n, -1, np.int32)
        self._spare = (np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32), np.zeros(n, np.float32))
        self._prev_poses = None
        self._prev_camera = None
        self.frames = 0
        self.nonfinite_last = 0
        self.nonfinite_total = 0
        self.last_fetch_kind: np.ndarray | None = None  # motion mode: (H, W) int8, 0 reset 1 bilinear 2 nearest 3 exact

    @property
    def alpha(self) -> float:
        return self.settings.alpha

    @property
    def mode(self) -> str:
        return self.settings.mode

    def reset(self) -> None:
        """Forget every pixel's history (a scene cut, a calibration change): the next frame is
        output as rendered."""
        self._n[:] = 0.0
        self._hi[:] = 0.0
        self._lo[:] = 0.0
        self._id[:] = -1
        self._prev_poses = None
        self._prev_camera = None

    @property
    def history(self) -> np.ndarray:
        """(H, W, 3) float32 current history (the reused image without the split screen)."""
        return self._hi.reshape(self.height, self.width, 3).copy()

    @property
    def history_length(self) -> np.ndarray:
        """(H, W) float32 frames since the last reset (bilinear-blended in motion mode)."""
        return self._n.reshape(self.height, self.width).copy()

    def reprojection(self, object_id, model_position, camera) -> tuple[np.ndarray, np.ndarray] | None:
        """Motion mode: where each pixel's surface point was in this history's previous frame
        (`reproject`), or None before a first frame. Histories updated in lockstep (the stage's
        diffuse and specular ones) share it: `update(..., reprojected=…)`."""
        if self._prev_poses is None:
            return None
        return reproject(np.asarray(object_id), model_position, self._prev_poses, self._prev_camera, camera)

    def follows_same_frames(self, other: "TemporalReuse") -> bool:
        """Whether this history's previous frame is `other`'s (same poses and camera)."""
        a, b = self._prev_poses, other._prev_poses
        if a is None or b is None:
            return a is b
        return (self._prev_camera is other._prev_camera and len(a) == len(b)
                and all(np.array_equal(p.R, q.R) and np.array_equal(p.t, q.t) for p, q in zip(a, b)))

    def update(self, radiance: np.ndarray, object_id: np.ndarray | None = None, model_position: np.ndarray | None = None,
               poses=None, camera=None, reprojected: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Blend one frame into the history and return the output.

        Parameters
        ----------
        radiance : (H, W, 3) float, linear (1 spp)
        object_id : (H, W) int32, −1 background (required unless mode is "off")
        model_position : (H, W, 3) float, model-space hit points (motion mode)
        poses : list of Pose, model→world per object id, of *this* frame (motion mode)
        camera : PinholeCamera of this frame (motion mode)
        reprojected : motion mode, `reprojection(...)` of this frame, computed once for several
            histories whose previous frame is the same (see `follows_same_frames`)
        """
        H, W = self.height, self.width
        rad = np.asarray(radiance)
        if rad.shape != (H, W, 3):
            raise ReuseError(f"radiance: expected shape ({H}, {W}, 3), got {rad.shape}")
        s = self.settings
        self.frames += 1
        if s.mode == "off":
            out = np.array(rad, dtype=np.float32, copy=True)
            bad = ~np.isfinite(out).all(axis=2)
            self.nonfinite_last = int(bad.sum())
            self.nonfinite_total += self.nonfinite_last
            out[bad] = 0.0
            return out
        if object_id is None or np.shape(object_id) != (H, W):
            raise ReuseError(f"object_id: expected an (H, W) = ({H}, {W}) int array, got {None if object_id is None else np.shape(object_id)}")
        cur = np.ascontiguousarray(rad.reshape(-1, 3), dtype=np.float32)
        ids = np.ascontiguousarray(np.asarray(object_id).reshape(-1), dtype=np.int32)
        out = np.empty((H * W, 3), np.float32)
        if s.mode == "same-pixel":
            bad = _same_pixel_kernel(H * W, cur, ids, self._hi, self._lo, self._n, self._id, s.alpha, s.warmup, out)
        else:
            if model_position is None or poses is None or camera is None:
                raise ReuseError("motion mode needs model_position, poses and camera for every frame")
            if self._prev_poses is None:  # no previous frame: everything resets
                prev_xy = np.zeros((H * W, 2))
                prev_ok = np.zeros(H * W, bool)
            elif reprojected is not None:
                prev_xy, prev_ok = reprojected
            else:
                prev_xy, prev_ok = self.reprojection(object_id, model_position, camera)
            new_hi, new_lo, new_n = self._spare
            kind = np.empty(H * W, np.int8)
            bad = _motion_kernel(H * W, cur, ids, prev_xy, prev_ok, W, H, self._hi, self._lo, self._n, self._id, s.alpha, s.warmup,
                                 new_hi, new_lo, new_n, out, kind)
            self._spare = (self._hi, self._lo, self._n)
            self._hi, self._lo, self._n = new_hi, new_lo, new_n
            self._id[:] = ids
            self._prev_poses = list(poses)
            self._prev_camera = camera
            self.last_fetch_kind = kind.reshape(H, W)
        self.nonfinite_last = int(bad)
        self.nonfinite_total += self.nonfinite_last
        out = out.reshape(H, W, 3)
        if s.split_screen:
            half = W // 2
            left = rad[:, :half].astype(np.float32)
            left[~np.isfinite(left).all(axis=2)] = 0.0
            out[:, :half] = left
        return out

    def update_frame(self, frame, poses=None, camera=None) -> np.ndarray:
        """`update` from a renderer Frame (poses/camera of that frame, for motion mode)."""
        return self.update(frame.radiance, frame.object_id, frame.model_position, poses, camera)


def split_screen(plain: np.ndarray, reused: np.ndarray) -> np.ndarray:
    """(H, W, 3): columns < W // 2 from `plain`, the rest from `reused` (the paper's layout)."""
    if plain.shape != reused.shape:
        raise ReuseError(f"split_screen: shapes differ, {plain.shape} vs {reused.shape}")
    out = np.array(reused, copy=True)
    half = plain.shape[1] // 2
    out[:, :half] = plain[:, :half]
    return out
