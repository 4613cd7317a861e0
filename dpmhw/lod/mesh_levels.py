"""Mesh level of detail: quadric-simplified levels, one model-space BVH each, chosen per object.

Levels are built once per mesh with `fast-simplification` (Garland–Heckbert quadric edge
collapse, the maintained PyPI package; extra `lod`). Level 0 is the mesh itself. Each level is a
whole mesh — closed if the input is closed (edge collapse keeps a manifold closed; open borders
are kept with `preserve_border`) — and is swapped atomically for the whole object, so there are
no T-junctions between levels and no cracks: the only artefact of a switch is the pop, the image
difference between two levels, which `pop_visibility` measures against the visibility threshold.

Each level carries its geometric error ε (model metres): a symmetric, conservative estimate of
the Hausdorff distance between the level and the original, taken as the larger of the two
one-sided maxima; a vertex's distance to the other surface is bounded above by the nearer of
(a) the hit along its normal (both ways) through the other surface's BVH and (b) the nearest
vertex of the other surface. The BVH (embreex, model space) is built once per level and serves
these queries and the pop renders. In the pipeline (`mesh_pipeline.MeshLod`) the renderer gets its
own copy of each level's rows and BVH once (`SceneGeometry.add_levels`) and swaps them in place;
`scene_at_levels` builds the equivalent scene from scratch (the tests' reference).

Selection per object per frame (`MeshLodSelector`): from the object's nearest depth and its
visibility (max V over the tiles it covered last frame). For visible objects a level is allowed
only beyond the depth where the measured pop of every switch up to it is below the visibility
threshold; for invisible ones, where its projected error ε · f_px / z is below a pixel allowance;
for both, only once the next finer level's triangles project to at most `edge_px` projector
pixels per edge (projected size: mean edge · f_px / z).
Coarsening needs a hysteresis margin, so an object at a switch depth does not flip every frame.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from embreex import mesh_construction, rtcore_scene
from scipy.spatial import cKDTree

from dpmhw.lod.csf import A_PEAK, sensitivity
from dpmhw.lod.visibility import LodSettingsError, VisibilitySettings, check_number
from dpmhw.meshes import TriangleMesh, clean
from dpmhw.transforms import Pose

DEFAULT_REDUCTIONS = (0.0, 0.5, 0.75, 0.9, 0.97)  # fraction of triangles removed per level


def build_bvh(mesh: TriangleMesh) -> rtcore_scene.EmbreeScene:
    """A model-space Embree BVH of one mesh (built once; queries with `run`)."""
    scene = rtcore_scene.EmbreeScene(robust=True)
    mesh_construction.TriangleMesh(scene, np.ascontiguousarray(mesh.vertices, np.float32), np.ascontiguousarray(mesh.faces, np.int32))
    return scene


@dataclass
class MeshLevel:
    mesh: TriangleMesh
    error_m: float  # conservative symmetric Hausdorff distance to level 0, model metres
    bvh: rtcore_scene.EmbreeScene

    @property
    def triangles(self) -> int:
        return len(self.mesh.faces)


def _distance_bound(points: np.ndarray, normals: np.ndarray, mesh: TriangleMesh, bvh, tree: cKDTree) -> np.ndarray:
    """Upper bound of each point's distance to `mesh`'s surface (see the module docstring)."""
    near, _ = tree.query(points)
    o = np.ascontiguousarray(points, np.float32)
    best = near.copy()
    for sign in (1.0, -1.0):
        d = np.ascontiguousarray(sign * normals, np.float32)
        res = bvh.run(o, d, output=True)
        t = np.where(res["primID"] >= 0, res["tfar"], np.inf)
        best = np.minimum(best, t)
    return best


def hausdorff_bound(a: TriangleMesh, bvh_a, b: TriangleMesh, bvh_b) -> float:
    """Conservative symmetric Hausdorff distance between two meshes (vertex samples)."""
    def normals(m):
        if m.vertex_normals is not None:
            return m.vertex_normals
        return clean(m.vertices, m.faces, True, m.source).vertex_normals

    ab = _distance_bound(a.vertices, normals(a), b, bvh_b, cKDTree(b.vertices))
    ba = _distance_bound(b.vertices, normals(b), a, bvh_a, cKDTree(a.vertices))
    return float(max(ab.max(initial=0.0), ba.max(initial=0.0)))


class MeshLevels:
    """The levels of one mesh, finest first; built once."""

    def __init__(self, mesh: TriangleMesh, reductions=DEFAULT_REDUCTIONS, aggressiveness: float = 7.0):
        import fast_simplification  # the `lod` extra

        reductions = tuple(float(r) for r in reductions)
        if not reductions or reductions[0] != 0.0 or any(not (0 <= r < 1) for r in reductions) or list(reductions) != sorted(set(reductions)):
            raise LodSettingsError(f"reductions: expected ascending fractions in [0, 1) starting at 0, got {reductions!r}")
        smooth = mesh.vertex_normals is not None
        base_bvh = build_bvh(mesh)
        self.levels = [MeshLevel(mesh, 0.0, base_bvh)]
        for r in reductions[1:]:
            v, f = fast_simplification.simplify(mesh.vertices, mesh.faces.astype(np.int32), target_reduction=r, agg=aggressiveness,
                                                  preserve_border=True)
            used = np.unique(f)  # drop vertices no face uses any more
            remap = np.full(len(v), -1, np.int64)
            remap[used] = np.arange(len(used))
            level = clean(v[used], remap[f], smooth, f"{mesh.source} (−{r:.0%})")
            bvh = build_bvh(level)
            self.levels.append(MeshLevel(level, hausdorff_bound(mesh, base_bvh, level, bvh), bvh))
        # ε must not shrink as levels coarsen (a coarser level with a smaller bound would be
        # chosen closer than a finer one): keep the running maximum
        running = 0.0
        for lv in self.levels:
            running = max(running, lv.error_m)
            lv.error_m = running

    def __len__(self) -> int:
        return len(self.levels)

    @property
    def errors_m(self) -> np.ndarray:
        return np.array([lv.error_m for lv in self.levels])

    @property
    def triangle_counts(self) -> list[int]:
        return [lv.triangles for lv in self.levels]

    @property
    def edges_m(self) -> np.ndarray:
        """Mean triangle edge length per level (model metres): the projected size's scale."""
        if not hasattr(self, "_edges_m"):
            out = []
            for lv in self.levels:
                tri = lv.mesh.triangles
                out.append(float(np.mean(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2))))
            self._edges_m = np.array(out)
        return self._edges_m


