"""Late reprojection: exact at the capture's poses, geometry through depth and lens distortion,
cracks and disocclusions filled, static occluders respected, error against fresh renders, bad input."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from dpmhw.metrics import masked_psnr
from dpmhw.postprocess import to_srgb8
from dpmhw.reconstruct.reproject import PRESENT_FRAMES, Reprojector
from dpmhw.render.cameras import PinholeCamera
from dpmhw.transforms import Pose, rotation_about_axis

W, H = 96, 72
K = np.array([[80.0, 0, 47.5], [0, 80.0, 35.5], [0, 0, 1]])


def _camera(dist=(0, 0, 0, 0, 0)) -> PinholeCamera:
    return PinholeCamera(K, np.array(dist, float), W, H, Pose.identity())


def _shifted(dx=0.0, dy=0.0, dz=0.0) -> Pose:
    return Pose(np.eye(3), np.array([dx, dy, dz]))


def _planes(camera, layers):
    """A synthetic G-buffer: layers = [(object, depth, (y0, y1, x0, x1))], later ones in front.
    Colours code the pixel index (24 bits), so each one's origin can be told."""
    ids = np.full(H * W, -1, np.int32)
    depth = np.zeros(H * W, np.float32)
    for obj, z, (y0, y1, x0, x1) in layers:
        m = np.zeros((H, W), bool)
        m[y0:y1, x0:x1] = True
        ids[m.ravel()] = obj
        depth[m.ravel()] = z
    p = np.arange(H * W)
    image = np.stack([p & 255, (p >> 8) & 255, 200 + ((p >> 16) & 7)], axis=1).astype(np.uint8).reshape(H, W, 3)
    image[ids.reshape(H, W) < 0] = 0
    return image, ids, depth


def _source(out) -> np.ndarray:
    """The captured pixel index each output pixel shows (its colour's code)."""
    o = out.reshape(-1, 3).astype(np.int64)
    return o[:, 0] | (o[:, 1] << 8) | ((o[:, 2] - 200) << 16)


def test_the_capture_poses_give_the_captured_image_bit_for_bit_and_channel_writes_only_its_own():
    cam = _camera()
    image, ids, depth = _planes(cam, [(0, 1.0, (10, 40, 20, 60))])
    rp = Reprojector(cam, [True])
    cap = rp.capture(image, ids, depth, [_shifted()])
    assert cap.lit == 30 * 40
    out = np.full_like(image, 77)
    st = rp.reproject(cap, [_shifted()], out)
    assert np.array_equal(out, image) and st.holes == st.disoccluded == st.vacated == 0
    for k in range(3):
        out = np.full_like(image, 77)
        rp.reproject(cap, [_shifted()], out, channel=k)
        assert np.array_equal(out[..., k], image[..., k])
        assert (np.delete(out, k, axis=2) == 77).all()


def test_a_pose_change_too_small_to_move_a_pixel_takes_the_splat_path_and_changes_nothing():
    cam = _camera(dist=(-0.2, 0.05, 0.001, -0.001, 0.0))
    image, ids, depth = _planes(cam, [(0, 1.2, (5, 60, 5, 80)), (1, 0.9, (20, 40, 30, 50))])
    rp = Reprojector(cam, [True, True])
    cap = rp.capture(image, ids, depth, [_shifted(), _shifted()])
    out = np.zeros_like(image)
    st = rp.reproject(cap, [_shifted(1e-7), _shifted(0, 1e-7)], out)
    assert st.moved == cap.lit and st.dropped == 0  # every point splatted (not the unchanged-pose copy)
    assert np.array_equal(out, image)


