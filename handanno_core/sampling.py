"""Reading depth maps and images at sub-pixel points: the one depth lookup, the one visibility rule
and the one bilinear sampler of the engine.

* :func:`depth_at` - observed depth ``D`` (mm) under 2D points: the closest valid surface in the
  ``(2 near_px + 1)^2`` block around the rounded pixel, else the nearest valid pixel within
  ``window`` px (lift's observed depth, propagation's per-frame depth read).
* :func:`visible_by_depth` - **the** visibility rule (simulated annotator, export, review seeding):
  a joint at ``X = (x, y, z)`` mm is visible when its rounded projection lies on the image and the
  closest valid surface ``D`` in the 3x3 pixels around it satisfies
  ``D >= z - o - VISIBILITY_MARGIN_MM`` (``o`` the joint's surface offset: nothing is much closer to
  the camera than the joint's own surface). No valid depth in the 3x3 block -> not visible.
  The 3x3 minimum makes the test robust to sensor dropout at silhouette edges.
* :func:`bilinear` / :func:`bilinear_gradient` - bilinear samples of an image ``(H, W)`` or of
  frame ``frame`` of a stack ``(N, H, W)`` (a memmap stays on disk), border replicated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import CameraIntrinsics

__all__ = [
    "VISIBILITY_MARGIN_MM",
    "Bilinear",
    "bilinear",
    "bilinear_gradient",
    "depth_at",
    "visible_by_depth",
]

#: a joint whose surface ``z - o`` is more than this behind the observed depth is occluded (mm)
VISIBILITY_MARGIN_MM = 10.0


def depth_at(
    depth_mm: np.ndarray,
    uv_px: np.ndarray,
    *,
    window: int = 3,
    near_px: int = 1,
    front_band_mm: float | None = None,
) -> np.ndarray:
    """Observed depth ``(P,)`` mm under 2D points ``uv_px (P, 2)`` px of a depth map ``(H, W)``.

    The closest valid surface (finite, > 0) in the ``(2 near_px + 1)^2`` block around the rounded
    point (that block counts as distance 0: ``near_px=1`` is 3x3; ``2`` tolerates points a pixel or
    two off a thin finger, which would otherwise read the surface behind it); if none, the nearest
    valid pixel within ``window`` px (Euclidean; among equally near pixels the closer surface).
    ``near_px=0`` is plain "nearest valid pixel". NaN where none or where the point is not finite.

    ``front_band_mm``: instead of the closest pixel of the block, the median of the block's valid
    pixels within that many mm behind the closest one (the front surface without the background
    behind a finger's edge). The closest of 9 noisy readings lies about 1.5 sensor noise SDs in
    front of the surface; the median of the front surface does not (sensor noise differs between
    sensors, so a constant cannot absorb that bias).
    """
    depth = np.asarray(depth_mm)
    h, w = depth.shape
    uv = np.asarray(uv_px, dtype=np.float64)
    out = np.full(len(uv), np.nan)
    ok = np.all(np.isfinite(uv), axis=1)
    if not np.any(ok):
        return out
    window = max(window, near_px)
    r = np.arange(-window, window + 1)
    dv, du = np.meshgrid(r, r, indexing="ij")
    dist2 = (du**2 + dv**2).ravel().astype(np.float64)
    uu = np.rint(uv[ok, 0]).astype(np.int64)[:, None] + du.ravel()[None, :]
    vv = np.rint(uv[ok, 1]).astype(np.int64)[:, None] + dv.ravel()[None, :]
    inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
    vals = np.zeros(uu.shape, dtype=np.float64)
    vals[inside] = depth[vv[inside], uu[inside]]
    valid = inside & np.isfinite(vals) & (vals > 0)
    cheb = np.maximum(np.abs(du), np.abs(dv)).ravel()
    ring = np.where(cheb <= near_px, 0.0, dist2)
    # nearest first, then the closer surface: depths (< 1e6 mm) only break distance ties
    key = np.where(valid, ring[None, :] * 1e6 + vals, np.inf)
    best = np.argmin(key, axis=1)
    rows = np.arange(len(best))
    found = np.isfinite(key[rows, best])
    picked = vals[rows, best]
    if front_band_mm is not None:
        block = valid & (ring[None, :] == 0)
        front = block & (vals <= picked[:, None] + front_band_mm)
        use = block[rows, best] & front.any(axis=1)
        if np.any(use):
            picked = picked.copy()
            picked[use] = np.nanmedian(np.where(front[use], vals[use], np.nan), axis=1)
    out[np.flatnonzero(ok)] = np.where(found, picked, np.nan)
    return out


def visible_by_depth(
    joints_mm: np.ndarray,
    depth_mm: np.ndarray,
    camera: CameraIntrinsics,
    offsets_mm: np.ndarray | float = 0.0,
    margin_mm: float = VISIBILITY_MARGIN_MM,
) -> np.ndarray:
    """Visibility ``(J,)`` bool of joints ``(J, 3)`` mm (camera frame) in a depth map ``(H, W)`` mm.

    Visible iff the rounded projection is on the image and the closest valid depth ``D`` in the 3x3
    pixels around it satisfies ``D >= z - offsets_mm - margin_mm`` (``offsets_mm`` scalar or
    ``(J,)``, the skeleton's surface offsets). Non-finite joints are not visible.
    """
    x = np.asarray(joints_mm, dtype=np.float64)
    uv = camera.project(x)
    col, row = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    h, w = np.shape(depth_mm)
    with np.errstate(invalid="ignore"):
        inside = np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col < w) & (row >= 0)
        inside &= row < h
    d = depth_at(depth_mm, np.where(inside[:, None], uv, np.nan), window=1, near_px=1)
    offsets = np.asarray(offsets_mm, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return inside & np.isfinite(d) & (d >= x[:, 2] - offsets - margin_mm)


@dataclass(frozen=True)
class Bilinear:
    """Bilinear samples with the interpolant's gradient and the range of the four neighbours.

    All arrays have the points' shape. ``dx``/``dy``: derivative of the interpolant along x/y (per
    px); ``lo``/``hi``: the smallest/largest of the four neighbouring pixels (e.g. to tell whether
    all of them are foreground)."""

    value: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def _corners(image: np.ndarray, x: np.ndarray, y: np.ndarray, frame, dtype):
    """The four neighbours ``c00, c01, c10, c11`` and fractions ``fx, fy`` (border replicated)."""
    img = np.asarray(image)
    h, w = img.shape[-2:]
    flat = img.reshape(-1)  # a view for contiguous arrays and memmaps
    xc = np.clip(np.nan_to_num(np.asarray(x, dtype=np.float64)), 0.0, w - 1)
    yc = np.clip(np.nan_to_num(np.asarray(y, dtype=np.float64)), 0.0, h - 1)
    x0 = np.minimum(xc.astype(np.int64), w - 2)
    y0 = np.minimum(yc.astype(np.int64), h - 2)
    fx = (xc - x0).astype(dtype)
    fy = (yc - y0).astype(dtype)
    i00 = y0 * w + x0
    if frame is not None:
        i00 = i00 + np.asarray(frame, dtype=np.int64) * (h * w)
    c00 = flat[i00].astype(dtype)
    c01 = flat[i00 + 1].astype(dtype)
    c10 = flat[i00 + w].astype(dtype)
    c11 = flat[i00 + w + 1].astype(dtype)
    return c00, c01, c10, c11, fx, fy


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray, *, frame=None, dtype=np.float64):
    """Bilinear samples (shape of ``x``) of ``image (H, W)``, or of ``image[frame] (N, H, W)`` with
    ``frame`` an integer array broadcasting against ``x``, at px ``(x, y)``.

    Points off the image read the border (replicated); non-finite coordinates read pixel 0.
    Computed in ``dtype`` (float32 halves the memory of large batches)."""
    c00, c01, c10, c11, fx, fy = _corners(image, x, y, frame, dtype)
    top = c00 + fx * (c01 - c00)
    bot = c10 + fx * (c11 - c10)
    return top + fy * (bot - top)


def bilinear_gradient(
    image: np.ndarray, x: np.ndarray, y: np.ndarray, *, frame=None, dtype=np.float64
) -> Bilinear:
    """As :func:`bilinear`, with the interpolant's gradient and the neighbours' range."""
    c00, c01, c10, c11, fx, fy = _corners(image, x, y, frame, dtype)
    top = c00 + fx * (c01 - c00)
    bot = c10 + fx * (c11 - c10)
    return Bilinear(
        value=top + fy * (bot - top),
        dx=(1 - fy) * (c01 - c00) + fy * (c11 - c10),
        dy=(1 - fx) * (c10 - c00) + fx * (c11 - c01),
        lo=np.minimum(np.minimum(c00, c01), np.minimum(c10, c11)),
        hi=np.maximum(np.maximum(c00, c01), np.maximum(c10, c11)),
    )
