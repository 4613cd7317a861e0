"""Capture folders: the documented layout, loading with checks, and live capture glue.

Layout::

    CAPTURE_DIR/
      capture.json        {"format": "dpmhw.capture", "version": 1,
                           "projector": {"width": W, "height": H},
                           "board": {"kind": "chessboard", "cols": 9, "rows": 6, "square": 0.03}}
      pose_000/000.png    one folder per board pose; frames in pattern order
      pose_000/001.png    (see calibration.patterns: white, black, column bits + inverses,
      ...                  row bits + inverses), 8- or 16-bit, grey or colour
      pose_001/...

Pose folders are processed in name order; any folder name works, files are sorted by name.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibration.board import BoardSpec
from calibration.errors import CaptureError
from calibration.patterns import PatternSet
from dpmhw.frame_sink import FrameSink

FORMAT = "dpmhw.capture"
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg", ".pgm")


@dataclass
class CaptureMeta:
    root: Path
    projector_width: int
    projector_height: int
    board: BoardSpec
    poses: list[Path]

    @property
    def patterns(self) -> PatternSet:
        return PatternSet(self.projector_width, self.projector_height)


def write_capture_meta(root: Path, width: int, height: int, board: BoardSpec) -> Path:
    doc = {"format": FORMAT, "version": 1, "projector": {"width": width, "height": height}, "board": board.to_dict()}
    p = Path(root) / "capture.json"
    p.write_text(json.dumps(doc, indent=2) + "\n")
    return p


def open_capture(root: str | Path) -> CaptureMeta:
    """Read ``capture.json`` and list the pose folders; errors name the file and field."""
    meta = read_capture_meta(root)
    if not meta.poses:
        raise CaptureError(str(meta.root), "(folder)", "no pose folders (expected pose_000/, pose_001/, ...)")
    return meta


def read_capture_meta(root: str | Path) -> CaptureMeta:
    """Like :func:`open_capture` but a folder without poses yet is fine (live capture)."""
    root = Path(root)
    meta = root / "capture.json"
    if not root.is_dir():
        raise CaptureError(str(root), "(folder)", "no such capture folder")
    if not meta.is_file():
        raise CaptureError(str(meta), "(file)", "missing; a capture folder needs capture.json (see docs/calibration.md)")
    try:
        doc = json.loads(meta.read_text())
    except json.JSONDecodeError as exc:
        raise CaptureError(str(meta), "(file)", f"not valid JSON: {exc.msg} at line {exc.lineno}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CaptureError(str(meta), "format", f"expected {FORMAT!r}")
    proj = doc.get("projector")
    if not isinstance(proj, dict):
        raise CaptureError(str(meta), "projector", "missing; expected {\"width\": W, \"height\": H}")
    size = []
    for k in ("width", "height"):
        v = proj.get(k)
        if not isinstance(v, int) or isinstance(v, bool) or v < 2:
            raise CaptureError(str(meta), f"projector.{k}", f"expected an integer >= 2, got {v!r}")
        size.append(v)
    b = doc.get("board")
    if not isinstance(b, dict):
        raise CaptureError(str(meta), "board", "missing; expected {\"kind\", \"cols\", \"rows\", \"square\"}")
    try:
        board = BoardSpec(**b)
    except (TypeError, ValueError) as exc:
        raise CaptureError(str(meta), "board", str(exc)) from None
    poses = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(("_", ".")))
    return CaptureMeta(root, size[0], size[1], board, poses)


def pose_frames(meta: CaptureMeta, pose: Path) -> list[Path]:
    files = sorted(p for p in pose.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    need = meta.patterns.count
    if len(files) != need:
        raise CaptureError(
            str(pose), "(frames)",
            f"has {len(files)} images, a {meta.projector_width}x{meta.projector_height} projector needs {need} "
            "(white, black, then each Gray-code bit and its inverse); re-capture this pose or delete the folder",
        )
    return files


def load_pose(meta: CaptureMeta, pose: Path) -> np.ndarray:
    """(N, H, W) float32 grey frames of one pose; errors name the bad image."""
    frames = []
    shape = None
    for f in pose_frames(meta, pose):
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CaptureError(str(f), "(image)", "unreadable or corrupt image file")
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.shape[2] == 3 else img[..., 0]
        if shape is None:
            shape = img.shape
        elif img.shape != shape:
            raise CaptureError(str(f), "(image)", f"size {img.shape[::-1]} differs from the pose's first frame {shape[::-1]}")
        frames.append(img)
    return np.stack(frames)


def iter_poses(meta: CaptureMeta) -> Iterator[tuple[str, np.ndarray]]:
    for pose in meta.poses:
        yield pose.name, load_pose(meta, pose)


def capture_live(
    sink: FrameSink,
    out_dir: str | Path,
    pose_name: str,
    width: int,
    height: int,
    board: BoardSpec,
    *,
    camera: int | str = 0,
    settle_s: float = 0.15,
    discard: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Show every pattern through ``sink`` and grab a camera frame for each (one board pose).

    ``sink`` is a :class:`dpmhw.frame_sink.FrameSink` (e.g. ``drivers.frame_sinks.WindowSink``
    on the projector's display).  Thin glue over ``cv2.VideoCapture``: after presenting a
    pattern it waits ``settle_s`` and discards ``discard`` buffered frames so the grab shows
    the new pattern.  ``camera`` is a device index, a URL or an image-sequence pattern.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "capture.json").exists():
        write_capture_meta(out, width, height, board)
    pose_dir = out / pose_name
    pose_dir.mkdir(exist_ok=True)
    cap = cv2.VideoCapture(camera)
    if not cap.isOpened():
        raise CaptureError(str(camera), "(camera)", "cannot open the camera with cv2.VideoCapture")
    try:
        frames = PatternSet(width, height).generate()
        for i, pat in enumerate(frames):
            sink.present(cv2.cvtColor(pat, cv2.COLOR_GRAY2RGB), time.monotonic_ns())
            time.sleep(settle_s)
            for _ in range(discard):
                cap.grab()
            ok, img = cap.read()
            if not ok:
                raise CaptureError(str(camera), "(camera)", f"no frame for pattern {i}")
            cv2.imwrite(str(pose_dir / f"{i:03d}.png"), img)
            if progress is not None:
                progress(i + 1, len(frames))
    finally:
        cap.release()
    return pose_dir
