"""Finding 8 of issue 14: hostile scene, mesh and calibration files give one-line errors that
name the file and the field, quickly and without runaway memory."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from dpmhw.errors import RenderError, SceneError
from dpmhw.limits import render_memory_problem
from dpmhw.meshes import load_mesh
from dpmhw.scene_file import load_scene, parse_scene

from .test_scene_file import GOOD, write


def refused(path, field, words):
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert info.value.field == field, str(info.value)
    assert words in str(info.value) and str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_finding_8_huge_sphere_radius_is_a_field_error_not_an_overflow(tmp_path):
    path = write(tmp_path, GOOD + '[[objects]]\nshape = "sphere"\nradius = 1e300\n')
    refused(path, "objects[1].radius", "magnitude")


def test_finding_8_huge_quaternion_is_a_field_error(tmp_path):
    refused(write(tmp_path, GOOD + "rotation = [1e300, 1e300, 1e300, 1e300]\n"), "objects[0].rotation", "magnitude")


def test_finding_8_deeply_nested_toml_is_a_syntax_error(tmp_path):
    path = tmp_path / "deep.toml"
    path.write_text("x = " + "[" * 50_000 + "]" * 50_000 + "\n")
    refused(path, "(syntax)", "nested too deeply")


def test_finding_8_non_utf8_scene_names_the_byte(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes(textwrap.dedent(GOOD).replace('name = "light"', 'name = "lumi\xe8re"').encode("latin-1"))
    refused(path, "(file)", "not UTF-8")


def test_finding_8_oversized_scene_file_is_refused_before_reading(tmp_path, monkeypatch):
    path = write(tmp_path, GOOD + "#" * 4096 + "\n")
    monkeypatch.setenv("DPMHW_MAX_SCENE_KB", "2")
    refused(path, "(file)", "DPMHW_MAX_SCENE_KB")
    monkeypatch.delenv("DPMHW_MAX_SCENE_KB")
    load_scene(path)


def test_finding_8_a_sparse_2_gb_scene_file_is_refused_at_once(tmp_path):
    path = tmp_path / "huge.toml"
    with open(path, "wb") as f:  # sparse: takes no disk space, but stat() says 2 GB
        f.truncate(2 * 1024**3)
    refused(path, "(file)", "over the limit")


def test_finding_8_oversized_mesh_is_refused_before_trimesh_reads_it(tmp_path):
    path = tmp_path / "huge.obj"
    with open(path, "wb") as f:
        f.truncate(2 * 1024**3)
    mesh_scene = GOOD + '[[objects]]\nshape = "mesh"\nmesh = "huge.obj"\n'
    refused(write(tmp_path, mesh_scene), "objects[1].mesh", "DPMHW_MAX_MESH_MB")


def test_finding_8_mesh_with_huge_coordinates_is_refused(tmp_path):
    path = tmp_path / "far.obj"
    path.write_text("v 0 0 0\nv 1e300 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="far.obj.*1e\\+300"):
        load_mesh(path)


def test_finding_8_a_16384_square_render_names_the_memory_limit(tmp_path):
    path = write(tmp_path, GOOD.replace("width = 16", "width = 16384").replace("height = 12", "height = 16384"))
    refused(path, "render.width", "DPMHW_RENDER_MEMORY_MB")


def test_finding_8_render_memory_limit_can_be_raised(monkeypatch):
    assert render_memory_problem(3840, 2160) is None  # 4K fits the default
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", "10")
    assert "10 MiB" in render_memory_problem(256, 192)
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", "lots")
    with pytest.raises(ValueError, match="DPMHW_RENDER_MEMORY_MB"):
        render_memory_problem(16, 12)


def test_finding_8_the_renderer_itself_refuses_an_oversized_frame(tmp_path, monkeypatch):
    from dataclasses import replace

    from dpmhw.render.integrator import PathIntegrator

    scene = load_scene(write(tmp_path, GOOD))
    scene.render = replace(scene.render, width=16384, height=16384)  # e.g. a session config override
    with pytest.raises(RenderError, match="16384×16384.*DPMHW_RENDER_MEMORY_MB"):
        PathIntegrator(scene)


def test_finding_8_a_16384_square_calibration_cannot_drive_a_render(tmp_path):
    from dpmhw.projector_calibration import ProjectorCalibration

    ProjectorCalibration(width=16384, height=16384, K=np.eye(3) * [9000, 9000, 1], dist=np.zeros(5)).save(tmp_path / "p.json")
    text = GOOD.replace("width = 16", "width = 16384").replace("height = 12", "height = 16384").replace(
        "fx = 10.0\nfy = 10.0\ncx = 8.0\ncy = 3.0\nposition = [0.0, 0.0, 2.0]\nlook_at = [0.0, 0.0, 0.0]",
        'calibration = "p.json"')
    refused(write(tmp_path, text), "render.width", "DPMHW_RENDER_MEMORY_MB")


def test_finding_8_a_typo_in_render_is_reported_as_that_typo(tmp_path):
    refused(write(tmp_path, "[render]\nwidht = 1024\nheight = 768\n"), "render.widht", "unknown field")


# ------------------------------------------------------------------ fuzz (bounded, seeded)

_tokens = st.sampled_from([
    "[render]", "[camera]", "[[objects]]", "[viewer]", "width = ", "height = ", "radius = ", "shape = ", "fx = ",
    "rotation = ", "position = ", "size = ", "emission = ", "motion = ", "1e300", "-1e300", "nan", "inf", "0", "-1",
    "16384", '"sphere"', '"mesh"', '"box"', "[1.0, 2.0, 3.0]", "[1e300, 1e300, 1e300, 1e300]", "{ a = 1 }", "\n", "=",
    "[", "]", '"', "\\", "\x00", "\xff", "é", "true", "[[", "]]",
])


@settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(pieces=st.lists(_tokens, max_size=40), splice=st.integers(0, 400), keep_good=st.booleans())
def test_scene_loader_fuzz_raises_only_scene_errors(pieces, splice, keep_good):
    """Random token soup, alone or spliced into a valid scene: a Scene or a SceneError, nothing else."""
    noise = "".join(pieces)
    good = textwrap.dedent(GOOD)
    text = (good[:splice] + noise + good[splice:]) if keep_good else noise
    try:
        parse_scene(text, "fuzz.toml", Path("."))
    except SceneError as exc:
        assert "\n" not in str(exc).split(": ", 2)[-1] or "(syntax)" in str(exc)


def test_deeply_nested_calibration_json_is_a_field_error(tmp_path):
    (tmp_path / "p.json").write_text("[" * 100_000 + "]" * 100_000)
    text = GOOD.replace(
        "fx = 10.0\nfy = 10.0\ncx = 8.0\ncy = 3.0\nposition = [0.0, 0.0, 2.0]\nlook_at = [0.0, 0.0, 0.0]",
        'calibration = "p.json"')
    refused(write(tmp_path, text), "camera.calibration", "p.json")


def test_a_timeline_of_1e300_seconds_a_frame_is_a_field_error(tmp_path):
    """Frame 1 at 1e-300 fps lies 1e300 s out, where a rotating object's angle overflows."""
    text = GOOD.replace("height = 12", "height = 12\nfps = 1e-300") + "motion = { rotate_deg_per_s = 90.0 }\n"
    refused(write(tmp_path, text), "render.fps", "[0.001")


