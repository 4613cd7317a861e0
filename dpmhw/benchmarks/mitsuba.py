"""`dpmhw bench mitsuba`: Mitsuba 3 (LLVM backend) on the same scene as dpmhw, the renderer's speed baseline.

The scene is converted in memory (`scene_dict`): every object becomes an `mi.Mesh` in world space
(its pose at t = 0; a textured one with its texture coordinates, v flipped to Mitsuba's
top-row-first convention, and its texture as a linear `bitmap` with bilinear filtering and repeat
wrapping, the albedo multiplied in), with a two-sided BSDF (dpmhw shades both faces; Mitsuba's BSDFs alone are
black from behind: `bsdf_dict` for the glossy lobe) and an `area` emitter where it emits
(one-sided, like dpmhw's); a background becomes a `constant` emitter. The camera is dpmhw's
OpenCV pinhole as a `perspective` sensor (`sensor_dict`): horizontal FOV from fx, the principal
point as an offset from the film centre, and OpenCV's axes (x right, y down) turned into
Mitsuba's (x left, y up).

Light transport: dpmhw's `max_bounces` = B gives paths of B + 2 segments at most (an emitter seen
by the camera; direct light at vertices 1 … B + 1), which is Mitsuba's `max_depth` = B + 2. For
paper-static (B = 1): `max_depth` = 3. Mitsuba reaches its last vertex's direct light with MIS
(NEE plus one more BSDF ray per path), dpmhw with NEE alone for diffuse scenes: same estimator
target, one extra continuation ray per path for Mitsuba (with a sharp glossy lobe dpmhw traces
that ray too: `mis_last`). Russian roulette starts at depth 5 in Mitsuba and at depth 3 in dpmhw
(never reached with one bounce). Pixels: Mitsuba always samples a
random point of the pixel; a `box` filter makes each sample land in its own pixel only, which is
what dpmhw's `jitter` sampling does. dpmhw's default (`centre`) traces pixel centres: same ray
count, so timings compare, while the converged images are compared with dpmhw in `jitter` mode.

Timing (`bench_mitsuba`): the two renderers alternate frame by frame in one process (the load of
a shared machine hits both alike), each frame after a short idle pause (SETTLE_S: the other
renderer's threads wind down), each warmed up first (LLVM compilation for Mitsuba, numba and
caches for dpmhw). Camera "fixed": seeds change, the pose does not (dpmhw reuses its cached camera
hits; Mitsuba traces camera rays every frame anyway). Camera "moved": the camera pans by a small,
different angle every frame; Mitsuba's sensor is moved through `mi.traverse` (its `to_world` is an
opaque JIT variable, so the kernel is reused: `kernels_compiled` counts in-memory cache misses
during the timed frames, `render_kernel_cache_hit` says whether the megakernel was reused). A
frame is wall time from the call to the image in host memory as a numpy array; CPU time is the
process's (all threads).
"""

from __future__ import annotations

import glob
import os
import re
import time
from dataclasses import dataclass

import numpy as np

from dpmhw.benchmarks.render import PAN_DEG, panned_pose  # noqa: F401  (the same pans as bench render)
from dpmhw.errors import DpmhwError, SceneError
from dpmhw.render.kernels import MIN_ALPHA
from dpmhw.scene_file import Scene, load_scene
from dpmhw.transforms import Pose

VARIANT = "llvm_ad_rgb"  # the CPU variant PyPI's wheels ship (no non-AD llvm_rgb there)
WARMUP_FRAMES = 2
EDGE_RADIUS_PX = 3  # comparison regions keep pixels at least this far from an object or normal edge
NORMAL_EDGE = 0.2  # on a flat-shaded object, a normal component varying more than this within the radius is an edge
MAX_SPP_PER_CALL = 16  # Mitsuba's wavefront is width × height × spp lanes: bounded memory
# Before each timed frame the process idles this long (not timed): drjit's worker threads keep
# running for a while after a Mitsuba frame, and in the same process they were charged to, and
# competed with, the dpmhw frame timed next (its CPU-ms per frame 161 → 148 fixed, 206 → 184
# moved with a 0.1 s pause, two alternated runs each; Mitsuba's own unchanged, 295-300)
SETTLE_S = 0.1


