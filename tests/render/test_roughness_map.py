"""Roughness that varies within one object (a scene's `roughness_map`): parsed with one-line field
errors, banded per triangle, and read by the renderer's material lookup and the native G-buffer."""

import textwrap

import numpy as np
import pytest

from dpmhw.errors import SceneError
from dpmhw.scene_file import load_scene

SCENE = """
[render]
width = 32
height = 24

[camera]
fx = 30.0
fy = 30.0
cx = 16.0
cy = 12.0
position = [0.0, 1.0, 0.0]
look_at = [0.0, 0.0, 0.0]
up = [0.0, 0.0, -1.0]

[[objects]]
name = "light"
shape = "quad"
size = [0.2, 0.2]
position = [0.0, 1.5, 0.0]
rotation = [180.0, 0.0, 0.0]
emission = [20.0, 20.0, 20.0]

[[objects]]
name = "tile"
shape = "quad"
size = [1.0, 1.0]
segments = [8, 2]
specular = [0.5, 0.5, 0.5]
roughness_map = { axis = [1.0, 0.0, 0.0], edges = [0.0], values = [0.1, 0.6] }
"""


def load(tmp_path, text):
    path = tmp_path / "scene.toml"
    path.write_text(textwrap.dedent(text))
    return load_scene(path), path


def test_bands_follow_triangle_centroids(tmp_path):
    scene, _ = load(tmp_path, SCENE)
    tile = scene.objects[1]
    assert len(tile.mesh.faces) == 32
    centre_x = tile.mesh.triangles.mean(axis=1)[:, 0]
    np.testing.assert_array_equal(tile.face_roughness, np.where(centre_x < 0.0, 0.1, 0.6))
    assert tile.roughness == 0.1  # the smallest: what MIS decisions need
    assert scene.objects[0].face_roughness is None


@pytest.mark.parametrize(
    "old, new, field, words",
    [
        ("edges = [0.0]", "edges = [0.2, 0.1]", "objects[1].roughness_map.edges", "increasing"),
        ("values = [0.1, 0.6]", "values = [0.1]", "objects[1].roughness_map.values", "expected 2"),
        ("values = [0.1, 0.6]", "values = [0.1, 1.5]", "objects[1].roughness_map.values", "[0.0, 1.0]"),
        ("values = [0.1, 0.6]", 'values = [0.1, "x"]', "objects[1].roughness_map.values", "finite numbers"),
        ("axis = [1.0, 0.0, 0.0]", "axis = [0.0, 0.0, 0.0]", "objects[1].roughness_map.axis", "non-zero"),
        ("axis = [1.0, 0.0, 0.0], ", "", "objects[1].roughness_map.axis", "missing"),
        ("edges = [0.0]", "edge = [0.0]", "objects[1].roughness_map.edge", "unknown field"),
        ("specular = [0.5, 0.5, 0.5]", "specular = [0.5, 0.5, 0.5]\nroughness = 0.2", "objects[1].roughness_map", "cannot be combined"),
        ("segments = [8, 2]", "segments = [8, 0]", "objects[1].segments", "[1"),
        ("segments = [8, 2]", "segments = [8.5, 2]", "objects[1].segments", "whole numbers"),
        ('name = "light"', 'name = "light"\nsegments = [2, 2]\nshape2 = 1', "objects[0].shape2", "unknown field"),
    ],
    ids=["edges-order", "values-count", "values-range", "values-type", "axis-zero", "axis-missing", "typo", "both",
         "segments-zero", "segments-fraction", "typo-2"],
)
def test_bad_roughness_map_names_the_field(tmp_path, old, new, field, words):
    assert old in SCENE
    with pytest.raises(SceneError) as info:
        load(tmp_path, SCENE.replace(old, new))
    assert info.value.field == field
    assert words in str(info.value)
    assert "\n" not in str(info.value)


def test_segments_only_on_a_quad(tmp_path):
    text = SCENE.replace('shape = "quad"\nsize = [0.2, 0.2]', 'shape = "box"\nsize = [0.2, 0.2, 0.2]\nsegments = [2, 2]')
    with pytest.raises(SceneError) as info:
        load(tmp_path, text)
    assert info.value.field == "objects[0].segments" and "only a quad" in str(info.value)


def test_renderer_and_native_gbuffer_read_the_per_triangle_roughness(tmp_path):
    from dpmhw.render.gbuffer import NativeGBuffer
    from dpmhw.render.integrator import PathIntegrator

    scene, _ = load(tmp_path, SCENE)
    with PathIntegrator(scene, threads=1) as integ:
        frame = integ.render(spp=1, seed=0)
        hit = frame.object_id == 1
        x = frame.position[..., 0]
        rough = frame.roughness
        # the G-buffer roughness is √α with α = roughness² (floored): the band's roughness
        np.testing.assert_allclose(rough[hit & (x < -0.05)], 0.1, rtol=1e-5)
        np.testing.assert_allclose(rough[hit & (x > 0.05)], 0.6, rtol=1e-5)
        g = NativeGBuffer(scene, integ.geometry, 32, 24, threads=1)
        try:
            g.update(scene.object_poses(0.0))
            # (not at x = 0, the bands' shared edge: the image centre's ray meets it exactly, so
            # either band is a right answer there, and the rasterised camera hits and the
            # native G-buffer's traced ones may take different sides)
            off_edge = hit & (np.abs(x) > 1e-6)
            np.testing.assert_allclose(g.roughness.reshape(24, 32)[off_edge], rough[off_edge], rtol=1e-5)
            assert off_edge.sum() >= hit.sum() - 24  # (at most the column of pixels the edge passes through)
        finally:
            g.close()


def test_a_one_band_map_renders_exactly_as_the_plain_roughness(tmp_path):
    from dpmhw.render.integrator import PathIntegrator

    mapped, _ = load(tmp_path, SCENE.replace("values = [0.1, 0.6]", "values = [0.3, 0.3]"))
    plain, _ = load(tmp_path, SCENE.replace("roughness_map = { axis = [1.0, 0.0, 0.0], edges = [0.0], values = [0.1, 0.6] }",
                                            "roughness = 0.3"))
    images = []
    for scene in (mapped, plain):
        with PathIntegrator(scene, threads=1) as integ:
            images.append(integ.render(spp=4, seed=3).radiance)
    np.testing.assert_array_equal(images[0], images[1])