def test_model_points_follow_the_gbuffer_depth_and_lens_distortion():
    """A plane moved sideways: every point lands where `PinholeCamera.project` (float64, an
    independent path) puts its pixel's surface point moved the same way."""
    cam = _camera(dist=(-0.25, 0.08, 0.002, -0.001, 0.0))
    image, ids, depth = _planes(cam, [(0, 1.0, (0, H, 0, W))])
    rp = Reprojector(cam, [True])
    pose0 = Pose(rotation_about_axis((0, 1, 0), 0.3), np.array([0.01, -0.02, 0.0]))
    cap = rp.capture(image, ids, depth, [pose0])
    # the model points are the pixels' rays at depth 1 taken into the object's frame
    ideal = cam.ideal_points().astype(np.float64)
    cam_pts = np.concatenate([ideal, np.ones((H * W, 1))], axis=1)
    assert np.allclose(cap.point.T, pose0.inverse().apply(cam_pts), atol=1e-6)
    move = np.array([0.03, 0.01, 0.0])
    out = np.zeros_like(image)
    rp.reproject(cap, [Pose(pose0.R, pose0.t + move)], out)
    px, front = cam.project(cam_pts + move)
    q = np.floor(px + 0.5).astype(int)
    inside = front & (q[:, 0] >= 0) & (q[:, 0] < W) & (q[:, 1] >= 0) & (q[:, 1] < H)
    # pixels near a rounding boundary may go either way: compare those whose position is clear
    clear = inside & (np.abs(px - np.round(px)) < 0.45).all(axis=1)
    got = _source(out)[q[clear, 1] * W + q[clear, 0]]
    assert clear.sum() > 0.5 * H * W
    assert np.mean(got == np.flatnonzero(clear)) > 0.99


def test_the_box_bounds_the_landed_points_and_is_none_when_every_point_leaves_the_frame():
    cam = _camera()
    image, ids, depth = _planes(cam, [(0, 1.0, (20, 40, 30, 50))])
    rp = Reprojector(cam, [True])
    cap = rp.capture(image, ids, depth, [_shifted()])
    out = np.zeros_like(image)
    st = rp.reproject(cap, [_shifted(5 / 80, -3 / 80)], out)  # 5 px right, 3 px up: rows 17–36, columns 35–54
    assert st.box == (17, 37, 35, 55) and st.moved == cap.lit
    # the square slid partly off the left edge: the box is clipped to the frame, the rest dropped
    st = rp.reproject(cap, [_shifted(-40 / 80)], out)
    assert st.box == (20, 40, 0, 10) and st.dropped == cap.lit - 10 * 20
    for gone in (_shifted(2.0), _shifted(dz=-1.5)):  # off the side; behind the projector
        out[:] = 7
        st = rp.reproject(cap, [gone], out)
        assert st.box is None and st.moved == 0 and st.dropped == st.vacated == cap.lit
        assert (out[ids.reshape(H, W) == 0] == 0).all()  # the plate: black where nothing else was seen


def test_magnification_cracks_are_filled_with_the_surface_and_counted():
    cam = _camera()
    image, ids, depth = _planes(cam, [(0, 1.0, (26, 46, 38, 58))])
    rp = Reprojector(cam, [True])
    cap = rp.capture(image, ids, depth, [_shifted()])
    out = np.zeros_like(image)
    st = rp.reproject(cap, [_shifted(dz=-0.4)], out)  # 1/0.6: a 1.67× magnification
    assert st.holes > 0.3 * cap.lit
    # the square's new footprint, well inside its edges: every pixel shows the surface (no black crack)
    s = 1 / 0.6
    y0, y1 = (26 - 35.5) * s + 35.5, (45 - 35.5) * s + 35.5
    x0, x1 = (38 - 47.5) * s + 47.5, (57 - 47.5) * s + 47.5
    inner = out[math.ceil(y0) + 1:int(y1), math.ceil(x0) + 1:int(x1)]
    assert inner.size and (inner[..., 2] >= 200).all()


def test_cracks_are_filled_up_to_the_frames_first_pixel():
    """The splats' box starting at pixel (0, 0): its first row has no pixel before it, and its
    cracks close as anywhere else."""
    cam = _camera()
    image, ids, depth = _planes(cam, [(0, 1.0, (0, 30, 0, 40))])
    rp = Reprojector(cam, [True])
    cap = rp.capture(image, ids, depth, [_shifted()])
    out = np.zeros_like(image)
    st = rp.reproject(cap, [_shifted(dz=-0.4)], out)  # 1.67×, away from the principal point: past the corner
    assert st.box[0] == 0 and st.box[2] == 0 and st.holes > 0.3 * st.moved
    assert (out[:24, :34, 2] >= 200).all()  # the surface everywhere it now covers, the first row too


