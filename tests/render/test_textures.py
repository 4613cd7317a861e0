"""Albedo textures: a mesh file's base-colour image through the loader, the path tracer and the
G-buffers, its bounds and errors, and the warning for what a file declares that the renderer does
not model."""

import numpy as np
import pytest
from textured_assets import DARK, LIGHT, checker, write_checker_quad

from dpmhw.errors import DpmhwError
from dpmhw.meshes import load_mesh
from dpmhw.render.gbuffer import NativeGBuffer
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene
from dpmhw.postprocess import srgb_decode

SIZE = 1.0
BACKGROUND = 2.0


def quad_scene(folder, *, albedo="", extra="", width=64, height=48, rigid_body=False) -> str:
    """The checker quad (write_checker_quad) seen obliquely, under a constant environment."""
    obj = write_checker_quad(folder, size=SIZE)
    text = f"""
[render]
width = {width}
height = {height}
max_bounces = 1
background = [{BACKGROUND}, {BACKGROUND}, {BACKGROUND}]

[camera]
fx = {0.9 * width}
fy = {0.9 * width}
cx = {width / 2}
cy = {height / 2}
position = [0.1, 1.1, 0.9]
look_at = [0.0, 0.0, 0.0]

[[objects]]
name = "quad"
shape = "mesh"
mesh = "{obj.name}"
smooth = false
{albedo}
{"rigid_body = 1" if rigid_body else ""}
{extra}
"""
    path = folder / "scene.toml"
    path.write_text(text)
    return path


def expected_albedo(camera, texture: np.ndarray, albedo=1.0) -> tuple[np.ndarray, np.ndarray]:
    """(albedo per pixel, on the quad) from the camera rays met with the plane y = 0 and the
    texture sampled bilinearly (repeat wrapping, texel centres at half-integers), in float64."""
    o, d = camera.generate_rays()
    o, d = np.asarray(o, float), np.asarray(d, float)
    t = -o[:, 1] / d[:, 1]
    p = o + t[:, None] * d
    h = SIZE / 2
    on = (t > 0) & (np.abs(p[:, 0]) < h * 0.98) & (np.abs(p[:, 2]) < h * 0.98)
    u, v = (p[:, 0] + h) / SIZE, (h - p[:, 2]) / SIZE
    H, W = texture.shape[:2]
    x, y = u * W - 0.5, (1 - v) * H - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    ax, ay = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(int) % W, y0.astype(int) % H
    x1, y1 = (x0 + 1) % W, (y0 + 1) % H
    value = ((1 - ax) * (1 - ay) * texture[y0, x0] + ax * (1 - ay) * texture[y0, x1]
             + (1 - ax) * ay * texture[y1, x0] + ax * ay * texture[y1, x1])
    return value * albedo, on


def linear_checker() -> np.ndarray:
    return np.repeat(srgb_decode(checker() / 255.0)[:, :, None], 3, axis=2)


# ---------------------------------------------------------------- loading

def test_an_obj_with_map_kd_loads_uv_and_a_linear_texture(tmp_path):
    mesh = load_mesh(write_checker_quad(tmp_path), smooth=False)
    assert mesh.uv is not None and mesh.uv.shape == (len(mesh.vertices), 2)
    corner_uv = {tuple(np.round(v, 6)): tuple(uv) for v, uv in zip(mesh.vertices, mesh.uv)}
    assert corner_uv[(-0.5, 0.0, 0.5)] == (0.0, 0.0) and corner_uv[(0.5, 0.0, -0.5)] == (1.0, 1.0)
    texels = mesh.texture.texels
    assert texels.shape == (32, 32, 3) and texels.dtype == np.float32
    assert texels[0, 0, 0] == pytest.approx(srgb_decode(LIGHT / 255), rel=1e-6)  # top-left cell light
    assert texels[0, 8, 0] == pytest.approx(srgb_decode(DARK / 255), rel=1e-6)
    assert mesh.notes == []  # Kd 1 and map_Kd: everything modelled


def test_what_a_material_declares_and_the_renderer_does_not_model_gets_one_warning_naming_it(tmp_path):
    path = quad_scene(tmp_path)
    (tmp_path / "quad.mtl").write_text("newmtl checker\nKd 0.8 0.8 0.8\nKs 0.5 0.5 0.5\nNs 20\nmap_Kd checker.png\n"
                                       "map_Bump -bm 0.5 bump.png\nnorm normal.png\nmap_Ks spec.png\nillum 2\n"
                                       "newmtl unused\nmap_Bump other.png\n")
    scene = load_scene(path)
    assert len(scene.notes) == 1
    note = scene.notes[0]
    for name in ("Kd 0.8 0.8 0.8", "Ks 0.5 0.5 0.5", "map_Bump bump.png", "norm normal.png", "map_Ks spec.png"):
        assert name in note, name
    assert "other.png" not in note  # a material no face uses declares nothing
    assert "illum" not in note and "Ns" not in note
    assert scene.objects[0].mesh.texture is not None  # the texture itself still applies


