"""`dpmhw calibrate`: projector-camera calibration (Gray code, Moreno & Taubin 2012) and the
projector's pose in the tracker frame.  Heavy imports happen inside the commands."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from dpmhw.cli.apps import app
from dpmhw.cli.choices import SinkKind
from dpmhw.progress import Progress

calibrate_app = typer.Typer(no_args_is_help=True, help="Calibrate the projector (intrinsics, lens shift, pose in the tracker frame).")
app.add_typer(calibrate_app, name="calibrate")


def _size(text: str, what: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"{what} must look like 1280x800, got {text!r}") from None
    if w < 2 or h < 2:
        raise typer.BadParameter(f"{what} must be at least 2x2, got {text!r}")
    return w, h


def _fail(exc: Exception) -> None:
    typer.secho(f"error: {exc}", err=True, fg=typer.colors.RED)
    raise typer.Exit(code=1)


@calibrate_app.command()
def patterns(
    out: Annotated[Path, typer.Option("--out", help="Folder for 000.png, 001.png, ... in projection order.")],
    size: Annotated[str, typer.Option("--size", help="Projector resolution WxH (any size, not only powers of two).")] = "1280x800",
) -> None:
    """Write the Gray-code sequence (white, black, each bit and its inverse) as PNG files."""
    import cv2

    from calibration.patterns import PatternSet

    w, h = _size(size, "--size")
    out.mkdir(parents=True, exist_ok=True)
    frames = PatternSet(w, h).generate()
    for i, f in enumerate(frames):
        cv2.imwrite(str(out / f"{i:03d}.png"), f)
    typer.echo(f"wrote {len(frames)} patterns for a {w}x{h} projector to {out}")


@calibrate_app.command()
def decode(
    pose: Annotated[Path, typer.Argument(help="One pose folder of a capture (its parent holds capture.json).")],
    out: Annotated[Optional[Path], typer.Option("--out", help="Write x, y, valid arrays to this .npz file.")] = None,
) -> None:
    """Decode one pose and report how much of the image decoded and which bits were dropped."""
    import numpy as np

    from calibration.capture import load_pose, open_capture
    from calibration.decode import decode as run_decode
    from dpmhw.errors import CalibrationError

    try:
        meta = open_capture(pose.parent)
        frames = load_pose(meta, pose)
    except CalibrationError as exc:
        _fail(exc)
    t0 = time.perf_counter()
    d = run_decode(frames, meta.projector_width, meta.projector_height)
    dt = time.perf_counter() - t0
    typer.echo(f"{pose.name}: {d.valid_fraction:.1%} of pixels decoded in {dt * 1000:.0f} ms; "
               f"dropped bits x {d.dropped_bits_x}, y {d.dropped_bits_y}")
    typer.echo("bit contrast x: " + " ".join(f"{c:.2f}" for c in d.contrast_x))
    typer.echo("bit contrast y: " + " ".join(f"{c:.2f}" for c in d.contrast_y))
    if out is not None:
        np.savez_compressed(out, x=d.x, y=d.y, valid=d.valid)
        typer.echo(f"wrote {out}")


@calibrate_app.command()
def capture(
    out: Annotated[Path, typer.Argument(help="Capture folder (created; capture.json written on first use).")],
    pose: Annotated[str, typer.Option("--pose", help="Name of this board pose's folder, e.g. pose_003.")],
    size: Annotated[Optional[str], typer.Option("--size", help="Projector resolution WxH (default: from capture.json).")] = None,
    board: Annotated[str, typer.Option("--board", help="Chessboard inner corners COLSxROWS.")] = "9x6",
    square: Annotated[float, typer.Option("--square", help="Square side in metres.")] = 0.03,
    camera: Annotated[str, typer.Option("--camera", help="cv2.VideoCapture source: device index, URL or image sequence.")] = "0",
    sink: Annotated[SinkKind, typer.Option("--sink", help="Frame sink: window (projector display), file or recording.")] = SinkKind("window"),
    display: Annotated[int, typer.Option("--display", help="Display index of the projector (window sink).")] = 1,
    settle: Annotated[float, typer.Option("--settle", help="Seconds to wait after each pattern.")] = 0.15,
    discard: Annotated[int, typer.Option("--discard", min=0, help="Buffered camera frames to drop before each grab.")] = 2,
) -> None:
    """Live capture of one board pose: show each pattern on the projector, grab the camera."""
    from calibration.board import BoardSpec
    from calibration.capture import capture_live, read_capture_meta
    from calibration.patterns import PatternSet
    from dpmhw.errors import CalibrationError

    try:
        if (out / "capture.json").exists():  # later poses: the folder's projector and board win
            meta = read_capture_meta(out)
            w, h, spec = meta.projector_width, meta.projector_height, meta.board
            if size is not None and _size(size, "--size") != (w, h):
                raise typer.BadParameter(f"--size {size} differs from {out / 'capture.json'} ({w}x{h})")
        else:
            if size is None:
                raise typer.BadParameter("--size is needed for a new capture folder")
            w, h = _size(size, "--size")
            cols, rows = _size(board, "--board")
            spec = BoardSpec(cols, rows, square)
        from drivers.frame_sinks import make_sink

        kwargs = {"window": {"display": display, "size": (w, h)}, "file": {"path": out / "_shown"}, "recording": {"shape": (h, w)}}
        frame_sink = make_sink(sink.value, **kwargs.get(sink.value, {}))
        try:
            with Progress() as bar:
                task = bar.task(f"capturing {pose}, patterns", total=PatternSet(w, h).count)
                capture_live(frame_sink, out, pose, w, h, spec, camera=int(camera) if camera.isdigit() else camera,
                             settle_s=settle, discard=discard, progress=lambda i, n: task.advance())
        finally:
            frame_sink.close()
    except CalibrationError as exc:
        _fail(exc)
    typer.echo(f"captured {out / pose}")


def _observe_capture(capture: Path, options):
    from calibration.capture import iter_poses, open_capture
    from calibration.procam import observe

    meta = open_capture(capture)
    obs = []
    with Progress() as bar:
        task = bar.task("decoding poses", total=len(meta.poses))
        for name, frames in iter_poses(meta):
            obs.append(observe(name, frames, meta.board, (meta.projector_width, meta.projector_height), options))
            task.advance()
    return meta, obs


def _run_procam(capture: Path, out: Path, report: Optional[Path], truth: Optional[Path], release_object: Optional[bool]):
    from dpmhw import __version__
    from calibration.procam import SolveOptions, calibrate_procam

    import cv2

    options = SolveOptions(release_object=release_object)
    t0 = time.perf_counter()
    meta, obs = _observe_capture(capture, options)
    t_obs = time.perf_counter() - t0
    result = calibrate_procam(obs, meta.board, (meta.projector_width, meta.projector_height), options)
    result.timings = {
        "load_images": t_obs - sum(sum(o.timings.values()) for o in obs),
        "detect_board": sum(o.timings.get("detect", 0) for o in obs),
        "decode_gray_code": sum(o.timings.get("decode", 0) for o in obs),
        **result.timings,
    }
    cal = result.to_calibration({
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "dpmhw": __version__,
        "opencv": cv2.__version__,
        "source": str(capture.resolve()),
        "method": "Gray code + local homographies (Moreno & Taubin 2012), calibrateCameraExtended, stereoCalibrateExtended",
    })
    cal.save(out)
    _print_result(result, cal)
    typer.echo(f"wrote {out}")
    if report is not None:
        from calibration.report import write_report

        write_report(result, report)
        typer.echo(f"wrote {report}")
    if truth is not None:
        _print_truth(cal, truth)
    return result, cal


def _print_result(result, cal) -> None:
    Kc, Kp = result.camera.K, result.projector.K
    sp, sc = result.projector.std, result.camera.std
    typer.echo(f"camera    fx {Kc[0, 0]:.2f} fy {Kc[1, 1]:.2f} cx {Kc[0, 2]:.2f} cy {Kc[1, 2]:.2f}  "
               f"(sigma fx {sc['fx']:.2f}, cy {sc['cy']:.2f})  RMS {result.camera.rms:.3f} px")
    typer.echo(f"projector fx {Kp[0, 0]:.2f} fy {Kp[1, 1]:.2f} cx {Kp[0, 2]:.2f} cy {Kp[1, 2]:.2f}  "
               f"(sigma fx {sp['fx']:.2f}, cy {sp['cy']:.2f})  RMS {result.projector.rms:.3f} px")
    typer.echo(f"stereo RMS {result.stereo_rms:.3f} px; projector at ({', '.join(f'{v:.1f}' for v in 1000 * cal.t)}) mm in the camera frame")
    typer.echo(f"{'view':<12} {'used':<5} {'camera px':>9} {'projector px':>12}  reason")
    for v in result.views_table():
        st = v["stereo_rms_px"] or [float('nan')] * 2
        typer.echo(f"{v['name']:<12} {'yes' if v['used'] else 'NO':<5} {st[0]:>9.3f} {st[1]:>12.3f}  {v['reason']}")
    for d in result.diagnostics:
        typer.secho(f"warning: {d}", fg=typer.colors.YELLOW)
    typer.echo("time per stage: " + ", ".join(f"{k} {v:.2f} s" for k, v in result.timings.items()))


def _print_truth(cal, truth_path: Path) -> dict:
    from calibration.evaluate import compare_with_truth, format_table

    cmp = compare_with_truth(cal, json.loads(truth_path.read_text()))
    typer.echo("against ground truth:")
    typer.echo(format_table(cmp))
    return cmp


@calibrate_app.command()
def procam(
    capture: Annotated[Path, typer.Argument(help="Capture folder: capture.json + one folder per board pose.")],
    out: Annotated[Path, typer.Option("--out", help="Calibration file to write (JSON, written atomically).")] = Path("calib.json"),
    report: Annotated[Optional[Path], typer.Option("--report", help="Also write a PNG report here.")] = None,
    truth: Annotated[Optional[Path], typer.Option("--truth", help="truth.json of a synthetic dataset: print errors.")] = None,
    release_object: Annotated[Optional[bool], typer.Option("--release-object/--planar-board", help="Force calibrateCameraRO on or off (default: only when the board looks bowed).")] = None,
) -> None:
    """Calibrate camera + projector from a capture folder; the file is only written on success."""
    from dpmhw.errors import CalibrationError

    try:
        _run_procam(capture, out, report, truth, release_object)
    except CalibrationError as exc:
        _fail(exc)


@calibrate_app.command()
def tracker(
    capture: Annotated[Path, typer.Argument(help="Capture folder of the tracked board (same layout as for procam).")],
    calibration: Annotated[Path, typer.Option("--calibration", help="Calibration file from `calibrate procam`.")],
    poses: Annotated[Path, typer.Option("--poses", help="Tracker poses JSON: world_from_board per pose folder.")],
    out: Annotated[Path, typer.Option("--out", help="Calibration file to write with the pose in the tracker frame.")],
    truth: Annotated[Optional[Path], typer.Option("--truth", help="truth.json of a synthetic dataset: print errors.")] = None,
) -> None:
    """Place the projector in the tracker's world frame (projector intrinsics held fixed)."""
    from calibration.procam import SolveOptions
    from calibration.tracker import load_tracker_poses, projector_pose_from_tracked_board
    from dpmhw.errors import CalibrationError
    from dpmhw.projector_calibration import load_projector_calibration

    try:
        cal = load_projector_calibration(calibration)
        world_from_board = load_tracker_poses(poses)
        meta, obs = _observe_capture(capture, SolveOptions())
        pose = projector_pose_from_tracked_board(obs, world_from_board, meta.board, cal)
    except CalibrationError as exc:
        _fail(exc)
    cal.R, cal.t, cal.frame = pose.R, pose.t, "tracker"
    cal.stats["tracker_rms_px"] = pose.rms_px
    cal.stats["tracker_per_view_rms_px"] = pose.per_view_rms_px
    cal.stats["tracker_outliers"] = int((~pose.inliers).sum())
    cal.provenance["tracker_poses"] = str(poses.resolve())
    cal.save(out)
    typer.echo(f"projector in the tracker frame: t = {pose.t.round(4).tolist()} m, RMS {pose.rms_px:.3f} px over "
               f"{int(pose.inliers.sum())} points ({int((~pose.inliers).sum())} outliers)")
    typer.echo(f"wrote {out}")
    if truth is not None:
        _print_truth(cal, truth)