class MitsubaUnavailable(DpmhwError, RuntimeError):
    """Mitsuba 3 (or a libLLVM its LLVM variants can use) is not installed."""


MIN_LLVM = 16  # drjit 1.5 refuses LLVM 14, and its path tracer kernel aborts LLVM 15's code generator


def libllvm_path() -> str | None:
    """DRJIT_LIBLLVM_PATH, else the newest libLLVM (version ≥ MIN_LLVM) in the usual library
    folders. Not an older one: with LLVM 15, drjit's path tracer kills the process in LLVM's code
    generator (`LLVM ERROR: Cannot select: … fminimum`, an abort, not an exception)."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return os.environ["DRJIT_LIBLLVM_PATH"]
    found = []
    for folder in ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib", "/usr/local/lib"):
        for path in glob.glob(os.path.join(folder, "libLLVM*.so*")):
            m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
            if m and int(m.group(1)) >= MIN_LLVM:
                found.append((int(m.group(1)), path))
    return max(found)[1] if found else None


def load_mitsuba(variant: str = VARIANT):
    """Import mitsuba with `variant` set, or raise MitsubaUnavailable saying what to install."""
    if variant.startswith("llvm"):
        path = libllvm_path()
        if path is None:
            raise MitsubaUnavailable(f"variant {variant}: no libLLVM ≥ {MIN_LLVM} found; install one (Debian: apt-get install libllvm19) "
                                     "or set DRJIT_LIBLLVM_PATH")
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    try:
        import mitsuba as mi
    except ImportError:
        raise MitsubaUnavailable("mitsuba is not installed: pip install -e '.[mitsuba]'") from None
    if variant not in mi.variants():
        raise MitsubaUnavailable(f"variant {variant}: not in this mitsuba build (it has {', '.join(mi.variants())})")
    try:
        mi.set_variant(variant)
    except Exception as exc:  # drjit could not initialise its backend (e.g. libLLVM unusable)
        raise MitsubaUnavailable(f"variant {variant}: cannot be set: {exc}") from None
    return mi


def max_depth(max_bounces: int) -> int:
    """Mitsuba's path `max_depth` covering dpmhw's paths: camera → emitter is depth 1, direct
    light at vertex 1 depth 2, and each indirect bounce one more."""
    return max_bounces + 2


def to_world_matrix(pose: Pose) -> np.ndarray:
    """Mitsuba's camera→world (4, 4) for dpmhw's OpenCV camera pose: Mitsuba's camera looks
    along +z like OpenCV's, but its x is image-left and its y image-up (a half turn about z)."""
    m = np.eye(4)
    m[:3, :3] = pose.R @ np.diag([-1.0, -1.0, 1.0])
    m[:3, 3] = pose.t
    return m


def sensor_dict(scene: Scene, spp: int = 1, near_clip: float = 1e-4) -> dict:
    """The `perspective` sensor equal to the scene's camera (no distortion, square pixels),
    with a box-filtered RGB film and an independent sampler."""
    import mitsuba as mi

    cam, r = scene.camera, scene.render
    K = cam.K
    if np.any(cam.dist != 0):
        raise SceneError(scene.source, "camera.dist", "Mitsuba's perspective sensor has no lens distortion; the conversion needs dist = 0")
    if not np.isclose(K[0, 0], K[1, 1], rtol=1e-9) or K[0, 1] != 0:
        raise SceneError(scene.source, "camera.fy", f"Mitsuba's perspective sensor has square pixels; the conversion needs fx = fy "
                                                    f"and no skew, got fx {K[0, 0]}, fy {K[1, 1]}")
    W, H = r.width, r.height
    # OpenCV's pixel (0, 0) is the centre of the top-left pixel, so the film centre is
    # ((W − 1) / 2, (H − 1) / 2); Mitsuba's offset is in film widths/heights, towards −x, −y
    return {
        "type": "perspective",
        "fov": float(np.degrees(2.0 * np.arctan(W / (2.0 * K[0, 0])))),
        "fov_axis": "x",
        "principal_point_offset_x": float(-(K[0, 2] - (W - 1) / 2) / W),
        "principal_point_offset_y": float(-(K[1, 2] - (H - 1) / 2) / H),
        "near_clip": near_clip,
        "to_world": mi.ScalarTransform4f(to_world_matrix(cam.pose).tolist()),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {"type": "hdrfilm", "width": W, "height": H, "pixel_format": "rgb", "rfilter": {"type": "box"}},
    }


