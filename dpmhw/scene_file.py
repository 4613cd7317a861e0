"""Scene files (TOML, written by hand) and the built-in scenes.

Every error names the file, the field and what was expected, because the person reading it is a
lab operator with the file open in an editor. Unknown fields are errors too: a typo must not pass
silently as a default.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from dpmhw.errors import CalibrationError, SceneError
from dpmhw.limits import check_file_size, max_mesh_bytes, max_scene_bytes, render_memory_problem
from dpmhw.mesh_limits import MeshCounts, budget_problem, count_file, scene_budget_problem
from dpmhw.meshes import (DEFAULT_SMOOTH_ANGLE_DEG, TriangleMesh, box_mesh, load_mesh, quad_mesh, smooth_within, sphere_mesh,
                           stanford_bunny, BOX_FACES, BUNNY_DATA)
from dpmhw.motion import ScriptedMotion
from dpmhw.transforms import Pose, look_at, rotation_from_euler_xyz_deg, rotation_from_quat_xyzw

log = logging.getLogger(__name__)

BUILTIN_SCENES = ("paper-static", "paper-dynamic", "dpm-bunny", "glossy-roughness")
# No quantity in a scene (metres, pixels, radiance) is near this; larger ones are typos or attacks,
# and would overflow into infinities and NaNs downstream (1e300 squared is inf).
MAX_MAGNITUDE = 1e9
# A timeline slower than a frame every 1000 s is a typo; below it, frame k sits so far out on the timeline
# that scripted motion loses every digit of precision (1 / 1e-300 s).
MIN_FPS = 1e-3
SHAPES = ("quad", "box", "sphere", "mesh")
SCENE_SECTIONS = {"render", "camera", "viewer", "objects"}


@dataclass(frozen=True)
class RenderSettings:
    width: int
    height: int
    max_bounces: int  # indirect bounces after the first hit; 0 = direct light only
    background: np.ndarray  # (3,) radiance of escaping rays; a constant environment light
    fps: float  # frame k of the timeline is at t = k / fps


@dataclass(frozen=True)
class CameraSpec:
    """OpenCV pinhole + distortion, and its camera→world pose (x right, y down, z forward)."""

    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    pose: Pose


@dataclass
class ObjectSpec:
    name: str
    shape: str
    mesh: TriangleMesh  # model space, metres, scale applied
    pose: Pose  # model→world at t = 0 (before scripted motion)
    albedo: np.ndarray
    specular: np.ndarray
    roughness: float  # with a roughness_map, its smallest value (what decisions such as MIS need)
    emission: np.ndarray
    rigid_body: int | None = None
    motion: ScriptedMotion | None = None
    face_roughness: np.ndarray | None = None  # (F,) per triangle, from a roughness_map; None: `roughness` everywhere

    @property
    def is_dynamic(self) -> bool:
        return self.motion is not None or self.rigid_body is not None

    @property
    def is_emissive(self) -> bool:
        return bool(np.any(self.emission > 0))

    def pose_at(self, t: float) -> Pose:
        return self.motion.pose_at(t, self.pose) if self.motion is not None else self.pose


@dataclass
class Scene:
    source: str
    render: RenderSettings
    camera: CameraSpec
    viewer_position: np.ndarray  # (3,) eye for view-dependent shading
    objects: list[ObjectSpec] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # e.g. "procedural bunny used"

    def object_poses(self, t: float) -> list[Pose]:
        return [obj.pose_at(t) for obj in self.objects]

    def at_size(self, width: int, height: int) -> "Scene":
        """The same scene rendered at another size: a point lands on the same place of the
        picture (intrinsics scaled about pixel centres, lens shift kept)."""
        r = self.render
        if (width, height) == (r.width, r.height):
            return self
        K = scale_intrinsics(self.camera.K, width / r.width, height / r.height)
        return dataclasses.replace(self, render=dataclasses.replace(r, width=width, height=height),
                                   camera=dataclasses.replace(self.camera, K=K))


def scale_intrinsics(K, sx: float, sy: float) -> np.ndarray:
    """K of the same camera with its image scaled by (sx, sy) about pixel centres (pixel x's
    centre is at x, so c' = (c + 0.5)·s − 0.5); the skew scales with x, as fx does."""
    K = np.array(K, dtype=np.float64, copy=True)
    K[0, 0], K[0, 1], K[0, 2] = K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5
    K[1, 1], K[1, 2] = K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5
    return K


class _Fields:
    """Typed access to one TOML table, raising SceneError with the full field path."""

    def __init__(self, source: str, table: dict, path: str, known: set[str]):
        self.source, self.table, self.path = source, table, path
        if not isinstance(table, dict):
            self.fail("", f"expected a table, got {type(table).__name__}")
        unknown = sorted(set(table) - known)
        if unknown:
            self.fail(unknown[0], f"unknown field (known fields: {', '.join(sorted(known))})")

    def fail(self, key: str, message: str):
        name = f"{self.path}.{key}" if key and self.path else (key or self.path)
        raise SceneError(self.source, name, message)

    def has(self, key: str) -> bool:
        return key in self.table

    def number(self, key, default=None, lo=-math.inf, hi=math.inf, integer=False, lo_open=False):
        if key not in self.table:
            if default is None:
                self.fail(key, "missing required field")
            return default
        value = self.table[key]
        kind = "an integer" if integer else "a number"
        if isinstance(value, bool) or not isinstance(value, (int,) if integer else (int, float)):
            self.fail(key, f"expected {kind}, got {value!r}")
        if not math.isfinite(value):
            self.fail(key, f"expected a finite number, got {value!r}")
        if abs(value) > MAX_MAGNITUDE:
            self.fail(key, f"expected a magnitude of at most {MAX_MAGNITUDE:g}, got {value!r}")
        if value < lo or value > hi or (lo_open and value == lo):
            bracket = "(" if lo_open else "["
            self.fail(key, f"expected {kind} in {bracket}{lo}, {hi}], got {value!r}")
        return value

    def vector(self, key, n=3, default=None, lo=-math.inf, hi=math.inf, scalar_ok=False) -> np.ndarray:
        if key not in self.table:
            if default is None:
                self.fail(key, "missing required field")
            return np.asarray(default, dtype=float)
        value = self.table[key]
        if scalar_ok and isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value] * n
        if not isinstance(value, list) or len(value) != n or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
        ):
            self.fail(key, f"expected a list of {n} numbers, got {value!r}")
        arr = np.asarray(value, dtype=float)
        if not np.all(np.isfinite(arr)):
            self.fail(key, f"expected finite numbers, got {value!r}")
        if np.any(np.abs(arr) > MAX_MAGNITUDE):
            self.fail(key, f"expected magnitudes of at most {MAX_MAGNITUDE:g}, got {value!r}")
        if np.any(arr < lo) or np.any(arr > hi):
            self.fail(key, f"expected every value in [{lo}, {hi}], got {value!r}")
        return arr

    def string(self, key, default=None, choices=None) -> str:
        if key not in self.table:
            if default is None:
                self.fail(key, "missing required field")
            return default
        value = self.table[key]
        if not isinstance(value, str):
            self.fail(key, f"expected a string, got {value!r}")
        if choices and value not in choices:
            self.fail(key, f"expected one of {', '.join(choices)}, got {value!r}")
        return value