def test_newly_visible_surface_takes_the_farther_side_and_is_counted_as_disoccluded():
    cam = _camera()
    far = (0, 1.0, (10, 60, 10, 86))
    image, ids, depth = _planes(cam, [far, (1, 0.5, (25, 45, 30, 50))])
    rp = Reprojector(cam, [True, True])
    cap = rp.capture(image, ids, depth, [_shifted(), _shifted()])
    out = np.zeros_like(image)
    dx = -3 * 0.5 / 80  # the near square 3 px to the left
    st = rp.reproject(cap, [_shifted(), _shifted(dx)], out)
    assert st.disoccluded >= 3 * 20
    band = out[26:44, 47:50]  # what the near square uncovered on its right: the far plane's colours now
    codes = _source(band).reshape(band.shape[:2])
    assert (np.isin(codes, np.flatnonzero(ids == 0))).all()


def test_a_static_object_in_front_hides_the_moved_points_and_the_plate_fills_what_they_leave():
    cam = _camera()
    rp = Reprojector(cam, [True, False])
    # first frame: the static wall alone (the plate learns its colour and depth)
    wall = (1, 0.7, (20, 50, 60, 90))
    image0, ids0, depth0 = _planes(cam, [wall])
    rp.capture(image0, ids0, depth0, [_shifted(), _shifted()])
    image, ids, depth = _planes(cam, [wall, (0, 1.0, (20, 50, 20, 50))])
    image[ids.reshape(H, W) == 1] = (9, 9, 9)
    cap = rp.capture(image, ids, depth, [_shifted(), _shifted()])
    out = np.zeros_like(image)
    st = rp.reproject(cap, [_shifted(25 / 80), _shifted()], out)  # 25 px to the right, behind the wall
    assert st.dropped > 0
    assert (out[20:50, 60:90] == (9, 9, 9)).all()  # the wall stays in front
    assert (out[20:50, 20:45] == 0).all()  # what the object left shows the plate: the background it saw


def test_against_fresh_renders_the_reprojection_beats_the_stale_frame_inside_the_object():
    """dpm-bunny at 192×144, 16 spp, rotate-oscillate: at 20 and 40 ms the reprojected frame must
    be closer to a fresh render than the stale one is, by a margin. Measured: 23.4–23.5 dB against
    18.0 and 15.8 dB stale (two renders at one pose agree to 28 dB: their noise caps every
    figure); the bounds leave 2–5 dB. (At this size 10 ms moves the bunny about a pixel.)"""
    from dpmhw.render.integrator import PathIntegrator
    from dpmhw.scene_file import load_scene
    from dpmhw.session.factory import mock_trajectory

    scene = load_scene("dpm-bunny").at_size(192, 144)
    path = mock_trajectory("rotate-oscillate", scene.objects[0].pose.t, 1.0)

    def poses(t):
        rot, pos = path.pose_floats(t)
        p = scene.object_poses(0.0)
        p[0] = Pose(np.array(rot).reshape(3, 3), np.array(pos))
        return p

    with PathIntegrator(scene, threads=1) as r:
        f0 = r.render(poses=poses(0.3), spp=16, seed=1)
        img0 = to_srgb8(f0.radiance)
        rp = Reprojector(r.camera, [o.is_dynamic for o in scene.objects])
        cap = rp.capture(img0, f0.object_id.reshape(-1).astype(np.int32), f0.depth.reshape(-1).astype(np.float32), poses(0.3))
        out = np.empty_like(img0)
        for h in (0.02, 0.04):
            f1 = r.render(poses=poses(0.3 + h), spp=16, seed=2)
            ref, mask = to_srgb8(f1.radiance), f1.object_id == 0
            st = rp.reproject(cap, poses(0.3 + h), out)
            assert st.moved > 0.8 * cap.lit
            moved, stale = masked_psnr(out, ref, mask), masked_psnr(img0, ref, mask)
            assert moved > stale + 3.0 and moved > 20.0, (h, moved, stale)


