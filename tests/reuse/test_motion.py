"""Motion mode: reprojection lands where geometry says, and the history fetch is as defined in
dpmhw.reconstruct.reuse (bilinear over matching taps, renormalised; else the nearest matching tap; else reset)."""

import numpy as np
import pytest

from dpmhw.reconstruct.reuse import ReuseError, TemporalReuse, reproject
from dpmhw.transforms import Pose, rotation_about_axis

from .conftest import make_camera, plane_gbuffer


def test_rigid_translation_lands_on_the_analytic_pixels():
    """A plane at depth z moved by δ along x: the previous position of every pixel is f·δ/z
    pixels to the left, to sub-pixel accuracy."""
    cam = make_camera(40, 30, f=50.0, cx=17.3, cy=11.8)  # off-centre principal point (projector lens shift)
    prev, cur = Pose(np.eye(3), np.array([0.0, 0.0, 0.0])), Pose(np.eye(3), np.array([0.03, -0.01, 0.0]))
    ids, mpos = plane_gbuffer(cam, depth=2.0, pose=cur)
    xy, ok = reproject(ids, mpos, [prev], cam, cam)
    ys, xs = np.mgrid[0:30, 0:40]
    assert ok.all()
    np.testing.assert_allclose(xy[:, 0], xs.ravel() - 50.0 * 0.03 / 2.0, atol=1e-4)
    np.testing.assert_allclose(xy[:, 1], ys.ravel() + 50.0 * 0.01 / 2.0, atol=1e-4)


def test_rigid_rotation_about_the_optical_axis_rotates_pixels_about_the_principal_point():
    cam = make_camera(40, 30, f=30.0, cx=20.0, cy=14.0)
    theta = np.radians(7.0)
    prev = Pose(np.eye(3), np.zeros(3))
    cur = Pose(rotation_about_axis([0, 0, 1], theta), np.zeros(3))
    ids, mpos = plane_gbuffer(cam, depth=1.5, pose=cur)
    xy, ok = reproject(ids, mpos, [prev], cam, cam)
    ys, xs = np.mgrid[0:30, 0:40]
    u, v = xs.ravel() - 20.0, ys.ravel() - 14.0
    c, s = np.cos(-theta), np.sin(-theta)  # undo this frame's rotation
    np.testing.assert_allclose(xy[:, 0], 20.0 + c * u - s * v, atol=1e-4)
    np.testing.assert_allclose(xy[:, 1], 14.0 + s * u + c * v, atol=1e-4)


def test_reprojection_agrees_with_the_camera_model_with_distortion_and_a_moved_camera():
    rng = np.random.default_rng(6)
    cam_pose = Pose(rotation_about_axis([0.3, 1, 0.1], 0.2), np.array([0.1, -0.05, 0.02]))
    cam = make_camera(20, 16, f=18.0, cx=9.0, cy=8.5, dist=np.array([-0.2, 0.05, 0.001, -0.002, 0.01]), pose=cam_pose)
    poses = [Pose(rotation_about_axis(rng.normal(size=3), 0.4), rng.normal(size=3) * 0.1) for _ in range(3)]
    ids = rng.integers(-1, 3, size=(16, 20)).astype(np.int32)
    mpos = (rng.normal(size=(16, 20, 3)) * 0.2 + [0, 0, 2]).astype(np.float32)
    xy, ok = reproject(ids, mpos, poses, cam, cam)
    hit = ids.ravel() >= 0
    world = np.array([poses[i].apply(m[None].astype(np.float64))[0] for i, m in zip(ids.ravel()[hit], mpos.reshape(-1, 3)[hit])])
    expected, front = cam.project(world)
    np.testing.assert_allclose(xy[hit][front], expected[front], atol=1e-6)
    assert np.array_equal(ok[hit], front)
    # background: same pixel while the camera holds still, reset once it moves
    ys, xs = np.divmod(np.flatnonzero(~hit), 20)
    np.testing.assert_array_equal(xy[~hit], np.stack([xs, ys], 1))
    assert ok[~hit].all()
    moved = cam.with_pose(Pose(cam_pose.R, cam_pose.t + 0.01))
    assert not reproject(ids, mpos, poses, cam, moved)[1][~hit].any()


