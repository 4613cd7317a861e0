"""Mesh level of detail inside a running pipeline (the session loop, `dpmhw bench lod`).

Built once (`MeshLod.__init__`): the levels of every moving mesh object (`MeshLevels`:
quadric simplification with `fast-simplification`, ε per level; identical meshes share them),
installed into the renderer's `SceneGeometry` (triangle rows and one model-space Embree BVH per
level, `add_levels`) and into the native G-buffer (its region of interest holds every level,
`use_mesh`), and the selector's pop-safe depths (`MeshLodSelector`, measured once per mesh).

Per frame:
- `choose(poses, camera_pose)`, before the render: the selector picks each object's level from
  its nearest depth (its projected size through the intrinsics) and the visibility it had in
  the previous output; a change swaps the object's triangle offset, BVH and bounding sphere in
  place (`SceneGeometry.set_level`) and tells the G-buffer (`use_mesh`). Nothing is rebuilt.
- `observe(image, depth, object_id)`, after the output: the visibility map of the output frame
  (the uint8 projector frame decoded to linear light: the contrast the audience sees) over the
  tiles the objects cover, reduced to one V per object for the next choice.

Before the first observation, and while it shows on no pixel, an object counts as visible (the
strict rule); only one the map calls invisible where it shows uses the error allowance. With no object
that has levels (`MeshLod.active` False) nothing is installed and frames are untouched.
"""

from __future__ import annotations

import hashlib
import logging
import math

import numba as nb
import numpy as np

from dpmhw.lod.mesh_levels import MeshLevels, MeshLodSelector, MeshLodSettings, object_visibility
from dpmhw.lod.visibility import VisibilityMap, VisibilitySettings, visibility_map
from dpmhw.postprocess import srgb_decode
from dpmhw.transforms import Pose

log = logging.getLogger(__name__)
MIN_FACES = 1000  # smaller meshes cost too little to be worth levels

# sRGB 8-bit code → linear light: the projector's output, before its gamma
SRGB8_TO_LINEAR = srgb_decode(np.arange(256) / 255.0).astype(np.float32)


def build_levels(scene, reductions=None) -> list[MeshLevels | None]:
    """Levels for every moving, non-emissive, untextured mesh object of ≥ MIN_FACES triangles
    without a roughness map (None for the others: simplification keeps no texture coordinates);
    objects with identical meshes share one MeshLevels."""
    by_content: dict[str, MeshLevels] = {}
    out: list[MeshLevels | None] = []
    for o in scene.objects:
        if (o.shape != "mesh" or not o.is_dynamic or o.is_emissive or o.face_roughness is not None or o.mesh.texture is not None
                or len(o.mesh.faces) < MIN_FACES):
            out.append(None)
            continue
        key = hashlib.sha256(o.mesh.vertices.tobytes() + o.mesh.faces.tobytes()).hexdigest()
        if key not in by_content:
            by_content[key] = MeshLevels(o.mesh) if reductions is None else MeshLevels(o.mesh, reductions)
        out.append(by_content[key])
    return out


@nb.njit(nogil=True, cache=True)
def _objects_box(object_id, has_levels):
    """Bounding box (y0, y1, x0, x1) of the pixels showing an object with levels (y0 = −1: none)."""
    H, W = object_id.shape
    y0, y1, x0, x1 = -1, -1, W, -1
    n = has_levels.shape[0]
    for y in range(H):
        for x in range(W):
            k = object_id[y, x]
            if 0 <= k < n and has_levels[k]:
                if y0 < 0:
                    y0 = y
                y1 = y
                if x < x0:
                    x0 = x
                if x > x1:
                    x1 = x
    return y0, y1 + 1, x0, x1 + 1