def _check_convertible(scene: Scene) -> None:
    if not np.allclose(scene.viewer_position, scene.camera.pose.t):
        raise SceneError(scene.source, "viewer", "Mitsuba shades towards the camera; the conversion needs no separate viewer")
    for i, obj in enumerate(scene.objects):
        if obj.face_roughness is not None:
            raise SceneError(scene.source, f"objects[{i}].roughness_map", "the conversion supports one roughness per object")
        bsdf_dict(obj, scene.source, i)  # refuses a specular colour it cannot express


def bsdf_dict(obj, source: str = "", index: int = 0) -> dict:
    """dpmhw's BSDF, albedo·(1 − s)/π + s·D·G/(4 cos_o cos_i) (GGX, separable Smith G, no
    Fresnel), two-sided. Diffuse-only objects: `diffuse`. With a specular lobe the sum is a
    `blendbsdf` of weight w = max(s): (1 − w)·diffuse(albedo·(1 − s)/(1 − w)) +
    w·roughconductor(material "none" (Fresnel = 1), α as dpmhw's, specular_reflectance s/w),
    equal to the sum exactly while both reflectances stay in [0, 1] (always for a grey s)."""
    albedo, spec = np.asarray(obj.albedo, float), np.asarray(obj.specular, float)
    diffuse = {"type": "diffuse", "reflectance": _reflectance(obj, albedo)}
    if not np.any(spec > 0):
        return {"type": "twosided", "bsdf": diffuse}
    w = float(spec.max())
    diffuse_part = albedo * (1.0 - spec)
    if w >= 1.0:
        if np.any(diffuse_part > 0):
            raise SceneError(source, f"objects[{index}].specular", "a specular of 1 in one channel with a diffuse part in "
                                                                   "another has no blendbsdf equivalent")
        kd = np.zeros(3)
    else:
        kd = diffuse_part / (1.0 - w)
    if np.any(kd > 1.0 + 1e-9):
        raise SceneError(source, f"objects[{index}].specular", f"specular channels {spec.tolist()} differ too much for "
                                                               "a blendbsdf with reflectances in [0, 1]")
    diffuse["reflectance"] = _reflectance(obj, np.minimum(kd, 1.0))
    glossy = {"type": "roughconductor", "material": "none", "distribution": "ggx", "alpha": max(obj.roughness**2, MIN_ALPHA),
              "specular_reflectance": {"type": "rgb", "value": (spec / w).tolist()}}
    return {"type": "twosided", "bsdf": {"type": "blendbsdf", "weight": w, "bsdf_0": diffuse, "bsdf_1": glossy}}


def _reflectance(obj, factor: np.ndarray) -> dict:
    """A diffuse reflectance of `factor` (3,), times the object's texture where it has one."""
    if obj.mesh.texture is None:
        return {"type": "rgb", "value": np.asarray(factor, float).tolist()}
    import mitsuba as mi

    data = np.ascontiguousarray(obj.mesh.texture.texels * np.asarray(factor, np.float32), np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(data), "raw": True, "filter_type": "bilinear", "wrap_mode": "repeat"}