def test_scripted_rotation_far_out_on_the_timeline_is_still_a_rotation(tmp_path):
    scene = load_scene(write(tmp_path, GOOD + "motion = { rotate_deg_per_s = 90.0 }\n"))
    for t in (1e300, -1e300, 4.0):  # 4 s at 90°/s is a whole turn
        R = scene.objects[0].pose_at(t).R
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(scene.objects[0].pose_at(4.0).R, np.eye(3), atol=1e-12)


def test_a_calibration_file_that_is_not_utf8_names_the_file(tmp_path):
    from dpmhw.projector_calibration import CalibrationFileError, load_projector_calibration

    (tmp_path / "p.json").write_bytes(b'{"projector": "\xe9cran"}')
    with pytest.raises(CalibrationFileError) as info:
        load_projector_calibration(tmp_path / "p.json")
    assert str(info.value).startswith(f"{tmp_path / 'p.json'}: (file): not UTF-8 text (byte 15")
    text = GOOD.replace(
        "fx = 10.0\nfy = 10.0\ncx = 8.0\ncy = 3.0\nposition = [0.0, 0.0, 2.0]\nlook_at = [0.0, 0.0, 0.0]",
        'calibration = "p.json"')
    refused(write(tmp_path, text), "camera.calibration", "not UTF-8")
