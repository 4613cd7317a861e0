"""Gray-code patterns and the vectorised decoder."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from calibration.board import BoardSpec
from calibration.decode import decode
from calibration.patterns import PatternSet, gray_decode, gray_encode
from calibration.synthetic import make_rig


@given(st.lists(st.integers(0, 2**40), min_size=1, max_size=50))
def test_gray_round_trip_and_single_bit_steps(values):
    v = np.array(values, dtype=np.int64)
    assert (gray_decode(gray_encode(v)) == v).all()
    diff = gray_encode(v) ^ gray_encode(v + 1)
    assert all(bin(int(d)).count("1") == 1 for d in diff)


@pytest.mark.parametrize("size", [(400, 300), (37, 23), (1024, 768), (912, 1140)])
def test_patterns_match_opencv_order(size):
    w, h = size
    ps = PatternSet(w, h)
    frames = ps.generate()
    assert len(frames) == ps.count == 2 + 2 * (int(np.ceil(np.log2(w))) + int(np.ceil(np.log2(h))))
    assert frames[0].min() == 255 and frames[1].max() == 0
    ok, ocv = cv2.structured_light.GrayCodePattern_create(w, h).generate()
    assert len(ocv) == len(frames) - 2
    for mine, theirs in zip(frames[2:], ocv):
        assert np.array_equal(mine, theirs)


@pytest.mark.parametrize("size", [(37, 23), (400, 300), (256, 200)])
def test_decoding_the_patterns_themselves_gives_every_pixel(size):
    """A camera that is the projector (identity map) must decode every pixel exactly."""
    w, h = size
    d = decode(np.stack(PatternSet(w, h).generate()), w, h)
    yy, xx = np.mgrid[0:h, 0:w]
    assert d.valid.all()
    assert np.array_equal(d.x, xx.astype(np.float32)) and np.array_equal(d.y, yy.astype(np.float32))
    assert d.dropped_bits_x == d.dropped_bits_y == 0


def test_shadow_and_low_contrast_pixels_are_masked():
    w, h = 64, 32
    frames = np.stack(PatternSet(w, h).generate()).astype(np.float32)
    frames[:, :, :10] = 30.0  # a shadow: every frame equally dark
    frames[:, :5, 20:30] = frames[:, :5, 20:30] * 0.02 + 100  # lit but almost no contrast
    d = decode(frames, w, h)
    assert not d.valid[:, :10].any()
    assert not d.valid[:5, 20:30].any()
    assert d.valid[5:, 10:].all()
    assert np.isnan(d.x[:, :10]).all()


def test_wrong_frame_count_is_an_error():
    frames = np.stack(PatternSet(40, 30).generate())
    with pytest.raises(ValueError, match="expected 2"):
        decode(frames[:-1], 40, 30)


@pytest.fixture(scope="module")
def one_view():
    rig = make_rig(seed=3, n_views=1, supersample=1)
    return rig, rig.render_view(0)


def _truth_projector_coords(rig, pts_uv):
    """Projector pixel each camera pixel centre sees (only on the board plane)."""
    R, t = rig.views[0]
    d = rig.camera.rays(pts_uv)
    n = R[:, 2]
    P = d * ((n @ t) / (d @ n))[:, None]
    return rig.projector.project(P @ rig.R_pc.T + rig.t_pc)


def test_decoder_matches_ground_truth_on_a_rendered_view(one_view):
    rig, frames = one_view
    d = decode(frames, rig.projector.width, rig.projector.height)
    v, u = np.nonzero(d.valid)
    assert len(u) > 30000
    truth = _truth_projector_coords(rig, np.column_stack([u, v]).astype(np.float64))
    err = np.abs(np.column_stack([d.x[v, u], d.y[v, u]]) - truth)
    # a pixel centre decodes to the projector pixel it sees (|err| <= 0.5); blur moves stripe
    # edges, and a Gray code then errs by one code at most
    e = err.max(axis=1)
    assert np.mean(e <= 0.5 + 1e-6) > 0.85
    assert np.mean(e <= 1.0) > 0.98
    assert np.mean(e > 2.5) < 1e-3
    signed = np.column_stack([d.x[v, u], d.y[v, u]]) - truth
    assert np.abs(signed.mean(axis=0)).max() < 0.02  # no half-pixel convention slip


def test_decoder_agrees_with_opencv_getprojpixel(one_view):
    """OpenCV's per-pixel decoder (slow: used on a sample only; its flag is True on *failure*)."""
    rig, frames = one_view
    d = decode(frames, rig.projector.width, rig.projector.height)
    gc = cv2.structured_light.GrayCodePattern_create(rig.projector.width, rig.projector.height)
    pattern_images = [f for f in frames[2:]]
    v, u = np.nonzero(d.valid)
    idx = np.random.default_rng(0).choice(len(u), 300, replace=False)
    agree = decoded = 0
    for i in idx:
        failed, pix = gc.getProjPixel(pattern_images, int(u[i]), int(v[i]))
        if not failed:  # OpenCV also rejects pixels on any stripe edge, so it decodes fewer
            decoded += 1
            agree += int(pix[0] == d.x[v[i], u[i]] and pix[1] == d.y[v[i], u[i]])
    assert decoded > 0.7 * len(idx)
    assert agree == decoded


def test_narrow_stripes_drop_unresolvable_bits():
    """A projector with ~4x finer pixels than the camera sees: the finest stripes are sub-pixel."""
    from calibration.synthetic import Lens

    cam_d = make_rig(seed=0, n_views=1).camera
    proj = Lens(1600, 1200, np.array([[2800.0, 0, 820], [0, 2800.0, 1240], [0, 0, 1]]), np.zeros(5))
    rig = make_rig(seed=5, n_views=1, camera=cam_d, projector=proj, projector_size=(1600, 1200), supersample=3,
                   board=BoardSpec(cols=6, rows=4, square=0.03), distance=(0.6, 0.7))
    frames = rig.render_view(0)
    naive = decode(frames, 1600, 1200, adapt=False)
    d = decode(frames, 1600, 1200)
    assert d.dropped_bits_x >= 1 and d.dropped_bits_y >= 1
    assert d.contrast_x[-1] < 0.25 and d.contrast_x[0] > 0.9
    v, u = np.nonzero(d.valid)
    truth = _truth_projector_coords(rig, np.column_stack([u, v]).astype(np.float64))
    err = np.abs(np.column_stack([d.x[v, u], d.y[v, u]]) - truth).max(axis=1)
    stripe = 2 ** max(d.dropped_bits_x, d.dropped_bits_y)
    assert d.valid_fraction > 0.1
    assert np.mean(err <= stripe) > 0.95  # right to within the stripe width that was kept
    assert np.median(err) <= 0.4 * stripe  # max of two axes each uniform in [0, stripe/2]
    # the corners' projector coordinates (local homographies) stay sub-pixel
    from calibration.board import detect
    from calibration.procam import projector_corners, undistortion_grid

    corners, ids = detect(frames[0], rig.board)
    grid = undistortion_grid(rig.camera.K, rig.camera.dist, (640, 480))
    pc, _ = projector_corners(d, corners, grid, rig.camera.K, rig.camera.dist, window=12)
    e = pc - rig.corners_projector(0)[ids]
    assert np.isfinite(pc).all()
    assert np.sqrt((e**2).sum(axis=1).mean()) < 0.5
    # decoding the noise bits instead loses (almost) every corner
    pc_naive, _ = projector_corners(naive, corners, grid, rig.camera.K, rig.camera.dist, window=12)
    assert np.isnan(pc_naive[:, 0]).mean() > 0.8
