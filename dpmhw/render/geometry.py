"""The scene as the kernels see it: flat triangle, material and light tables, plus Embree BVHs.

Built once per scene. Triangles are stored in each object's model space (scale applied), so the
G-buffer's model-space hit point comes straight from the barycentrics, and a moving object only
changes its pose row in `poses()`.
"""

from __future__ import annotations

import numpy as np

from dpmhw.render.embree import capi
from dpmhw.render.embree.accel import EmbreeAccel
from dpmhw.render.kernels import MIN_ALPHA, TRI_ALPHA, TRI_COLS, TRI_E1, TRI_E2, TRI_N0, TRI_NG, TRI_V0
from dpmhw.scene_file import Scene
from dpmhw.transforms import Pose

f32 = np.float32


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def make_accel(objects, tri_offsets, threads: int):
    """Embree through its C API from the kernels (RtcAccel), or embreex's one-ray path when
    libembree4 cannot be loaded (capi.load warns once)."""
    if capi.load():
        from dpmhw.render.embree.accel import RtcAccel

        return RtcAccel(objects, tri_offsets, threads=threads)
    return EmbreeAccel(objects, tri_offsets, threads=threads)


def _triangle_rows(mesh, alpha: np.ndarray | None = None) -> np.ndarray:
    """`SceneGeometry.tri` rows of one mesh (columns: kernels.TRI_V0 … TRI_ALPHA). TRI_ALPHA:
    each triangle's GGX α from a roughness map; 0 (no map) = the object's (obj_alpha)."""
    tri = mesh.triangles
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    rows = np.zeros((len(tri), TRI_COLS), f32)
    rows[:, TRI_V0:TRI_V0 + 3], rows[:, TRI_E1:TRI_E1 + 3], rows[:, TRI_E2:TRI_E2 + 3] = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    rows[:, TRI_NG:TRI_NG + 3] = normal
    corner = mesh.vertex_normals[mesh.faces] if mesh.vertex_normals is not None else np.repeat(normal[:, None], 3, 1)
    rows[:, TRI_N0:TRI_N0 + 9] = corner.reshape(len(tri), 9)  # the three corners' normals, TRI_N0, TRI_N1, TRI_N2
    if alpha is not None:
        rows[:, TRI_ALPHA] = alpha
    return rows


