"""Scene files: what users write by hand must fail with the file and the field named."""

import math
import textwrap

import numpy as np
import pytest

from dpmhw.errors import SceneError
from dpmhw.scene_file import BUILTIN_SCENES, load_scene

GOOD = """
[render]
width = 16
height = 12

[camera]
fx = 10.0
fy = 10.0
cx = 8.0
cy = 3.0
position = [0.0, 0.0, 2.0]
look_at = [0.0, 0.0, 0.0]

[[objects]]
name = "light"
shape = "quad"
size = [1.0, 1.0]
emission = [1.0, 1.0, 1.0]
"""


def write(tmp_path, text):
    path = tmp_path / "scene.toml"
    path.write_text(textwrap.dedent(text))
    return path


def test_good_scene_loads_with_defaults(tmp_path):
    scene = load_scene(write(tmp_path, GOOD))
    assert scene.render.max_bounces == 1
    assert scene.render.fps == 947.0
    np.testing.assert_array_equal(scene.viewer_position, [0, 0, 2])
    assert scene.camera.K[1, 2] == 3.0  # the principal point is whatever the file says


@pytest.mark.parametrize(
    "edit, field, words",
    [
        (lambda s: s.replace("width = 16\n", ""), "render.width", "missing"),
        (lambda s: s.replace("width = 16", 'width = "16"'), "render.width", "integer"),
        (lambda s: s.replace('shape = "quad"', 'shape = "torus"'), "objects[0].shape", "quad, box, sphere, mesh"),
        (lambda s: s.replace('shape = "quad"', 'shape = "mesh"\nmesh = "nowhere.obj"'), "objects[0].mesh", "not found"),
        (lambda s: s + "albedo = [-0.1, 0.5, 0.5]\n", "objects[0].albedo", "[0.0, 1.0]"),
        (lambda s: s.replace("emission = [1.0, 1.0, 1.0]", "emission = [nan, 1.0, 1.0]"), "objects[0].emission", "finite"),
        (lambda s: s.replace("fx = 10.0", "fx = -10.0"), "camera.fx", "(0"),
        (lambda s: s + "albdo = 0.5\n", "objects[0].albdo", "unknown field"),
        (lambda s: s.replace("look_at = [0.0, 0.0, 0.0]", "look_at = [0.0, 0.0, 2.0]"), "camera.look_at", "undefined"),
        (lambda s: s.replace("emission = [1.0, 1.0, 1.0]", ""), "objects", "no light"),
        (lambda s: s + "rotation = [0.0, 0.0, 0.0, 0.0]\n", "objects[0].rotation", "zero length"),
        (lambda s: s + "motion = { oscillate_period_s = 0.0 }\n", "objects[0].motion.oscillate_period_s", "(0.0"),
        (lambda s: s.replace("[render]", "[render\n"), "(syntax)", "TOML"),
    ],
    ids=["missing", "wrong-type", "unknown-shape", "missing-mesh", "negative-albedo", "emission-nan", "bad-fx",
         "typo", "degenerate-view", "no-light", "zero-quaternion", "zero-period", "syntax"],
)
def test_bad_scene_names_file_and_field(tmp_path, edit, field, words):
    path = write(tmp_path, edit(textwrap.dedent(GOOD)))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert str(path) in message
    assert info.value.field == field
    assert words in message


def test_missing_scene_file_lists_builtins(tmp_path):
    with pytest.raises(SceneError, match="paper-static"):
        load_scene(tmp_path / "nope.toml")


def test_builtin_scenes_load_with_the_packaged_bunny():
    for name in BUILTIN_SCENES:
        scene = load_scene(name)
        assert scene.render.width == 1024 and scene.render.height == 768
        bunnies = [o for o in scene.objects if o.shape == "mesh"]
        assert name == "glossy-roughness" or (bunnies and all(len(o.mesh.faces) == 69_451 for o in bunnies))
    assert load_scene("paper-dynamic").objects[3].is_dynamic
    assert load_scene("dpm-bunny").objects[0].rigid_body == 1


