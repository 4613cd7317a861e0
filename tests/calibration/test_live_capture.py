"""Live capture glue, with OpenCV's image-sequence backend standing in for the camera."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.capture import capture_live, load_pose, open_capture
from calibration.errors import CaptureError
from calibration.patterns import PatternSet
from calibration.synthetic import make_rig


class RecordingSink:
    def __init__(self) -> None:
        self.frames: list[np.ndarray] = []

    def present(self, frame: np.ndarray) -> None:
        self.frames.append(frame.copy())


def test_capture_live_shows_every_pattern_and_stores_the_grabs(tmp_path):
    rig = make_rig(seed=8, n_views=1, supersample=1)
    rendered = rig.render_view(0)
    seq = tmp_path / "camera"
    seq.mkdir()
    for i, img in enumerate(rendered):
        cv2.imwrite(str(seq / f"{i:03d}.png"), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    sink = RecordingSink()
    progress: list[tuple[int, int]] = []
    out = tmp_path / "capture"
    capture_live(sink, out, "pose_000", 400, 300, rig.board, camera=str(seq / "%03d.png"), settle_s=0.0,
                 discard=0, progress=lambda i, n: progress.append((i, n)))
    expected = PatternSet(400, 300).generate()
    assert len(sink.frames) == len(expected) == 38
    for shown, pattern in zip(sink.frames, expected):
        assert shown.shape == (300, 400, 3) and np.array_equal(shown[..., 0], pattern)
    assert progress[-1] == (38, 38) and len(progress) == 38
    meta = open_capture(out)
    assert (meta.projector_width, meta.projector_height) == (400, 300) and meta.board == rig.board
    assert np.array_equal(load_pose(meta, meta.poses[0]), rendered)


def test_capture_live_reports_a_camera_that_does_not_open(tmp_path):
    with pytest.raises(CaptureError, match="cannot open the camera"):
        capture_live(RecordingSink(), tmp_path, "pose_000", 64, 32, make_rig(seed=8, n_views=1).board,
                     camera=str(tmp_path / "none" / "%03d.png"), settle_s=0.0)