def _mesh(mi, obj, pose: Pose):
    """One object as an in-memory `mi.Mesh` in world space, with its BSDF and emitter."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf_dict(obj))
    if obj.is_emissive:
        props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": obj.emission.tolist()}})
    m = obj.mesh
    normals = m.vertex_normals
    mesh = mi.Mesh(obj.name, len(m.vertices), len(m.faces), props=props, has_vertex_normals=normals is not None,
                   has_vertex_texcoords=m.uv is not None)
    params = mi.traverse(mesh)

    def put(key, values, dtype):  # flat buffers, in whatever array type this variant stores them
        params[key] = type(params[key])(np.ascontiguousarray(values, dtype).ravel())

    put("vertex_positions", pose.apply(m.vertices), np.float32)
    put("faces", m.faces, np.uint32)
    if normals is not None:
        put("vertex_normals", normals @ pose.R.T, np.float32)
    if m.uv is not None:
        put("vertex_texcoords", np.stack([m.uv[:, 0], 1.0 - m.uv[:, 1]], 1), np.float32)
    params.update()
    return mesh


def scene_dict(scene: Scene, t: float = 0.0, spp: int = 1) -> dict:
    """The Mitsuba scene dict of a dpmhw scene at time t (see the module doc)."""
    import mitsuba as mi

    _check_convertible(scene)
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth(scene.render.max_bounces)},
        "sensor": sensor_dict(scene, spp),
    }
    background = scene.render.background
    if np.any(background > 0):
        d["background"] = {"type": "constant", "radiance": {"type": "rgb", "value": background.tolist()}}
    for i, (obj, pose) in enumerate(zip(scene.objects, scene.object_poses(t))):
        d[f"object{i}"] = _mesh(mi, obj, pose)
    return d


class MitsubaRenderer:
    """A dpmhw scene loaded in Mitsuba; `render` returns (H, W, 3) float32 radiance."""

    def __init__(self, scene: Scene, variant: str = VARIANT, threads: int = 2):
        self.mi = load_mitsuba(variant)
        import drjit as dr

        self.dr = dr
        self.variant = variant
        if variant.startswith("llvm"):
            dr.set_thread_count(threads)
        self.scene = scene
        self.mi_scene = self.mi.load_dict(scene_dict(scene))
        self.params = self.mi.traverse(self.mi_scene)
        self._pose_key = (scene.camera.pose.R.tobytes(), scene.camera.pose.t.tobytes())

    @property
    def threads(self) -> int:
        return int(self.dr.thread_count()) if self.variant.startswith("llvm") else 1

    def set_camera(self, pose: Pose) -> None:
        """Move the sensor without rebuilding the scene (a parameter update, no recompilation)."""
        key = (pose.R.tobytes(), pose.t.tobytes())
        if key != self._pose_key:
            self.params["sensor.to_world"] = self.mi.Transform4f(to_world_matrix(pose).tolist())
            self.params.update()
            self._pose_key = key

    def render(self, seed: int, spp: int = 1, camera_pose: Pose | None = None) -> np.ndarray:
        if camera_pose is not None:
            self.set_camera(camera_pose)
        return np.array(self.mi.render(self.mi_scene, spp=spp, seed=seed), dtype=np.float32)


@dataclass
class _Clock:
    wall_ms: list
    cpu_ms: list

    def time(self, fn):
        time.sleep(SETTLE_S)
        start, start_cpu = time.perf_counter(), time.process_time()
        out = fn()
        self.wall_ms.append((time.perf_counter() - start) * 1e3)
        self.cpu_ms.append((time.process_time() - start_cpu) * 1e3)
        return out


def _kernel_stats(dr) -> tuple[int, bool]:
    """Since the last call: kernels not in drjit's in-memory cache (compiled by LLVM, or loaded
    from its disk cache, ~/.drjit), and whether every launch of the largest kernel (the
    path tracer's megakernel) was an in-memory cache hit."""
    jit = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]
    misses = sum(1 for k in jit if not k.get("cache_hit", True))
    largest = max((k.get("operation_count", 0) for k in jit), default=0)
    return misses, all(k.get("cache_hit", True) for k in jit if k.get("operation_count", 0) == largest)


def _timing_row(renderer: str, variant: str, scene: Scene, scene_name: str, camera: str, clock: _Clock, threads: int, **extra) -> dict:
    return {
        "kind": "timing", "renderer": renderer, "variant": variant, "scene": scene_name, "camera": camera,
        "frames": len(clock.wall_ms), "spp": 1, "width": scene.render.width, "height": scene.render.height, "threads": threads,
        "frame_ms_median": float(np.median(clock.wall_ms)), "frame_ms_min": float(np.min(clock.wall_ms)),
        "frame_ms_max": float(np.max(clock.wall_ms)), "frame_cpu_ms_median": float(np.median(clock.cpu_ms)),
        "max_bounces": scene.render.max_bounces, **extra,
    }