@dataclass(frozen=True)
class MeshLodSettings:
    """invisible_error_px: geometric error allowed on objects nobody can see (V ≤ 0 on all their
    tiles); edge_px: a level is left for a coarser one only while its own triangles project to
    at most this many projector pixels per edge (finer than the projector can draw);
    hysteresis: relative margin before moving to a coarser level; far_m / step: the depth scan
    for pop-safe switch depths (from far_m nearer by factor `step`)."""

    invisible_error_px: float = 2.0
    edge_px: float = 1.0
    hysteresis: float = 0.2
    far_m: float = 100.0
    step: float = 1.15

    def __post_init__(self):
        object.__setattr__(self, "invisible_error_px", check_number("invisible_error_px", self.invisible_error_px, 0.0, 1e3, lo_open=True))
        object.__setattr__(self, "edge_px", check_number("edge_px", self.edge_px, 0.0, 1e3, lo_open=True))
        object.__setattr__(self, "hysteresis", check_number("hysteresis", self.hysteresis, 0.0, 0.99))
        object.__setattr__(self, "far_m", check_number("far_m", self.far_m, 0.0, 1e4, lo_open=True))
        object.__setattr__(self, "step", check_number("step", self.step, 1.0, 4.0, lo_open=True))


@nb.njit(nogil=True, cache=True)
def _object_max(vis, object_id, tile, n_objects, out):
    out[:] = -np.inf
    H, W = object_id.shape
    for y in range(H):
        for x in range(W):
            k = object_id[y, x]
            if 0 <= k < n_objects:
                v = vis[y // tile, x // tile]
                if v > out[k]:
                    out[k] = v


def object_visibility(visibility: np.ndarray, tile: int, object_id: np.ndarray, n_objects: int) -> np.ndarray:
    """(n_objects,) max V over the tiles each object covered (−inf: not on screen)."""
    out = np.empty(n_objects, np.float64)
    _object_max(np.ascontiguousarray(visibility, np.float32), np.ascontiguousarray(object_id, np.int32), int(tile), int(n_objects), out)
    return out


def pop_safe_depth(levels: MeshLevels, level: int, focal_px: float, visibility: VisibilitySettings, far_m: float = 100.0,
                   step: float = 1.15) -> float:
    """Nearest depth from which switching between `level` − 1 and `level` stays invisible:
    scanning from `far_m` nearer by `step`, the last depth where `pop_visibility` ≤ 0 before
    the first visible pop (inf if the pop is visible even at `far_m`)."""
    z, safe = far_m, math.inf
    while z > 1e-3:
        if pop_visibility(levels, level, z, focal_px, visibility) > 0:
            break
        safe, z = z, z / step
    return safe


class MeshLodSelector:
    """Chooses a level per object per frame; keeps the current choice (hysteresis state).

    Level l is allowed for an object whose nearest point is at depth z when
    - the object is visible (V > 0 on a tile it covered last frame) and z ≥ the measured
      pop-safe depth of every switch up to l (`pop_safe_depth`, computed here once per mesh), or
    - it is invisible and l's projected error ε_l · f_px / z ≤ `invisible_error_px`.
    Moving to a coarser level needs the condition with margin (depth × (1 + h), error × (1 − h));
    moving finer happens as soon as the current level is no longer allowed."""

    def __init__(self, levels: list[MeshLevels | None], focal_px: float, settings: MeshLodSettings = MeshLodSettings(),
                 visibility: VisibilitySettings = VisibilitySettings()):
        self.levels, self.focal_px, self.settings = levels, float(focal_px), settings
        self.current = np.zeros(len(levels), np.int64)
        self._bounds, self.safe_depths = [], []
        measured: dict[int, np.ndarray] = {}
        for lv in levels:
            if lv is None:
                self._bounds.append(None)
                self.safe_depths.append(None)
                continue
            v = lv.levels[0].mesh.vertices  # model-space bounding sphere of level 0
            c = (v.min(0) + v.max(0)) / 2
            self._bounds.append((c, float(np.linalg.norm(v - c, axis=1).max())))
            if id(lv) not in measured:
                per_switch = [0.0] + [pop_safe_depth(lv, k, self.focal_px, visibility, settings.far_m, settings.step) for k in range(1, len(lv))]
                measured[id(lv)] = np.maximum.accumulate(per_switch)  # level l needs every switch up to l safe
            self.safe_depths.append(measured[id(lv)])

    def nearest_depth(self, k: int, pose: Pose, camera_pose: Pose) -> float:
        c, r = self._bounds[k]
        centre_cam = (pose.apply(c[None])[0] - camera_pose.t) @ camera_pose.R
        return float(centre_cam[2] - r)

    def edge_px(self, k: int, depth: float) -> np.ndarray:
        """Projected size: projector pixels per mean triangle edge of each level at `depth`
        (inf at or behind the projector's plane)."""
        return self.levels[k].edges_m * self.focal_px / depth if depth > 0 else np.full(len(self.levels[k]), np.inf)

    def _allowed(self, k: int, depth: float, visible: bool, margin: float) -> int:
        """Coarsest allowed level (margin 0: as is; > 0: with the hysteresis margin). Level l
        needs the pop (visible) or error (invisible) rule, and level l − 1's triangles at most
        `edge_px` wide on screen. A NaN depth or one at or behind the plane allows level 0 only."""
        if not depth > 0:
            return 0
        if visible:
            ok = self.safe_depths[k] * (1.0 + margin) <= depth
        else:
            ok = self.levels[k].errors_m * self.focal_px / depth <= self.settings.invisible_error_px * (1.0 - margin)
        small = self.edge_px(k, depth) <= self.settings.edge_px * (1.0 - margin)
        ok[1:] &= small[:-1]
        ok = np.logical_and.accumulate(ok)
        return int(np.nonzero(ok)[0].max()) if ok.any() else 0

    def select(self, poses: list[Pose], camera_pose: Pose, visibility: np.ndarray) -> np.ndarray:
        """Levels (n_objects,) for this frame from the poses and per-object visibility
        (`object_visibility`); objects without levels stay at 0."""
        h = self.settings.hysteresis
        for k, lv in enumerate(self.levels):
            if lv is None:
                continue
            depth = self.nearest_depth(k, poses[k], camera_pose)
            visible = bool(visibility[k] > 0)
            cur = int(self.current[k])
            allowed = self._allowed(k, depth, visible, 0.0)
            if allowed > cur:
                allowed = max(cur, self._allowed(k, depth, visible, h))
            self.current[k] = allowed
        return self.current.copy()


def scene_at_levels(scene, level_sets: list[MeshLevels | None], choice) -> object:
    """A copy of `scene` whose objects use the chosen levels' meshes (whole meshes: no cracks)."""
    objects = [o if lv is None or int(c) == 0 else dataclasses.replace(o, mesh=lv.levels[int(c)].mesh)
               for o, lv, c in zip(scene.objects, level_sets, choice)]
    return dataclasses.replace(scene, objects=objects)


# ----------------------------------------------------------------------------------------------
# pop measurement


def _shade(mesh: TriangleMesh, bvh, depth_m: float, rotation: np.ndarray, focal_px: float, size: int, ss: int) -> np.ndarray:
    """Luminance of the mesh rotated by `rotation`, its centre `depth_m` in front of a pinhole
    camera, Lambert under a fixed light plus 10 % ambient, black background, `ss`² samples per
    pixel on a grid (box filter): the image a projector pixel integrates."""
    v = mesh.vertices
    centre = (v.min(0) + v.max(0)) / 2
    n = size * ss
    ys, xs = np.mgrid[0:n, 0:n]
    px = (np.stack([xs.ravel(), ys.ravel()], 1) + 0.5) / ss - size / 2
    d = np.concatenate([px / focal_px, np.ones((n * n, 1))], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # camera at the origin looking down +z; model point x → rotation @ (x − centre) + (0, 0, depth)
    o_model = rotation.T @ (np.array([0.0, 0.0, -depth_m])) + centre
    d_model = d @ rotation  # rows: Rᵀ d
    res = bvh.run(np.ascontiguousarray(np.broadcast_to(o_model, d.shape), np.float32), np.ascontiguousarray(d_model, np.float32), output=True)
    hit = res["primID"] >= 0
    lum = np.zeros(n * n)
    if hit.any():
        f = mesh.faces[res["primID"][hit]]
        u, w = res["u"][hit][:, None], res["v"][hit][:, None]
        vn = mesh.vertex_normals
        if vn is None:
            tri = v[f]
            nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        else:
            nrm = (1 - u - w) * vn[f[:, 0]] + u * vn[f[:, 1]] + w * vn[f[:, 2]]
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        nrm = np.where((nrm * d_model[hit]).sum(1, keepdims=True) > 0, -nrm, nrm)  # face the camera
        light = rotation.T @ (np.array([0.4, -0.6, -1.0]) / np.linalg.norm([0.4, -0.6, -1.0]))
        lum[hit] = 0.1 + 0.9 * np.clip(nrm @ light, 0, None)
    return lum.reshape(size, ss, size, ss).mean(axis=(1, 3))


def _views() -> list[np.ndarray]:
    def rot_y(a):
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    def rot_x(a):
        c, s = math.cos(a), math.sin(a)
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])

    return [np.diag([1.0, -1.0, -1.0]) @ r for r in (np.eye(3), rot_y(math.pi / 2), rot_y(math.pi), rot_x(math.pi / 2))]


