"""Registration error: how far the projected picture is from where the object really is.

For a presented frame we know the pose it was rendered with (measured or predicted) and, in a
simulated world, the object's true pose at the instant the frame was lit. Both silhouettes are
rasterised from the object's mesh with the projector's camera; the error is measured between
their outlines, in projector pixels:

- `mean_px`: symmetric mean boundary distance — every outline pixel of one silhouette, distance
  to the nearest outline pixel of the other, averaged over both outlines;
- `max_px`: the largest of those distances (Hausdorff distance of the outlines);
- `vertex_px`: mean image displacement of the mesh's vertices (ignores the outline's shape).
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import cv2
import numba as nb
import numpy as np

from dpmhw.render.cameras import PinholeCamera
from dpmhw.transforms import Pose

__all__ = ["RegistrationError", "registration_error", "silhouette"]


@nb.njit(cache=True, nogil=True)
def _fill_faces(px, front, faces, x0, y0, mask):
    """Set every pixel of `mask` (the image part whose top-left pixel is (x0, y0)) whose centre
    (x + ½, y + ½) lies inside or on a face whose three vertices are in front of the camera
    (`px`: the vertices' pixel coordinates; either winding): the union of the faces, each
    visiting only its bounding box."""
    H, W = mask.shape
    for k in range(faces.shape[0]):
        i0, i1, i2 = faces[k, 0], faces[k, 1], faces[k, 2]
        if not (front[i0] and front[i1] and front[i2]):
            continue
        x0_, y0_, x1, y1 = px[i0, 0] - x0, px[i0, 1] - y0, px[i1, 0] - x0, px[i1, 1] - y0
        x2, y2 = px[i2, 0] - x0, px[i2, 1] - y0
        area = (x1 - x0_) * (y2 - y0_) - (x2 - x0_) * (y1 - y0_)
        if area == 0.0:
            continue
        s = 1.0 if area > 0 else -1.0
        lo_x = max(int(math.floor(min(x0_, x1, x2) - 0.5)), 0)
        hi_x = min(int(math.ceil(max(x0_, x1, x2) - 0.5)), W - 1)
        lo_y = max(int(math.floor(min(y0_, y1, y2) - 0.5)), 0)
        hi_y = min(int(math.ceil(max(y0_, y1, y2) - 0.5)), H - 1)
        for y in range(lo_y, hi_y + 1):
            py = y + 0.5
            for x in range(lo_x, hi_x + 1):
                px_ = x + 0.5
                e0 = s * ((x1 - x0_) * (py - y0_) - (y1 - y0_) * (px_ - x0_))
                e1 = s * ((x2 - x1) * (py - y1) - (y2 - y1) * (px_ - x1))
                e2 = s * ((x0_ - x2) * (py - y2) - (y0_ - y2) * (px_ - x2))
                if e0 >= 0.0 and e1 >= 0.0 and e2 >= 0.0:
                    mask[y, x] = 1


def silhouette(camera: PinholeCamera, vertices: np.ndarray, faces: np.ndarray, pose: Pose,
               window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """(H, W) bool: pixels (by their centres) covered by the mesh at `pose` (object→world) seen by
    `camera`; with `window` (y0, y1, x0, x1) only that part of the image (the same pixels, cropped)."""
    px, in_front = camera.project(pose.apply(vertices))
    return _silhouette_px(camera, px, in_front, faces, window)


def _silhouette_px(camera, px, in_front, faces, window) -> np.ndarray:
    y0, y1, x0, x1 = window if window is not None else (0, camera.height, 0, camera.width)
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    _fill_faces(np.ascontiguousarray(px, np.float64), np.ascontiguousarray(in_front, np.bool_),
                np.ascontiguousarray(faces, np.int64), float(x0), float(y0), mask)
    return mask.astype(bool)


def _outline(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the outer outline of the silhouette (rasterisation pinholes between
    triangles would otherwise count as outline)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    out = np.zeros(mask.shape, np.uint8)
    cv2.drawContours(out, contours, -1, 1, 1)
    return out.astype(bool)


@dataclass(frozen=True)
class RegistrationError:
    mean_px: float
    max_px: float
    vertex_px: float


def _window(camera: PinholeCamera, *pixels: np.ndarray, margin: int = 4) -> tuple[int, int, int, int]:
    """The image part holding every projected vertex plus a margin (clipped to the image): the
    silhouettes, their outlines and distances there are those of the whole image."""
    p = np.concatenate(pixels)
    p = p[np.all(np.isfinite(p), axis=1)]
    if not len(p):
        return 0, camera.height, 0, camera.width
    x0, y0 = np.floor(p.min(axis=0)).astype(int) - margin
    x1, y1 = np.ceil(p.max(axis=0)).astype(int) + margin + 1
    return max(0, y0), min(camera.height, max(y1, 1)), max(0, x0), min(camera.width, max(x1, 1))


def registration_error(camera: PinholeCamera, vertices: np.ndarray, faces: np.ndarray,
                       shown: Pose, true: Pose) -> RegistrationError:
    """Outline distance between the silhouette at `shown` and at `true` (see module doc), over the
    image part both lie in."""
    px_a, front_a = camera.project(shown.apply(vertices))
    px_b, front_b = camera.project(true.apply(vertices))
    vertex = float(np.linalg.norm(px_a - px_b, axis=1).mean())
    window = _window(camera, px_a[front_a], px_b[front_b])
    if window[1] <= window[0] or window[3] <= window[2]:
        return RegistrationError(float("inf"), float("inf"), vertex)
    a = _outline(_silhouette_px(camera, px_a, front_a, faces, window))
    b = _outline(_silhouette_px(camera, px_b, front_b, faces, window))
    if not a.any() or not b.any():
        return RegistrationError(float("inf"), float("inf"), vertex)
    # distance of every pixel to the nearest outline pixel of the other silhouette
    dist_to_b = cv2.distanceTransform((~b).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    dist_to_a = cv2.distanceTransform((~a).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d = np.concatenate([dist_to_b[a], dist_to_a[b]])
    return RegistrationError(float(d.mean()), float(d.max()), vertex)
