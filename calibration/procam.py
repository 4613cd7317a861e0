"""Projector-camera calibration after Moreno & Taubin (2012).

1. per pose: find the board corners in the white frame, decode the Gray code;
2. calibrate the camera from the corners (``calibrateCameraExtended``, outlier views
   rejected, degeneracy guards; ``calibrateCameraRO`` when the board is not flat);
3. per corner: fit a homography (RANSAC) from the undistorted camera pixels around the corner
   to their decoded projector coordinates and map the corner through it -> the corner's
   projector coordinates;
4. calibrate the projector as a camera from those (principal point free: lens shift);
5. refine everything jointly with ``stereoCalibrateExtended`` -> projector_from_camera.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration.board import BoardSpec, detect
from calibration.decode import Decoded, decode
from calibration.errors import DegenerateViewsError

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


@dataclass
class SolveOptions:
    """Tuning of the solver and its guards (defaults suit 8-bit captures of a printed board)."""

    min_views: int = 3
    outlier_factor: float = 3.0  # a view is an outlier above factor * median per-view RMS ...
    outlier_floor_px: float = 0.3  # ... and above median + this
    min_tilt_deg: float = 10.0  # the most tilted view must be tilted at least this much
    max_rel_std: float = 0.01  # sigma(f)/f above this flags a degenerate view set
    fix_k3: bool | None = None  # None: free k3 only if points reach all four image corners
    release_object: bool | None = None  # None: calibrateCameraRO if the plain fit looks bowed
    flatness_rms_px: float = 0.15  # camera RMS above which a bowed board is suspected
    window: int | None = None  # half-size of the local-homography window; None: 0.5 * corner spacing
    ransac_px: float = 1.5  # RANSAC threshold in projector pixels (scaled when bits are dropped)
    min_window_fraction: float = 0.25  # decoded pixels needed in a window
    min_corner_fraction: float = 0.5  # corners with projector coordinates needed per view (others are dropped)
    point_outlier_factor: float = 6.0  # a single point is an outlier above factor * RMS ...
    point_outlier_floor_px: float = 0.5  # ... and above this
    decode: dict = field(default_factory=dict)  # keyword arguments for calibration.decode.decode


@dataclass
class Observation:
    """One board pose: corners in the camera, decoded projector coordinates, and their fate."""

    name: str
    camera_px: np.ndarray | None  # (m, 2)
    ids: np.ndarray | None  # (m,)
    decoded: Decoded | None
    image_size: tuple[int, int]
    projector_px: np.ndarray | None = None  # (m, 2), NaN where the local homography failed
    reason: str = ""  # why the view is unusable, if it is
    timings: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)  # what was dropped from a usable view


@dataclass
class LensFit:
    """A pinhole + distortion fit to several views."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    rms: float
    names: list[str]  # views used
    per_view: dict[str, float]
    std: dict[str, float]
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]
    rejected: dict[str, str] = field(default_factory=dict)
    k3_fixed: bool = True
    object_points: np.ndarray | None = None  # released (non-planar) board, if used
    diagnostics: list[str] = field(default_factory=list)
    kept: dict[str, np.ndarray] = field(default_factory=dict)  # per view: mask of the input points used


