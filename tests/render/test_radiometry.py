"""Known answers: the point-to-rectangle form factor, the furnace, closed rooms."""

import numpy as np
import pytest

FLOOR_LIGHT = """
[render]
width = 32
height = 24
max_bounces = 0

[camera]
fx = 27.0
fy = 27.0
cx = 13.0
cy = 14.0
position = [1.6, 1.2, 1.4]
look_at = [0.0, 0.0, 0.0]

[[objects]]
name = "floor"
shape = "quad"
size = [3.0, 3.0]
albedo = [0.5, 0.5, 0.5]

[[objects]]
name = "light"
shape = "quad"
size = [0.6, 0.4]
position = [0.0, 0.5, 0.0]
rotation = [180.0, 0.0, 0.0]
albedo = 0.0
emission = [5.0, 5.0, 5.0]
"""


def rectangle_form_factor(x, z, hx, hz, c):
    """Differential area at (x, 0, z) facing +y to a parallel rectangle [−hx, hx]×[−hz, hz] at height c."""

    def corner(a, b):
        A, B = a / c, b / c
        sa, sb = np.sqrt(1 + A * A), np.sqrt(1 + B * B)
        return (A / sa * np.arctan(B / sa) + B / sb * np.arctan(A / sb)) / (2 * np.pi)

    x1, x2, z1, z2 = -hx - x, hx - x, -hz - z, hz - z
    return corner(x2, z2) - corner(x1, z2) - corner(x2, z1) + corner(x1, z1)


@pytest.mark.parametrize("mis_last", [False, True], ids=["nee-only", "mis"])
def test_direct_light_matches_form_factor(make_scene, render, mis_last):
    scene = make_scene(FLOOR_LIGHT)
    frame = render(scene, spp=4096, seed=3, mis_last=mis_last)
    on_floor = frame.object_id == 0
    assert on_floor.sum() > 300
    p = frame.position[on_floor]
    expected = 0.5 * 5.0 * rectangle_form_factor(p[:, 0], p[:, 2], 0.3, 0.2, 0.5)
    rel = frame.radiance[on_floor][:, 0] / expected - 1.0
    assert abs(np.mean(rel)) < 0.005
    assert np.percentile(np.abs(rel), 95) < 0.02
    assert frame.nonfinite_samples == 0


FURNACE = """
[render]
width = 40
height = 30
max_bounces = {bounces}
background = [2.0, 2.0, 2.0]

[camera]
fx = 30.0
fy = 30.0
cx = 20.0
cy = 15.0
position = [0.0, 0.0, {distance}]
look_at = [0.0, 0.0, 0.0]

[[objects]]
name = "ball"
{shape}
albedo = [0.6, 0.6, 0.6]
"""


@pytest.mark.parametrize("bounces", [0, 3])
@pytest.mark.parametrize(
    "shape, distance, tol",
    [
        ('shape = "box"\nsize = [1.0, 0.8, 0.6]\nrotation = [30.0, 40.0, 0.0]', 2.0, 1e-4),
        ('shape = "sphere"\nradius = 0.5', 2.0, 0.02),
        ('shape = "sphere"\nradius = 1e-3', 4e-3, 0.02),
        ('shape = "sphere"\nradius = 1e3', 4e3, 0.02),
    ],
    ids=["box", "sphere", "sphere-1mm", "sphere-1km"],
)
def test_furnace(make_scene, render, shape, distance, tol, bounces):
    """A convex diffuse object under a constant environment L reflects exactly ρ·L."""
    scene = make_scene(FURNACE.format(shape=shape, distance=distance, bounces=bounces))
    frame = render(scene, spp=8)
    obj = frame.object_id == 0
    assert obj.sum() > 50
    values = frame.radiance[obj]
    assert np.all(np.isfinite(values))
    # no self-intersection acne: not one pixel darker than the tolerance allows
    assert values.min() > 1.2 * (1 - 5 * tol) and values.max() < 1.2 * (1 + tol)
    assert abs(values.mean() / 1.2 - 1) < tol
    np.testing.assert_allclose(frame.radiance[~obj], 2.0)


CLOSED_ROOM = """
[render]
width = 32
height = 24
max_bounces = 8
background = [0.0, 1000.0, 0.0]

[camera]
fx = 12.0
fy = 12.0
cx = 16.0
cy = 12.0
position = [0.1, 0.0, 0.2]
look_at = [0.5, -0.2, -0.3]

[[objects]]
name = "room"
shape = "box"
size = [2.0, 2.0, 2.0]
albedo = [0.7, 0.7, 0.7]

[[objects]]
name = "light"
shape = "quad"
size = [0.5, 0.5]
position = [0.0, 0.99, 0.0]
rotation = [180.0, 0.0, 0.0]
albedo = 0.0
emission = [4.0, 4.0, 4.0]
"""


def test_camera_inside_closed_box_sees_no_leak(make_scene, render):
    """Every ray stays inside: a leak through an edge would pick up the huge green environment."""
    frame = render(make_scene(CLOSED_ROOM), spp=16)
    assert np.all(frame.object_id >= 0)
    assert frame.nonfinite_samples == 0
    r, g = frame.radiance[..., 0], frame.radiance[..., 1]
    np.testing.assert_allclose(g, r, rtol=1e-5, atol=1e-6)
    assert r.min() > 0.0 and r.max() < 50.0


def test_glossy_lobe_energy_and_mis_agree(make_scene, render):
    """A white glossy sphere under a white furnace reflects at most L, and NEE-only and MIS
    estimators agree (a wrong VNDF pdf would bias the MIS one)."""
    text = FURNACE.format(shape='shape = "sphere"\nradius = 0.5', distance=2.0, bounces=0).replace(
        "albedo = [0.6, 0.6, 0.6]", "albedo = [1.0, 1.0, 1.0]\nspecular = [1.0, 1.0, 1.0]\nroughness = 0.4"
    )
    scene = make_scene(text)
    nee = render(scene, spp=256, seed=1, mis_last=False)
    mis = render(scene, spp=256, seed=2, mis_last=True)
    obj = nee.object_id == 0
    a, b = nee.radiance[obj][:, 0], mis.radiance[obj][:, 0]
    assert a.mean() < 2.0 and b.mean() < 2.0  # reflectance ≤ 1
    assert a.mean() > 1.2  # a GGX lobe with Smith G loses little energy at this roughness
    assert abs(a.mean() / b.mean() - 1) < 0.01
    np.testing.assert_allclose(nee.specular[obj], nee.radiance[obj], rtol=1e-6)
    np.testing.assert_allclose(nee.diffuse[obj], 0.0, atol=1e-7)
