"""Mesh LOD: levels, closed meshes (no cracks), BVHs built once, hysteresis, pops below threshold."""

import numpy as np
import pytest

from dpmhw.lod import mesh_levels
from dpmhw.lod.mesh_levels import (
    MeshLevels,
    MeshLodSelector,
    MeshLodSettings,
    object_visibility,
    pop_visibility,
    scene_at_levels,
)
from dpmhw.lod.visibility import LodSettingsError, VisibilitySettings
from dpmhw.meshes import sphere_mesh
from dpmhw.scene_file import load_scene
from dpmhw.transforms import Pose

FOCAL = 1500.0


@pytest.fixture(scope="module")
def sphere_levels():
    return MeshLevels(sphere_mesh(0.1, subdivisions=4), reductions=(0.0, 0.5, 0.8, 0.95))


def edge_use(faces):
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    return np.unique(e, axis=0, return_counts=True)[1]


def test_levels_are_coarser_closed_meshes(sphere_levels):
    counts = sphere_levels.triangle_counts
    assert counts[0] == 5120 and all(a > b for a, b in zip(counts, counts[1:]))
    assert counts[-1] <= 0.06 * counts[0]
    errs = sphere_levels.errors_m
    assert errs[0] == 0 and np.all(np.diff(errs) >= 0) and errs[-1] > 0
    for lv in sphere_levels.levels:  # closed 2-manifold: every edge in exactly two triangles
        assert np.all(edge_use(lv.mesh.faces) == 2)
        assert lv.mesh.vertex_normals is not None


def test_error_bound_covers_the_true_distance(sphere_levels):
    """On a sphere the distance to the original surface is | |x| − r | (plus the facet sag)."""
    r = 0.1
    for lv in sphere_levels.levels[1:]:
        radial = np.abs(np.linalg.norm(lv.mesh.vertices, axis=1) - r).max()
        assert lv.error_m >= radial - 1e-9


def test_bad_reductions_name_the_field():
    with pytest.raises(LodSettingsError, match="reductions"):
        MeshLevels(sphere_mesh(0.1, 2), reductions=(0.5, 0.9))


def pose_at(depth):
    """Object centre at (0, 0, depth) in front of a camera at the origin looking down +z."""
    return Pose(np.eye(3), np.array([0.0, 0.0, depth]))


def test_visible_switches_only_where_the_pop_is_below_threshold(sphere_levels):
    vis = VisibilitySettings()
    sel = MeshLodSelector([sphere_levels], FOCAL, MeshLodSettings(hysteresis=0.2), vis)
    safe = sel.safe_depths[0]
    assert safe[0] == 0 and np.all(np.diff(safe) >= 0)
    r = 0.1
    for level in range(1, len(sphere_levels)):
        if np.isfinite(safe[level]):
            # measured pop at the switch depth (and slightly further) is below the threshold
            for z in (safe[level], safe[level] * 1.2):
                assert pop_visibility(sphere_levels, level, z, FOCAL, vis) <= 0
    # walking away from near: the level only ever coarsens, and only beyond the safe depths (+ margin)
    levels = []
    for z in np.geomspace(0.5, 200, 60):
        got = int(sel.select([pose_at(z + r)], Pose.identity(), np.array([5.0]))[0])
        assert z >= safe[got] * 1.2 - 1e-9 or got == 0
        levels.append(got)
    assert levels == sorted(levels)


def test_hysteresis_stops_flicker_at_a_switch_depth(sphere_levels):
    sel = MeshLodSelector([sphere_levels], FOCAL, MeshLodSettings(hysteresis=0.2))
    z1 = sel.safe_depths[0][1]
    assert np.isfinite(z1)
    r = 0.1
    seq = [0.9, 1.05, 0.99, 1.1, 1.19, 1.21, 1.05, 1.01, 0.99, 1.1]
    got = [int(sel.select([pose_at(z1 * f + r)], Pose.identity(), np.array([1.0]))[0]) for f in seq]
    first_coarse = got.index(1) if 1 in got else None
    assert got[:5] == [0] * 5 and first_coarse == 5  # coarser only past 1.2 × the safe depth
    assert got[5:8] == [1, 1, 1] and got[8] == 0  # kept until nearer than the safe depth


