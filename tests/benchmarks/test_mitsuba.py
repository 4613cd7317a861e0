"""`dpmhw bench mitsuba`: the dpmhw → Mitsuba 3 scene conversion and the comparison masks.

The conversion tests need mitsuba (`pip install -e '.[mitsuba]'`) and skip without it; the
camera ones use the scalar variant, the render one the LLVM variant and a libLLVM ≥ 16."""

import dataclasses
import sys
import textwrap

import numpy as np
import pytest

from dpmhw.benchmarks import mitsuba as mb
from dpmhw.errors import SceneError
from dpmhw.render.cameras import PinholeCamera
from dpmhw.scene_file import load_scene
from dpmhw.transforms import Pose
from scene_texts import lit_room

BALL = """
[[objects]]
name = "ball"
shape = "sphere"
radius = 0.15
position = [0.1, 0.15, 0.1]
albedo = [0.6, 0.7, 0.8]
"""


@pytest.fixture
def room(tmp_path):
    """A small lit room with a sphere, camera principal point off centre (cx, cy not W/2, H/2)."""

    def make(width=64, height=48, f=60.0, cx=30.3, cy=25.1, extra=""):
        path = tmp_path / "room.toml"
        path.write_text(textwrap.dedent(lit_room(BALL + extra, width=width, height=height, f=f, cx=cx, cy=cy, max_bounces=1)))
        return load_scene(path)

    return make


def test_max_depth_covers_one_bounce():
    # camera → light (1), direct light at the first hit (2), at the second hit (3)
    assert mb.max_depth(0) == 2
    assert mb.max_depth(1) == 3


def test_to_world_turns_opencv_axes_into_mitsuba_axes():
    R = Pose.identity().R
    m = mb.to_world_matrix(Pose(R, np.array([1.0, 2.0, 3.0])))
    assert np.allclose(m[:3, 2], [0, 0, 1])  # both look along +z
    assert np.allclose(m[:3, 0], [-1, 0, 0]) and np.allclose(m[:3, 1], [0, -1, 0])  # Mitsuba x left, y up
    assert np.allclose(m[:3, 3], [1, 2, 3])


def test_panned_poses_differ_every_frame_and_stay_small(room):
    pose = room().camera.pose
    poses = [mb.panned_pose(pose, k) for k in range(9)]
    angles = [np.degrees(np.arccos(np.clip((np.trace(p.R @ pose.R.T) - 1) / 2, -1, 1))) for p in poses]
    assert max(angles) <= mb.PAN_DEG + 1e-9
    assert len({round(a, 6) for a in angles}) == 9
    assert all(np.array_equal(p.t, pose.t) for p in poses)


def test_interior_mask_keeps_pixels_away_from_object_and_normal_edges():
    ids = np.zeros((40, 40), np.int32)
    ids[:, 20:] = 1
    normal = np.zeros((40, 40, 3), np.float32)
    normal[:20, :, 1] = 1.0  # top half faces +y, bottom half +z: a corner along row 20
    normal[20:, :, 2] = 1.0
    ids[0:5, 0:5] = -1  # background
    m = mb.interior_mask(ids, normal, radius=3)
    assert not m[:, 17:23].any() and not m[17:23, :].any()  # within 3 px of either edge
    assert m[10, 10] and m[30, 30] and m[10, 30] and m[30, 10]
    assert not m[0:5, 0:5].any()
    smooth = mb.interior_mask(ids, normal, radius=3, crease_ids=[1])  # object 0 smooth: its normals may turn
    assert smooth[20, 10] and not smooth[20, 30] and not smooth[10, 20]


def test_regions_split_the_room_by_face(room):
    scene = room()
    ids = np.zeros((60, 60), np.int32)  # all "room" (object 0)
    normal = np.zeros((60, 60, 3), np.float32)
    normal[:30, :, 1] = 1.0
    normal[30:, :, 2] = 1.0
    names = set(mb.regions(scene, ids, normal))
    assert names == {"all interior", "room normal +y", "room normal +z"}


GLOSSY_BALL = """
[[objects]]
name = "glossy"
shape = "sphere"
radius = 0.2
position = [-0.15, 0.2, -0.2]
albedo = [0.8, 0.5, 0.3]
specular = [0.5, 0.5, 0.5]
roughness = 0.5
"""


def test_glossy_bsdf_is_the_sum_of_dpmhw_lobes(room):
    obj = room(extra=GLOSSY_BALL).objects[-1]
    d = mb.bsdf_dict(obj)["bsdf"]
    w, kd = d["weight"], np.array(d["bsdf_0"]["reflectance"]["value"])
    ks = np.array(d["bsdf_1"]["specular_reflectance"]["value"])
    assert np.allclose((1 - w) * kd, obj.albedo * (1 - obj.specular))  # the Lambert lobe
    assert np.allclose(w * ks, obj.specular) and d["bsdf_1"]["material"] == "none"  # GGX lobe, Fresnel 1
    assert d["bsdf_1"]["alpha"] == pytest.approx(0.25)
    assert mb.bsdf_dict(room().objects[-1]) == {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
        "type": "rgb", "value": [0.6, 0.7, 0.8]}}}


