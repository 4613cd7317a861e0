"""The whole Moreno-Taubin pipeline against the synthetic world's ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.evaluate import compare_with_truth, rotation_error_deg


def _check_lens(K, dist, lens, f_rel=0.002, pp_px=2.0):
    assert abs(K[0, 0] / lens.K[0, 0] - 1) < f_rel
    assert abs(K[1, 1] / lens.K[1, 1] - 1) < f_rel
    assert abs(K[0, 2] - lens.K[0, 2]) < pp_px
    assert abs(K[1, 2] - lens.K[1, 2]) < pp_px
    assert np.allclose(dist[:2], lens.dist[:2], atol=0.01)


def test_camera_intrinsics_match_truth(world):
    r = world.result
    _check_lens(r.camera.K, r.camera.dist, world.rig.camera)
    assert r.camera.rms < 0.2
    assert r.camera.k3_fixed  # the views do not reach the image corners


def test_projector_intrinsics_match_truth_with_lens_shift(world):
    r, rig = world.result, world.rig
    assert rig.projector.K[1, 2] > rig.projector.height  # principal point below the image
    _check_lens(r.projector.K, r.projector.dist, rig.projector)
    assert r.projector.rms < 0.2


def test_stereo_extrinsics_match_truth(world):
    r, rig = world.result, world.rig
    assert r.stereo_rms < 0.2
    assert rotation_error_deg(r.R, rig.R_pc) < 0.05
    assert np.linalg.norm(r.T - rig.t_pc) < 0.5e-3


def test_no_view_rejected_and_all_corners_found(world):
    r = world.result
    assert r.camera.rejected == {} and r.projector.rejected == {} and r.stereo_rejected == {}
    assert len(r.stereo_per_view) == 13
    for o in world.observations:
        assert np.isfinite(o.projector_px).all()


def test_projector_corners_match_truth(world):
    """The local homographies recover each corner's projector coordinates to a small fraction of a pixel."""
    errs = []
    for i, o in enumerate(world.observations):
        errs.append(o.projector_px - world.rig.corners_projector(i)[o.ids])
    e = np.concatenate(errs)
    assert np.sqrt((e**2).sum(axis=1).mean()) < 0.1
    assert np.abs(e.mean(axis=0)).max() < 0.02  # no half-pixel convention slip


def test_heldout_projector_reprojection(world):
    cal = world.result.to_calibration()
    cmp = compare_with_truth(cal, world.rig.truth())
    assert cmp["heldout_points"] > 1000
    assert cmp["heldout_rms_px"] < 0.5
    assert cmp["rotation_deg"] < 0.05 and cmp["translation_mm"] < 0.5


def test_standard_deviations_reported_and_small(world):
    std = world.result.projector.std
    assert 0 < std["fx"] < 0.002 * world.rig.projector.K[0, 0]
    assert 0 < std["cy"] < 2.0


@pytest.mark.parametrize("who", ["camera", "projector"])
def test_per_view_errors_cover_every_view(world, who):
    fit = getattr(world.result, who)
    assert set(fit.per_view) == {o.name for o in world.observations}
    assert max(fit.per_view.values()) < 0.3
