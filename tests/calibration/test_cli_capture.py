"""`dpmhw calibrate …` end to end on a small synthetic capture, and broken capture folders."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from dpmhw.cli import _register, app
from dpmhw.projector_calibration import load_projector_calibration

SMALL = ["--camera", "640x480", "--projector", "400x300", "--supersample", "1"]


@pytest.fixture(scope="module")
def synth_run(tmp_path_factory):
    _register()
    out = tmp_path_factory.mktemp("synth") / "data"
    result = CliRunner().invoke(app, ["calibrate", "synth", "--out", str(out), "--views", "5", "--seed", "2", *SMALL, "--solve"])
    return out, result


def _invoke(*args):
    _register()
    return CliRunner().invoke(app, ["calibrate", *map(str, args)])


def test_synth_solve_writes_files_and_reports_against_truth(synth_run):
    out, result = synth_run
    assert result.exit_code == 0, result.output
    for name in ("capture.json", "truth.json", "tracker_poses.json", "calib.json", "calib_tracker.json", "report.png"):
        assert (out / name).is_file(), name
    assert len(list((out / "pose_000").glob("*.png"))) == 38
    report = cv2.imread(str(out / "report.png"))
    assert report.shape[:2] == (850, 1200)
    for hex_rgb in ("1f77b4", "e6550d"):  # camera and projector bars/residuals are drawn
        bgr = [int(hex_rgb[i:i + 2], 16) for i in (4, 2, 0)]
        assert (np.abs(report.astype(int) - bgr).sum(axis=2) < 10).sum() > 200
    assert "against ground truth" in result.output and "held-out projector reprojection" in result.output
    assert "time per stage" in result.output
    cal = load_projector_calibration(out / "calib.json")
    truth = json.loads((out / "truth.json").read_text())
    assert cal.frame == "camera"
    assert abs(cal.K[0, 0] / truth["projector"]["K"][0][0] - 1) < 0.005
    trk = load_projector_calibration(out / "calib_tracker.json")
    assert trk.frame == "tracker"
    assert np.linalg.norm(trk.t - np.array(truth["world_from_projector"]["t"])) < 0.003
    assert len(cal.views) == 5 and cal.provenance["source"].endswith("data")


def test_patterns_command(tmp_path):
    r = _invoke("patterns", "--out", tmp_path, "--size", "600x400")
    assert r.exit_code == 0, r.output
    assert len(list(tmp_path.glob("*.png"))) == 2 + 2 * (10 + 9)


def test_decode_command(synth_run, tmp_path):
    out, _ = synth_run
    r = _invoke("decode", out / "pose_001", "--out", tmp_path / "d.npz")
    assert r.exit_code == 0, r.output
    with np.load(tmp_path / "d.npz") as d:
        assert d["valid"].mean() > 0.1 and "dropped bits x 0" in r.output


@pytest.fixture
def capture_copy(synth_run, tmp_path):
    out, _ = synth_run
    dst = tmp_path / "cap"
    shutil.copytree(out, dst, ignore=shutil.ignore_patterns("calib*.json", "report.png"))
    return dst


def test_missing_frame_names_the_pose_folder(capture_copy, tmp_path):
    (capture_copy / "pose_002" / "017.png").unlink()
    r = _invoke("procam", capture_copy, "--out", tmp_path / "c.json")
    assert r.exit_code == 1
    assert "pose_002: (frames): has 37 images" in r.output
    assert not (tmp_path / "c.json").exists()


def test_corrupt_image_names_the_file(capture_copy, tmp_path):
    (capture_copy / "pose_003" / "005.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    r = _invoke("procam", capture_copy, "--out", tmp_path / "c.json")
    assert r.exit_code == 1
    assert "pose_003/005.png: (image): unreadable" in r.output


def test_missing_or_bad_capture_json(capture_copy, tmp_path):
    meta = capture_copy / "capture.json"
    doc = json.loads(meta.read_text())
    doc["projector"]["width"] = "wide"
    meta.write_text(json.dumps(doc))
    r = _invoke("procam", capture_copy, "--out", tmp_path / "c.json")
    assert r.exit_code == 1 and "capture.json: projector.width: expected an integer" in r.output
    meta.unlink()
    r = _invoke("procam", capture_copy, "--out", tmp_path / "c.json")
    assert r.exit_code == 1 and "capture.json: (file): missing" in r.output


def test_failed_run_keeps_the_previous_good_file(synth_run, capture_copy):
    out, _ = synth_run
    good = capture_copy / "calib.json"
    shutil.copy(out / "calib.json", good)
    before = good.read_bytes()
    for extra in ("pose_002", "pose_003", "pose_004"):
        shutil.rmtree(capture_copy / extra)
    r = _invoke("procam", capture_copy, "--out", good)
    assert r.exit_code == 1
    assert "only 2 usable board pose(s)" in r.output
    assert good.read_bytes() == before


def test_tracker_command_reports_a_bad_calibration_file(synth_run, tmp_path):
    out, _ = synth_run
    bad = tmp_path / "broken.json"
    bad.write_text((out / "calib.json").read_text().replace('"version": 1', '"version": 7'))
    r = _invoke("tracker", out, "--calibration", bad, "--poses", out / "tracker_poses.json", "--out", tmp_path / "t.json")
    assert r.exit_code == 1 and "broken.json: version: this dpmhw reads version 1" in r.output