def pop_visibility(levels: MeshLevels, level: int, depth_m: float, focal_px: float,
                   settings: VisibilitySettings = VisibilitySettings(), supersample: int = 4, max_size: int = 512) -> float:
    """Worst visibility of the pop when an object switches between `level` − 1 and `level` with
    its nearest point at camera depth `depth_m` (as the selector measures it), over four views
    (front, side, back, top).

    Both levels are rendered (`_shade`); per 16-px tile the pop's contrast is
    c = max |ΔL| / (L_max + L_min) over the tile's pixels of both images, and its frequency is
    that of a one-pixel feature, f = 1 / (2 θ_px) with θ_px the angle one projector pixel
    subtends for the viewer (the change of a geometric switch sits at silhouettes and shading
    edges: a pixel wide). V_pop = S(f) − 1/c + α_v; the switch is invisible when V_pop ≤ 0.
    """
    if not 1 <= level < len(levels):
        raise LodSettingsError(f"level: expected 1 … {len(levels) - 1}, got {level}")
    a, b = levels.levels[level - 1], levels.levels[level]
    v = a.mesh.vertices
    radius = float(np.linalg.norm(v - (v.min(0) + v.max(0)) / 2, axis=1).max())
    size = int(min(max_size, max(16, math.ceil(2.2 * radius * focal_px / max(depth_m, 1e-6)))))
    tile = settings.tile
    size = -(-size // tile) * tile
    worst = -math.inf
    for rot in _views():
        la = _shade(a.mesh, a.bvh, depth_m + radius, rot, focal_px, size, supersample)
        lb = _shade(b.mesh, b.bvh, depth_m + radius, rot, focal_px, size, supersample)
        worst = max(worst, image_pop_visibility(la, lb, depth_m, focal_px, settings))
    return worst


def image_pop_visibility(before: np.ndarray, after: np.ndarray, depth_m: float, focal_px: float,
                         settings: VisibilitySettings = VisibilitySettings()) -> float:
    """Worst visibility of the change between two luminance images (H, W) of the same view, a
    level switch apart, of a surface at `depth_m`: per tile c = max |ΔL| / (L_max + L_min) over
    the tile's pixels of both images, at the frequency of a one-pixel feature for the viewer;
    V = S(f) − 1/c + α_v (≤ 0: the pop is below the threshold; −1e4 + α_v when nothing changed)."""
    tile = settings.tile
    H, W = before.shape
    th, tw = -(-H // tile), -(-W // tile)
    pad = lambda img: np.pad(np.nan_to_num(np.asarray(img, np.float64)), ((0, th * tile - H), (0, tw * tile - W)))  # noqa: E731
    blocks = lambda img: pad(img).reshape(th, tile, tw, tile).swapaxes(1, 2).reshape(th, tw, -1)  # noqa: E731
    la, lb = blocks(before), blocks(after)
    diff = np.abs(la - lb).max(-1)
    both = np.concatenate([la, lb], -1)
    denom = both.max(-1) + both.min(-1)
    c = np.where(denom > 0, diff / np.where(denom > 0, denom, 1.0), 0.0)
    inv_c = np.where(c > 1e-4, 1.0 / np.maximum(c, 1e-4), 1e4)
    theta = math.degrees(math.atan(depth_m / focal_px / settings.viewer_distance_m))
    s_px = sensitivity(1.0 / (2.0 * theta), settings.peak_sensitivity, A_PEAK)
    return float((s_px - inv_c + settings.alpha_v).max())