def test_vertex_colours_and_a_missing_material_library_are_named(tmp_path):
    (tmp_path / "coloured.obj").write_text("mtllib gone.mtl\nv 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 0 1 0 0 0 1\nf 1 2 3\n")
    notes = load_mesh(tmp_path / "coloured.obj").notes
    assert any("vertex colours" in n for n in notes), notes
    assert any("gone.mtl" in n for n in notes), notes


def test_a_ply_texture_file_loads_like_an_obj_texture(tmp_path):
    from PIL import Image

    Image.fromarray(checker()).convert("RGB").save(tmp_path / "skin.png")
    (tmp_path / "tex.ply").write_text(
        "ply\nformat ascii 1.0\ncomment TextureFile skin.png\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty float s\nproperty float t\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n0 0 0 0 0\n1 0 0 1 0\n0 1 0 0 1\n3 0 1 2\n")
    mesh = load_mesh(tmp_path / "tex.ply")
    assert mesh.texture.size == (32, 32) and mesh.notes == []
    assert {tuple(uv) for uv in mesh.uv} == {(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)}
    (tmp_path / "skin.png").unlink()
    with pytest.raises(ValueError, match="skin.png"):
        load_mesh(tmp_path / "tex.ply")


@pytest.mark.parametrize("suffix", ["glb", "gltf"])
def test_a_gltf_base_colour_texture_loads_and_its_other_textures_are_named(tmp_path, suffix):
    import trimesh
    from PIL import Image

    material = trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(checker()).convert("RGB"),
                                                   normalTexture=Image.new("RGB", (4, 4)))
    visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [0, 1]], material=material)
    exported = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], visual=visual, process=False).export(file_type=suffix)
    for name, data in (exported.items() if suffix == "gltf" else [("tex.glb", exported)]):  # .gltf: the JSON and its buffers
        (tmp_path / ("tex.gltf" if name == "model.gltf" else name)).write_bytes(data)
    mesh = load_mesh(tmp_path / f"tex.{suffix}")
    assert mesh.texture.size == (32, 32)
    assert mesh.texture.texels[0, 0, 0] == pytest.approx(srgb_decode(LIGHT / 255), rel=1e-6)
    assert {tuple(uv) for uv in mesh.uv} == {(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)}  # v up, as an OBJ's
    assert len(mesh.notes) == 1 and "normalTexture" in mesh.notes[0] and "baseColorTexture" not in mesh.notes[0]


def test_ply_vertex_colours_are_named(tmp_path):
    (tmp_path / "colour.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n0 0 0 255 0 0\n1 0 0 0 255 0\n0 1 0 0 0 255\n3 0 1 2\n")
    notes = load_mesh(tmp_path / "colour.ply").notes
    assert any("vertex colours" in n for n in notes), notes


@pytest.mark.parametrize("damage", ["missing", "garbage", "truncated", "directory"])
def test_a_texture_declared_but_unreadable_is_a_one_line_error_naming_it(tmp_path, damage):
    path = quad_scene(tmp_path)
    png = tmp_path / "checker.png"
    if damage == "missing":
        png.unlink()
    elif damage == "garbage":
        png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00garbage" * 10)
    elif damage == "truncated":
        png.write_bytes(png.read_bytes()[:60])
    else:
        png.unlink()
        png.mkdir()
    with pytest.raises(DpmhwError) as caught:
        load_scene(path)
    message = str(caught.value)
    assert "checker.png" in message and "\n" not in message, message


@pytest.mark.parametrize("vt", ["nan 0", "1e7 0"])
def test_texture_coordinates_must_be_finite_and_bounded(tmp_path, vt):
    obj = write_checker_quad(tmp_path)
    obj.write_text(obj.read_text().replace("vt 1 0\n", f"vt {vt}\n"))
    with pytest.raises(ValueError, match="texture coordinates"):
        load_mesh(obj)


