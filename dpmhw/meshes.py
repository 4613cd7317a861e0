"""Triangle meshes: loading (OBJ/PLY through trimesh), primitive shapes, and a procedural bunny.

Every mesh is cleaned once at load: degenerate (zero-area) triangles are dropped and counted, so
no stage downstream divides by a zero-length normal.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from dpmhw.limits import check_file_size, max_mesh_bytes
from dpmhw.mesh_limits import describe, read_mesh

log = logging.getLogger(__name__)

BOX_FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
# Larger coordinates are a wrong unit or a corrupt file, and overflow (squared areas) in `clean`.
MAX_COORDINATE = 1e9


@dataclass
class TriangleMesh:
    """vertices : (V, 3) float64; faces : (F, 3) int32; vertex_normals : (V, 3) or None (flat shading)."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray | None = None
    source: str = ""
    dropped_degenerate: int = field(default=0)

    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) float64 corner positions."""
        return self.vertices[self.faces]

    def face_areas(self) -> np.ndarray:
        tri = self.triangles
        return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)

    def scaled(self, scale) -> "TriangleMesh":
        scale = np.broadcast_to(np.asarray(scale, dtype=float), (3,))
        normals = None
        if self.vertex_normals is not None:
            normals = self.vertex_normals / scale  # normals transform by the inverse transpose
            normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return TriangleMesh(self.vertices * scale, self.faces, normals, self.source, self.dropped_degenerate)

    def recentred(self, mode: str) -> "TriangleMesh":
        """Move the model origin: 'none', 'centroid' (bounding-box centre) or 'bottom' (centre of the lowest face of the box)."""
        if mode == "none":
            return self
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        origin = (lo + hi) / 2
        if mode == "bottom":
            origin[1] = lo[1]
        return TriangleMesh(self.vertices - origin, self.faces, self.vertex_normals, self.source, self.dropped_degenerate)


def clean(vertices: np.ndarray, faces: np.ndarray, smooth: bool, source: str) -> TriangleMesh:
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int32)
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    scale = max(float(np.abs(vertices).max(initial=0.0)), 1e-30)
    keep = area2 > (scale * 1e-7) ** 2
    dropped = int((~keep).sum())
    faces = faces[keep]
    normals = None
    if smooth:
        normals = np.zeros_like(vertices)
        for corner in range(3):  # area-weighted face normals accumulated at their corners
            np.add.at(normals, faces[:, corner], cross[keep])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    if dropped:
        log.info("%s: dropped %d degenerate triangles", source, dropped)
    return TriangleMesh(vertices, faces, normals, source, dropped)


def quad_mesh(size, segments=(1, 1)) -> TriangleMesh:
    """A size[0] × size[1] rectangle in the local XZ plane, centred, facing +Y; `segments`
    (nx, nz) > (1, 1) splits it into a grid of cells, two triangles each, so that per-face
    attributes (a scene's roughness_map) can vary across it."""
    sx, sz = np.asarray(size, dtype=float) / 2
    nx, nz = int(segments[0]), int(segments[1])
    if (nx, nz) == (1, 1):
        v = np.array([[-sx, 0, -sz], [sx, 0, -sz], [sx, 0, sz], [-sx, 0, sz]])
        f = np.array([[0, 2, 1], [0, 3, 2]])  # counter-clockwise seen from +Y → normal +Y
        return clean(v, f, smooth=False, source="quad")
    xs, zs = np.linspace(-sx, sx, nx + 1), np.linspace(-sz, sz, nz + 1)
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    v = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1)
    i, k = np.meshgrid(np.arange(nx), np.arange(nz), indexing="ij")
    c0 = (i * (nz + 1) + k).ravel()  # corner (i, k); the cell's others: +x is + (nz + 1), +z is + 1
    c1, c2, c3 = c0 + nz + 1, c0 + nz + 2, c0 + 1
    f = np.concatenate([np.stack([c0, c2, c1], 1), np.stack([c0, c3, c2], 1)])
    return clean(v, f, smooth=False, source=f"quad {nx}×{nz}")