def bench_mitsuba(scene_name: str = "paper-static", frames: int = 9, threads: int = 2, variant: str = VARIANT,
                  with_dpmhw: bool = True, mesh=None, progress=None) -> list[dict]:
    """Timing rows (and dpmhw/Mitsuba ratio rows with `with_dpmhw`), frames alternated."""
    scene = load_scene(scene_name, mesh_override=mesh)
    mr = MitsubaRenderer(scene, variant, threads)
    dr = mr.dr
    integrator = None
    if with_dpmhw:
        from dpmhw.render.integrator import PathIntegrator

        integrator = PathIntegrator(scene, threads=threads)
    clocks = {(r, c): _Clock([], []) for r in ("mitsuba", "dpmhw") for c in ("fixed", "moved")}
    compiled = {"fixed": (0, True), "moved": (0, True)}
    total = WARMUP_FRAMES + 2 * frames
    try:
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        warm = _Clock([], [])
        for k in range(WARMUP_FRAMES):
            warm.time(lambda: mr.render(seed=1000 + k))
            if integrator is not None:
                integrator.render(time=0.0, seed=1000 + k)
            if progress:
                progress("warm-up", k + 1, total)
        warmup_compiled = _kernel_stats(dr)[0]
        for camera in ("fixed", "moved"):
            for k in range(frames):
                pose = panned_pose(scene.camera.pose, k) if camera == "moved" else scene.camera.pose
                clocks["mitsuba", camera].time(lambda: mr.render(seed=k, camera_pose=pose))
                if integrator is not None:
                    clocks["dpmhw", camera].time(lambda: integrator.render(time=0.0, seed=k, camera_pose=None if camera == "fixed" else pose))
                if progress:
                    progress(f"camera {camera}", WARMUP_FRAMES + (camera == "moved") * frames + k + 1, total)
            compiled[camera] = _kernel_stats(dr)
            mr.set_camera(scene.camera.pose)
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        llvm = os.path.basename(os.environ.get("DRJIT_LIBLLVM_PATH", "")) if variant.startswith("llvm") else ""
        tracer = "embree" if getattr(mr.mi, "MI_ENABLE_EMBREE", False) else "mitsuba kd-tree"
        rows = [_timing_row("mitsuba", variant, scene, scene_name, c, clocks["mitsuba", c], mr.threads,
                            max_depth=max_depth(scene.render.max_bounces), kernels_compiled=compiled[c][0],
                            render_kernel_cache_hit=compiled[c][1],
                            warmup_ms=warm.wall_ms[0], warmup_kernels_compiled=warmup_compiled, libllvm=llvm,
                            mitsuba_version=mr.mi.__version__, ray_tracer=tracer) for c in ("fixed", "moved")]
        if integrator is not None:
            backend = type(integrator.geometry.accel).__name__
            rows += [_timing_row("dpmhw", backend, scene, scene_name, c, clocks["dpmhw", c], threads,
                                 pixel_sampling=integrator.pixel_sampling) for c in ("fixed", "moved")]
            for c, goal in (("fixed", 0.5), ("moved", 0.67)):
                m, d = clocks["mitsuba", c], clocks["dpmhw", c]
                rows.append({"kind": "ratio", "scene": scene_name, "camera": c,
                             "dpmhw_over_mitsuba_wall": float(np.median(d.wall_ms) / np.median(m.wall_ms)),
                             "dpmhw_over_mitsuba_cpu": float(np.median(d.cpu_ms) / np.median(m.cpu_ms)), "goal": goal})
        return rows
    finally:
        if integrator is not None:
            integrator.close()