@dataclass
class ProcamResult:
    camera: LensFit
    projector: LensFit
    R: np.ndarray  # projector_from_camera
    T: np.ndarray
    stereo_rms: float
    stereo_per_view: dict[str, tuple[float, float]]
    observations: list[Observation]
    diagnostics: list[str]
    timings: dict[str, float]
    stereo_rejected: dict[str, str] = field(default_factory=dict)
    stereo_data: dict = field(default_factory=dict)  # names, obj, camera, projector, rvecs, tvecs

    def residuals(self) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
        """Per device, per used view: (observed (m, 2), residual = projected - observed (m, 2))."""
        d = self.stereo_data
        out: dict[str, list] = {"camera": [], "projector": []}
        for o, c, p, rv, tv in zip(d["obj"], d["camera"], d["projector"], d["rvecs"], d["tvecs"]):
            uc, _ = cv2.projectPoints(o.reshape(-1, 1, 3), rv, tv, self.camera.K, self.camera.dist)
            Rc = cv2.Rodrigues(np.asarray(rv, dtype=np.float64))[0]
            r2 = cv2.Rodrigues(self.R @ Rc)[0]
            t2 = self.R @ np.ravel(tv) + self.T
            up, _ = cv2.projectPoints(o.reshape(-1, 1, 3), r2, t2, self.projector.K, self.projector.dist)
            out["camera"].append((c, uc.reshape(-1, 2) - c))
            out["projector"].append((p, up.reshape(-1, 2) - p))
        return out

    def views_table(self) -> list[dict]:
        """One row per pose: used or not, per-device RMS, and why (not) used."""
        rows = []
        for ob in self.observations:
            n = ob.name
            used = n in self.stereo_per_view
            why = [ob.reason] if ob.reason else []
            for who, rej in (("camera", self.camera.rejected), ("projector", self.projector.rejected), ("stereo", self.stereo_rejected)):
                if n in rej:
                    why.append(f"{who}: {rej[n]}")
            rows.append({
                "name": n,
                "used": used,
                "camera_rms_px": self.camera.per_view.get(n),
                "projector_rms_px": self.projector.per_view.get(n),
                "stereo_rms_px": list(self.stereo_per_view[n]) if used else None,
                "reason": "; ".join(why + ob.notes),
            })
        return rows

    def to_calibration(self, provenance: dict | None = None):
        """The :class:`dpmhw.projector_calibration.ProjectorCalibration` (world = camera frame)."""
        from dpmhw.projector_calibration import LensModel, ProjectorCalibration

        R_cp = self.R.T
        t_cp = -R_cp @ self.T
        stats = {
            "camera_rms_px": self.camera.rms,
            "projector_rms_px": self.projector.rms,
            "stereo_rms_px": self.stereo_rms,
            "std": {"camera": self.camera.std, "projector": self.projector.std},
            "k3_fixed": {"camera": self.camera.k3_fixed, "projector": self.projector.k3_fixed},
            "diagnostics": self.diagnostics,
            "timings_s": self.timings,
        }
        if self.camera.object_points is not None:
            stats["released_board_points"] = self.camera.object_points.tolist()
        return ProjectorCalibration(
            self.projector.width, self.projector.height, self.projector.K, self.projector.dist, R_cp, t_cp, "camera",
            LensModel(self.camera.width, self.camera.height, self.camera.K, self.camera.dist), (self.R, self.T),
            stats, self.views_table(), dict(provenance or {}),
        )