def test_scenes_the_conversion_cannot_express_are_refused_by_field(room):
    with pytest.raises(SceneError, match=r"objects\[\d+\]\.roughness_map"):
        mb._check_convertible(load_scene("glossy-roughness"))
    colourful = room(extra=GLOSSY_BALL.replace("specular = [0.5, 0.5, 0.5]", "specular = [0.9, 0.05, 0.05]"))
    with pytest.raises(SceneError, match=r"objects\[3\]\.specular: specular channels"):
        mb._check_convertible(colourful)
    scene = room()
    scene.viewer_position = scene.viewer_position + 1.0
    with pytest.raises(SceneError, match="viewer"):
        mb._check_convertible(scene)


def test_missing_mitsuba_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # import raises ImportError
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/nonexistent/libLLVM.so")
    with pytest.raises(mb.MitsubaUnavailable, match=r"mitsuba is not installed.*\[mitsuba\]"):
        mb.load_mitsuba()


def test_libllvm_path_prefers_the_environment(monkeypatch):
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/some/libLLVM.so.19")
    assert mb.libllvm_path() == "/some/libLLVM.so.19"


# ---- with mitsuba -----------------------------------------------------------------------------

def _scalar_mitsuba():
    pytest.importorskip("mitsuba")
    return mb.load_mitsuba("scalar_rgb")


def _rays(mi, sensor, scene, pixels):
    """Mitsuba's ray through the centre of each OpenCV pixel (x, y)."""
    W, H = scene.render.width, scene.render.height
    out = []
    for x, y in pixels:
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((x + 0.5) / W, (y + 0.5) / H), mi.Point2f(0.5, 0.5))
        out.append((np.array(ray.o, float), np.array(ray.d, float)))
    return out


@pytest.mark.parametrize("cx, cy", [(32.0, 24.0), (30.3, 25.1), (40.0, 10.0)])
def test_sensor_rays_match_dpmhw_camera_rays(room, cx, cy):
    mi = _scalar_mitsuba()
    scene = room(cx=cx, cy=cy)
    sensor = mi.load_dict(mb.sensor_dict(scene))
    cam = PinholeCamera(scene.camera.K, scene.camera.dist, scene.render.width, scene.render.height, scene.camera.pose)
    _, d = cam.generate_rays()
    pixels = [(0, 0), (63, 0), (0, 47), (63, 47), (31, 23), (10, 40), (50, 5)]
    for (x, y), (_, md) in zip(pixels, _rays(mi, sensor, scene, pixels)):
        assert np.allclose(md, d[y * scene.render.width + x], atol=2e-6), (x, y)


def test_known_points_project_to_the_same_pixels(room):
    """World points projected by dpmhw's camera lie on Mitsuba's rays through those pixels."""
    mi = _scalar_mitsuba()
    scene = room()
    pose = mb.panned_pose(scene.camera.pose, 3)  # also after moving the sensor
    sensor = mi.load_dict(mb.sensor_dict(scene))
    params = mi.traverse(sensor)
    params["to_world"] = mi.Transform4f(mb.to_world_matrix(pose).tolist())
    params.update()
    cam = PinholeCamera(scene.camera.K, scene.camera.dist, scene.render.width, scene.render.height, pose)
    points = np.array([[0.0, 0.4, 0.0], [0.3, 0.1, -0.2], [-0.35, 0.8, -0.45], [0.1, 0.15, 0.1]])
    px, in_front = cam.project(points)
    assert in_front.all()
    W, H = scene.render.width, scene.render.height
    for p, (u, v) in zip(points, px):
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((u + 0.5) / W, (v + 0.5) / H), mi.Point2f(0.5, 0.5))
        o, d = np.array(ray.o, float), np.array(ray.d, float)
        off = (p - o) - np.dot(p - o, d) * d  # the point's distance from the ray
        assert np.linalg.norm(off) < 1e-5 * np.linalg.norm(p - o), (p, u, v)


def test_scene_dict_has_every_object_in_world_space(room):
    mi = _scalar_mitsuba()
    scene = room()
    mscene = mi.load_dict(mb.scene_dict(scene))
    shapes = {s.id(): s for s in mscene.shapes()}
    assert len(shapes) == len(scene.objects)
    for i, obj in enumerate(scene.objects):  # keyed by index: an object may be named "sensor"
        bbox = shapes[f"object{i}"].bbox()
        world = obj.pose.apply(obj.mesh.vertices)
        assert np.allclose(np.array(bbox.min), world.min(axis=0), atol=1e-5), obj.name
        assert np.allclose(np.array(bbox.max), world.max(axis=0), atol=1e-5), obj.name
        assert shapes[f"object{i}"].is_emitter() == obj.is_emissive
    assert len(mscene.emitters()) == 1
    assert mb.scene_dict(scene)["integrator"]["max_depth"] == 3


