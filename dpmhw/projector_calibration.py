"""The projector calibration file: what `dpmhw calibrate` writes and the renderer reads.

One JSON document, versioned (``"format": "dpmhw.projector_calibration", "version": 1``)::

    {
      "format": "dpmhw.projector_calibration", "version": 1,
      "projector": {"width": 1280, "height": 800,
                    "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
                    "dist": [k1, k2, p1, p2, k3]},
      "world_from_projector": {"R": [[...], [...], [...]], "t": [x, y, z], "frame": "camera"},
      "camera": {"width": ..., "height": ..., "K": ..., "dist": ...} | null,
      "projector_from_camera": {"R": ..., "t": ...} | null,
      "stats": {"camera_rms_px": ..., "projector_rms_px": ..., "stereo_rms_px": ...,
                "std": {"projector": {"fx": ..., ...}, "camera": {...}}, ...},
      "views": [{"name": "pose_000", "used": true, "camera_rms_px": ..., "projector_rms_px": ...,
                 "reason": ""}, ...],
      "provenance": {"created": "2026-...Z", "dpmhw": "0.1.0", "opencv": "...", "source": "..."}
    }

The model is OpenCV's pinhole + distortion (same convention as ``cv2.projectPoints``, row 0 at
the top, pixel centres at integer coordinates), metres.  ``world_from_projector`` maps
projector coordinates to the world: ``x_world = R @ x_projector + t``.  ``frame`` says which
world that is: ``"camera"`` (the calibration camera, before tracker registration) or
``"tracker"`` (the motion-capture frame, the one scenes use).  The principal point may lie
outside the image (projector lens shift).
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dpmhw.errors import CalibrationError

FORMAT = "dpmhw.projector_calibration"
VERSION = 1
FRAMES = ("camera", "tracker")


class CalibrationFileError(CalibrationError):
    """A calibration file is missing, unreadable, of another format, or has a bad field."""


@dataclass
class LensModel:
    """A pinhole + distortion device: ``K`` (3, 3) float64, ``dist`` (5,) float64."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray

    def to_dict(self) -> dict:
        return {"width": int(self.width), "height": int(self.height), "K": np.asarray(self.K).tolist(), "dist": np.asarray(self.dist).tolist()}