# -- per view -------------------------------------------------------------------------------------
def observe(name: str, frames: np.ndarray, board: BoardSpec, projector_size: tuple[int, int], options: SolveOptions | None = None) -> Observation:
    """Detect the board in the white frame and decode the Gray code of one pose."""
    options = options or SolveOptions()
    frames = np.asarray(frames)
    white = frames[0]
    if white.dtype != np.uint8:
        white = cv2.normalize(white.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    size = (frames.shape[2], frames.shape[1])
    t0 = time.perf_counter()
    found = detect(white, board)
    t1 = time.perf_counter()
    dec = decode(frames, projector_size[0], projector_size[1], **options.decode)
    timings = {"detect": t1 - t0, "decode": time.perf_counter() - t1}
    if found is None:
        return Observation(name, None, None, dec, size, reason="board not found in the white frame", timings=timings)
    return Observation(name, found[0], found[1], dec, size, timings=timings)


def undistortion_grid(K: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W, 2) ideal (undistorted) pixel coordinates of every camera pixel."""
    w, h = size
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
    und = cv2.undistortPoints(pts, K, dist, None, None, K, crit)
    return und.reshape(h, w, 2)


def projector_corners(
    decoded: Decoded,
    corners: np.ndarray,
    und_grid: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    *,
    window: int,
    ransac_px: float = 1.5,
    min_fraction: float = 0.25,
) -> tuple[np.ndarray, np.ndarray]:
    """Projector coordinates of camera corners through local homographies (Moreno & Taubin).

    Returns
    -------
    proj : (m, 2) float64, NaN where there were too few decoded pixels or RANSAC inliers
    inliers : (m,) int, inlier count per corner
    """
    h, w = decoded.valid.shape
    corners = np.asarray(corners, dtype=np.float64)
    c_und = cv2.undistortPoints(corners.reshape(-1, 1, 2), K, dist, None, None, K).reshape(-1, 2)
    scale = float(1 << max(decoded.dropped_bits_x, decoded.dropped_bits_y))
    thr = ransac_px * scale
    need = max(12, int(min_fraction * (2 * window + 1) ** 2))
    out = np.full((len(corners), 2), np.nan)
    counts = np.zeros(len(corners), np.int64)
    for i, (x, y) in enumerate(np.rint(corners).astype(int)):
        y0, y1, x0, x1 = max(0, y - window), min(h, y + window + 1), max(0, x - window), min(w, x + window + 1)
        m = decoded.valid[y0:y1, x0:x1]
        if m.sum() < need:
            continue
        src = und_grid[y0:y1, x0:x1][m]
        dst = np.stack([decoded.x[y0:y1, x0:x1][m], decoded.y[y0:y1, x0:x1][m]], 1).astype(np.float64)
        H, inl = cv2.findHomography(src, dst, cv2.RANSAC, thr, maxIters=2000, confidence=0.999)
        if H is None or inl is None or int(inl.sum()) < need:
            continue
        p = H @ np.array([c_und[i, 0], c_und[i, 1], 1.0])
        out[i] = p[:2] / p[2]
        counts[i] = int(inl.sum())
    return out, counts


# -- guards ---------------------------------------------------------------------------------------
def view_tilts_deg(obj: list[np.ndarray], img: list[np.ndarray], size: tuple[int, int]) -> np.ndarray:
    """Board tilt w.r.t. the image plane per view, from a nominal camera (for the guard only)."""
    w, h = size
    f = float(max(w, h))
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    tilts = []
    for o, p in zip(obj, img):
        Hm, _ = cv2.findHomography(o[:, :2], p, 0)
        if Hm is None:
            tilts.append(0.0)
            continue
        # rotation columns from K^-1 H (Zhang); normalise r1, r2 and take the normal
        A = np.linalg.inv(K) @ Hm
        r1 = A[:, 0] / np.linalg.norm(A[:, 0])
        r2 = A[:, 1] / np.linalg.norm(A[:, 1])
        n = np.cross(r1, r2)
        tilts.append(float(np.degrees(np.arccos(min(1.0, abs(n[2]) / np.linalg.norm(n))))))
    return np.array(tilts)


def edge_coverage(img: list[np.ndarray], size: tuple[int, int]) -> int:
    """How many of the four image corners (outer 30 % of the half-diagonal) hold points."""
    w, h = size
    pts = np.concatenate(img)
    c = np.array([w / 2, h / 2])
    r = np.linalg.norm((pts - c) / c, axis=1) / np.sqrt(2)
    outer = pts[r > 0.7]
    quads = {(bool(x > c[0]), bool(y > c[1])) for x, y in outer}
    return len(quads)


def _check_views(who: str, names: list[str], obj: list[np.ndarray], img: list[np.ndarray], size, options: SolveOptions) -> None:
    if len(names) < options.min_views:
        raise DegenerateViewsError(
            who, "views",
            f"only {len(names)} usable board pose(s) ({', '.join(names) or 'none'}); at least {options.min_views} are "
            "needed and 10-15 recommended: capture more poses, tilting the board 20-45 degrees in different directions",
        )
    tilts = view_tilts_deg(obj, img, size)
    if tilts.max() < options.min_tilt_deg:
        raise DegenerateViewsError(
            who, "views",
            f"all {len(names)} board poses are nearly fronto-parallel (largest tilt {tilts.max():.1f} deg < "
            f"{options.min_tilt_deg:.0f} deg): focal length and distance cannot be told apart; re-capture with the board "
            "tilted 20-45 degrees about different axes",
        )


# -- lens calibration -----------------------------------------------------------------------------
def _f32(a: Iterable[np.ndarray], d: int) -> list[np.ndarray]:
    return [np.ascontiguousarray(x, dtype=np.float32).reshape(-1, 1, d) for x in a]


def calibrate_lens(
    who: str,
    names: list[str],
    obj: list[np.ndarray],
    img: list[np.ndarray],
    size: tuple[int, int],
    options: SolveOptions | None = None,
    *,
    allow_release: bool = False,
) -> LensFit:
    """Intrinsics from board views, with outlier-view rejection and degeneracy guards.

    obj : per view (m_i, 3) board points; img : per view (m_i, 2) pixels; size : (width, height)
    ``allow_release``: consider ``calibrateCameraRO`` (all views must show all corners).
    """
    options = options or SolveOptions()
    names, obj, img = list(names), list(obj), list(img)
    masks = [np.ones(len(o), bool) for o in obj]  # points kept, per view, over the input points
    full_obj, full_img = list(obj), list(img)
    _check_views(who, names, obj, img, size, options)
    fix_k3 = options.fix_k3 if options.fix_k3 is not None else edge_coverage(img, size) < 4
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rejected: dict[str, str] = {}
    diagnostics: list[str] = []
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    release = False
    new_obj = None
    while True:
        if len(names) < options.min_views:
            _check_views(who, names, obj, img, size, options)
        rms, K, dist, rvecs, tvecs, std_i, _, pve = cv2.calibrateCameraExtended(
            _f32(obj, 3), _f32(img, 2), size, None, None, flags=flags, criteria=crit
        )
        errs = np.asarray(pve, dtype=np.float64).ravel()
        # single bad points (a corner next to an occluder): drop them when the rest of the view is fine
        pthr = max(options.point_outlier_factor * rms, options.point_outlier_floor_px)
        dropped_points = False
        for v in range(len(names)):
            proj, _ = cv2.projectPoints(obj[v].reshape(-1, 1, 3), rvecs[v], tvecs[v], K, dist)
            res = np.linalg.norm(proj.reshape(-1, 2) - img[v], axis=1)
            bad = res > pthr
            if bad.any() and bad.mean() <= 0.25 and (~bad).sum() >= 6:
                idx = np.nonzero(masks[v])[0]
                masks[v][idx[bad]] = False
                obj[v], img[v] = full_obj[v][masks[v]], full_img[v][masks[v]]
                dropped_points = True
        if dropped_points:
            continue
        med = float(np.median(errs))
        thr = max(options.outlier_factor * med, med + options.outlier_floor_px)
        worst = int(np.argmax(errs))
        if errs[worst] > thr and len(names) > options.min_views:
            rejected[names[worst]] = f"reprojection RMS {errs[worst]:.2f} px > {thr:.2f} px (median of views {med:.2f} px)"
            for lst in (names, obj, img, masks, full_obj, full_img):
                lst.pop(worst)
            continue
        if (
            not release
            and allow_release
            and options.release_object is not False
            and len({len(o) for o in obj}) == 1
            and (options.release_object or rms > options.flatness_rms_px)
        ):
            plain_rms = rms
            release = True
            plain = (rms, K, dist, rvecs, tvecs, std_i, errs)
            out = cv2.calibrateCameraROExtended(
                _f32(obj, 3), _f32(img, 2), size, _fixed_point_index(obj[0]), None, None, flags=flags, criteria=crit
            )
            ro_rms = out[0]
            if options.release_object or ro_rms < 0.6 * plain_rms:
                rms, K, dist, rvecs, tvecs, new_obj, std_i, _, _, pve = out
                new_obj = np.asarray(new_obj, dtype=np.float64).reshape(-1, 3)
                errs = np.asarray(pve, dtype=np.float64).ravel()
                dev = _plane_deviation(new_obj)
                diagnostics.append(
                    f"{who}: board is not flat: RMS {plain_rms:.3f} px with a planar board, {ro_rms:.3f} px with released "
                    f"object points (calibrateCameraRO); largest deviation from a plane {dev * 1000:.2f} mm"
                )
            else:
                release = False
                rms, K, dist, rvecs, tvecs, std_i, errs = plain
                diagnostics.append(
                    f"{who}: RMS {plain_rms:.3f} px is high but releasing the board points does not explain it "
                    f"({ro_rms:.3f} px): check focus, motion blur and the board print"
                )
        break
    std_i = np.asarray(std_i, dtype=np.float64).ravel()
    std = {n: float(s) for n, s in zip(INTRINSIC_NAMES, std_i)}
    fit = LensFit(
        size[0], size[1], K, np.asarray(dist, dtype=np.float64).ravel()[:5], float(rms), names,
        {n: float(e) for n, e in zip(names, errs)}, std, [np.ravel(r) for r in rvecs], [np.ravel(t) for t in tvecs],
        rejected, bool(fix_k3), new_obj if release else None, diagnostics, dict(zip(names, masks)),
    )
    rel = max(std["fx"] / K[0, 0], std["fy"] / K[1, 1])
    if not np.isfinite(rel) or rel > options.max_rel_std:
        raise DegenerateViewsError(
            who, "views",
            f"focal length is poorly determined (sigma/f = {rel:.2%} > {options.max_rel_std:.0%}) with {len(names)} poses; "
            "add poses with the board tilted in different directions and covering the image edges",
        )
    return fit


def _fixed_point_index(obj: np.ndarray) -> int:
    """calibrateCameraRO's second fixed point (it must be in 1 .. n-2; OpenCV recommends the
    board's top-right corner): the point farthest from both the first and the last point."""
    d = np.linalg.norm(obj - obj[0], axis=1) + np.linalg.norm(obj - obj[-1], axis=1)
    return int(1 + np.argmax(d[1:-1]))


def _plane_deviation(pts: np.ndarray) -> float:
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c)
    return float(np.abs((pts - c) @ vt[2]).max())