def box_mesh(size, open_faces=()) -> TriangleMesh:
    """An axis-aligned box with outward normals; `open_faces` (e.g. '+z') are left out (a room's open front)."""
    half = np.asarray(size, dtype=float) / 2
    verts, faces = [], []
    for name in BOX_FACES:
        if name in open_faces:
            continue
        axis = "xyz".index(name[1])
        sign = 1.0 if name[0] == "+" else -1.0
        u_axis, v_axis = [(1, 2), (2, 0), (0, 1)][axis]
        normal = np.zeros(3)
        normal[axis] = sign
        u = np.zeros(3)
        u[u_axis] = 1.0
        v = np.zeros(3)
        v[v_axis] = 1.0
        centre = normal * half
        corners = [centre + (a * u + b * v) * half for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        base = len(verts)
        verts.extend(corners)
        # u × v = normal for the cyclic axis order, so (0,1,2) is counter-clockwise seen from outside
        tri = [[0, 1, 2], [0, 2, 3]] if sign > 0 else [[0, 2, 1], [0, 3, 2]]
        faces.extend([[base + i for i in t] for t in tri])
    return clean(np.array(verts), np.array(faces), smooth=False, source="box")


def sphere_mesh(radius: float, subdivisions: int = 4, smooth: bool = True) -> TriangleMesh:
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    mesh = clean(np.asarray(ico.vertices) * radius, ico.faces, smooth=False, source=f"sphere r={radius}")
    if smooth:  # the exact sphere normal, not an average of facets
        mesh.vertex_normals = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    return mesh


def load_mesh(path: Path, smooth: bool = True) -> TriangleMesh:
    """Load a mesh file (see `mesh_limits` for the formats and the bounds on what is decoded).
    Raises FileNotFoundError / ValueError with the path in the message."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    check_file_size(path, max_mesh_bytes(), "mesh file", "DPMHW_MAX_MESH_MB")
    try:
        vertices, faces = read_mesh(path)
    except (ValueError, OSError) as exc:
        raise ValueError(f"cannot read mesh {path}: {describe(exc)}") from exc
    if len(faces) == 0:
        raise ValueError(f"mesh {path} has no triangles")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"mesh {path} has non-finite vertex coordinates")
    largest = float(np.abs(vertices).max())
    if largest > MAX_COORDINATE:
        raise ValueError(f"mesh {path} has a vertex coordinate of {largest:.3g}, over {MAX_COORDINATE:g} (wrong units?)")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"mesh {path} has faces that index missing vertices")
    return clean(vertices, faces, smooth=smooth, source=str(path))


def _shared_data_dir() -> Path:
    # ../shared/data beside the checkout (present in CI and on developer machines, absent in a user's clone)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def find_bunny() -> Path | None:
    """The Stanford bunny: $DPMHW_BUNNY, else ../shared/data/stanford-bunny.obj; None if neither exists."""
    env = os.environ.get("DPMHW_BUNNY")
    for candidate in ([Path(env)] if env else []) + [_shared_data_dir() / "stanford-bunny.obj"]:
        if candidate.is_file():
            return candidate
    return None


@lru_cache(maxsize=4)
def procedural_bunny(resolution: int = 118) -> TriangleMesh:
    """A bunny-like closed surface (body, head, ears, tail) of about the Stanford bunny's size
    (≈0.15 wide) and triangle count (≈70k at the default resolution), from marching cubes on a
    smooth union of ellipsoids. Used when the real scan is not available."""
    from skimage.measure import marching_cubes

    def ellipsoid(p, centre, radii):
        q = (p - np.asarray(centre)) / np.asarray(radii)
        return (np.linalg.norm(q, axis=-1) - 1.0) * min(radii)

    def smooth_union(a, b, k=0.012):
        h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
        return b * (1 - h) + a * h - k * h * (1 - h)

    lo, hi = np.array([-0.10, 0.0, -0.075]), np.array([0.10, 0.20, 0.075])
    axes = [np.linspace(lo[i], hi[i], resolution) for i in range(3)]
    p = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    d = ellipsoid(p, (0.0, 0.055, 0.0), (0.075, 0.052, 0.058))  # body
    d = smooth_union(d, ellipsoid(p, (-0.055, 0.095, 0.0), (0.036, 0.034, 0.032)))  # head
    d = smooth_union(d, ellipsoid(p, (-0.05, 0.15, 0.016), (0.011, 0.04, 0.008)), 0.006)  # ears
    d = smooth_union(d, ellipsoid(p, (-0.045, 0.15, -0.016), (0.011, 0.04, 0.008)), 0.006)
    d = smooth_union(d, ellipsoid(p, (0.075, 0.05, 0.0), (0.016, 0.016, 0.016)), 0.008)  # tail
    spacing = (hi - lo) / (resolution - 1)
    verts, faces, _, _ = marching_cubes(d, level=0.0, spacing=tuple(spacing))
    verts = verts + lo
    return clean(verts, faces, smooth=True, source="procedural bunny")