def one_spp_frame(scene: Scene, frames: int = 5, threads: int = 2, variants: tuple[str, ...] = (VARIANT, "scalar_rgb")) -> dict:
    """Mitsuba's 1-spp frame of `scene` as a cost yardstick: median CPU-ms (the process, all
    threads) and wall ms over `frames` after the warm-up, with the first of `variants` this machine
    can run. Only the cost counts here, so what the conversion refuses but the cost ignores is
    changed and said in `mitsuba_note`: a separate viewer (Mitsuba shades towards its sensor) and
    lens distortion (the same rays, bent a little). Raises MitsubaUnavailable when no variant runs."""
    import dataclasses

    notes = []
    if not np.allclose(scene.viewer_position, scene.camera.pose.t):
        scene = dataclasses.replace(scene, viewer_position=scene.camera.pose.t.copy())
        notes.append("shaded towards the camera, not the scene's viewer")
    if np.any(scene.camera.dist != 0):
        scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, dist=np.zeros_like(scene.camera.dist)))
        notes.append("without lens distortion")
    refused = []
    for variant in variants:
        try:
            mr = MitsubaRenderer(scene, variant, threads)
            break
        except MitsubaUnavailable as exc:
            refused.append(str(exc))
    else:
        raise MitsubaUnavailable("; ".join(refused))
    if refused:
        notes.append(f"fell back to {variant}: {refused[-1]}")
    for k in range(WARMUP_FRAMES):
        mr.render(seed=1000 + k)
    clock = _Clock([], [])
    for k in range(frames):
        clock.time(lambda: mr.render(seed=k))
    return {"mitsuba_variant": variant, "mitsuba_threads": mr.threads, "mitsuba_frames": frames,
            "mitsuba_cpu_ms": round(float(np.median(clock.cpu_ms)), 3), "mitsuba_wall_ms": round(float(np.median(clock.wall_ms)), 3),
            "mitsuba_version": mr.mi.__version__, "mitsuba_note": "; ".join(notes)}


# ---- converged images compared ---------------------------------------------------------------

def interior_mask(object_id: np.ndarray, normal: np.ndarray, radius: int = EDGE_RADIUS_PX, crease_ids=None) -> np.ndarray:
    """Pixels at least `radius` from a change of object, or of normal on the objects in
    `crease_ids` (default: all; flat-shaded ones have creases, e.g. a box's wall corners, where a
    smooth object's normals turn within a few pixels without an edge)."""
    from scipy import ndimage

    size = 2 * radius + 1
    same_obj = ndimage.maximum_filter(object_id, size) == ndimage.minimum_filter(object_id, size)
    flat = np.ones(object_id.shape, bool)
    for c in range(3):
        n = normal[..., c]
        flat &= ndimage.maximum_filter(n, size) - ndimage.minimum_filter(n, size) <= NORMAL_EDGE
    if crease_ids is not None:
        flat |= ~np.isin(object_id, np.asarray(list(crease_ids), np.int64))
    return same_obj & flat & (object_id >= 0)


def regions(scene: Scene, object_id: np.ndarray, normal: np.ndarray, tile: int = 0) -> dict[str, np.ndarray]:
    """Named pixel masks away from edges (creases only on flat-shaded objects): every interior
    pixel, each object, a box's faces split by their normal's dominant axis (floor, walls,
    ceiling), and with `tile` > 0 each tile × tile block of the image whose interior pixels fill
    at least half of it ("tile y,x", its top-left pixel)."""
    inside = interior_mask(object_id, normal, crease_ids=[i for i, o in enumerate(scene.objects) if o.mesh.vertex_normals is None])
    out = {"all interior": inside}
    axis = np.argmax(np.abs(normal), axis=-1)
    sign = np.take_along_axis(normal, axis[..., None], -1)[..., 0] > 0
    names = {(0, True): "+x", (0, False): "−x", (1, True): "+y", (1, False): "−y", (2, True): "+z", (2, False): "−z"}
    for i, obj in enumerate(scene.objects):
        m = inside & (object_id == i)
        if not m.any():
            continue
        if obj.shape == "box":
            for (a, s), name in names.items():
                part = m & (axis == a) & (sign == s)
                if part.sum() >= 100:
                    out[f"{obj.name} normal {name}"] = part
        else:
            out[obj.name] = m
    if tile > 0:
        H, W = object_id.shape
        for y in range(0, H - tile + 1, tile):
            for x in range(0, W - tile + 1, tile):
                if inside[y:y + tile, x:x + tile].sum() >= tile * tile // 2:
                    m = np.zeros_like(inside)
                    m[y:y + tile, x:x + tile] = inside[y:y + tile, x:x + tile]
                    out[f"tile {y},{x}"] = m
    return out