def _texture_tables(objects, tri_offsets, rows: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The albedo textures as the kernels read them (`kernels.albedo_at`): (tri_uv, obj_tex,
    texels). tri_uv (rows, 6) float32: the texture coordinates of each triangle row's three
    corners; obj_tex (O, 3) int64: each object's texture as (first texel, width, height), width
    0 for none; texels (N, 3) float32, linear RGB, each texture's rows top to bottom. Without a
    texture in the scene, one-row placeholders (no kernel reads them)."""
    obj_tex = np.zeros((len(objects), 3), np.int64)
    if not any(o.mesh.texture is not None for o in objects):
        return np.zeros((1, 6), f32), obj_tex, np.zeros((1, 3), f32)
    tri_uv = np.zeros((rows, 6), f32)
    texels, start, seen = [], 0, {}
    for i, o in enumerate(objects):
        mesh = o.mesh
        if mesh.texture is None:
            continue
        if id(mesh.texture) not in seen:
            seen[id(mesh.texture)] = start
            texels.append(mesh.texture.texels.reshape(-1, 3))
            start += len(texels[-1])
        width, height = mesh.texture.size
        obj_tex[i] = seen[id(mesh.texture)], width, height
        tri_uv[tri_offsets[i]:tri_offsets[i] + len(mesh.faces)] = mesh.uv[mesh.faces].reshape(-1, 6)
    return tri_uv, obj_tex, np.ascontiguousarray(texels[0] if len(texels) == 1 else np.concatenate(texels), f32)


class SceneGeometry:
    def __init__(self, scene: Scene, threads: int = 2):
        self.scene = scene
        objects = scene.objects
        unique: dict[tuple, int] = {}  # id(mesh) → offset of its triangles (own rows with a roughness map)
        rows = []
        offset = 0
        self.tri_offsets = np.zeros(len(objects), np.int32)
        for i, obj in enumerate(objects):
            mesh = obj.mesh
            key = (id(mesh),) if obj.face_roughness is None else (id(mesh), i)
            if key not in unique:
                unique[key] = offset
                alpha = None if obj.face_roughness is None else np.maximum(obj.face_roughness**2, MIN_ALPHA)
                rows.append(_triangle_rows(mesh, alpha))
                offset += len(mesh.faces)
            self.tri_offsets[i] = unique[key]
        self.tri = np.concatenate(rows)
        self.triangle_count = sum(len(o.mesh.faces) for o in objects)
        self.textures = _texture_tables(objects, self.tri_offsets, len(self.tri))

        self.obj_albedo = np.array([o.albedo for o in objects], f32)
        self.obj_specular = np.array([o.specular for o in objects], f32)
        self.obj_alpha = np.array([max(o.roughness**2, MIN_ALPHA) for o in objects], f32)
        self.obj_emission = np.array([o.emission for o in objects], f32)

        # Emissive triangles, chosen with probability ∝ area × luminance(emission).
        light_prim, light_obj, weight = [], [], []
        for i, o in enumerate(objects):
            if o.is_emissive:
                areas = o.mesh.face_areas()
                light_prim.append(self.tri_offsets[i] + np.arange(len(areas)))
                light_obj.append(np.full(len(areas), i))
                weight.append(areas * max(_luminance(o.emission), 1e-12))
        self.obj_pdf_area = np.zeros(len(objects), f32)
        if light_prim:
            w = np.concatenate(weight)
            total = w.sum()
            self.light_prim = np.concatenate(light_prim).astype(np.int32)
            self.light_obj = np.concatenate(light_obj).astype(np.int32)
            self.light_cdf = (np.cumsum(w) / total).astype(f32)
            self.light_cdf[-1] = 1.0
            for i, o in enumerate(objects):
                if o.is_emissive:  # pdf per unit area on any of its triangles
                    self.obj_pdf_area[i] = max(_luminance(o.emission), 1e-12) / total
        else:
            self.light_prim = np.zeros(1, np.int32)
            self.light_obj = np.zeros(1, np.int32)
            self.light_cdf = np.ones(1, f32)
        background = scene.render.background
        has_bg = bool(np.any(background > 0))
        # One shadow ray per vertex: the environment or the area lights, half and half when both exist.
        self.p_env = 0.0 if not has_bg else (1.0 if not light_prim else 0.5)
        self.background = background.astype(f32)
        self.accel = make_accel(objects, self.tri_offsets, threads)

    def light_rows(self, R: np.ndarray, T: np.ndarray) -> np.ndarray:
        """The emissive triangles in world space for poses R, T (from `poses`): (L, 12) float32
        rows of v0, e1, e2 and the unit geometric normal, in `light_cdf` order. The shading
        kernel samples lights from these, instead of transforming a model-space row per vertex."""
        rows = self.tri[self.light_prim]
        Rl, Tl = R[self.light_obj], T[self.light_obj]
        out = np.empty((len(rows), 12), f32)
        for c in range(4):  # v0 is a point (rotated and moved), e1, e2 and n directions (rotated)
            out[:, 3 * c:3 * c + 3] = np.einsum("lij,lj->li", Rl, rows[:, 3 * c:3 * c + 3])
        out[:, 0:3] += Tl
        return out

    def poses(self, poses: list[Pose]) -> tuple[np.ndarray, np.ndarray]:
        """Per-object model→world rotation (O, 3, 3) and translation (O, 3), float32."""
        R = np.array([p.R for p in poses], f32)
        t = np.array([p.t for p in poses], f32)
        return R, t

    # ---- mesh levels of detail (dpmhw.lod.mesh_pipeline) -------------------------------------------
    def add_levels(self, k: int, meshes) -> None:
        """Install the levels of moving object k (`meshes[0]` its own mesh, then coarser ones):
        their triangle rows are appended to `tri` and their model-space BVHs built, once; then
        `set_level` swaps them in place. Objects given the same level list (instances of one
        mesh, equal in content) share rows and BVHs."""
        obj = self.scene.objects[k]
        same = meshes[0] is obj.mesh or (np.array_equal(meshes[0].faces, obj.mesh.faces)
                                         and np.array_equal(meshes[0].vertices, obj.mesh.vertices))
        if not obj.is_dynamic or obj.is_emissive or obj.face_roughness is not None or obj.mesh.texture is not None or not same:
            raise ValueError(f"objects[{k}]: mesh levels need a moving, non-emissive, untextured object without a roughness "
                             "map, and its own mesh as level 0")
        if not hasattr(self, "_levels"):
            self._levels: dict[int, list] = {}  # object → [(tri offset, bvh, sphere, triangles) per level]
            self._level_cache: dict[int, list] = {}  # id(meshes[1]) → the same, shared by instances
            self._level_scenes: list = []
            self.level = np.zeros(len(self.scene.objects), np.int64)
        j = self.accel.dynamic_objects.index(k)
        base = (int(self.tri_offsets[k]), *self._dynamic_slot(j), len(obj.mesh.faces))
        key = id(meshes[1]) if len(meshes) > 1 else None
        if key not in self._level_cache:
            rows, entries, offset = [], [], len(self.tri)
            for mesh in meshes[1:]:
                rows.append(_triangle_rows(mesh))
                bvh, sphere = self._level_bvh(mesh)
                entries.append((offset, bvh, sphere, len(mesh.faces)))
                offset += len(mesh.faces)
            self.tri = np.concatenate([self.tri, *rows])
            self._level_cache[key] = entries
        self._levels[k] = [base] + self._level_cache[key]

    def _dynamic_slot(self, j: int):
        """(BVH, bounding sphere) the accelerator holds for its j-th moving object."""
        a = self.accel
        if hasattr(a, "acc"):  # RtcAccel: handle table and sphere rows the kernels read
            return int(a.acc[0][1 + j]), a.acc[4][j].copy()
        return a.dynamic_scenes[j], a.dynamic_bounds[j]

    def _level_bvh(self, mesh):
        """One model-space BVH of a level for this geometry's accelerator, and its bounding
        sphere (the accelerator's own formula)."""
        from dpmhw.render.embree.accel import _embree_scene

        v = np.asarray(mesh.vertices)
        centre = (v.min(axis=0) + v.max(axis=0)) / 2
        radius = np.linalg.norm(v - centre, axis=1).max() * (1 + 1e-4) + 1e-9
        if hasattr(self.accel, "acc"):
            scene = capi.RtcScene([np.asarray(v, np.float32)], [mesh.faces])
            self._level_scenes.append(scene)
            return scene.handle, np.array([*centre.astype(f32), f32(radius)], f32)
        return _embree_scene([v], [mesh.faces]), (centre.astype(f32), f32(radius))

    def set_level(self, k: int, level: int) -> None:
        """Object k uses its level `level` from the next query on: the global triangle offset,
        its BVH and its bounding sphere are swapped in place (no rebuild, kernel signatures as
        they are)."""
        offset, bvh, sphere, _ = self._levels[k][level]
        j = self.accel.dynamic_objects.index(k)
        self.tri_offsets[k] = offset
        a = self.accel
        if hasattr(a, "acc"):
            a.acc[0][1 + j] = bvh
            a.acc_moving[0][1 + j] = bvh
            a.acc[4][j] = sphere
        else:
            a.dynamic_scenes[j] = bvh
            a.dynamic_bounds[j] = sphere
        self.level[k] = level

    @property
    def active_triangles(self) -> int:
        """Triangles of the levels in use (`triangle_count` without levels)."""
        if not hasattr(self, "_levels"):
            return self.triangle_count
        return self.triangle_count + sum(lv[int(self.level[k])][3] - lv[0][3] for k, lv in self._levels.items())

    def close(self) -> None:
        self.accel.close()
        for scene in getattr(self, "_level_scenes", []):
            scene.close()
