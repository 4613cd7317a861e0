"""A scene at another size: the same point lands on the same place of the picture."""

from __future__ import annotations

import numpy as np

from dpmhw.scene_file import load_scene, scale_intrinsics


def test_pixel_centres_map_onto_each_other_and_skew_scales_with_x():
    K = np.array([[1000.0, 3.0, 511.5], [0.0, 900.0, 700.0], [0.0, 0.0, 1.0]])
    K2 = scale_intrinsics(K, 0.25, 0.5)
    x, y = 0.3, -0.2  # a normalised image point
    u, v = K @ [x, y, 1.0], K2 @ [x, y, 1.0]
    # the same point at (u + 0.5)·s − 0.5 in the scaled image: pixel centres onto pixel centres
    assert np.allclose(v[:2], [(u[0] + 0.5) * 0.25 - 0.5, (u[1] + 0.5) * 0.5 - 0.5])
    assert K2[0, 1] == 3.0 * 0.25 and K[0, 1] == 3.0  # skew with x; the input untouched


def test_at_size_keeps_the_scene_and_changes_only_size_and_intrinsics():
    scene = load_scene("dpm-bunny")
    same = scene.at_size(scene.render.width, scene.render.height)
    assert same is scene
    small = scene.at_size(64, 48)
    assert (small.render.width, small.render.height) == (64, 48)
    assert np.array_equal(small.camera.K, scale_intrinsics(scene.camera.K, 64 / scene.render.width, 48 / scene.render.height))
    assert small.objects is scene.objects and small.camera.pose is scene.camera.pose
