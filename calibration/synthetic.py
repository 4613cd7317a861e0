"""A synthetic projector + camera + board world with known ground truth.

A virtual camera and projector (OpenCV pinhole + distortion, projector with strong vertical
lens shift) look at a planar (or bowed) chessboard held at random tilted poses.  For every
pose the camera image of each Gray-code frame is rendered by tracing supersampled camera
rays to the board, looking up the projector pixel each surface point receives through the
projector's lens (nearest projector pixel, i.e. box-shaped projector pixels), and shading
``albedo * (ambient + cos * projector)``; then optical blur, gamma, noise and 8-bit
quantisation.  Nothing in the calibration pipeline sees the truth.

Frames: ``camera_from_board`` (board -> camera), ``projector_from_camera`` (camera ->
projector), ``world_from_camera`` (camera -> tracker world).  Metres.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from calibration.board import BoardSpec
from calibration.patterns import PatternSet, gray_encode
from dpmhw.render.distortion import distort


@dataclass
class Lens:
    """An OpenCV pinhole + distortion device (camera or projector)."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray

    def project(self, pts: np.ndarray) -> np.ndarray:
        """(n, 3) points in the device frame -> (n, 2) pixels (the ``cv2.projectPoints`` model)."""
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        x = pts[:, 0] / pts[:, 2]
        y = pts[:, 1] / pts[:, 2]
        xd, yd = distort(x, y, *self.dist)
        K = self.K
        return np.column_stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]])

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """(n, 2) pixels -> (n, 3) ray directions (x, y, 1) in the device frame."""
        uv = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
        xy = cv2.undistortPoints(uv, self.K, self.dist, None, None, None, crit).reshape(-1, 2)
        return np.column_stack([xy, np.ones(len(xy))])

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "K": self.K.tolist(), "dist": self.dist.tolist()}


def _rot(rvec) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))[0]