class MeshLod:
    """Levels of the moving meshes of one renderer (and its native G-buffer), chosen per frame."""

    def __init__(self, renderer, gbuffer=None, settings: MeshLodSettings = MeshLodSettings(),
                 visibility: VisibilitySettings = VisibilitySettings(), levels: list[MeshLevels | None] | None = None,
                 native_K=None):
        scene = renderer.scene
        self.geometry = renderer.geometry
        self.gbuffer = gbuffer
        self.visibility = visibility
        self.levels = build_levels(scene) if levels is None else levels
        if len(self.levels) != len(scene.objects):
            raise ValueError(f"levels: expected one entry per scene object ({len(scene.objects)}), got {len(self.levels)}")
        self.has_levels = np.array([lv is not None for lv in self.levels], np.bool_)
        self.active = bool(self.has_levels.any())
        # the selector measures depth in projector pixels at the output (native) resolution
        K = np.asarray(native_K if native_K is not None else (gbuffer.camera.K if gbuffer is not None else renderer.camera.K), float)
        self.K = K
        self.selector = MeshLodSelector(self.levels, math.sqrt(abs(K[0, 0] * K[1, 1])), settings, visibility)
        self.object_vis = np.full(len(self.levels), np.inf)  # no map yet: every object counts as visible
        self.switches = 0
        for k, lv in enumerate(self.levels):
            if lv is None:
                continue
            meshes = [level.mesh for level in lv.levels]
            self.geometry.add_levels(k, meshes)
            if gbuffer is not None:
                gbuffer.use_mesh(k, meshes[0], all_levels=meshes)

    @property
    def choice(self) -> np.ndarray:
        return self.selector.current.copy()

    @property
    def triangles(self) -> int:
        """Triangles of the whole scene at the levels in use."""
        return int(self.geometry.active_triangles)

    def choose(self, poses: list[Pose], camera_pose: Pose) -> np.ndarray:
        """Pick and install this frame's levels (before the render); returns them."""
        before = self.selector.current.copy()
        choice = self.selector.select(poses, camera_pose, self.object_vis)
        for k in np.nonzero(choice != before)[0]:
            self.geometry.set_level(int(k), int(choice[k]))
            if self.gbuffer is not None:
                self.gbuffer.use_mesh(int(k), self.levels[k].levels[int(choice[k])].mesh)
            self.switches += 1
        return choice

    def observe(self, image: np.ndarray, depth: np.ndarray, object_id: np.ndarray,
                visibility: VisibilityMap | None = None) -> np.ndarray:
        """Per-object visibility from the output frame (uint8 sRGB (H, W, 3), or linear float) with
        the G-buffer depth and object ids of the same frame (native size); only the tiles the
        objects cover are mapped. `visibility`: a map of this output already made (the tile
        refiner's `output_map`, same tile grid): used instead of mapping the frame again (one map
        for all three uses; it maps the linear radiance, before the sRGB encoding's clipping).
        Returns (n_objects,) V; an object on no pixel (off screen,
        hidden, too small) gets +inf, the strict rule: a coarse level chosen while it was unseen
        would otherwise switch finer in plain view the frame after it appears."""
        ids = np.ascontiguousarray(object_id, np.int32)
        roi = self.gbuffer.roi_box if self.gbuffer is not None and ids.shape == (self.gbuffer.height, self.gbuffer.width) else None
        if roi is None:  # no moving-objects box of this frame: scan every pixel
            roi = (0, ids.shape[0], 0, ids.shape[1])
        # objects with levels move, so they lie inside the G-buffer's moving-objects box: scan only that
        y0, y1, x0, x1 = _objects_box(ids[roi[0]:roi[1], roi[2]:roi[3]], self.has_levels)
        y0, y1, x0, x1 = (y0, y1, x0, x1) if y0 < 0 else (y0 + roi[0], y1 + roi[0], x0 + roi[2], x1 + roi[2])
        n = len(self.levels)
        if y0 < 0:
            self.object_vis = np.full(n, np.inf)
            return self.object_vis
        t = self.visibility.tile
        y0, x0 = y0 // t * t, x0 // t * t  # whole tiles of the frame's grid
        y1, x1 = min(-(-y1 // t) * t, ids.shape[0]), min(-(-x1 // t) * t, ids.shape[1])
        if visibility is not None and visibility.tile == t and visibility.visibility.shape == (-(-ids.shape[0] // t), -(-ids.shape[1] // t)):
            tiles = visibility.visibility[y0 // t : -(-y1 // t), x0 // t : -(-x1 // t)]
        else:
            crop = image[y0:y1, x0:x1]
            radiance = SRGB8_TO_LINEAR[crop] if crop.dtype == np.uint8 else crop
            tiles = visibility_map(radiance, depth[y0:y1, x0:x1], self.K, self.visibility).visibility
        v = object_visibility(tiles, t, ids[y0:y1, x0:x1], n)
        self.object_vis = np.where(np.isneginf(v), np.inf, v)  # on no pixel: the strict rule (see the docstring)
        return self.object_vis


def mesh_lod(renderer, gbuffer, section) -> MeshLod | None:
    """The loop's MeshLod from the config's `lod` section (None when `mesh` is off or the scene
    has no moving mesh to simplify)."""
    if not getattr(section, "mesh", False):
        return None
    if not hasattr(renderer, "geometry"):  # a renderer without Embree geometry (a test double): nothing to simplify
        log.warning("lod.mesh: the renderer %s has no scene geometry; mesh levels off", type(renderer).__name__)
        return None
    lod = MeshLod(renderer, gbuffer, MeshLodSettings(),
                  VisibilitySettings(viewer_distance_m=section.viewer_distance_m, alpha_v=section.alpha_v))
    return lod if lod.active else None
