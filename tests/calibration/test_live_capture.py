"""Live capture glue, with OpenCV's image-sequence backend standing in for the camera."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.capture import capture_live, load_pose, open_capture
from calibration.errors import CaptureError
from calibration.patterns import PatternSet
from calibration.synthetic import make_rig
from drivers.frame_sinks import RecordingSink


def test_capture_live_shows_every_pattern_and_stores_the_grabs(tmp_path):
    rig = make_rig(seed=8, n_views=1, supersample=1)
    rendered = rig.render_view(0)
    seq = tmp_path / "camera"
    seq.mkdir()
    for i, img in enumerate(rendered):
        cv2.imwrite(str(seq / f"{i:03d}.png"), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    sink = RecordingSink(shape=(300, 400))  # the project's frame sink: rejects a wrong shape or dtype
    progress: list[tuple[int, int]] = []
    out = tmp_path / "capture"
    capture_live(sink, out, "pose_000", 400, 300, rig.board, camera=str(seq / "%03d.png"), settle_s=0.0,
                 discard=0, progress=lambda i, n: progress.append((i, n)))
    expected = PatternSet(400, 300).generate()
    assert len(sink.frames) == len(expected) == 38
    for shown, pattern in zip(sink.frames, expected):
        assert np.array_equal(shown.frame[..., 0], pattern) and np.array_equal(shown.frame[..., 2], pattern)
    assert progress[-1] == (38, 38) and len(progress) == 38
    meta = open_capture(out)
    assert (meta.projector_width, meta.projector_height) == (400, 300) and meta.board == rig.board
    assert np.array_equal(load_pose(meta, meta.poses[0]), rendered)


def test_capture_live_reports_a_camera_that_does_not_open(tmp_path):
    with pytest.raises(CaptureError, match="cannot open the camera"):
        capture_live(RecordingSink(), tmp_path, "pose_000", 64, 32, make_rig(seed=8, n_views=1).board,
                     camera=str(tmp_path / "none" / "%03d.png"), settle_s=0.0)


def test_capture_command_records_poses_into_one_folder(tmp_path):
    """`dpmhw calibrate capture` with the recording sink and an image sequence as the camera."""
    from typer.testing import CliRunner

    from dpmhw.cli import _register, app

    _register()
    seq = tmp_path / "camera"
    seq.mkdir()
    for i in range(2 + 2 * (6 + 5)):  # a 64x32 projector
        cv2.imwrite(str(seq / f"{i:03d}.png"), np.full((24, 32), 7 * i, np.uint8))
    out = tmp_path / "cap"
    args = ["calibrate", "capture", str(out), "--camera", str(seq / "%03d.png"), "--sink", "recording", "--settle", "0",
            "--discard", "0"]
    r = CliRunner().invoke(app, [*args, "--pose", "pose_000", "--size", "64x32", "--board", "7x5", "--square", "0.02"])
    assert r.exit_code == 0, r.output
    meta = open_capture(out)
    assert (meta.projector_width, meta.projector_height, meta.board.cols, meta.board.square) == (64, 32, 7, 0.02)
    assert load_pose(meta, meta.poses[0])[5, 0, 0] == 35
    r = CliRunner().invoke(app, [*args, "--pose", "pose_001", "--size", "80x32"])
    assert r.exit_code != 0 and "differs from" in r.output
    r = CliRunner().invoke(app, [*args, "--pose", "pose_001"])
    assert r.exit_code == 0, r.output
    assert [p.name for p in open_capture(out).poses] == ["pose_000", "pose_001"]