@calibrate_app.command()
def synth(
    out: Annotated[Path, typer.Option("--out", help="Folder for the dataset (capture layout + truth.json + tracker_poses.json).")],
    views: Annotated[int, typer.Option("--views", min=1, help="Board poses.")] = 13,
    seed: Annotated[int, typer.Option("--seed")] = 0,
    camera: Annotated[str, typer.Option("--camera", help="Camera resolution WxH.")] = "1280x960",
    projector: Annotated[str, typer.Option("--projector", help="Projector resolution WxH.")] = "1024x768",
    projector_cy: Annotated[float, typer.Option("--projector-cy", help="Projector cy as a multiple of its height (lens shift).")] = 1.03,
    noise: Annotated[float, typer.Option("--noise", help="Camera noise sigma in 8-bit DN.")] = 1.5,
    blur: Annotated[float, typer.Option("--blur", help="Optical blur sigma in camera pixels.")] = 0.7,
    bow: Annotated[float, typer.Option("--bow", help="Board sag in metres (0 = flat).")] = 0.0,
    supersample: Annotated[int, typer.Option("--supersample", min=1, max=4)] = 2,
    tracker_noise_mm: Annotated[float, typer.Option("--tracker-noise", help="Noise (sigma, mm) on the tracked board positions in tracker_poses.json.")] = 0.2,
    solve: Annotated[bool, typer.Option("--solve", help="Then run procam + tracker on it and print errors against the truth.")] = False,
) -> None:
    """Generate a synthetic capture with known truth (camera, projector with lens shift, board poses)."""
    from calibration.synthetic import make_rig

    cw, ch = _size(camera, "--camera")
    pw, ph = _size(projector, "--projector")
    t0 = time.perf_counter()
    rig = make_rig(seed, views, camera_size=(cw, ch), projector_size=(pw, ph), projector_cy=projector_cy,
                   noise_sigma=noise, blur_sigma=blur, bow=bow, supersample=supersample)
    with Progress() as bar:
        task = bar.task(f"rendering {views} synthetic poses", total=views)
        rig.write(out, tracker_noise=tracker_noise_mm / 1000.0, progress=task.update)
    typer.echo(f"wrote {views} poses x {rig.patterns.count} frames ({cw}x{ch} camera, {pw}x{ph} projector) to {out} "
               f"in {time.perf_counter() - t0:.1f} s")
    if solve:
        from dpmhw.errors import CalibrationError

        try:
            _run_procam(out, out / "calib.json", out / "report.png", out / "truth.json", None)
        except CalibrationError as exc:
            _fail(exc)
        tracker(out, out / "calib.json", out / "tracker_poses.json", out / "calib_tracker.json", out / "truth.json")