def test_bad_input_names_the_argument():
    cam = _camera()
    image, ids, depth = _planes(cam, [(0, 1.0, (10, 40, 20, 60))])
    rp = Reprojector(cam, [True])
    ok = [_shifted()]
    cases = [
        (lambda: rp.capture(image[:, :-1], ids, depth, ok), "image"),
        (lambda: rp.capture(image.astype(np.float32), ids, depth, ok), "image"),
        (lambda: rp.capture(image, ids.astype(np.int64), depth, ok), "object_id"),
        (lambda: rp.capture(image, ids[:-1], depth, ok), "object_id"),
        (lambda: rp.capture(image, np.where(ids >= 0, 3, -1).astype(np.int32), depth, ok), "object_id"),
        (lambda: rp.capture(image, ids, depth.astype(np.float64), ok), "depth"),
        (lambda: rp.capture(image, ids, depth, []), "poses"),
        (lambda: rp.capture(image, ids, depth, [Pose(np.eye(3), np.array([0, np.nan, 0]))]), r"poses\[0\]"),
        (lambda: rp.capture(image, ids, depth, ["pose"]), r"poses\[0\]"),
        (lambda: rp.capture(image, ids, depth, ok, box=(0, H + 1, 0, W)), "box"),
        (lambda: rp.capture(image, ids, depth, ok, box=(0, 1.5, 0, W)), "box"),
        (lambda: Reprojector(cam, []), "dynamic"),
        (lambda: Reprojector(object(), [True]), "camera"),
    ]
    cap = rp.capture(image, ids, depth, ok)
    out = np.zeros_like(image)
    cases += [
        (lambda: rp.reproject(cap, [Pose(np.full((3, 3), np.inf), np.zeros(3))], out), r"poses\[0\]"),
        (lambda: rp.reproject(cap, ok, out[:, ::2]), "out"),
        (lambda: rp.reproject(cap, ok, out.astype(np.uint16)), "out"),
        (lambda: rp.reproject(cap, ok, out, channel=3), "channel"),
        (lambda: rp.reproject(cap, ok, out, channel=True), "channel"),
        (lambda: rp.reproject("capture", ok, out), "capture"),
        (lambda: rp.reproject(cap, ok, image), "out"),
    ]
    cases += [
        (lambda: rp.capture(image, ids, depth, ok, background=np.zeros(5, np.uint8)), "background"),
        (lambda: rp.capture(image, ids, depth, ok, background=image.astype(np.float32)), "background"),
        (lambda: rp.present(cap, [(ok, 0), (ok, 1)]), "windows"),
        (lambda: rp.present(cap, [(ok, 0), (ok, 1), (ok, 1)]), "windows"),
        (lambda: rp.present("capture", [(ok, None)]), "capture"),
    ]
    for call, name in cases:
        with pytest.raises(ValueError, match=f"^{name}"):
            call()


