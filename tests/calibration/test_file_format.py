"""The calibration file: round trip, atomic writes, and errors that name the file and field."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dpmhw.errors import CalibrationError, DpmhwError
from dpmhw.projector_calibration import CalibrationFileError, LensModel, ProjectorCalibration, load_projector_calibration


def _cal() -> ProjectorCalibration:
    K = np.array([[1500.0, 0, 640.5], [0, 1501.0, 870.0], [0, 0, 1]])  # cy below the 800-row image
    a = 0.3
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return ProjectorCalibration(
        1280, 800, K, [0.01, -0.02, 0.001, 0.0005, 0.0], R, [0.1, 1.8, -0.4], "tracker",
        LensModel(1280, 960, np.array([[1400.0, 0, 650], [0, 1400, 470], [0, 0, 1]]), np.zeros(5)),
        (R.T, np.array([0.1, 0.2, 0.0])), {"stereo_rms_px": 0.08, "std": {"projector": {"fx": 0.4}}},
        [{"name": "pose_000", "used": True}], {"source": "unit test"},
    )


def test_round_trip(tmp_path):
    cal = _cal()
    path = cal.save(tmp_path / "calib.json")
    back = load_projector_calibration(path)
    assert (back.width, back.height, back.frame) == (1280, 800, "tracker")
    np.testing.assert_array_equal(back.K, cal.K)
    np.testing.assert_array_equal(back.dist, cal.dist)
    np.testing.assert_array_equal(back.R, cal.R)
    np.testing.assert_array_equal(back.t, cal.t)
    np.testing.assert_array_equal(back.camera.K, cal.camera.K)
    assert back.stats == cal.stats and back.views == cal.views and back.provenance == cal.provenance
    doc = json.loads(path.read_text())
    assert doc["format"] == "dpmhw.projector_calibration" and doc["version"] == 1


def test_project_matches_pose_convention():
    cal = _cal()
    R_pw, t_pw = cal.projector_from_world
    p_proj = np.array([[0.05, -0.1, 2.0]])
    world = p_proj @ cal.R.T + cal.t  # x_world = R x_projector + t
    uv = cal.project(world)
    x, y = 0.05 / 2.0, -0.1 / 2.0
    r2 = x * x + y * y
    k1, k2, p1, p2, _ = cal.dist
    rad = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    np.testing.assert_allclose(uv[0], [1500 * xd + 640.5, 1501 * yd + 870.0], atol=1e-9)
    np.testing.assert_allclose(R_pw @ world[0] + t_pw, p_proj[0], atol=1e-12)


def _write(tmp_path, mutate) -> str:
    doc = _cal().to_dict()
    mutate(doc)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    return str(p)


@pytest.mark.parametrize(
    ("field", "mutate"),
    [
        ("format", lambda d: d.update(format="something.else")),
        ("version", lambda d: d.update(version=2)),
        ("projector", lambda d: d.pop("projector")),
        ("projector.width", lambda d: d["projector"].update(width=-3)),
        ("projector.height", lambda d: d["projector"].update(height=800.5)),
        ("projector.K", lambda d: d["projector"].update(K=[[1, 0, 0], [0, 1, 0]])),
        ("projector.K", lambda d: d["projector"].update(K=[[-5, 0, 640], [0, 1500, 400], [0, 0, 1]])),
        ("projector.K", lambda d: d["projector"].update(K=[[1500, 0, 640], [0, 1500, 9000], [0, 0, 1]])),
        ("projector.dist", lambda d: d["projector"].update(dist=[0.1, 0.2])),
        ("projector.dist", lambda d: d["projector"].update(dist=[0.1, "x", 0, 0, 0])),
        ("world_from_projector.R", lambda d: d["world_from_projector"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]])),
        ("world_from_projector.t", lambda d: d["world_from_projector"].update(t=None)),
        ("world_from_projector.frame", lambda d: d["world_from_projector"].update(frame="lab")),
        ("camera.K", lambda d: d["camera"].update(K=[[1400, 0, 650], [0, 1400, 470], [0, 0, 2]])),
        ("projector_from_camera.R", lambda d: d["projector_from_camera"].update(R=[[2, 0, 0], [0, 1, 0], [0, 0, 1]])),
        ("stats", lambda d: d.update(stats=[1, 2])),
    ],
)
def test_bad_fields_name_file_and_field(tmp_path, field, mutate):
    path = _write(tmp_path, mutate)
    with pytest.raises(CalibrationFileError) as info:
        load_projector_calibration(path)
    assert info.value.source == path and info.value.field == field
    assert str(info.value).startswith(f"{path}: {field}: ")
    assert isinstance(info.value, CalibrationError) and isinstance(info.value, DpmhwError)


def test_nan_in_a_matrix(tmp_path):
    p = tmp_path / "nan.json"
    text = json.dumps(_cal().to_dict()).replace("1500.0", "NaN", 1)
    p.write_text(text)
    with pytest.raises(CalibrationFileError, match=r"nan\.json: projector\.K: contains NaN"):
        load_projector_calibration(p)


_json = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=False) | st.text(max_size=5),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=5), c, max_size=4),
    max_leaves=12,
)
_FIELDS = [("projector", "K"), ("projector", "dist"), ("projector", "width"), ("world_from_projector", "R"),
           ("world_from_projector", "t"), ("world_from_projector", "frame"), ("camera", "K"), (None, "views"), (None, "camera")]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from(_FIELDS), value=_json)
def test_loader_is_total(tmp_path, field, value):
    """Any value in any field either loads or raises CalibrationFileError naming a field."""
    doc = _cal().to_dict()
    outer, inner = field
    (doc if outer is None else doc[outer])[inner] = value
    p = tmp_path / "fuzz.json"
    p.write_text(json.dumps(doc))
    try:
        cal = load_projector_calibration(p)
    except CalibrationFileError as exc:
        assert exc.source == str(p) and exc.field
    else:
        assert cal.K.shape == (3, 3) and cal.R.shape == (3, 3) and cal.dist.shape == (5,)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(CalibrationFileError, match=r"nope\.json: \(file\): no such file"):
        load_projector_calibration(tmp_path / "nope.json")
    p = tmp_path / "trunc.json"
    p.write_text(json.dumps(_cal().to_dict())[:200])
    with pytest.raises(CalibrationFileError, match=r"trunc\.json: \(file\): not valid JSON \(line 1"):
        load_projector_calibration(p)
    p.write_text("[1, 2]")
    with pytest.raises(CalibrationFileError, match="top level"):
        load_projector_calibration(p)


def test_invalid_calibration_never_replaces_a_good_file(tmp_path):
    path = tmp_path / "calib.json"
    _cal().save(path)
    before = path.read_bytes()
    bad = _cal()
    bad.R = np.diag([1.0, 1.0, -1.0])  # a reflection: not a pose
    with pytest.raises(CalibrationFileError, match="world_from_projector.R"):
        bad.save(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib.json"]  # no temporary left behind
