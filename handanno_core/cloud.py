"""A clean point cloud of the hand: no flying pixels, no forearm past the wrist.

Two filters on hand points ``(M, 3)`` mm (camera frame) taken from one depth map:

- **Flying pixels** (:func:`flying_pixel_mask`): a time-of-flight / structured-light sensor
  reports, along depth edges, pixels between the foreground and what is behind it. On the image
  grid (the points are projected back to their pixels, so any subset of a depth map works) a
  point is kept when at least ``min_neighbours`` of its 8 neighbouring points lie on the same
  surface (depth within ``max(jump_mm, jump_px * z / fx)``), or ``min_edge_neighbours`` if a
  neighbour is nearer by more than that (the far side of a depth edge, where flying pixels
  trail behind a finger); a flying pixel has few neighbours on any one surface.
- **Forearm cut** (:func:`wrist_plane`, :func:`beyond_wrist_mask`): once the wrist is placed or
  estimated, the plane through it whose normal points from the wrist to the palm (the mean of
  the root's children, e.g. the four MCPs and the thumb base in MSRA-21); points more than
  ``margin_mm`` behind it are forearm.

:func:`clean_hand_cloud` applies both and optionally colours the kept points by depth.
"""

from __future__ import annotations

import numpy as np

from .camera import CameraIntrinsics
from .skeleton import Skeleton

__all__ = ["beyond_wrist_mask", "clean_hand_cloud", "flying_pixel_mask", "wrist_plane"]

#: neighbouring pixels within this depth difference (mm) are on one surface ...
JUMP_MM = 8.0
#: ... or within this many pixel footprints (z / fx mm each; a steep surface).
JUMP_PX = 6.0
#: points behind the wrist plane by more than this (mm) are forearm.
WRIST_MARGIN_MM = 10.0


def flying_pixel_mask(
    points_mm: np.ndarray,
    camera: CameraIntrinsics,
    *,
    jump_mm: float = JUMP_MM,
    jump_px: float = JUMP_PX,
    min_neighbours: int = 2,
    min_edge_neighbours: int = 5,
) -> np.ndarray:
    """``(M,)`` bool: True for flying pixels among ``points_mm`` ``(M, 3)`` (see module docstring).

    Points are put back on their pixels (rounded projection; of two points on one pixel the
    nearer one counts as the pixel's depth); points off the image are never flying.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    m = len(pts)
    if m == 0:
        return np.zeros(0, bool)
    h, w = camera.height, camera.width
    uv = np.rint(camera.project(pts))
    ok = np.all(np.isfinite(uv), axis=1)
    u = np.where(ok, uv[:, 0], -1).astype(np.int64)
    v = np.where(ok, uv[:, 1], -1).astype(np.int64)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    z = pts[:, 2]
    grid = np.full((h + 2, w + 2), np.inf)
    np.minimum.at(grid, (v[ok] + 1, u[ok] + 1), z[ok])
    tol = np.maximum(jump_mm, jump_px * z / camera.fx)
    same = np.zeros(m, np.int64)
    vi, ui = v[ok] + 1, u[ok] + 1
    zi, ti = z[ok], tol[ok]
    count = np.zeros(int(ok.sum()), np.int64)
    behind = np.zeros(int(ok.sum()), bool)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            if dv == 0 and du == 0:
                continue
            zn = grid[vi + dv, ui + du]
            count += np.abs(zn - zi) <= ti
            behind |= zn < zi - ti
    same[ok] = count
    edge = np.zeros(m, bool)
    edge[ok] = behind
    # isolated, or a thin trail (few same-surface neighbours) behind a nearer edge
    return ok & ((same < min_neighbours) | (edge & (same < min_edge_neighbours)))


def wrist_plane(joints_mm: np.ndarray, skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray] | None:
    """``(point (3,), unit normal (3,))`` of the wrist plane from joints ``(J, 3)`` mm: through
    the root joint, normal towards the mean of its children. None if those joints are missing."""
    j = np.asarray(joints_mm, dtype=np.float64)
    parents = np.asarray(skeleton.parent_array)
    roots = np.flatnonzero(parents < 0)
    if len(roots) != 1:
        return None
    root = int(roots[0])
    children = np.flatnonzero(parents == root)
    if len(children) == 0 or not np.all(np.isfinite(j[[root, *children]])):
        return None
    n = j[children].mean(axis=0) - j[root]
    length = np.linalg.norm(n)
    if length < 1e-6:
        return None
    return j[root].copy(), n / length


def beyond_wrist_mask(
    points_mm: np.ndarray,
    plane: tuple[np.ndarray, np.ndarray],
    margin_mm: float = WRIST_MARGIN_MM,
) -> np.ndarray:
    """``(M,)`` bool: points more than ``margin_mm`` behind the wrist ``plane`` (forearm)."""
    point, normal = plane
    return (np.asarray(points_mm, dtype=np.float64) - point) @ normal < -margin_mm


def clean_hand_cloud(
    points_mm: np.ndarray,
    camera: CameraIntrinsics,
    *,
    joints_mm: np.ndarray | None = None,
    skeleton: Skeleton | None = None,
    margin_mm: float = WRIST_MARGIN_MM,
    colour_by_depth: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Hand points without flying pixels and, if ``joints_mm`` ``(J, 3)`` (with ``skeleton``)
    place the wrist, without forearm past the wrist plane.

    Returns ``(keep (M,) bool, t (K,) float or None)``: ``t`` (with ``colour_by_depth``) is the
    kept points' depth scaled to [0, 1] over their own range (0 = nearest), for a colour map.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    keep = ~flying_pixel_mask(pts, camera)
    if joints_mm is not None and skeleton is not None:
        plane = wrist_plane(joints_mm, skeleton)
        if plane is not None:
            keep &= ~beyond_wrist_mask(pts, plane, margin_mm)
    t = None
    if colour_by_depth:
        z = pts[keep, 2]
        t = (z - z.min()) / max(float(np.ptp(z)), 1e-6) if len(z) else np.zeros(0)
    return keep, t