def test_packaged_bunny_is_its_obj_read_back_bit_for_bit(tmp_path):
    """The package stores coordinates × 10⁶; the six-decimal OBJ they came from parses to the
    same float64 values, so the built-in scenes equal the OBJ's figures."""
    from dpmhw.meshes import load_mesh, stanford_bunny

    packaged = stanford_bunny()
    obj = tmp_path / "bunny.obj"
    with obj.open("w") as out:
        np.savetxt(out, packaged.vertices, fmt="v %.6f %.6f %.6f")
        np.savetxt(out, packaged.faces + 1, fmt="f %d %d %d")
    read = load_mesh(obj)
    assert len(packaged.faces) == 69_451 and packaged.dropped_degenerate == 0
    np.testing.assert_array_equal(read.vertices, packaged.vertices)
    np.testing.assert_array_equal(read.faces, packaged.faces)
    np.testing.assert_array_equal(read.vertex_normals, packaged.vertex_normals)


def test_bunny_override_from_the_environment_names_a_missing_file(monkeypatch, tmp_path):
    monkeypatch.setenv("DPMHW_BUNNY", str(tmp_path / "absent.obj"))
    with pytest.raises(SceneError, match="absent.obj"):
        load_scene("dpm-bunny")


def test_quaternion_and_euler_agree(tmp_path):
    a = load_scene(write(tmp_path, GOOD + "rotation = [0.0, 90.0, 0.0]\n"))
    b = load_scene(write(tmp_path, GOOD + f"rotation = [0.0, {math.sin(math.pi / 4)}, 0.0, {math.cos(math.pi / 4)}]\n"))
    np.testing.assert_allclose(a.objects[0].pose.R, b.objects[0].pose.R, atol=1e-12)
    np.testing.assert_allclose(a.objects[0].pose.R @ [1, 0, 0], [0, 0, -1], atol=1e-12)


def test_camera_from_calibration_file_drops_into_the_renderer(tmp_path):
    from dpmhw.projector_calibration import ProjectorCalibration
    from dpmhw.render.cameras import PinholeCamera
    from dpmhw.transforms import rotation_from_euler_xyz_deg

    K = np.array([[14.0, 0.0, 8.2], [0.0, 13.9, 11.0], [0.0, 0.0, 1.0]])  # lens shift: cy near the bottom
    calib = ProjectorCalibration(
        width=16, height=12, K=K, dist=np.array([0.05, -0.1, 0.001, 0.0, 0.0]),
        R=rotation_from_euler_xyz_deg([170.0, 10.0, 0.0]), t=np.array([0.1, 0.9, 1.2]), frame="tracker",
    )
    calib.save(tmp_path / "projector.json")
    text = GOOD.replace(
        "fx = 10.0\nfy = 10.0\ncx = 8.0\ncy = 3.0\nposition = [0.0, 0.0, 2.0]\nlook_at = [0.0, 0.0, 0.0]",
        'calibration = "projector.json"',
    )
    scene = load_scene(write(tmp_path, text))
    cam = PinholeCamera(scene.camera.K, scene.camera.dist, 16, 12, scene.camera.pose)
    pts = np.random.default_rng(0).uniform(-0.3, 0.3, (20, 3))
    np.testing.assert_allclose(cam.project(pts)[0], calib.project(pts), atol=1e-6)


def test_calibration_for_another_resolution_is_rejected(tmp_path):
    from dpmhw.projector_calibration import ProjectorCalibration

    ProjectorCalibration(width=1920, height=1080, K=np.eye(3) * [1000, 1000, 1], dist=np.zeros(5)).save(tmp_path / "p.json")
    text = GOOD.replace(
        "fx = 10.0\nfy = 10.0\ncx = 8.0\ncy = 3.0\nposition = [0.0, 0.0, 2.0]\nlook_at = [0.0, 0.0, 0.0]",
        'calibration = "p.json"',
    )
    with pytest.raises(SceneError, match="1920×1080"):
        load_scene(write(tmp_path, text))