def _luminance(img: np.ndarray) -> np.ndarray:
    return img @ np.array([0.2126, 0.7152, 0.0722], np.float32)


def compare(scene_name: str = "paper-static", spp: int = 256, threads: int = 2, variant: str = VARIANT, mesh=None,
            progress=None, tile: int = 0) -> list[dict]:
    """Both renderers at `spp` (dpmhw with pixel jitter, the box-filtered pixel integral like
    Mitsuba's), in chunks of up to MAX_SPP_PER_CALL: mean luminance per region (see `regions`,
    with its `tile`s), relative difference, and its standard error from the spread of the chunks."""
    from dpmhw.render.integrator import PathIntegrator

    scene = load_scene(scene_name, mesh_override=mesh)
    mr = MitsubaRenderer(scene, variant, threads)
    chunk = min(spp, MAX_SPP_PER_CALL)
    n_chunks = max(1, spp // chunk)
    with PathIntegrator(scene, threads=threads, pixel_sampling="jitter") as integrator:
        ref = integrator.render(time=0.0, seed=0, spp=1)
        masks = regions(scene, ref.object_id, ref.normal, tile)
        sums = {"dpmhw": 0.0, "mitsuba": 0.0}
        per_chunk = {"dpmhw": [], "mitsuba": []}
        for c in range(n_chunks):
            for name, img in (("dpmhw", integrator.render(time=0.0, seed=7919 + c, spp=chunk).radiance),
                              ("mitsuba", mr.render(seed=7919 + c, spp=chunk))):
                sums[name] = sums[name] + img
                lum = _luminance(img)
                per_chunk[name].append([float(lum[m].mean()) for m in masks.values()])
            if progress:
                progress(f"converging at {spp} spp", c + 1, n_chunks)
    images = {k: v / n_chunks for k, v in sums.items()}
    rows = []
    pc = {k: np.array(v) for k, v in per_chunk.items()}  # (chunks, regions)
    for j, (name, m) in enumerate(masks.items()):
        md, mm = pc["dpmhw"][:, j].mean(), pc["mitsuba"][:, j].mean()
        se = 0.0
        if n_chunks > 1:  # standard error of the ratio mm / md from both renderers' chunk spread
            sd, sm = (pc[k][:, j].std(ddof=1) / np.sqrt(n_chunks) for k in ("dpmhw", "mitsuba"))
            se = float(np.hypot(sd / md, sm / mm) * mm / md)
        rows.append({"kind": "compare", "scene": scene_name, "region": name, "pixels": int(m.sum()), "spp": chunk * n_chunks,
                     "mean_dpmhw": float(md), "mean_mitsuba": float(mm), "rel_diff": float(mm / md - 1.0), "rel_stderr": se})
    # how many pixels each renderer shows the light in (≥ half the brightest emitter's luminance)
    emit = max((float(_luminance(o.emission.astype(np.float32))) for o in scene.objects), default=0.0)
    if emit > 0:
        row = {"kind": "compare", "scene": scene_name, "region": "pixels ≥ half the emitter's luminance", "spp": chunk * n_chunks}
        for k, img in images.items():
            row[f"pixels_{k}"] = int((_luminance(img) >= 0.5 * emit).sum())
        rows.append(row)
    return rows


def format_table(rows: list[dict]) -> str:
    lines = []
    timing = [r for r in rows if r["kind"] == "timing"]
    if timing:
        r0 = timing[0]
        lines.append(f"scene {r0['scene']}  {r0['width']}×{r0['height']}  1 spp  max_bounces {r0['max_bounces']}")
        lines.append(f"{'renderer':10s} {'variant':14s} {'camera':7s} {'threads':>7s} {'frames':>6s} {'wall ms (median)':>17s} "
                     f"{'min–max':>15s} {'CPU-ms (median)':>16s}  notes")
        for r in timing:
            notes = ""
            if r["renderer"] == "mitsuba":
                notes = (f"max_depth {r['max_depth']}, kernels compiled {r['kernels_compiled']} "
                         f"(render kernel {'reused' if r['render_kernel_cache_hit'] else 'RECOMPILED'}), warm-up {r['warmup_ms']:.0f} ms "
                         f"({r['warmup_kernels_compiled']} compiled), {r['libllvm']}")
            lines.append(f"{r['renderer']:10s} {r['variant']:14s} {r['camera']:7s} {r['threads']:7d} {r['frames']:6d} "
                         f"{r['frame_ms_median']:17.1f} {r['frame_ms_min']:7.1f}–{r['frame_ms_max']:<7.1f} "
                         f"{r['frame_cpu_ms_median']:16.1f}  {notes}")
    for r in (r for r in rows if r["kind"] == "ratio"):
        lines.append(f"dpmhw / Mitsuba, camera {r['camera']}: {r['dpmhw_over_mitsuba_wall']:.2f}× wall, "
                     f"{r['dpmhw_over_mitsuba_cpu']:.2f}× CPU (goal ≤ {r['goal']}×)")
    cmp_rows = [r for r in rows if r["kind"] == "compare"]
    if cmp_rows:
        lines += ["", f"converged images, {cmp_rows[0]['spp']} spp (dpmhw with pixel jitter), mean luminance away from edges:",
                  f"{'region':32s} {'pixels':>8s} {'dpmhw':>9s} {'Mitsuba':>9s} {'Mitsuba/dpmhw − 1':>18s}"]
        for r in cmp_rows:
            if "pixels_dpmhw" in r:
                lines.append(f"{r['region']}: dpmhw {r['pixels_dpmhw']}, Mitsuba {r['pixels_mitsuba']}")
            else:
                lines.append(f"{r['region']:32s} {r['pixels']:8d} {r['mean_dpmhw']:9.4f} {r['mean_mitsuba']:9.4f} "
                             f"{100 * r['rel_diff']:+11.3f} % ± {100 * r['rel_stderr']:.3f}")
    return "\n".join(lines)


def plot(rows: list[dict], path) -> None:
    """Frame time bars (wall and CPU) per renderer and camera mode, and region differences."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    timing = [r for r in rows if r["kind"] == "timing"]
    cmp_rows = [r for r in rows if r["kind"] == "compare" and "rel_diff" in r]
    fig, axes = plt.subplots(1, 2 if cmp_rows else 1, figsize=(13 if cmp_rows else 7, 4.5), squeeze=False)
    ax = axes[0, 0]
    labels = [f"{r['renderer']}\ncamera {r['camera']}" for r in timing]
    x = np.arange(len(timing))
    ax.bar(x - 0.2, [r["frame_ms_median"] for r in timing], 0.4, label="wall ms (median)")
    ax.bar(x + 0.2, [r["frame_cpu_ms_median"] for r in timing], 0.4, label="CPU-ms, all threads (median)")
    ax.set_xticks(x, labels)
    ax.set_ylabel("ms per 1-spp frame")
    if timing:
        t = timing[0]
        ax.set_title(f"{t['scene']} {t['width']}×{t['height']}, {t['threads']} threads")
    ax.legend()
    if cmp_rows:
        ax = axes[0, 1]
        y = np.arange(len(cmp_rows))
        ax.barh(y, [100 * r["rel_diff"] for r in cmp_rows], xerr=[100 * r["rel_stderr"] for r in cmp_rows])
        ax.set_yticks(y, [r["region"] for r in cmp_rows])
        ax.axvline(0, color="k", lw=0.8)
        ax.set_xlabel("Mitsuba / dpmhw − 1 (%), mean luminance")
        ax.set_title(f"converged images, {cmp_rows[0]['spp']} spp, away from edges")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