@dataclass
class ProjectorCalibration:
    """A calibrated projector: intrinsics, distortion and its pose in a world frame.

    width, height : projector resolution (pixels)
    K : (3, 3) float64 intrinsic matrix (cx, cy may lie outside the image)
    dist : (5,) float64 (k1, k2, p1, p2, k3)
    R, t : (3, 3), (3,) float64, world_from_projector
    frame : "camera" or "tracker", the world ``R, t`` refer to
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    frame: str = "camera"
    camera: LensModel | None = None
    projector_from_camera: tuple[np.ndarray, np.ndarray] | None = None
    stats: dict[str, Any] = field(default_factory=dict)
    views: list[dict[str, Any]] = field(default_factory=list)
    provenance: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64)
        self.dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        self.R = np.asarray(self.R, dtype=np.float64)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)

    # -- geometry ---------------------------------------------------------------------------
    @property
    def projector_from_world(self) -> tuple[np.ndarray, np.ndarray]:
        return self.R.T, -self.R.T @ self.t

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """(n, 3) world points -> (n, 2) projector pixels (``cv2.projectPoints`` convention)."""
        import cv2

        Rp, tp = self.projector_from_world
        pts = np.ascontiguousarray(points_world, dtype=np.float64).reshape(-1, 1, 3)
        uv, _ = cv2.projectPoints(pts, cv2.Rodrigues(Rp)[0], tp, self.K, self.dist)
        return uv.reshape(-1, 2)

    # -- files ------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        pfc = None
        if self.projector_from_camera is not None:
            pfc = {"R": np.asarray(self.projector_from_camera[0]).tolist(), "t": np.asarray(self.projector_from_camera[1]).tolist()}
        return {
            "format": FORMAT,
            "version": VERSION,
            "projector": {"width": int(self.width), "height": int(self.height), "K": self.K.tolist(), "dist": self.dist.tolist()},
            "world_from_projector": {"R": self.R.tolist(), "t": self.t.tolist(), "frame": self.frame},
            "camera": self.camera.to_dict() if self.camera is not None else None,
            "projector_from_camera": pfc,
            "stats": _jsonable(self.stats),
            "views": _jsonable(self.views),
            "provenance": _jsonable(self.provenance),
        }

    def save(self, path: str | Path) -> Path:
        """Validate, then write atomically (a temporary file renamed over ``path``).

        A file that fails validation is never written, so a failed run cannot replace a good
        calibration.
        """
        path = Path(path)
        doc = self.to_dict()
        _parse(doc, str(path))  # refuse to write what we could not read back
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "w") as fh:
                fh.write(_dumps(doc))
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path


def load_projector_calibration(path: str | Path) -> ProjectorCalibration:
    """Read and validate a calibration file.

    Raises
    ------
    CalibrationFileError
        naming the file and the field (e.g. ``projector.K``) and what was expected.
    """
    path = Path(path)
    src = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CalibrationFileError(src, "(file)", "no such file; run `dpmhw calibrate procam` to create it") from None
    except UnicodeDecodeError as exc:
        raise CalibrationFileError(src, "(file)", f"not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    except OSError as exc:
        raise CalibrationFileError(src, "(file)", f"cannot read: {exc}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CalibrationFileError(src, "(file)", f"not valid JSON (line {exc.lineno}, column {exc.colno}): {exc.msg}") from None
    return _parse(doc, src)


# -- validation ---------------------------------------------------------------------------------
def _parse(doc: Any, src: str) -> ProjectorCalibration:
    if not isinstance(doc, dict):
        raise CalibrationFileError(src, "(file)", "expected a JSON object at the top level")
    if doc.get("format") != FORMAT:
        raise CalibrationFileError(src, "format", f"expected {FORMAT!r}, got {doc.get('format')!r}")
    version = doc.get("version")
    if version != VERSION:
        raise CalibrationFileError(src, "version", f"this dpmhw reads version {VERSION}, the file has {version!r}")
    proj = _obj(doc, "projector", src)
    lens = _lens(proj, "projector", src)
    pose = _obj(doc, "world_from_projector", src)
    R = _rotation(pose, "world_from_projector.R", src)
    t = _array(pose.get("t"), (3,), "world_from_projector.t", src)
    frame = pose.get("frame", "camera")
    if frame not in FRAMES:
        raise CalibrationFileError(src, "world_from_projector.frame", f"expected one of {FRAMES}, got {frame!r}")
    camera = None
    if doc.get("camera") is not None:
        camera = _lens(_obj(doc, "camera", src), "camera", src)
    pfc = None
    if doc.get("projector_from_camera") is not None:
        p = _obj(doc, "projector_from_camera", src)
        pfc = (_rotation(p, "projector_from_camera.R", src), _array(p.get("t"), (3,), "projector_from_camera.t", src))
    stats = doc.get("stats") or {}
    views = doc.get("views") or []
    prov = doc.get("provenance") or {}
    for name, val, typ in (("stats", stats, dict), ("views", views, list), ("provenance", prov, dict)):
        if not isinstance(val, typ):
            raise CalibrationFileError(src, name, f"expected a JSON {'object' if typ is dict else 'array'}")
    return ProjectorCalibration(
        lens.width, lens.height, lens.K, lens.dist, R, t, frame, camera, pfc, stats, views, prov
    )


def _obj(doc: dict, key: str, src: str) -> dict:
    val = doc.get(key)
    if not isinstance(val, dict):
        raise CalibrationFileError(src, key, "missing or not a JSON object")
    return val


def _lens(d: dict, prefix: str, src: str) -> LensModel:
    size = []
    for key in ("width", "height"):
        v = d.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= 100_000:
            raise CalibrationFileError(src, f"{prefix}.{key}", f"expected a positive integer number of pixels, got {v!r}")
        size.append(v)
    w, h = size
    K = _array(d.get("K"), (3, 3), f"{prefix}.K", src)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (fx > 0 and fy > 0):
        raise CalibrationFileError(src, f"{prefix}.K", f"focal lengths must be positive, got fx={fx}, fy={fy}")
    if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise CalibrationFileError(src, f"{prefix}.K", "expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    if not (-w <= cx <= 2 * w and -h <= cy <= 2 * h):
        raise CalibrationFileError(
            src, f"{prefix}.K", f"principal point ({cx:.1f}, {cy:.1f}) is implausibly far outside the {w}x{h} image"
        )
    dist = _array(d.get("dist"), (5,), f"{prefix}.dist", src)
    if np.abs(dist).max() > 100:
        raise CalibrationFileError(src, f"{prefix}.dist", f"distortion coefficients out of range: {dist.tolist()}")
    return LensModel(w, h, K, dist)


def _array(val: Any, shape: tuple[int, ...], name: str, src: str) -> np.ndarray:
    if val is None:
        raise CalibrationFileError(src, name, f"missing; expected an array of shape {shape}")
    try:
        arr = np.asarray(val, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationFileError(src, name, f"expected numbers in an array of shape {shape}") from None
    if arr.shape != shape:
        raise CalibrationFileError(src, name, f"expected shape {shape}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise CalibrationFileError(src, name, "contains NaN or infinity")
    return arr


def _rotation(d: dict, name: str, src: str) -> np.ndarray:
    R = _array(d.get("R"), (3, 3), name, src)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or not math.isclose(np.linalg.det(R), 1.0, abs_tol=1e-6):
        raise CalibrationFileError(src, name, "not a rotation matrix (expected orthonormal with determinant +1)")
    return R


_NUMBER_LIST = re.compile(r"\[\s+((?:-?[0-9.eE+-]+,\s+)*-?[0-9.eE+-]+)\s+\]")


def _dumps(doc: dict) -> str:
    """Indented JSON with each innermost list of numbers on one line (matrices stay readable)."""
    text = json.dumps(doc, indent=2, allow_nan=False)
    return _NUMBER_LIST.sub(lambda m: "[" + " ".join(m.group(1).split()) + "]", text) + "\n"


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.floating):
        x = float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
