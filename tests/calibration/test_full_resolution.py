"""The issue's accuracy targets at the `dpmhw calibrate synth` default resolution (slow: -m slow)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.evaluate import compare_with_truth
from calibration.procam import calibrate_procam, observe
from calibration.synthetic import make_rig
from calibration.tracker import projector_pose_from_tracked_board


@pytest.mark.slow
def test_default_resolution_meets_the_issue_tolerances():
    rig = make_rig(seed=0, n_views=13, camera_size=(1280, 960), projector_size=(1024, 768), supersample=2)
    obs = [observe(f"pose_{i:03d}", rig.render_view(i), rig.board, (1024, 768)) for i in range(13)]
    r = calibrate_procam(obs, rig.board, (1024, 768))
    cmp = compare_with_truth(r.to_calibration(), rig.truth())
    rows = {row["param"]: row for row in cmp["rows"]}
    for who in ("camera", "projector"):
        assert abs(rows[f"{who}.fx"]["rel_error"]) < 0.002 and abs(rows[f"{who}.fy"]["rel_error"]) < 0.002
    assert abs(rows["projector.cx"]["error"]) < 2 and abs(rows["projector.cy"]["error"]) < 2
    assert max(r.camera.rms, r.projector.rms, r.stereo_rms) < 0.2
    assert cmp["rotation_deg"] < 0.05 and cmp["translation_mm"] < 0.5
    assert cmp["heldout_rms_px"] < 0.5
    poses = {o.name: rig.world_from_board(i) for i, o in enumerate(obs)}
    pose = projector_pose_from_tracked_board(obs, poses, rig.board, r.to_calibration())
    cal = r.to_calibration()
    cal.R, cal.t, cal.frame = pose.R, pose.t, "tracker"
    tracked = compare_with_truth(cal, rig.truth())
    assert tracked["heldout_rms_px"] < 0.1 and np.isfinite(tracked["rotation_deg"])