def test_a_calibrated_camera_gives_the_size_and_a_mesh_is_no_calibration(tmp_path):
    from dpmhw.projector_calibration import ProjectorCalibration

    ProjectorCalibration(width=20, height=10, K=np.eye(3) * [30, 30, 1], dist=np.zeros(5)).save(tmp_path / "p.json")
    camera = "fx = 10.0\nfy = 10.0\ncx = 8.0\ncy = 3.0\nposition = [0.0, 0.0, 2.0]\nlook_at = [0.0, 0.0, 0.0]"
    text = GOOD.replace(camera, 'calibration = "p.json"').replace("width = 16\nheight = 12\n", "")
    render = load_scene(write(tmp_path, text)).render
    assert (render.width, render.height) == (20, 10)
    with pytest.raises(SceneError, match=r"render\.width: give both"):
        load_scene(write(tmp_path, text.replace("[render]\n", "[render]\nheight = 10\n")))
    (tmp_path / "box.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(SceneError, match=r"camera\.calibration: cannot load .*box\.obj"):
        load_scene(write(tmp_path, text.replace("p.json", "box.obj")))


BOX_OBJ = "".join(f"v {x} {y} {z}\n" for x in (0, 1) for y in (0, 1) for z in (0, 1)) + """\
f 1 2 4
f 1 4 3
f 5 7 8
f 5 8 6
f 1 5 6
f 1 6 2
f 3 4 8
f 3 8 7
f 1 3 7
f 1 7 5
f 2 6 8
f 2 8 4
"""


@pytest.mark.parametrize("fields, corners, flat", [
    ("", 24, True),  # default: 90° edges are sharper than the 30° default, each face is flat
    ("smooth_angle = 95.0\n", 8, False),  # every edge smooth: one averaged normal per corner
    ("smooth = true\n", 8, False),
    ("smooth = false\n", 8, True),  # flat shading has no vertex normals at all
])
def test_a_shared_vertex_box_mesh_has_sharp_edges_by_default(tmp_path, fields, corners, flat):
    (tmp_path / "box.obj").write_text(BOX_OBJ)
    scene = load_scene(write(tmp_path, GOOD + '[[objects]]\nname = "box"\nshape = "mesh"\nmesh = "box.obj"\n' + fields))
    mesh = scene.objects[1].mesh
    assert len(mesh.vertices) == corners
    tri = mesh.triangles
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face_n /= np.linalg.norm(face_n, axis=1, keepdims=True)
    if mesh.vertex_normals is None:
        assert flat
    else:
        agree = np.einsum("fkj,fj->fk", mesh.vertex_normals[mesh.faces], face_n)
        assert np.allclose(agree, 1.0) == flat and np.all(agree > 0.3)  # outward, wound consistently


def test_smooth_angle_keeps_a_sphere_smooth_and_names_misuse(tmp_path):
    import trimesh

    from dpmhw.meshes import DEFAULT_SMOOTH_ANGLE_DEG, load_mesh, smooth_within, sphere_mesh

    sphere = smooth_within(sphere_mesh(1.0, smooth=False), DEFAULT_SMOOTH_ANGLE_DEG)
    assert len(sphere.vertices) == 2562  # no vertex split
    np.testing.assert_allclose(np.einsum("ij,ij->i", sphere.vertex_normals, sphere.vertices), 1.0, atol=1e-4)
    (tmp_path / "box.obj").write_text(BOX_OBJ)
    base = GOOD + '[[objects]]\nname = "box"\nshape = "mesh"\nmesh = "box.obj"\n'
    stl = tmp_path / "sphere.stl"  # an STL shares no vertex: corners at one position are joined
    trimesh.creation.icosphere(subdivisions=3).export(stl)
    assert len(smooth_within(load_mesh(stl, smooth=False), DEFAULT_SMOOTH_ANGLE_DEG).vertices) == 642
    with pytest.raises(SceneError, match=r"objects\[1\]\.smooth_angle: only a mesh"):
        load_scene(write(tmp_path, base + "smooth = true\nsmooth_angle = 10.0\n"))
    with pytest.raises(SceneError, match=r"objects\[1\]\.smooth_angle: expected a number in \[0.0, 180.0\]"):
        load_scene(write(tmp_path, base + "smooth_angle = 200.0\n"))