def test_invisible_objects_use_the_pixel_allowance(sphere_levels):
    sel = MeshLodSelector([sphere_levels], FOCAL, MeshLodSettings(invisible_error_px=2.0, edge_px=1e3, hysteresis=0.0))
    errs = sphere_levels.errors_m
    z = errs[2] * FOCAL / 2.0 * 1.01  # level 2's error projects to just under 2 px
    got = sel.select([pose_at(z + 0.1)], Pose.identity(), np.array([-10.0]))
    expect = int(np.nonzero(errs * FOCAL / z <= 2.0)[0].max())
    assert got[0] == expect >= 2


def test_level_follows_the_projected_triangle_size(sphere_levels):
    """A level is left for a coarser one only once its triangles are below `edge_px` on screen:
    a near object keeps level 0, a far one drops, and the projected edges say where."""
    settings = MeshLodSettings(invisible_error_px=1e3, edge_px=1.0, hysteresis=0.0)
    sel = MeshLodSelector([sphere_levels], FOCAL, settings)
    edges = sphere_levels.edges_m
    assert np.all(np.diff(edges) > 0)  # coarser levels have longer edges
    invisible = np.array([-10.0])
    z_near = edges[0] * FOCAL / 1.0 * 0.9  # level 0's edges are 1.1 px: keep it
    assert sel.select([pose_at(z_near + 0.1)], Pose.identity(), invisible)[0] == 0
    z_far = edges[1] * FOCAL / 1.0 * 1.05  # levels 0 and 1 below a pixel: at least level 2
    got = int(sel.select([pose_at(z_far + 0.1)], Pose.identity(), invisible)[0])
    assert got >= 2 and np.all(sel.edge_px(0, z_far)[:got] <= 1.0)
    assert sel.select([pose_at(z_near + 0.1)], Pose.identity(), invisible)[0] == 0  # back near: finest again


def test_zero_size_projection_and_behind_the_projector(sphere_levels):
    """Hard cases: an object so far that it projects to nothing takes the coarsest level; one
    behind (or straddling) the projector's plane, or at a NaN depth, takes level 0; all finite."""
    sel = MeshLodSelector([sphere_levels], FOCAL)
    far = sel.select([pose_at(1e6)], Pose.identity(), np.array([-np.inf]))
    assert far[0] == len(sphere_levels) - 1
    assert np.all(np.isfinite(sel.edge_px(0, 1e6))) and sel.edge_px(0, 1e6).max() < 1e-3
    for z in (-5.0, 0.05, 0.0):  # behind, straddling the plane (nearest point behind), at the plane
        assert sel.select([pose_at(z)], Pose.identity(), np.array([-np.inf]))[0] == 0
        assert sel.select([pose_at(1e6)], Pose.identity(), np.array([-np.inf]))[0] == len(sphere_levels) - 1
    assert np.all(np.isinf(sel.edge_px(0, -1.0)))
    nan_pose = Pose(np.eye(3), np.array([0.0, 0.0, np.nan]))
    assert sel.select([nan_pose], Pose.identity(), np.array([np.nan]))[0] == 0


def test_selection_never_rebuilds_a_bvh(sphere_levels, monkeypatch):
    sel = MeshLodSelector([sphere_levels, None], FOCAL)
    monkeypatch.setattr(mesh_levels, "build_bvh", lambda *a: pytest.fail("BVH rebuilt during selection"))
    for z in np.geomspace(0.5, 300, 30):
        sel.select([pose_at(z), pose_at(1.0)], Pose.identity(), np.array([1.0, 1.0]))
    assert sel.current[1] == 0


def test_object_visibility_is_the_max_over_covered_tiles():
    vis = np.array([[1.0, -5.0], [30.0, 2.0]], np.float32)
    ids = np.full((32, 32), -1, np.int32)
    ids[0:4, 0:20] = 0  # tiles (0,0) and (0,1)
    ids[20, 20] = 1  # tile (1,1)
    got = object_visibility(vis, 16, ids, 3)
    assert got[0] == 1.0 and got[1] == 2.0 and got[2] == -np.inf


def test_scene_at_levels_swaps_whole_meshes_only_where_chosen(sphere_levels):
    scene = load_scene("dpm-bunny")
    levels = [MeshLevels(scene.objects[0].mesh, reductions=(0.0, 0.9)), None]
    swapped = scene_at_levels(scene, levels, [1, 0])
    assert len(swapped.objects[0].mesh.faces) == levels[0].triangle_counts[1]
    assert swapped.objects[1] is scene.objects[1]
    assert scene_at_levels(scene, levels, [0, 0]).objects[0].mesh is scene.objects[0].mesh