# --- the fetch, on a hand-made history -------------------------------------------------------
#
# Camera K = identity-like (f = 1, c = 0), object pose identity: a model point (x, y, 1) was at
# pixel (x, y) in the previous frame, so the test places X_{i−1} anywhere it wants.

W, H = 4, 3


def _setup(prev_ids=None):
    cam = make_camera(W, H, f=1.0, cx=0.0, cy=0.0)
    reuse = TemporalReuse(W, H, alpha=0.5, mode="motion")
    values = np.arange(W * H, dtype=np.float32).reshape(H, W)
    ids = np.zeros((H, W), np.int32) if prev_ids is None else prev_ids
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    mpos = np.stack([xs, ys, np.ones_like(xs)], -1)
    reuse.update(np.repeat(values[..., None], 3, -1), ids, mpos, [Pose.identity()], cam)
    return reuse, cam, values


def _fetch(reuse, cam, x, y, ident=0):
    """History fetched for every pixel from X_{i−1} = (x, y); current sample 0, α = 0.5, so the
    fetched history is 2 × output."""
    mpos = np.empty((H, W, 3), np.float32)
    mpos[...] = (x, y, 1.0)
    out = reuse.update(np.zeros((H, W, 3), np.float32), np.full((H, W), ident, np.int32), mpos, [Pose.identity()], cam)
    return 2.0 * out[0, 0, 0], int(reuse.last_fetch_kind[0, 0]), float(reuse.history_length[0, 0])


def test_bilinear_fetch_when_all_taps_match():
    reuse, cam, v = _setup()
    got, kind, n = _fetch(reuse, cam, 1.25, 0.5)
    expected = 0.75 * 0.5 * v[0, 1] + 0.25 * 0.5 * v[0, 2] + 0.75 * 0.5 * v[1, 1] + 0.25 * 0.5 * v[1, 2]
    assert kind == 1 and got == pytest.approx(expected, rel=1e-6) and n == 2


def test_bilinear_fetch_renormalises_over_matching_taps():
    prev_ids = np.zeros((H, W), np.int32)
    prev_ids[0, 2] = 7  # one tap belongs to another object
    reuse, cam, v = _setup(prev_ids)
    got, kind, _ = _fetch(reuse, cam, 1.25, 0.5)
    w = {(0, 1): 0.375, (1, 1): 0.375, (1, 2): 0.125}
    expected = sum(wt * v[k] for k, wt in w.items()) / sum(w.values())
    assert kind == 1 and got == pytest.approx(expected, rel=1e-6)


def test_nearest_matching_tap_when_matching_weight_is_zero():
    prev_ids = np.full((H, W), 5, np.int32)
    prev_ids[1, 2] = 0  # X = (1, 1) exactly: its own tap (weight 1) is another object's
    reuse, cam, v = _setup(prev_ids)
    got, kind, _ = _fetch(reuse, cam, 1.0, 1.0)
    assert kind == 2 and got == pytest.approx(v[1, 2])


def test_no_matching_tap_resets():
    reuse, cam, _ = _setup(np.full((H, W), 3, np.int32))
    got, kind, n = _fetch(reuse, cam, 1.5, 1.5)
    assert kind == 0 and got == 0.0 and n == 1  # output = the current sample, history restarts


@pytest.mark.parametrize("x, y, kind", [(-0.51, 1.0, 0), (W - 0.5, 1.0, 0), (1.0, -0.6, 0), (1.0, H - 0.49, 0), (-0.4, 1.0, 1), (1.0, H - 0.51, 1)])
def test_out_of_image_resets_and_border_taps_outside_are_dropped(x, y, kind):
    reuse, cam, v = _setup()
    got, k, _ = _fetch(reuse, cam, x, y)
    assert k == kind
    if kind == 0:
        assert got == 0.0
    else:  # inside the half-pixel border: only the in-image taps, renormalised
        xi, yi = int(np.clip(round(x), 0, W - 1)), int(np.floor(y))
        fy = y - yi
        expected = v[yi, xi] if x < 0 else (1 - fy) * v[yi, xi] + fy * v[min(yi + 1, H - 1), xi]
        assert got == pytest.approx(expected, rel=1e-5)


def test_behind_the_previous_camera_resets():
    reuse, cam, _ = _setup()
    mpos = np.zeros((H, W, 3), np.float32)
    mpos[..., 2] = -1.0
    reuse.update(np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.int32), mpos, [Pose.identity()], cam)
    assert np.all(reuse.last_fetch_kind == 0)