def _rotation(f: _Fields, key: str = "rotation") -> np.ndarray:
    if not f.has(key):
        return np.eye(3)
    value = f.table[key]
    if isinstance(value, list) and len(value) == 4:
        q = f.vector(key, 4)
        if np.linalg.norm(q) < 1e-9:
            f.fail(key, "quaternion (x, y, z, w) has zero length")
        return rotation_from_quat_xyzw(q)
    if isinstance(value, list) and len(value) == 3:
        return rotation_from_euler_xyz_deg(f.vector(key, 3))
    f.fail(key, f"expected Euler XYZ degrees [rx, ry, rz] or a quaternion [x, y, z, w], got {value!r}")


def _parse_render(source: str, table: dict, calibrated: bool) -> RenderSettings:
    """`calibrated`: the camera comes from a calibration file, which gives the size (width and
    height 0 here unless the file states them, and then they must agree)."""
    f = _Fields(source, table, "render", {"width", "height", "max_bounces", "background", "fps"})
    width = f.number("width", default=0 if calibrated else None, lo=1, hi=16384, integer=True)
    height = f.number("height", default=0 if calibrated else None, lo=1, hi=16384, integer=True)
    if calibrated and (width == 0) != (height == 0):
        f.fail("height" if height == 0 else "width", "give both width and height, or neither (the calibration's)")
    problem = render_memory_problem(width, height) if width else None
    if problem is not None:
        f.fail("width", problem)
    return RenderSettings(
        width=width,
        height=height,
        max_bounces=f.number("max_bounces", default=1, lo=0, hi=64, integer=True),
        background=f.vector("background", default=(0, 0, 0), lo=0.0),
        fps=float(f.number("fps", default=947.0, lo=MIN_FPS, hi=1e5)),
    )