# -- the whole pipeline ---------------------------------------------------------------------------
def calibrate_procam(
    observations: list[Observation],
    board: BoardSpec,
    projector_size: tuple[int, int],
    options: SolveOptions | None = None,
) -> ProcamResult:
    """Camera intrinsics, projector intrinsics and projector_from_camera from observed poses."""
    options = options or SolveOptions()
    timings: dict[str, float] = {}
    diagnostics: list[str] = []
    good = [o for o in observations if o.camera_px is not None]
    if not good:
        raise DegenerateViewsError("capture", "views", "the board was not found in any pose's white frame")
    sizes = {o.image_size for o in good}
    if len(sizes) > 1:
        raise DegenerateViewsError("capture", "image size", f"poses have different camera image sizes: {sorted(sizes)}")
    cam_size = good[0].image_size
    board_obj = board.object_points()
    for o in good:  # this run's findings only
        o.reason, o.notes, o.projector_px = "", [], None

    t0 = time.perf_counter()
    cam = calibrate_lens(
        "camera", [o.name for o in good], [board_obj[o.ids] for o in good], [o.camera_px for o in good], cam_size,
        options, allow_release=board.kind == "chessboard",
    )
    timings["camera_intrinsics"] = time.perf_counter() - t0
    diagnostics += cam.diagnostics
    obj_pts = cam.object_points if cam.object_points is not None else board_obj

    t0 = time.perf_counter()
    grid = undistortion_grid(cam.K, cam.dist, cam_size)
    by_name = {o.name: o for o in good}
    p_names, p_obj, p_img, c_img = [], [], [], []
    for name in cam.names:
        o = by_name[name]
        keep_c = cam.kept[name]
        if not keep_c.all():
            o.notes.append(f"{int((~keep_c).sum())} corner(s) dropped as camera outliers")
        spacing = corner_spacing(o.camera_px, board, o.ids)
        win = options.window or int(np.clip(round(0.5 * spacing), 6, 40))
        proj, _ = projector_corners(o.decoded, o.camera_px, grid, cam.K, cam.dist, window=win,
                                    ransac_px=options.ransac_px, min_fraction=options.min_window_fraction)
        o.projector_px = proj
        ok = np.isfinite(proj).all(axis=1)
        ok &= (proj[:, 0] > -0.5) & (proj[:, 0] < projector_size[0] - 0.5) & (proj[:, 1] > -0.5) & (proj[:, 1] < projector_size[1] - 0.5)
        if (~ok & keep_c).any():
            o.notes.append(f"{int((~ok & keep_c).sum())} corner(s) without projector coordinates")
        ok &= keep_c
        if ok.mean() < options.min_corner_fraction or ok.sum() < 6:
            o.reason = (
                f"only {ok.sum()} of {len(ok)} corners have projector coordinates (decoded {o.decoded.valid_fraction:.0%} "
                "of pixels): check the projector lights the whole board and the exposure"
            )
            continue
        p_names.append(name)
        p_obj.append(obj_pts[o.ids[ok]])
        p_img.append(proj[ok])
        c_img.append(o.camera_px[ok])
    timings["projector_correspondences"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    proj_fit = calibrate_lens("projector", p_names, p_obj, p_img, projector_size, options)
    timings["projector_intrinsics"] = time.perf_counter() - t0
    diagnostics += proj_fit.diagnostics

    t0 = time.perf_counter()
    keep = [i for i, n in enumerate(p_names) if n in proj_fit.per_view]
    s_names = [p_names[i] for i in keep]
    s_obj = [p_obj[i][proj_fit.kept[p_names[i]]] for i in keep]
    s_cam = [c_img[i][proj_fit.kept[p_names[i]]] for i in keep]
    s_proj = [p_img[i][proj_fit.kept[p_names[i]]] for i in keep]
    stereo_rejected: dict[str, str] = {}
    R0, T0 = _initial_extrinsics(cam, proj_fit, s_names)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_USE_EXTRINSIC_GUESS
    if cam.k3_fixed or proj_fit.k3_fixed:
        flags |= cv2.CALIB_FIX_K3
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 300, 1e-12)
    while True:
        out = cv2.stereoCalibrateExtended(
            _f32(s_obj, 3), _f32(s_cam, 2), _f32(s_proj, 2), cam.K.copy(), cam.dist.copy(), proj_fit.K.copy(),
            proj_fit.dist.copy(), cam_size, R0.copy(), T0.reshape(3, 1).copy(), flags=flags, criteria=crit,
        )
        s_rms, Kc, dc, Kp, dp, R, T = out[:7]
        pve = np.asarray(out[-1], dtype=np.float64).reshape(len(s_names), 2)
        e = np.sqrt((pve**2).mean(axis=1))
        med = float(np.median(e))
        thr = max(options.outlier_factor * med, med + options.outlier_floor_px)
        worst = int(np.argmax(e))
        if e[worst] > thr and len(s_names) > options.min_views:
            stereo_rejected[s_names[worst]] = f"stereo reprojection RMS {e[worst]:.2f} px > {thr:.2f} px"
            for lst in (s_names, s_obj, s_cam, s_proj):
                lst.pop(worst)
            continue
        break
    timings["stereo"] = time.perf_counter() - t0
    cam.K, cam.dist = Kc, np.ravel(dc)[:5]
    proj_fit.K, proj_fit.dist = Kp, np.ravel(dp)[:5]
    per_view = {n: (float(a), float(b)) for n, (a, b) in zip(s_names, pve)}
    data = {"names": s_names, "obj": s_obj, "camera": s_cam, "projector": s_proj,
            "rvecs": [np.ravel(r) for r in out[9]], "tvecs": [np.ravel(t) for t in out[10]]}
    return ProcamResult(cam, proj_fit, R, np.ravel(T), float(s_rms), per_view, observations, diagnostics, timings,
                        stereo_rejected, data)


def corner_spacing(px: np.ndarray, board: BoardSpec, ids: np.ndarray) -> float:
    obj = board.object_points()[ids]
    d_obj = np.linalg.norm(obj[:, None, :2] - obj[None, :, :2], axis=2)
    near = np.isclose(d_obj, board.square)
    if not near.any():
        return 20.0
    d_img = np.linalg.norm(px[:, None] - px[None], axis=2)
    return float(np.median(d_img[near]))


def _initial_extrinsics(cam: LensFit, proj: LensFit, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """projector_from_camera from the per-view board poses (median rotation vector / translation)."""
    rv, tv = [], []
    ci = {n: i for i, n in enumerate(cam.names)}
    pi = {n: i for i, n in enumerate(proj.names)}
    for n in names:
        Rc = cv2.Rodrigues(cam.rvecs[ci[n]])[0]
        Rp = cv2.Rodrigues(proj.rvecs[pi[n]])[0]
        R = Rp @ Rc.T
        rv.append(cv2.Rodrigues(R)[0].ravel())
        tv.append(proj.tvecs[pi[n]] - R @ cam.tvecs[ci[n]])
    R = cv2.Rodrigues(np.median(np.array(rv), axis=0))[0]
    return R, np.median(np.array(tv), axis=0)