def test_static_scene_motion_mode_equals_same_pixel(static_view):
    ids, mpos, poses, cam = static_view(6, 8)
    rng = np.random.default_rng(7)
    a = TemporalReuse(8, 6, alpha=0.3, mode="motion")
    b = TemporalReuse(8, 6, alpha=0.3, mode="same-pixel")
    for _ in range(5):
        f = rng.random((6, 8, 3)).astype(np.float32)
        np.testing.assert_array_equal(a.update(f, ids, mpos, poses, cam), b.update(f, ids))


def test_motion_mode_follows_a_translating_object_where_same_pixel_smears():
    """A plane with a vertical stripe texture moving 1.5 px per frame: motion mode keeps the
    stripes (up to bilinear blur), same-pixel mode averages them away."""
    w, h = 48, 8
    cam = make_camera(w, h, f=20.0)
    depth, step = 2.0, 1.5 * 2.0 / 20.0  # metres per frame for 1.5 px
    motion = TemporalReuse(w, h, alpha=0.2, mode="motion")
    same = TemporalReuse(w, h, alpha=0.2, mode="same-pixel")
    for k in range(12):
        pose = Pose(np.eye(3), np.array([k * step, 0.0, 0.0]))
        ids, mpos = plane_gbuffer(cam, depth, pose)
        texture = (np.floor(mpos[..., 0] / (4 * 2.0 / 20.0)) % 2).astype(np.float32)  # 4-px stripes, in model space
        f = np.repeat(texture[..., None], 3, -1)
        out_m = motion.update(f, ids, mpos, [pose], cam)
        out_s = same.update(f, ids)
    inner = slice(20, 40)  # away from the left edge, where history was disoccluded
    err_m = np.abs(out_m - f)[:, inner].mean()
    err_s = np.abs(out_s - f)[:, inner].mean()
    assert err_m < 0.2 and err_s > 0.3 and err_m < 0.5 * err_s
    assert np.all(motion.last_fetch_kind[:, :1] == 0)  # the column that entered the view reset


def test_motion_mode_input_errors_name_what_is_missing(static_view):
    ids, mpos, poses, cam = static_view(3, 4)
    reuse = TemporalReuse(4, 3, alpha=0.5, mode="motion")
    with pytest.raises(ReuseError, match="model_position, poses and camera"):
        reuse.update(np.zeros((3, 4, 3), np.float32), ids)
    with pytest.raises(ReuseError, match=r"expected shape \(3, 4, 3\)"):
        reuse.update(np.zeros((4, 3, 3), np.float32), ids, mpos, poses, cam)
    bad_ids = ids.copy()
    bad_ids[0, 0] = 3  # an id with no pose
    with pytest.raises(ReuseError, match="only 1 previous poses"):
        reproject(bad_ids, mpos, poses, cam, cam)


def test_two_histories_sharing_one_reprojection_equal_two_computing_their_own():
    """The stage's diffuse and specular histories move in lockstep and reuse one reprojection."""
    cam = make_camera(24, 18, f=30.0, cx=12.0, cy=9.0)
    rng = np.random.default_rng(2)
    pair, alone = (TemporalReuse(24, 18, 0.2, "motion"), TemporalReuse(24, 18, 0.2, "motion")), TemporalReuse(24, 18, 0.2, "motion")
    assert pair[1].follows_same_frames(pair[0])
    for k in range(4):
        pose = Pose(rotation_about_axis([0, 1, 0], 0.05 * k), np.array([0.01 * k, 0.0, 0.0]))
        ids, mpos = plane_gbuffer(cam, depth=2.0, pose=pose)
        rad = rng.random((18, 24, 3)).astype(np.float32)
        rp = pair[0].reprojection(ids, mpos, cam)
        assert (rp is None) == (k == 0)
        assert pair[1].follows_same_frames(pair[0])
        outs = [r.update(rad, ids, mpos, [pose], cam, rp) for r in pair]
        ref = alone.update(rad, ids, mpos, [pose], cam)
        assert np.array_equal(outs[0], ref) and np.array_equal(outs[1], ref)
    other = TemporalReuse(24, 18, 0.2, "motion")
    other.update(rad, ids, mpos, [Pose(np.eye(3), np.zeros(3))], cam)
    assert not other.follows_same_frames(pair[0])