def _parse_camera(source: str, table: dict, base_dir: Path, render: RenderSettings) -> tuple[CameraSpec, RenderSettings]:
    """The camera, and `render` with the calibration's size where the file left it out."""
    f = _Fields(source, table, "camera", {"fx", "fy", "cx", "cy", "dist", "position", "look_at", "up", "calibration"})
    if f.has("calibration"):
        return _camera_from_calibration(f, base_dir, render)
    K = np.array(
        [
            [f.number("fx", lo=0, lo_open=True), 0.0, f.number("cx")],
            [0.0, f.number("fy", lo=0, lo_open=True), f.number("cy")],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = f.vector("dist", n=5, default=np.zeros(5))
    try:
        pose = look_at(f.vector("position"), f.vector("look_at"), f.vector("up", default=(0, 1, 0)))
    except ValueError as exc:
        f.fail("look_at", str(exc))
    return CameraSpec(K, dist, pose), render


def _camera_from_calibration(f: _Fields, base_dir: Path, render: RenderSettings) -> tuple[CameraSpec, RenderSettings]:
    extra = sorted(set(f.table) - {"calibration"})
    if extra:
        f.fail(extra[0], "cannot be combined with 'calibration' (the calibration file gives intrinsics and pose)")
    path = base_dir / f.string("calibration")
    try:
        from dpmhw.projector_calibration import load_projector_calibration
    except ImportError:
        f.fail("calibration", "calibration files need dpmhw.projector_calibration, which this install lacks")
    try:
        calib = load_projector_calibration(path)
    except CalibrationError as exc:
        f.fail("calibration", f"cannot load {path}: {exc}")
    except RecursionError:  # json nested too deeply to be a calibration file
        f.fail("calibration", f"cannot load {path}: JSON nested too deeply")
    if render.width == 0:
        problem = render_memory_problem(calib.width, calib.height)
        if problem is not None:
            f.fail("calibration", f"{path}: {problem}")
        render = replace(render, width=calib.width, height=calib.height)
    elif (calib.width, calib.height) != (render.width, render.height):
        f.fail("calibration", f"{path} is for {calib.width}×{calib.height}, but [render] asks {render.width}×{render.height}")
    dist = np.zeros(5)
    coeffs = np.asarray(calib.dist, float).reshape(-1)
    if coeffs.size > 5 and np.any(coeffs[5:] != 0):
        f.fail("calibration", f"{path} uses a distortion model with {coeffs.size} terms; the renderer supports k1 k2 p1 p2 k3")
    dist[: min(5, coeffs.size)] = coeffs[:5]
    return CameraSpec(np.asarray(calib.K, float), dist, Pose(np.asarray(calib.R, float), np.asarray(calib.t, float))), render


OBJECT_FIELDS = {
    "name", "shape", "size", "radius", "scale", "mesh", "smooth", "smooth_angle", "recentre", "open", "position", "rotation",
    "albedo", "specular", "roughness", "roughness_map", "emission", "rigid_body", "motion", "segments",
}
ROUGHNESS_MAP_FIELDS = {"axis", "edges", "values"}
MAX_ROUGHNESS_BANDS = 256
MAX_QUAD_SEGMENTS = 1024
MOTION_FIELDS = {"rotate_axis", "rotate_deg_per_s", "oscillate_direction", "oscillate_amplitude", "oscillate_period_s", "velocity"}


def _parse_motion(source: str, table, path: str) -> ScriptedMotion:
    f = _Fields(source, table, path, MOTION_FIELDS)
    axis = f.vector("rotate_axis", default=(0, 1, 0))
    direction = f.vector("oscillate_direction", default=(1, 0, 0))
    for key, v in (("rotate_axis", axis), ("oscillate_direction", direction)):
        if np.linalg.norm(v) < 1e-9:
            f.fail(key, "expected a non-zero direction")
    return ScriptedMotion(
        rotate_axis=tuple(axis),
        rotate_deg_per_s=float(f.number("rotate_deg_per_s", default=0.0)),
        oscillate_direction=tuple(direction),
        oscillate_amplitude=float(f.number("oscillate_amplitude", default=0.0, lo=0.0)),
        oscillate_period_s=float(f.number("oscillate_period_s", default=1.0, lo=0.0, lo_open=True)),
        velocity=tuple(f.vector("velocity", default=(0, 0, 0))),
    )


def _parse_mesh_shape(f: _Fields, shape: str, base_dir: Path, notes: list[str], mesh_override: Path | None) -> TriangleMesh:
    smooth = f.table.get("smooth", shape == "sphere")
    if not isinstance(smooth, bool):
        f.fail("smooth", f"expected true or false, got {smooth!r}")
    if f.has("smooth_angle") and (shape != "mesh" or f.has("smooth")):
        f.fail("smooth_angle", "only a mesh has one, and not together with smooth")
    # a mesh file's default: smooth within smooth_angle, its sharper edges kept (a box stays a box)
    angle = f.number("smooth_angle", default=DEFAULT_SMOOTH_ANGLE_DEG, lo=0.0, hi=180.0) if not f.has("smooth") else None
    if f.has("segments") and shape != "quad":
        f.fail("segments", "only a quad has segments")
    if shape == "quad":
        segments = f.vector("segments", n=2, default=(1, 1), lo=1, hi=MAX_QUAD_SEGMENTS)
        if np.any(segments != np.round(segments)):
            f.fail("segments", f"expected two whole numbers in [1, {MAX_QUAD_SEGMENTS}], got {f.table['segments']!r}")
        return quad_mesh(f.vector("size", n=2, lo=0.0), segments.astype(int))
    if shape == "box":
        open_faces = f.table.get("open", [])
        if not isinstance(open_faces, list) or any(face not in BOX_FACES for face in open_faces):
            f.fail("open", f"expected a list of faces among {', '.join(BOX_FACES)}, got {open_faces!r}")
        return box_mesh(f.vector("size", lo=0.0), open_faces)
    if shape == "sphere":
        return sphere_mesh(f.number("radius", lo=0.0, lo_open=True), smooth=smooth)
    name = f.string("mesh")
    if name == "builtin:bunny":
        override = mesh_override or os.environ.get("DPMHW_BUNNY")
        mesh = _load_mesh_field(f, Path(override), smooth) if override else stanford_bunny(smooth)
    else:
        mesh = _load_mesh_field(f, base_dir / name, smooth)
    notes += mesh.notes
    if angle is not None:
        mesh = smooth_within(mesh, angle)
    scale = f.vector("scale", default=(1, 1, 1), lo=0.0, scalar_ok=True)
    if np.any(scale <= 0):
        f.fail("scale", "expected positive scale factors")
    recentre = f.string("recentre", default="none", choices=("none", "centroid", "bottom"))
    return mesh.recentred(recentre).scaled(scale)


def _load_mesh_field(f: _Fields, path: Path, smooth: bool) -> TriangleMesh:
    try:
        return load_mesh(path, smooth=smooth)
    except (FileNotFoundError, ValueError) as exc:
        f.fail("mesh", str(exc))


def _parse_roughness_map(source: str, table, path: str, mesh: TriangleMesh) -> np.ndarray:
    """Per-triangle roughness from bands along a model-space direction: a triangle whose centroid
    c has c·axis/|axis| below edges[0] gets values[0], between edges[i−1] and edges[i] values[i],
    above the last edge values[-1]. Bands follow triangle boundaries (no texture lookup in the
    kernels: the renderer reads one roughness per triangle)."""
    f = _Fields(source, table, path, ROUGHNESS_MAP_FIELDS)
    axis = f.vector("axis")
    if np.linalg.norm(axis) < 1e-9:
        f.fail("axis", "expected a non-zero direction")
    edges, values = f.table.get("edges"), f.table.get("values")
    for key, v in (("edges", edges), ("values", values)):
        if v is None:
            f.fail(key, "missing required field")
        if not isinstance(v, list) or not v or len(v) > MAX_ROUGHNESS_BANDS or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and abs(x) <= MAX_MAGNITUDE for x in v):
            f.fail(key, f"expected a list of 1 to {MAX_ROUGHNESS_BANDS} finite numbers, got {v!r}")
    if any(b <= a for a, b in zip(edges, edges[1:])):
        f.fail("edges", f"expected strictly increasing positions (model-space metres), got {edges!r}")
    if len(values) != len(edges) + 1:
        f.fail("values", f"expected {len(edges) + 1} roughness values (one per band, one more than edges), got {len(values)}")
    if any(not 0.0 <= x <= 1.0 for x in values):
        f.fail("values", f"expected every roughness in [0.0, 1.0], got {values!r}")
    s = mesh.triangles.mean(axis=1) @ (axis / np.linalg.norm(axis))
    return np.asarray(values, float)[np.searchsorted(np.asarray(edges, float), s, side="right")]


def _check_mesh_budget(source: str, tables: list, base_dir: Path, mesh_override: Path | None) -> None:
    """Refuse a scene whose meshes, each within the budget, together exceed the render memory
    limit, before any of them is decoded (`mesh_limits.scene_budget_problem`). A file that cannot
    be counted, or is over the budget alone, is left to its object's own parse, which names what
    is wrong with it."""
    meshes: dict[str, MeshCounts] = {}
    for i, table in enumerate(tables):
        if not isinstance(table, dict):
            continue
        shape, name = table.get("shape"), table.get("mesh")
        if shape == "quad" and isinstance(table.get("segments"), list) and len(table["segments"]) == 2 \
                and all(isinstance(n, int) and 1 <= n <= MAX_QUAD_SEGMENTS for n in table["segments"]):
            nx, nz = table["segments"]
            meshes[f"objects[{i}] (quad {nx}×{nz})"] = MeshCounts((nx + 1) * (nz + 1), 2 * nx * nz, "grid")
        if shape != "mesh" or not isinstance(name, str):
            continue
        override = mesh_override or os.environ.get("DPMHW_BUNNY")
        if name == "builtin:bunny" and not override:
            with np.load(BUNNY_DATA) as data:
                meshes[f"objects[{i}] builtin:bunny"] = MeshCounts(len(data["vertices_e6"]), len(data["faces"]), "package data")
            continue
        path = Path(override) if name == "builtin:bunny" else base_dir / name
        try:
            check_file_size(path, max_mesh_bytes(), "mesh file", "DPMHW_MAX_MESH_MB")
            counts = count_file(path)[1]
        except (ValueError, OSError):
            continue
        if budget_problem(counts) is None:  # one over the budget alone: its object's parse says so
            meshes[f"objects[{i}] {path}"] = counts
    if problem := scene_budget_problem(meshes):
        raise SceneError(source, "objects", problem)


def _parse_object(source: str, table, index: int, base_dir: Path, notes: list[str], mesh_override) -> ObjectSpec:
    path = f"objects[{index}]"
    f = _Fields(source, table, path, OBJECT_FIELDS)
    shape = f.string("shape", choices=SHAPES)
    name = f.string("name", default=f"{shape}{index}")
    mesh = _parse_mesh_shape(f, shape, base_dir, notes, mesh_override)
    if len(mesh.faces) == 0:
        f.fail("size" if shape != "mesh" else "mesh", "the shape has no non-degenerate triangles")
    # a textured mesh's albedo multiplies its texture: 1 by default, the texture as painted
    albedo = f.vector("albedo", default=(0.8,) * 3 if mesh.texture is None else (1.0,) * 3, lo=0.0, hi=1.0, scalar_ok=True)
    specular = f.vector("specular", default=(0, 0, 0), lo=0.0, hi=1.0, scalar_ok=True)
    rigid_body = f.number("rigid_body", default=-1, lo=0, integer=True) if f.has("rigid_body") else None
    face_roughness = None
    if f.has("roughness_map"):
        if f.has("roughness"):
            f.fail("roughness_map", "cannot be combined with 'roughness' (the map gives every triangle its roughness)")
        face_roughness = _parse_roughness_map(source, f.table["roughness_map"], f"{path}.roughness_map", mesh)
    return ObjectSpec(
        name=name,
        shape=shape,
        mesh=mesh,
        pose=Pose(_rotation(f), f.vector("position", default=(0, 0, 0))),
        albedo=albedo,
        specular=specular,
        roughness=float(face_roughness.min()) if face_roughness is not None else float(f.number("roughness", default=0.5, lo=0.0, hi=1.0)),
        emission=f.vector("emission", default=(0, 0, 0), lo=0.0, scalar_ok=True),
        rigid_body=rigid_body,
        motion=_parse_motion(source, f.table["motion"], f"{path}.motion") if f.has("motion") else None,
        face_roughness=face_roughness,
    )


def _toml(text: str, source: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(source, "(syntax)", f"not valid TOML: {exc}") from None
    except RecursionError:
        raise SceneError(source, "(syntax)", "arrays or tables nested too deeply to be a scene") from None


def parse_scene(text: str, source: str, base_dir: Path, mesh_override: Path | None = None) -> Scene:
    data = _toml(text, source)
    top = _Fields(source, data, "", SCENE_SECTIONS)

    def section(name: str):
        if not top.has(name):
            top.fail(name, "missing required section")
        return data[name]

    # sections in file order, each parsed before the next is asked for: a typo in [render] is
    # reported as that typo, not as a missing [camera] further down
    calibrated = isinstance(data.get("camera"), dict) and "calibration" in data["camera"]
    render = _parse_render(source, section("render"), calibrated)
    camera, render = _parse_camera(source, section("camera"), base_dir, render)
    viewer = camera.pose.t.copy()
    if top.has("viewer"):
        viewer = _Fields(source, data["viewer"], "viewer", {"position"}).vector("position")
    objects_table = section("objects")
    if not isinstance(objects_table, list) or not objects_table:
        top.fail("objects", "expected at least one [[objects]] table")
    _check_mesh_budget(source, objects_table, base_dir, mesh_override)
    notes: list[str] = []
    objects = [_parse_object(source, t, i, base_dir, notes, mesh_override) for i, t in enumerate(objects_table)]
    names = [o.name for o in objects]
    for i, name in enumerate(names):
        if names.index(name) != i:
            raise SceneError(source, f"objects[{i}].name", f"duplicate object name {name!r}")
    if not any(o.is_emissive for o in objects) and not np.any(render.background > 0):
        top.fail("objects", "the scene has no light: give an object an emission or [render] a background")
    return Scene(source, render, camera, viewer, objects, sorted(set(notes)))


def _read_scene_text(path: Path) -> str:
    """The file's text, refusing (SceneError) a missing, oversized or non-UTF-8 file."""
    if not path.is_file():
        raise SceneError(str(path), "(file)", f"no such scene file; built-in scenes are {', '.join(BUILTIN_SCENES)}")
    try:
        check_file_size(path, max_scene_bytes(), "scene file", "DPMHW_MAX_SCENE_KB")
        raw = path.read_bytes()
    except (ValueError, OSError) as exc:
        raise SceneError(str(path), "(file)", str(exc)) from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise SceneError(str(path), "(file)", f"not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset {exc.start} "
                                              f"(line {line})") from None


def _scene_text(name_or_path: str | Path) -> tuple[str, str, Path]:
    """(text, source name, folder relative paths resolve against) of a built-in scene or a file."""
    key = str(name_or_path)
    if key in BUILTIN_SCENES:
        return resources.files("dpmhw.scenes").joinpath(f"{key}.toml").read_text(), f"built-in scene {key!r}", Path(".")
    path = Path(name_or_path)
    return _read_scene_text(path), str(path), path.parent


def scene_size(name_or_path: str | Path) -> tuple[int, int]:
    """A scene's (width, height) from its [render] table alone: no mesh is read."""
    text, source, base_dir = _scene_text(name_or_path)
    top = _Fields(source, _toml(text, source), "", SCENE_SECTIONS)
    if not top.has("render"):
        top.fail("render", "missing required section")
    camera = top.table.get("camera")
    calibrated = isinstance(camera, dict) and "calibration" in camera
    render = _parse_render(source, top.table["render"], calibrated)
    if calibrated and not render.width:  # the calibration file's size
        render = _parse_camera(source, camera, base_dir, render)[1]
    return render.width, render.height


def load_scene(name_or_path: str | Path, mesh_override: Path | None = None) -> Scene:
    """Load a scene by built-in name (see BUILTIN_SCENES) or from a TOML file."""
    scene = parse_scene(*_scene_text(name_or_path), mesh_override)
    for note in scene.notes:
        log.warning("%s: %s", scene.source, note)
    return scene