def test_several_textures_on_one_mesh_are_refused_naming_them(tmp_path):
    obj = write_checker_quad(tmp_path)
    (tmp_path / "quad.mtl").write_text("newmtl a\nmap_Kd checker.png\nnewmtl b\nmap_Kd other.png\n")
    obj.write_text(obj.read_text().replace("usemtl checker\nf 1/1/1 2/2/1 3/3/1\n", "usemtl a\nf 1/1/1 2/2/1 3/3/1\nusemtl b\n"))
    with pytest.raises(ValueError, match="other.png"):
        load_mesh(obj)


def test_a_texture_counts_against_the_render_memory_limit(tmp_path, monkeypatch):
    from PIL import Image

    obj = write_checker_quad(tmp_path)
    Image.new("RGB", (4096, 4096)).save(tmp_path / "checker.png")  # compresses to a few kB, decodes to 16 M texels
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", "300")
    with pytest.raises(ValueError, match="16,777,216 texels"):
        load_mesh(obj)
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", "1000")
    assert load_mesh(obj).texture.size == (4096, 4096)


def test_an_obj_without_texture_coordinates_warns_that_its_texture_is_not_applied(tmp_path):
    obj = write_checker_quad(tmp_path)
    obj.write_text("mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 0 0 -1\nusemtl checker\nf 1 2 3\n")
    mesh = load_mesh(obj)
    assert mesh.texture is None and any("checker.png" in n and "texture coordinates" in n for n in mesh.notes)


def test_smoothing_keeps_a_uv_seam(tmp_path):
    """Two coplanar triangles sharing an edge, with other texture coordinates on each side:
    smoothing joins their normals and keeps each side's coordinates."""
    from dpmhw.meshes import smooth_within

    obj = tmp_path / "seam.obj"
    write_checker_quad(tmp_path)
    obj.write_text("mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 1 0 -1\nv 0 0 -1\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvt 0.5 0.5\n"
                   "usemtl checker\nf 1/1 2/2 3/3\nf 1/5 3/3 4/4\n")
    mesh = smooth_within(load_mesh(obj, smooth=False), 30.0)
    assert len(mesh.vertices) == 5  # corner 1 has two texture coordinates
    corners = mesh.uv[mesh.faces]
    assert tuple(corners[0, 0]) == (0.0, 0.0) and tuple(corners[1, 0]) == (0.5, 0.5)


# ---------------------------------------------------------------- rendering

def test_the_albedo_guides_hold_the_texture(tmp_path):
    """The path tracer's G-buffer albedo and the native G-buffer's (traced and rasterised) equal
    the texture sampled at each pixel's hit, times the object's albedo."""
    scene = load_scene(quad_scene(tmp_path, albedo="albedo = [1.0, 0.5, 0.25]", rigid_body=True))
    tint = np.array([1.0, 0.5, 0.25])
    with PathIntegrator(scene) as integrator:
        frame = integrator.render(spp=1)
        expected, on = expected_albedo(integrator.camera, linear_checker(), tint)
        assert on.sum() > 0.3 * on.size
        got = frame.albedo.reshape(-1, 3)
        np.testing.assert_allclose(got[on], expected[on], atol=2e-3)  # float32 hit points vs float64
        light = srgb_decode(LIGHT / 255) * tint
        assert np.isclose(got[on], light, atol=1e-4).all(axis=1).sum() > 0.3 * on.sum()  # whole cells at the texel value
        for mode in ("trace", "raster"):
            gbuffer = NativeGBuffer(scene, integrator.geometry, scene.render.width, scene.render.height)
            try:
                gbuffer.update(scene.object_poses(0.0), mode=mode)
                np.testing.assert_allclose(gbuffer.albedo[on], expected[on], atol=2e-3, err_msg=mode)
            finally:
                gbuffer.close()


def test_a_converged_render_of_a_textured_quad_is_texture_times_environment(tmp_path):
    """A diffuse quad under a constant environment L alone reflects albedo · L: every pixel is
    its hit's texture value times L (the cosine-weighted light samples make this nearly exact)."""
    scene = load_scene(quad_scene(tmp_path))
    with PathIntegrator(scene) as integrator:
        frame = integrator.render(spp=16, seed=1)
        expected, on = expected_albedo(integrator.camera, linear_checker())
    got = frame.radiance.reshape(-1, 3)[on]
    want = expected[on] * BACKGROUND
    # bound: float32 hit points put a pixel on a cell edge up to 2e-3 off in albedo (× L), and
    # 16 passes of MIS-weighted samples leave well under 1 % noise
    np.testing.assert_allclose(got, want, rtol=0.01, atol=5e-3)
    assert abs(got.mean() / want.mean() - 1) < 2e-3
