"""The shading kernel's own arithmetic: its inline cos/sin, and the G-buffer rows it owns."""

import numba as nb
import numpy as np
from scene_texts import lit_room

from dpmhw.render import kernels

from .test_integrator import ROOM


@nb.njit
def _cos_sin_all(u, c, s):
    for i in range(u.shape[0]):
        c[i], s[i] = kernels._cos_sin_turn(u[i])


def test_inline_cos_sin_is_within_float32_rounding_of_libm():
    u = np.random.default_rng(3).random(200_000).astype(np.float32)
    edges = np.arange(9, dtype=np.float32) / np.float32(8)  # quadrant and octant boundaries, 0 and 1
    u = np.concatenate([u, edges, np.nextafter(edges, np.float32(2)), np.nextafter(edges, np.float32(-1))[1:]])
    c, s = np.empty_like(u), np.empty_like(u)
    _cos_sin_all(u, c, s)
    angle = 2 * np.pi * u.astype(np.float64)
    assert np.abs(c - np.cos(angle)).max() < 2e-7
    assert np.abs(s - np.sin(angle)).max() < 2e-7
    assert np.abs(c.astype(np.float64) ** 2 + s.astype(np.float64) ** 2 - 1).max() < 5e-7


def test_first_pass_writes_every_gbuffer_row_over_stale_memory(make_scene, render, monkeypatch):
    """clear_rows leaves the G-buffer to the first shading pass (a miss writes its no-hit values):
    stale values in the freshly allocated arrays must not survive."""
    from dpmhw.render import integrator

    scene = make_scene(ROOM.format(extra=""))
    clean = render(scene, spp=2, seed=5)
    assert (clean.object_id < 0).any() and (clean.object_id >= 0).any()

    class StaleGBuffer(integrator._GBuffer):
        def __init__(self, npix):
            super().__init__(npix)
            for a in (self.id, self.model, self.pos, self.normal, self.alb, self.spec, self.depth, self.rough):
                a.fill(7)

    monkeypatch.setattr(integrator, "_GBuffer", StaleGBuffer)
    stale = render(scene, spp=2, seed=5)
    for name in ("object_id", "model_position", "position", "normal", "depth", "albedo", "specular_albedo", "roughness", "radiance"):
        assert np.array_equal(getattr(clean, name), getattr(stale, name)), name
    miss = stale.object_id < 0
    assert np.all(np.isinf(stale.depth[miss])) and not stale.normal[miss].any() and not stale.albedo[miss].any()


def test_light_rows_are_the_emitters_in_world_space_at_their_pose(make_scene):
    """SceneGeometry.light_rows: the emissive triangles the kernel samples, at the frame's poses
    (a moving, turning emitter included), as the poses place the model-space meshes."""
    from dpmhw.render.geometry import SceneGeometry

    scene = make_scene(lit_room("""
[[objects]]
name = "lamp"
shape = "quad"
size = [0.2, 0.1]
position = [0.2, 0.4, 0.1]
rotation = [30.0, 10.0, 0.0]
albedo = 0.0
emission = [3.0, 2.0, 1.0]
motion = { rotate_axis = [0.3, 1.0, 0.0], rotate_deg_per_s = 90.0, oscillate_direction = [1.0, 0.0, 0.0], oscillate_amplitude = 0.1, oscillate_period_s = 2.0 }
""", width=16, height=12, f=13.0, cx=8.0, cy=6.0, max_bounces=1))
    geometry = SceneGeometry(scene, threads=1)
    try:
        for t in (0.0, 0.37):
            poses = scene.object_poses(t)
            rows = geometry.light_rows(*geometry.poses(poses))
            assert rows.shape == (len(geometry.light_prim), 12) and rows.dtype == np.float32
            assert set(geometry.light_obj) == {1, 2}
            for row, prim, k in zip(rows, geometry.light_prim, geometry.light_obj):
                pose, mesh = poses[k], scene.objects[k].mesh
                corners = pose.apply(mesh.triangles[prim - geometry.tri_offsets[k]])
                normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
                np.testing.assert_allclose(row[0:3], corners[0], atol=1e-5)
                np.testing.assert_allclose(row[3:6], corners[1] - corners[0], atol=1e-5)
                np.testing.assert_allclose(row[6:9], corners[2] - corners[0], atol=1e-5)
                np.testing.assert_allclose(row[9:12], normal / np.linalg.norm(normal), atol=1e-5)
    finally:
        geometry.close()