@pytest.mark.parametrize("extra", ["", GLOSSY_BALL], ids=["diffuse", "glossy"])
def test_converged_images_agree_away_from_edges(room, extra):
    pytest.importorskip("mitsuba")
    if mb.libllvm_path() is None:
        pytest.skip(f"no libLLVM ≥ {mb.MIN_LLVM} for Mitsuba's LLVM variant")
    path = room(width=128, height=96, f=120.0, cx=64.3, cy=48.1, extra=extra).source
    rows = mb.compare(path, spp=128, threads=2)
    by_region = {r["region"]: r for r in rows if "rel_diff" in r}
    assert by_region["all interior"]["pixels"] > 3000
    if extra:
        assert by_region["glossy"]["pixels"] >= 100  # the glossy lobe is compared, not masked away
    # 128 spp: region means carry ≲ 1 % noise; a wrong camera, BSDF side, lobe or depth is ≫ 5 %
    assert abs(by_region["all interior"]["rel_diff"]) < 0.03, by_region["all interior"]
    for r in by_region.values():
        if r["pixels"] >= 100:
            assert abs(r["rel_diff"]) < max(0.05, 4 * r["rel_stderr"]), r


def test_a_textured_object_converts_to_a_bitmap_with_mitsubas_texture_coordinates(tmp_path):
    pytest.importorskip("mitsuba")
    from textured_assets import write_checker_quad

    from dpmhw.meshes import load_mesh

    mb.load_mitsuba("scalar_rgb")
    mesh = load_mesh(write_checker_quad(tmp_path), smooth=False)
    obj = type("Obj", (), {"mesh": mesh, "albedo": np.array([1.0, 0.5, 0.25]), "specular": np.zeros(3), "roughness": 0.5})
    reflectance = mb.bsdf_dict(obj)["bsdf"]["reflectance"]
    assert reflectance["type"] == "bitmap" and reflectance["raw"] and reflectance["wrap_mode"] == "repeat"
    data = np.array(reflectance["bitmap"])
    np.testing.assert_allclose(data, mesh.texture.texels * np.float32([1.0, 0.5, 0.25]), rtol=1e-6)


@pytest.mark.slow
def test_the_textured_bunny_agrees_with_mitsuba_tile_by_tile(tmp_path):
    """The textured bunny (a checker by planar projection, glossy as dpm-bunny) converged in both
    renderers: every 16 × 16 tile away from edges within 2 % in mean luminance. Mitsuba's scalar
    variant (no libLLVM needed)."""
    pytest.importorskip("mitsuba")
    from textured_assets import textured_bunny_scene

    path = textured_bunny_scene(tmp_path, width=320, height=240)
    rows = mb.compare(str(path), spp=1024, threads=2, variant="scalar_rgb", tile=16)
    tiles = [r for r in rows if r.get("region", "").startswith("tile")]
    assert len(tiles) >= 10
    # 1024 spp: a 16 × 16 tile's mean carries about 0.4 % noise; a flipped v, a texture not
    # sRGB-decoded or filtered otherwise moves checker tiles by ≫ 2 %
    worst = max(tiles, key=lambda r: abs(r["rel_diff"]))
    assert abs(worst["rel_diff"]) < max(0.02, 3 * worst["rel_stderr"]), worst


def test_one_spp_frame_times_what_the_conversion_refuses_and_says_what_it_changed(room):
    """The cost yardstick of `bench session`: a separate viewer and lens distortion are changed
    (the same rays), said in the note; a variant this build lacks falls back to the next."""
    pytest.importorskip("mitsuba")
    scene = room(width=32, height=24, f=30.0, cx=15.5, cy=11.5)
    scene = dataclasses.replace(scene, viewer_position=scene.camera.pose.t + 0.3,
                                camera=dataclasses.replace(scene.camera, dist=np.array([0.01, 0, 0, 0, 0])))
    row = mb.one_spp_frame(scene, frames=3, threads=1, variants=("no_such_variant", "scalar_rgb"))
    assert row["mitsuba_variant"] == "scalar_rgb" and row["mitsuba_frames"] == 3
    assert row["mitsuba_cpu_ms"] > 0 and row["mitsuba_wall_ms"] > 0
    for said in ("towards the camera", "without lens distortion", "fell back to scalar_rgb"):
        assert said in row["mitsuba_note"]
    with pytest.raises(mb.MitsubaUnavailable, match="no_such_variant"):
        mb.one_spp_frame(scene, frames=3, variants=("no_such_variant",))