@dataclass
class SyntheticRig:
    """Everything the synthetic world needs, including the truth."""

    camera: Lens
    projector: Lens
    R_pc: np.ndarray  # projector_from_camera rotation
    t_pc: np.ndarray
    board: BoardSpec
    views: list[tuple[np.ndarray, np.ndarray]]  # camera_from_board (R, t)
    world_from_camera: tuple[np.ndarray, np.ndarray] = field(
        default_factory=lambda: (_rot([0.3, -0.5, 0.2]), np.array([0.4, 1.5, -2.0]))
    )
    bow: float = 0.0  # sag of the board centre line (metres); 0 = flat
    blur_sigma: float = 0.7  # camera pixels
    noise_sigma: float = 1.5  # DN (8-bit)
    gamma: float = 2.2
    ambient: float = 0.06
    black_albedo: float = 0.2
    white_albedo: float = 0.9
    projector_black: float = 0.01
    exposure: float = 0.85
    supersample: int = 2
    seed: int = 0
    _rays_cache: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def patterns(self) -> PatternSet:
        return PatternSet(self.projector.width, self.projector.height)

    # -- geometry ---------------------------------------------------------------------------
    def board_points(self) -> np.ndarray:
        """(n, 3) true corner positions in the board frame (bowed if ``bow``)."""
        p = self.board.object_points().copy()
        p[:, 2] = self._height(p[:, 0], p[:, 1])
        return p

    def _height(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        if self.bow == 0.0:
            return np.zeros_like(bx)
        s = self.board.square
        x0, x1 = -s, self.board.cols * s
        xc, hw = (x0 + x1) / 2, (x1 - x0) / 2
        return self.bow * (1.0 - ((bx - xc) / hw) ** 2)

    def corners_camera(self, i: int) -> np.ndarray:
        R, t = self.views[i]
        return self.camera.project(self.board_points() @ R.T + t)

    def corners_projector(self, i: int) -> np.ndarray:
        R, t = self.views[i]
        pc = self.board_points() @ R.T + t
        return self.projector.project(pc @ self.R_pc.T + self.t_pc)

    def _camera_rays(self) -> np.ndarray:
        if self._rays_cache is None:
            ss = self.supersample
            off = (np.arange(ss) + 0.5) / ss - 0.5
            v, u = np.mgrid[0 : self.camera.height, 0 : self.camera.width]
            # sample order (row, sub-row, col, sub-col) so a reshape averages each pixel
            uu = u[:, None, :, None] + off[None, None, None, :]
            vv = v[:, None, :, None] + off[None, :, None, None]
            uu, vv = np.broadcast_arrays(uu, vv)
            uv = np.column_stack([uu.ravel(), vv.ravel()])
            self._rays_cache = self.camera.rays(uv)
        return self._rays_cache

    # -- rendering --------------------------------------------------------------------------
    def render_view(self, i: int, frames: list[int] | None = None) -> np.ndarray:
        """Camera images (n_frames, H, W) uint8 of the Gray-code sequence at view ``i``.

        Edges (chessboard squares, projector stripes) are box-filtered analytically over each
        supersample's footprint, so 2x2 supersampling renders them without staircase bias.
        """
        R, t = self.views[i]
        H, W, ss = self.camera.height, self.camera.width, self.supersample
        d = self._camera_rays()
        n = R[:, 2]
        nd = d @ n
        nt = n @ t
        with np.errstate(divide="ignore", invalid="ignore"):
            h = np.zeros(len(d))
            for _ in range(6 if self.bow else 1):
                depth = (h + nt) / nd
                P = d * depth[:, None]
                b = (P - t) @ R
                h = self._height(b[:, 0], b[:, 1])
        hit = np.isfinite(depth) & (depth > 0)
        b = np.where(hit[:, None], b, 0.0)
        albedo = np.where(hit, self._albedo(b[:, 0], b[:, 1], (H * ss, W * ss)), 0.0)
        Pp = P @ self.R_pc.T + self.t_pc
        front = hit & (Pp[:, 2] > 1e-3)
        uvp = np.full((len(d), 2), -10.0)
        uvp[front] = self.projector.project(Pp[front])
        ix = np.floor(uvp[:, 0] + 0.5).astype(np.int64)
        iy = np.floor(uvp[:, 1] + 0.5).astype(np.int64)
        lit = front & (ix >= 0) & (ix < self.projector.width) & (iy >= 0) & (iy < self.projector.height)
        wpx = _footprint(uvp[:, 0], (H * ss, W * ss)).astype(np.float32)
        wpy = _footprint(uvp[:, 1], (H * ss, W * ss)).astype(np.float32)
        uvp32 = uvp.astype(np.float32)
        # projector irradiance falls off with the cosine of incidence (bowed boards: use the plane normal)
        to_proj = -(self.R_pc.T @ self.t_pc) - P
        cos = np.abs((to_proj / np.linalg.norm(to_proj, axis=1, keepdims=True)) @ n)
        A = (albedo * self.ambient).astype(np.float32)
        B = np.where(lit, albedo * cos, 0.0).astype(np.float32)
        gx = gray_encode(np.where(lit, ix, 0))
        gy = gray_encode(np.where(lit, iy, 0))

        def pix(a: np.ndarray) -> np.ndarray:
            return cv2.resize(a.reshape(H * ss, W * ss), (W, H), interpolation=cv2.INTER_AREA)

        A_m, B_m = pix(A), pix(B)
        leak = self.projector_black
        base = A_m + leak * B_m
        ps = self.patterns
        wanted = list(range(ps.count)) if frames is None else list(frames)
        rng = np.random.default_rng([self.seed, i, 7])
        out = np.empty((len(wanted), H, W), np.uint8)
        cache: dict[tuple[str, int], np.ndarray] = {}
        for j, f in enumerate(wanted):
            if f == 0:
                rad = base + (1 - leak) * B_m
            elif f == 1:
                rad = base
            else:
                axis = "x" if f < 2 + 2 * ps.col_bits else "y"
                k = (f - 2) // 2 if axis == "x" else (f - 2 - 2 * ps.col_bits) // 2
                inverse = (f % 2) == 1
                nb = ps.col_bits if axis == "x" else ps.row_bits
                if (axis, k) not in cache:
                    lsb = nb - 1 - k
                    code, coord, w = (gx, uvp32[:, 0], wpx) if axis == "x" else (gy, uvp32[:, 1], wpy)
                    bits = ((code >> lsb) & 1).astype(np.float32)
                    # distance to the nearest transition of this bit: between c-1 and c, c = 2^j mod 2^(j+1)
                    period = np.float32(2.0 ** (lsb + 1))
                    r = np.mod(coord + np.float32(0.5 - 2.0**lsb), period)
                    dist = np.minimum(r, period - r)
                    frac = np.float32(0.5) + np.minimum(dist, w * np.float32(0.5)) / w
                    val = (1 - frac) + bits * (2 * frac - 1)
                    cache[(axis, k)] = pix(B * val)
                S = cache[(axis, k)]
                rad = base + (1 - leak) * ((B_m - S) if inverse else S)
            out[j] = self._camera_response(rad, rng)
        return out

    def _albedo(self, bx: np.ndarray, by: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
        """Chessboard reflectance, box-filtered over each sample's footprint (ChArUco: texture)."""
        if self.board.kind == "charuco":
            return self._charuco_albedo(bx, by, grid)
        s = self.board.square
        wx = _footprint(bx, grid) / s
        wy = _footprint(by, grid) / s

        def wave(x: np.ndarray, w: np.ndarray) -> np.ndarray:
            q = np.floor(x)
            fr = x - q
            dist = np.minimum(fr, 1 - fr)
            parity = 1.0 - 2.0 * (np.mod(q, 2) != 0)
            return parity * np.clip(2 * dist / w, 0, 1)

        checker = wave(bx / s, wx) * wave(by / s, wy)  # +1 where (qi + qj) is even: dark
        dark = 0.5 * (1 + checker)
        cols, rows = self.board.cols, self.board.rows
        in_sq = (bx >= -s) & (bx <= cols * s) & (by >= -s) & (by <= rows * s)
        m = 0.8 * s
        on = (bx >= -s - m) & (bx <= cols * s + m) & (by >= -s - m) & (by <= rows * s + m)
        a = self.white_albedo + (self.black_albedo - self.white_albedo) * np.where(in_sq, dark, 0.0)
        return np.where(on, a, 0.0)

    def _charuco_albedo(self, bx: np.ndarray, by: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
        """ChArUco print (OpenCV's own board image) sampled bilinearly from a prefiltered texture."""
        s = self.board.square
        fp = float(np.median(np.maximum(_footprint(bx, grid), _footprint(by, grid))))
        ppm = 8.0 / max(fp, 1e-5)  # ~8 texels per sample footprint
        ppm = round(ppm * s) / s  # whole texels per square
        tex = _charuco_texture(self.board, ppm, 0.4 * ppm * fp)
        tx = (bx * ppm - 0.5).astype(np.float32).reshape(grid)
        ty = (by * ppm - 0.5).astype(np.float32).reshape(grid)
        val = cv2.remap(tex, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0).ravel()
        cols, rows = self.board.cols, self.board.rows
        m = 0.8 * s
        on = (bx >= -m) & (bx <= cols * s + m) & (by >= -m) & (by <= rows * s + m)
        a = self.black_albedo + (self.white_albedo - self.black_albedo) * val.astype(np.float64)
        return np.where(on, a, 0.0)

    def _camera_response(self, rad: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        img = rad.astype(np.float32)
        if self.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma)
        img = 255.0 * np.clip(img * self.exposure, 0, 1) ** (1.0 / self.gamma)
        if self.noise_sigma > 0:
            img += np.float32(self.noise_sigma) * rng.standard_normal(img.shape, dtype=np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    # -- truth and files --------------------------------------------------------------------
    def truth(self) -> dict:
        Rw, tw = self.world_from_camera
        R_cp = self.R_pc.T
        t_cp = -R_cp @ self.t_pc
        return {
            "camera": self.camera.to_dict(),
            "projector": self.projector.to_dict(),
            "projector_from_camera": {"R": self.R_pc.tolist(), "t": self.t_pc.tolist()},
            "world_from_camera": {"R": Rw.tolist(), "t": tw.tolist()},
            "world_from_projector": {"R": (Rw @ R_cp).tolist(), "t": (Rw @ t_cp + tw).tolist()},
            "camera_from_board": [{"R": R.tolist(), "t": t.tolist()} for R, t in self.views],
            "board": self.board.to_dict(),
            "bow": self.bow,
            "seed": self.seed,
        }

    def world_from_board(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        Rw, tw = self.world_from_camera
        R, t = self.views[i]
        return Rw @ R, Rw @ t + tw

    def write(self, out_dir: str | Path, *, tracker_noise: float = 0.0, progress=None) -> Path:
        """Write a capture folder (see :mod:`calibration.capture`) plus ``truth.json``.

        Also writes ``tracker_poses.json`` (world_from_board per pose, as a tracked rigid body
        would report it), with optional Gaussian position noise in metres. ``progress(done, total)``
        is called after each pose.
        """
        from calibration.capture import write_capture_meta

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_capture_meta(out, self.projector.width, self.projector.height, self.board)
        rng = np.random.default_rng([self.seed, 99])
        poses = []
        for i in range(len(self.views)):
            d = out / f"pose_{i:03d}"
            d.mkdir(exist_ok=True)
            for j, img in enumerate(self.render_view(i)):
                cv2.imwrite(str(d / f"{j:03d}.png"), img)
            R, t = self.world_from_board(i)
            poses.append({"pose": d.name, "R": R.tolist(), "t": (t + rng.normal(0, tracker_noise, 3)).tolist()})
            if progress is not None:
                progress(i + 1, len(self.views))
        (out / "truth.json").write_text(json.dumps(self.truth(), indent=1))
        (out / "tracker_poses.json").write_text(json.dumps({"units": "m", "world_from_board": poses}, indent=1))
        return out


def default_lenses(camera_size: tuple[int, int], projector_size: tuple[int, int], *, projector_cy: float = 1.03):
    """Camera and projector with realistic intrinsics; the projector's cy is ``projector_cy * height``."""
    cw, ch = camera_size
    pw, ph = projector_size
    cam = Lens(cw, ch, np.array([[1.10 * cw, 0, 0.51 * cw], [0, 1.10 * cw, 0.48 * ch], [0, 0, 1.0]]),
               np.array([-0.12, 0.09, 0.0006, -0.0004, 0.0]))
    proj = Lens(pw, ph, np.array([[1.45 * pw, 0, 0.515 * pw], [0, 1.45 * pw, projector_cy * ph], [0, 0, 1.0]]),
                np.array([0.03, -0.04, 0.0, 0.0, 0.0]))
    return cam, proj


def make_rig(
    seed: int = 0,
    n_views: int = 13,
    *,
    camera_size: tuple[int, int] = (640, 480),
    projector_size: tuple[int, int] = (400, 300),
    projector_cy: float = 1.03,
    board: BoardSpec | None = None,
    min_tilt_deg: float = 15.0,
    max_tilt_deg: float = 40.0,
    distance: tuple[float, float] = (0.55, 0.8),
    margin: float = 0.04,
    camera: Lens | None = None,
    projector: Lens | None = None,
    **options,
) -> SyntheticRig:
    """A rig with ``n_views`` random board poses fully visible to both camera and projector.

    ``min_tilt_deg = max_tilt_deg = 0`` gives fronto-parallel views (a degenerate set).
    Extra keyword arguments set :class:`SyntheticRig` fields (``bow``, ``noise_sigma``...).
    """
    rng = np.random.default_rng(seed)
    board = board or BoardSpec()
    cam_d, proj_d = default_lenses(camera_size, projector_size, projector_cy=projector_cy)
    cam = camera or cam_d
    proj = projector or proj_d
    # projector 12 cm right of and 15 cm below the camera, yawed toward the camera axis;
    # its lens shift throws the image upward
    R_cp = _rot([0.02, -0.10, 0.0])
    c_p = np.array([0.12, 0.15, 0.02])
    R_pc = R_cp.T
    t_pc = -R_pc @ c_p
    rig = SyntheticRig(cam, proj, R_pc, t_pc, board, [], seed=seed, **options)
    obj = rig.board_points()
    centre = obj.mean(axis=0)
    views: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(20000):
        if len(views) == n_views:
            break
        tilt = np.deg2rad(rng.uniform(min_tilt_deg, max_tilt_deg))
        phi = rng.uniform(0, 2 * np.pi)
        spin = np.deg2rad(rng.uniform(-20, 20))
        # board x right, y down, z away from the camera (OpenCV corner order); tilt in-plane
        R = _rot([np.cos(phi) * tilt, np.sin(phi) * tilt, 0]) @ _rot([0, 0, spin])
        z = rng.uniform(*distance)
        aim = np.array([rng.uniform(-0.25, 0.25), rng.uniform(-0.2, 0.2), 1.0])
        t = aim * z - R @ centre
        rig.views = views + [(R, t)]
        uc = rig.corners_camera(len(views))
        up = rig.corners_projector(len(views))
        pc = obj @ R.T + t
        if (pc[:, 2] <= 0).any():
            continue
        if not (_inside(uc, cam, margin) and _inside(up, proj, margin)):
            continue
        views.append((R, t))
    if len(views) < n_views:
        raise RuntimeError(f"could only place {len(views)} of {n_views} board poses in both fields of view")
    rig.views = views
    return rig


def _charuco_texture(board: BoardSpec, ppm: float, blur: float) -> np.ndarray:
    from calibration.board import charuco_image

    px_per_square = int(round(board.square * ppm))
    tex = charuco_image(board, px_per_square).astype(np.float32) / 255.0
    return cv2.GaussianBlur(tex, (0, 0), blur) if blur > 0 else tex


def _footprint(v: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """L1 width of a supersample's footprint in the units of ``v`` (finite differences)."""
    g = v.reshape(grid)
    du = np.abs(np.gradient(g, axis=1))
    dv = np.abs(np.gradient(g, axis=0))
    w = np.minimum(du + dv, 1e3).ravel()
    return np.maximum(w, 1e-6)


def _inside(uv: np.ndarray, lens: Lens, margin: float) -> bool:
    mx, my = margin * lens.width, margin * lens.height
    return bool(((uv[:, 0] > mx) & (uv[:, 0] < lens.width - mx) & (uv[:, 1] > my) & (uv[:, 1] < lens.height - my)).all())


def with_views(rig: SyntheticRig, idx: list[int]) -> SyntheticRig:
    """The same rig restricted to some views."""
    return replace(rig, views=[rig.views[i] for i in idx], _rays_cache=rig._rays_cache)
