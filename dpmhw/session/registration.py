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

import cv2
import numpy as np

from dpmhw.render.cameras import PinholeCamera
from dpmhw.transforms import Pose

__all__ = ["RegistrationError", "registration_error", "silhouette"]

_SHIFT = 4  # fixed-point bits for cv2.fillPoly: sub-pixel vertex positions


def silhouette(camera: PinholeCamera, vertices: np.ndarray, faces: np.ndarray, pose: Pose,
               window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """(H, W) bool: pixels covered by the mesh at `pose` (object→world) seen by `camera`; with
    `window` (y0, y1, x0, x1) only that part of the image (the same pixels, cropped)."""
    px, in_front = camera.project(pose.apply(vertices))
    keep = in_front[faces].all(axis=1)
    y0, y1, x0, x1 = window if window is not None else (0, camera.height, 0, camera.width)
    tri = np.round((px[faces[keep]] - (x0, y0)) * (1 << _SHIFT)).astype(np.int32)
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    if len(tri):
        cv2.fillPoly(mask, tri, 1, lineType=cv2.LINE_8, shift=_SHIFT)
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
    a = _outline(silhouette(camera, vertices, faces, shown, window))
    b = _outline(silhouette(camera, vertices, faces, true, window))
    if not a.any() or not b.any():
        return RegistrationError(float("inf"), float("inf"), vertex)
    # distance of every pixel to the nearest outline pixel of the other silhouette
    dist_to_b = cv2.distanceTransform((~b).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    dist_to_a = cv2.distanceTransform((~a).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d = np.concatenate([dist_to_b[a], dist_to_a[b]])
    return RegistrationError(float(d.mean()), float(d.max()), vertex)
