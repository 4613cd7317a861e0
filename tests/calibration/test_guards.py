"""Hard cases: each must give the right outcome, not just 'some' numbers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.board import detect
from calibration.errors import DegenerateViewsError
from calibration.evaluate import rotation_error_deg
from calibration.procam import SolveOptions, calibrate_lens, calibrate_procam, observe
from calibration.synthetic import make_rig

from .conftest import PROJECTOR, observe_all


def _copies(observations):
    return [dataclasses.replace(o) for o in observations]


def _white_frame_views(rig):
    names, obj, img = [], [], []
    for i in range(len(rig.views)):
        found = detect(rig.render_view(i, [0])[0], rig.board)
        assert found is not None
        names.append(f"pose_{i:03d}")
        obj.append(rig.board_points()[found[1]] if rig.bow == 0 else rig.board.object_points()[found[1]])
        img.append(found[0])
    return names, obj, img


def test_fewer_than_three_views_is_degenerate(world):
    with pytest.raises(DegenerateViewsError, match=r"only 2 usable board pose\(s\).*at least 3"):
        calibrate_procam(_copies(world.observations[:2]), world.rig.board, PROJECTOR)


def test_fronto_parallel_views_are_degenerate():
    rig = make_rig(seed=7, n_views=5, supersample=1, min_tilt_deg=0.0, max_tilt_deg=3.0)
    names, obj, img = _white_frame_views(rig)
    with pytest.raises(DegenerateViewsError, match="fronto-parallel") as info:
        calibrate_lens("camera", names, obj, img, (640, 480))
    assert "tilted" in str(info.value) and info.value.field == "views"


def test_k3_is_freed_only_when_points_reach_the_image_corners():
    from calibration.procam import edge_coverage

    centre = [np.random.default_rng(0).uniform([200, 150], [440, 330], (100, 2))]
    corners = centre + [np.array([[5.0, 5.0], [635.0, 5.0], [5.0, 475.0], [635.0, 475.0]])]
    assert edge_coverage(centre, (640, 480)) == 0
    assert edge_coverage(corners, (640, 480)) == 4


def test_corrupted_view_is_rejected_and_results_stay_within_tolerance(world):
    """The board was bumped between the white frame and the patterns of one pose."""
    rig = world.rig
    bad = 5
    frames = rig.render_view(bad)
    frames[2:] = np.roll(frames[2:], 4, axis=2)  # patterns shifted 4 camera pixels
    obs = _copies(world.observations)
    obs[bad] = observe(f"pose_{bad:03d}", frames, rig.board, PROJECTOR)
    r = calibrate_procam(obs, rig.board, PROJECTOR)
    rejected = {**r.projector.rejected, **r.stereo_rejected}
    assert list(rejected) == [f"pose_{bad:03d}"]
    assert "reprojection RMS" in rejected[f"pose_{bad:03d}"]
    assert f"pose_{bad:03d}" not in r.stereo_per_view and len(r.stereo_per_view) == 12
    row = next(v for v in r.views_table() if v["name"] == f"pose_{bad:03d}")
    assert not row["used"] and row["reason"]
    assert abs(r.projector.K[0, 0] / rig.projector.K[0, 0] - 1) < 0.002
    assert abs(r.projector.K[1, 2] - rig.projector.K[1, 2]) < 2
    assert rotation_error_deg(r.R, rig.R_pc) < 0.05 and np.linalg.norm(r.T - rig.t_pc) < 0.5e-3
    # a shifted pattern set looks like another board pose to the projector alone; only the joint
    # (stereo) model exposes it.  Without rejection the same data misses the tolerances:
    loose = calibrate_procam(_copies(obs), rig.board, PROJECTOR, SolveOptions(outlier_factor=1e9, outlier_floor_px=1e9))
    assert loose.stereo_rms > 3 * r.stereo_rms
    assert abs(loose.camera.K[0, 0] / rig.camera.K[0, 0] - 1) > 0.002


def test_principal_point_far_below_the_image_is_recovered():
    """Strong lens shift: cy at 1.25 x height (75 px below the last row) is free, not pulled to the centre."""
    rig = make_rig(seed=11, n_views=8, supersample=1, projector_cy=1.25)
    r = calibrate_procam(observe_all(rig), rig.board, PROJECTOR)
    true_cy = rig.projector.K[1, 2]
    assert true_cy == pytest.approx(375.0)
    assert abs(r.projector.K[1, 2] - true_cy) < 2.0
    assert abs(r.projector.K[0, 0] / rig.projector.K[0, 0] - 1) < 0.002
    assert r.stereo_rms < 0.2


def test_bowed_board_is_flagged_and_handled_by_releasing_object_points():
    rig = make_rig(seed=4, n_views=8, supersample=1, bow=0.003)  # 3 mm sag across 30 cm
    names, obj, img = _white_frame_views(rig)
    planar = calibrate_lens("camera", names, obj, img, (640, 480), SolveOptions(release_object=False))
    assert planar.rms > 0.15  # the planar model cannot fit: that is the symptom the guard looks for
    assert abs(planar.K[0, 0] / rig.camera.K[0, 0] - 1) > 0.01  # and its focal length is wrong
    fit = calibrate_lens("camera", names, obj, img, (640, 480), allow_release=True)
    assert any("board is not flat" in d for d in fit.diagnostics)
    assert fit.object_points is not None
    assert fit.rms < 0.1
    assert abs(fit.K[0, 0] / rig.camera.K[0, 0] - 1) < 0.002
    assert abs(fit.K[1, 2] - rig.camera.K[1, 2]) < 2.0
    # the released points show the bow: a few millimetres off their best-fit plane
    pts = fit.object_points
    c = pts.mean(axis=0)
    normal = np.linalg.svd(pts - c)[2][2]
    assert 0.0008 < np.abs((pts - c) @ normal).max() < 0.003


def test_flat_board_is_not_flagged():
    rig = make_rig(seed=4, n_views=6, supersample=1)
    names, obj, img = _white_frame_views(rig)
    fit = calibrate_lens("camera", names, obj, img, (640, 480), allow_release=True)
    assert fit.diagnostics == [] and fit.object_points is None


def test_charuco_partial_views_calibrate():
    """ChArUco: views where an occluder hides part of the board still contribute their visible corners."""
    from calibration.board import BoardSpec

    spec = BoardSpec(cols=7, rows=5, square=0.04, kind="charuco", marker=0.03, dictionary="DICT_4X4_50")
    rig = make_rig(seed=12, n_views=8, supersample=1, board=spec)
    obs = []
    for i in range(len(rig.views)):
        frames = rig.render_view(i)
        if i % 3 == 0:
            c = rig.corners_camera(i)
            cut = int(np.percentile(c[:, 0], 40))
            frames[:, :, :cut] = frames[1, :, :cut]  # an occluder in front of the left part
        obs.append(observe(f"pose_{i:03d}", frames, spec, PROJECTOR))
    partial = [o for i, o in enumerate(obs) if i % 3 == 0]
    assert all(6 <= len(o.ids) < 20 for o in partial)  # of 24 inner corners
    r = calibrate_procam(obs, spec, PROJECTOR)
    assert len(r.stereo_per_view) == 8
    assert r.stereo_rms < 0.2
    # 8 views of at most 24 corners constrain less than 13 chessboards of 54: looser bounds
    assert abs(r.projector.K[0, 0] / rig.projector.K[0, 0] - 1) < 0.005
    assert abs(r.projector.K[1, 2] - rig.projector.K[1, 2]) < 3.0
    assert rotation_error_deg(r.R, rig.R_pc) < 0.2 and np.linalg.norm(r.T - rig.t_pc) < 2e-3