def test_a_present_into_its_own_frames_gives_the_bits_of_a_whole_new_frame():
    """`present` copies only the boxes that changed into the frame it reuses (captures sharing a
    background); every present equals a reprojection into a fresh frame, whether the captures
    move, repeat, change background or have none, in both kinds of present."""
    cam = _camera()
    rp = Reprojector(cam, [True])
    background = np.full((H, W, 3), 7, np.uint8)

    def capture(x, bg):  # the moving square at column x, its box the lit box; the rest shows `bg`
        box = (10 + x // 3, 30 + x // 3, x, x + 20)
        image, ids, depth = _planes(cam, [(0, 0.9, box)])
        inside = np.zeros((H, W), bool)
        inside[box[0]:box[1], box[2]:box[3]] = True
        image[~inside] = bg[~inside] if bg is not None else 3
        return rp.capture(image, ids, depth, [_shifted()], box, None if bg is None else bg.reshape(-1))

    def poses(k):  # 0.9-3 px a step: the splats leave the capture's box
        return [_shifted(0.01 * k, -0.004 * k)]

    other = np.full((H, W, 3), 11, np.uint8)
    sequence = [(capture(x, bg), reps) for x, bg, reps in
                ((10, background, 2), (40, background, 1), (60, background, 3), (20, other, 1), (30, other, 1),
                 (50, None, 2), (15, background, 2))]
    frames = set()
    k = 0
    for cap, reps in sequence:
        for _ in range(reps):
            k += 1
            for windows in ([(poses(k), None)], [(poses(k + j), j) for j in (2, 0, 1)]):
                fresh = np.zeros_like(cap.image)
                expected = rp.reproject_windows(cap, windows, fresh)
                frame, stats = rp.present(cap, windows)
                frames.add(id(frame))
                assert stats == expected
                assert np.array_equal(frame, fresh), (k, windows[0][1])
    assert len(frames) == PRESENT_FRAMES


def test_windows_that_share_poses_give_each_windows_own_bits():
    """Windows at equal poses (one splat writes their channels together) equal their own
    `reproject` calls, in any order of channels, beside a window at other poses."""
    cam = _camera(dist=(-0.2, 0.05, 0.001, -0.001, 0.0))
    image, ids, depth = _planes(cam, [(0, 1.2, (5, 60, 5, 80)), (1, 0.9, (20, 40, 30, 50))])
    rp = Reprojector(cam, [False, True])
    cap = rp.capture(image, ids, depth, [_shifted(), _shifted()])
    a = [_shifted(), Pose(rotation_about_axis((0, 1, 0), 0.1), np.array([0.01, -0.004, -0.3]))]
    b = [_shifted(), _shifted(-0.02, 0.01)]
    st = rp.reproject(cap, a, np.zeros_like(image))
    assert st.holes > 0 and st.vacated > 0  # else this checks little
    for windows in ([(a, 0), (a, 1), (a, 2)], [(a, 0), (a, 1), (b, 2)], [(b, 0), (a, 1), (a, 2)],
                    [(a, 2), (a, 0), (a, 1)], [(a, 1), (a, 2)], [(a, 0), (b, 1), (a, 2)]):
        one_by_one = np.full_like(image, 5)
        expected = [rp.reproject(cap, poses, one_by_one, channel=ch) for poses, ch in windows]
        together = np.full_like(image, 5)
        assert rp.reproject_windows(cap, windows, together) == expected
        assert np.array_equal(together, one_by_one)


def test_a_presents_windows_in_one_call_give_each_windows_own_bits():
    """Three sub-frames (one channel each, each at its own poses; one of them unmoved) in one
    call equal three `reproject` calls; bad window sets are refused, naming the window."""
    cam = _camera(dist=(-0.2, 0.05, 0.001, -0.001, 0.0))
    image, ids, depth = _planes(cam, [(0, 1.2, (5, 60, 5, 80)), (1, 0.9, (20, 40, 30, 50))])
    rp = Reprojector(cam, [False, True])
    cap = rp.capture(image, ids, depth, [_shifted(), _shifted()])
    windows = [([_shifted(), _shifted(0.01 * k, -0.004 * k)], k) for k in range(3)]
    one_by_one = np.full_like(image, 5)
    expected = [rp.reproject(cap, poses, one_by_one, channel=ch) for poses, ch in windows]
    together = np.full_like(image, 9)
    assert rp.reproject_windows(cap, windows, together) == expected
    assert np.array_equal(together, one_by_one)
    assert expected[0].moved == cap.lit and expected[2].vacated > 0  # window 0 unmoved, window 2 moved
    alone = np.zeros_like(image)  # a single window of all channels
    assert rp.reproject_windows(cap, [(windows[2][0], None)], alone) == [rp.reproject(cap, windows[2][0], together)]
    assert np.array_equal(alone, together)
    ok = windows[0][0]
    for bad, name in (([(ok, 0), (ok, 0)], "windows"), ([(ok, None), (ok, 1)], "windows"), ([], "windows"),
                      ([(ok, 0), (ok, 4)], r"windows\[1\] channel"), ([(ok, 0), ([ok[0]], 1)], r"windows\[1\] poses")):
        with pytest.raises(ValueError, match=f"^{name}"):
            rp.reproject_windows(cap, bad, together)


def _interleaved(rp) -> dict:
    """Make rp's presents share their splats for certain: the calling thread holds its first
    splat until the helper has made one (a busy machine may otherwise leave them all to it).
    Returns the count of the helper's splats."""
    made, orig = {"helper": 0}, rp._splats

    def splats(common, scratch, plan, g_first, g_end):
        if plan:
            made["event"] = threading.Event()
        elif scratch[0] is rp._scratch[1].zbuf:  # the helper's
            orig(common, scratch, plan, g_first, g_end)
            made["helper"] += 1
            made["event"].set()
            return
        elif np.count_nonzero(rp._groups[:, 0] >= 0) > 1:  # a splat of a shared present, on the caller
            assert made["event"].wait(30.0)
        orig(common, scratch, plan, g_first, g_end)

    rp._splats = splats
    return made


def test_two_threads_give_the_bits_of_one():
    """A Reprojector with a helper thread presents and reprojects exactly as one without it:
    three own poses (three splats shared out), two equal ones beside a third (two splats), all
    three equal (one), one window unmoved, and a single window of all channels."""
    cam = _camera(dist=(-0.2, 0.05, 0.001, -0.001, 0.0))
    image, ids, depth = _planes(cam, [(0, 1.2, (5, 60, 5, 80)), (1, 0.9, (20, 40, 30, 50))])
    one, two = Reprojector(cam, [False, True]), Reprojector(cam, [False, True], threads=2)
    made = _interleaved(two)
    caps = [rp.capture(image, ids, depth, [_shifted(), _shifted()]) for rp in (one, two)]

    def at(k):
        return [_shifted(), Pose(rotation_about_axis((0, 1, 0), 0.01 * k), np.array([0.004 * k, -0.002 * k, 0.0]))]

    try:
        for k in range(1, 40):
            for windows in ([(at(k + j), j) for j in range(3)], [(at(k), 0), (at(k), 1), (at(k + 1), 2)],
                            [(at(k), j) for j in range(3)], [(at(0), 0), (at(k), 1), (at(k + 2), 2)], [(at(k), None)]):
                frames = [rp.present(cap, windows) for rp, cap in zip((one, two), caps)]
                assert frames[0][1] == frames[1][1]
                assert np.array_equal(frames[0][0], frames[1][0]), (k, windows)
        assert made["helper"] >= 39 * 3  # a splat or two of each present that makes two or three
    finally:
        two.close()
    with pytest.raises(ValueError, match="^threads"):
        Reprojector(cam, [True], threads=3)


def test_a_reprojector_left_unclosed_ends_its_helper_when_collected():
    """The helper thread holds nothing of the Reprojector between presents: dropping it ends the
    thread (no leak of threads and frames when a caller forgets `close`)."""
    import gc

    cam = _camera()
    rp = Reprojector(cam, [True], threads=2)
    _interleaved(rp)
    image, ids, depth = _planes(cam, [(0, 1.0, (10, 40, 10, 60))])
    cap = rp.capture(image, ids, depth, [_shifted()])
    rp.present(cap, [([_shifted(0.002 * j)], j) for j in range(3)])
    thread = rp._helper._thread
    del rp, cap
    gc.collect()
    thread.join(30.0)
    assert not thread.is_alive()


def test_the_splat_helper_shares_the_work_and_hands_back_its_errors():
    """Every splat is made once, some on the helper's thread; a splat that fails there fails
    the present; a closed helper's thread ends."""
    from dpmhw.reconstruct.reproject import _SplatHelper

    helper = _SplatHelper()
    try:
        for _ in range(5):
            made, helped = [], threading.Event()

            def splat(k, slot):
                made.append((k, slot))
                if slot == 1:
                    helped.set()
                else:  # the caller holds on until the helper has taken one
                    assert helped.wait(30.0)

            helper.share(splat, 3)
            assert sorted(k for k, _ in made) == [0, 1, 2] and {s for _, s in made} == {0, 1}

        tried = threading.Event()

        def fails_on_the_helper(k, slot):
            if slot == 1:
                tried.set()
                raise RuntimeError("splat failed")
            assert tried.wait(30.0)

        with pytest.raises(RuntimeError, match="splat failed"):
            helper.share(fails_on_the_helper, 2)
    finally:
        helper.close()
    assert not helper._thread.is_alive()
