"""Triangle meshes: loading (OBJ/PLY/STL through trimesh), shading normals, primitive shapes and
the Stanford bunny.

Every mesh is cleaned once at load: degenerate (zero-area) triangles are dropped and counted, so
no stage downstream divides by a zero-length normal.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dpmhw.limits import check_file_size, max_mesh_bytes
from dpmhw.mesh_limits import describe, read_mesh
from dpmhw.textures import Texture

log = logging.getLogger(__name__)

BOX_FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
# Larger coordinates are a wrong unit or a corrupt file, and overflow (squared areas) in `clean`.
MAX_COORDINATE = 1e9


@dataclass
class TriangleMesh:
    """vertices : (V, 3) float64; faces : (F, 3) int32; vertex_normals : (V, 3) or None (flat shading);
    uv : (V, 2) texture coordinates of `texture` (the albedo's), or both None; notes : what the
    mesh file declares that the renderer does not model."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray | None = None
    source: str = ""
    dropped_degenerate: int = field(default=0)
    uv: np.ndarray | None = None
    texture: Texture | None = None
    notes: list[str] = field(default_factory=list)

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
        return replace(self, vertices=self.vertices * scale, vertex_normals=normals)

    def recentred(self, mode: str) -> "TriangleMesh":
        """Move the model origin: 'none', 'centroid' (bounding-box centre) or 'bottom' (centre of the lowest face of the box)."""
        if mode == "none":
            return self
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        origin = (lo + hi) / 2
        if mode == "bottom":
            origin[1] = lo[1]
        return replace(self, vertices=self.vertices - origin)


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


# Edges whose faces turn by more than this stay sharp in a mesh file's default shading: a box's
# 90° edges do, a tessellated curve's few degrees per facet do not.
DEFAULT_SMOOTH_ANGLE_DEG = 30.0


def smooth_within(mesh: TriangleMesh, angle_deg: float) -> TriangleMesh:
    """Smooth shading across the edges whose two face normals differ by at most `angle_deg`;
    sharper edges (and faces wound against their neighbour) stay creases. Corners at the same
    coordinates are one vertex here (STL stores none shared; OBJ splits them at UV seams). A vertex
    is split into one copy per fan of faces joined by smooth edges around it, each copy with the
    area-weighted normal of its fan (the same coordinates, so the surface stays closed)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from trimesh.graph import face_adjacency

    _, at = np.unique(mesh.vertices, axis=0, return_inverse=True)
    faces = at.reshape(-1)[mesh.faces]  # vertex indices by position
    tri = mesh.triangles
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # nonzero: `clean` dropped degenerate faces
    unit = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    pairs, edges = face_adjacency(faces=faces, return_edges=True)
    smooth = np.einsum("ij,ij->i", unit[pairs[:, 0]], unit[pairs[:, 1]]) >= np.cos(np.radians(angle_deg))
    pairs, edges = pairs[smooth], edges[smooth]

    def corner(f, v):  # index into faces.ravel() of vertex v in face f
        return 3 * f + np.argmax(faces[f] == v[:, None], axis=1)

    a = np.concatenate([corner(pairs[:, 0], edges[:, 0]), corner(pairs[:, 0], edges[:, 1])])
    b = np.concatenate([corner(pairs[:, 1], edges[:, 0]), corner(pairs[:, 1], edges[:, 1])])
    n = faces.size
    count, label = connected_components(coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)), directed=False)
    normals = np.zeros((count, 3))
    np.add.at(normals, label, np.repeat(cross, 3, axis=0))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    group = label
    if mesh.uv is not None:  # a group's corners on two sides of a UV seam stay two vertices
        _, label = np.unique(np.stack([group, mesh.faces.ravel()], 1), axis=0, return_inverse=True)
        label = label.reshape(-1)
    first = np.empty(label.max() + 1, np.int64)
    first[label] = np.arange(n)  # a corner of each vertex
    corner = mesh.faces.ravel()[first]
    return replace(mesh, vertices=mesh.vertices[corner], faces=label.reshape(-1, 3).astype(np.int32),
                   vertex_normals=normals[group[first]], uv=None if mesh.uv is None else mesh.uv[corner])


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
        decoded = read_mesh(path)
    except (ValueError, OSError) as exc:
        raise ValueError(f"cannot read mesh {path}: {describe(exc)}") from exc
    vertices, faces = decoded.vertices, decoded.faces
    if len(faces) == 0:
        raise ValueError(f"mesh {path} has no triangles")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"mesh {path} has non-finite vertex coordinates")
    largest = float(np.abs(vertices).max())
    if largest > MAX_COORDINATE:
        raise ValueError(f"mesh {path} has a vertex coordinate of {largest:.3g}, over {MAX_COORDINATE:g} (wrong units?)")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"mesh {path} has faces that index missing vertices")
    mesh = clean(vertices, faces, smooth=smooth, source=str(path))
    mesh.uv, mesh.texture, mesh.notes = decoded.uv, decoded.texture, [f"{path.name}: {note}" for note in decoded.notes]
    return mesh


BUNNY_DATA = Path(__file__).parent / "data" / "stanford-bunny.npz"


def stanford_bunny(smooth: bool = True) -> TriangleMesh:
    """The Stanford bunny shipped as package data (its credit and terms in dpmhw/data/README.md),
    so every checkout renders the built-in scenes with the mesh their figures were measured on.
    The coordinates are stored as integers × 10⁶: the scan's six decimals, restored exactly."""
    with np.load(BUNNY_DATA) as data:
        vertices, faces = data["vertices_e6"] / 1e6, data["faces"]
    return clean(vertices, faces, smooth=smooth, source="builtin:bunny")
