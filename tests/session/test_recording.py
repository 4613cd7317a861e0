"""Recording: frames.csv, poses.csv and a PNG subsample, flushed while the session runs."""

from __future__ import annotations

import csv

from dpmhw.session.recording import SessionRecorder
from dpmhw.session.testing import fake_session, wait_for

WAIT_S = 60  # for what must happen eventually (a first frame may wait for numba); only broken code waits


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_recording_writes_frames_poses_and_pngs_while_running(tmp_path):
    loop = fake_session(["recording.frame_every=5"])
    loop.parts.recorder = SessionRecorder.create(tmp_path, loop.config, loop.parts.tracker)
    folder = loop.parts.recorder.folder
    loop.start()
    try:
        assert wait_for(lambda: loop.status()["frame_number"] >= 20, WAIT_S)
        # flushed at least once a second while running: a crash now loses at most the last second
        assert wait_for(lambda: len(rows(folder / "frames.csv")) >= 10, 5)  # a bound: 5 periods
    finally:
        loop.stop()
    frames = rows(folder / "frames.csv")
    numbers = [int(r["number"]) for r in frames]
    assert numbers == sorted(numbers) and len(numbers) >= 20
    assert float(frames[0]["render_ms"]) >= 0 and frames[0]["body"] == "1"
    live = loop.config.live_settings()  # every live setting, as the frame used it
    assert all(int(r["governor_level"]) >= 0 for r in frames)  # the quality governor's level per frame
    assert frames[0]["filter"] == live.filter and frames[0]["split_screen"] == str(int(live.split_screen))
    pngs = sorted(p.name for p in (folder / "frames").glob("*.png"))
    assert pngs and all(int(p[:6]) % 5 == 0 for p in pngs)
    assert (folder / "config.json").is_file()
    assert not any(r["body"] != "1" for r in frames)
