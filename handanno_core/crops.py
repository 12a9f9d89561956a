"""Hand localization without ground truth and normalized 3D-cube crops (DESIGN.md step 2).

Localization (:func:`locate_hand`) finds the nearest sizeable blob inside a depth band (a blob
that stands out in front of its surroundings beats a body part that only curves towards the
camera), takes the centre of mass of its nearest points and refines it with a few mean-shift
steps inside a sphere of ``0.4 * cube_mm`` (this keeps the centre on the hand, where the points
are densest, instead of the forearm). :func:`locate_hands` does this for every frame (the previous centre as a hint), fills
gaps by linear interpolation and smooths over time, never across ``sequence_breaks``.

Crops are a cube of ``cube_mm`` around the centre, projected to an image box and resampled to
``size x size`` pixels (nearest neighbour, so depth edges never blend), with depth normalized to
``(d - z_c) / (cube_mm / 2)`` in ``[-1, 1]``:

- no depth, and everything behind the cube (``d > z_c + cube/2``): ``+1`` (background);
- inside the cube: the normalized depth;
- just in front of the cube (``z_c - cube <= d < z_c - cube/2``): clamped to ``-1``: usually a
  finger pointing at the camera that sticks out of the cube, which should stay foreground;
- far in front (``d < z_c - cube``): ``+1``, treated as background: flying pixels or an unrelated
  occluder, not hand.

Crop geometry (``boxes (N, 4)`` = ``[u_left, v_top, sx, sy]``): crop pixel ``(x, y)`` covers image
pixel ``u = u_left + (x + 0.5) * sx - 0.5``, ``v = v_top + (y + 0.5) * sy - 0.5`` with
``sx = fx * cube_mm / z_c / size`` image px per crop px; the centre's projection maps to crop
``((size - 1) / 2, (size - 1) / 2)``.
"""

from __future__ import annotations

from collections.abc import Sequence as _Seq
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from .camera import CameraIntrinsics
from .datasets.base import BadFrameReport, DepthSequence, FrameError

__all__ = [
    "locate_hand",
    "locate_hands",
    "smooth_centres",
    "crop_boxes",
    "image_to_crop",
    "crop_to_image",
    "crop_depth",
    "compute_crops",
]

#: default metric area (mm^2) below which a blob is speckle/noise rather than a hand (a fist seen
#: edge-on is about 40 x 70 mm).
MIN_HAND_AREA_MM2 = 2500.0
#: a component's "near depth" is where its nearest NEAR_AREA_MM2 of surface are reached.
NEAR_AREA_MM2 = 1000.0
#: score penalty (mm of depth) for a component whose boundary is all smooth continuation.
ISOLATION_PENALTY_MM = 300.0


# ---------------------------------------------------------------------------------------------
# localization
# ---------------------------------------------------------------------------------------------
def _continuation_fraction(
    z: np.ndarray, valid: np.ndarray, labels: np.ndarray, k: int, box: np.ndarray, step_mm: float
) -> float:
    """Fraction of the ring around component ``k`` (image border excluded) where the surface
    continues smoothly (valid depth at most ``step_mm`` behind the adjacent component pixels).

    A hand in front of its surroundings is bounded by depth jumps (to no depth or to a farther
    body): small fraction. A body part that only entered the band because it curves towards the
    camera is bounded mostly by the band's far cut, where the surface continues: large fraction.
    """
    h, w = z.shape
    x0, y0, bw, bh = (int(t) for t in box[:4])
    pad = 3
    xa, ya, xb, yb = (
        max(0, x0 - pad),
        max(0, y0 - pad),
        min(w, x0 + bw + pad),
        min(h, y0 + bh + pad),
    )
    mk = (labels[ya:yb, xa:xb] == k).astype(np.uint8)
    zr = z[ya:yb, xa:xb]
    ker = np.ones((5, 5), np.uint8)
    ring = (cv2.dilate(mk, ker) > 0) & (mk == 0)
    ring[: max(0, 2 - ya)] = False
    ring[:, : max(0, 2 - xa)] = False
    ring[ring.shape[0] - max(0, yb - (h - 2)) :] = False
    ring[:, ring.shape[1] - max(0, xb - (w - 2)) :] = False
    n_ring = int(ring.sum())
    if n_ring == 0:
        return 0.0
    czmax = cv2.dilate(np.where(mk > 0, zr, 0).astype(np.float32), ker)
    cont = ring & valid[ya:yb, xa:xb] & (zr - czmax < step_mm) & (zr > czmax - 5.0)
    return float(cont.sum()) / n_ring


def _exit_pixels(
    z: np.ndarray, valid: np.ndarray, mask: np.ndarray, step_mm: float = 40.0
) -> np.ndarray:
    """Pixels of ``mask`` where the blob is attached to something: within 2 px of the image
    border, or next to a pixel where the surface continues smoothly out of the band (valid, at
    most ``step_mm`` behind). ``(H, W)`` bool."""
    mk = mask.astype(np.uint8)
    ker = np.ones((3, 3), np.uint8)
    czmax = cv2.dilate(np.where(mask, z, 0).astype(np.float32), ker)
    cont = (cv2.dilate(mk, ker) > 0) & ~mask & valid & (z - czmax < step_mm) & (z > czmax - 5.0)
    out = mask & (cv2.dilate(cont.astype(np.uint8), ker) > 0)
    out[:2] |= mask[:2]
    out[-2:] |= mask[-2:]
    out[:, :2] |= mask[:, :2]
    out[:, -2:] |= mask[:, -2:]
    return out


def _choose_component(
    z: np.ndarray,
    valid: np.ndarray,
    d_near: float,
    band_mm: float,
    min_area_mm2: float,
    pix_area_scale: float,
    prev_uvz: np.ndarray | None,
    prev_radius_px: float,
) -> tuple[np.ndarray | None, float]:
    """Components of ``valid & d_near <= z <= d_near + band``; return (mask, nearest depth) of
    the chosen one, or (None, NaN).

    Each sizeable component (metric area >= ``min_area_mm2``) is scored by its near depth (the
    depth at which its nearest 1000 mm^2 of surface are reached, robust to a few flying pixels)
    plus ``ISOLATION_PENALTY_MM`` times its :func:`_continuation_fraction`; the lowest score wins.
    With a previous centre, the sizeable component with the most pixels near its projection wins.
    """
    inband = valid & (z >= d_near) & (z <= d_near + band_mm)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(inband.astype(np.uint8), connectivity=4)
    if n <= 1:
        return None, np.nan
    lab = labels[inband]
    zz = z[inband].astype(np.float64)
    pix_area = zz * zz * pix_area_scale
    area = np.bincount(lab, weights=pix_area, minlength=n)  # mm^2
    ok = area >= min_area_mm2
    ok[0] = False
    if not ok.any():
        return None, np.nan
    cand = np.nonzero(ok)[0]
    # near depth per component: depth where the cumulative area (nearest first) reaches 1000 mm^2
    order = np.lexsort((zz, lab))
    lab_s, z_s, a_s = lab[order], zz[order], np.cumsum(pix_area[order])
    starts = np.searchsorted(lab_s, np.arange(n))
    base = np.where(starts > 0, a_s[np.maximum(starts - 1, 0)], 0.0)
    target = base + np.minimum(NEAR_AREA_MM2, 0.5 * area)
    idx = np.searchsorted(a_s, target)
    near = z_s[np.clip(idx, 0, len(z_s) - 1)]
    zmin = z_s[np.clip(starts, 0, len(z_s) - 1)]  # nearest depth of each component
    if prev_uvz is not None:
        u0, v0, _ = prev_uvz
        rr, cc = np.nonzero(inband)
        close = (cc - u0) ** 2 + (rr - v0) ** 2 <= prev_radius_px**2
        hits = np.bincount(lab[close], minlength=n).astype(np.float64)
        hits[~ok] = 0
        if hits.max() > 0:
            k = int(np.argmax(hits))
            return labels == k, float(zmin[k])
    if len(cand) == 1:
        k = int(cand[0])
        return labels == k, float(zmin[k])
    score = np.array(
        [
            near[k]
            + ISOLATION_PENALTY_MM * _continuation_fraction(z, valid, labels, k, stats[k], 40.0)
            for k in cand
        ]
    )
    k = int(cand[np.argmin(score)])
    return labels == k, float(zmin[k])


def locate_hand(
    depth: np.ndarray,
    camera: CameraIntrinsics,
    *,
    min_depth_mm: float = 150.0,
    max_depth_mm: float = 1500.0,
    band_mm: float = 150.0,
    min_area_mm2: float = MIN_HAND_AREA_MM2,
    cube_mm: float = 220.0,
    prev_centre_mm: np.ndarray | None = None,
    mean_shift_iters: int = 8,
    front_mm: float = 40.0,
    radius_mm: float | None = None,
) -> np.ndarray:
    """Centre of the hand ``(3,)`` mm in the camera frame, or all-NaN if no hand-sized blob.

    ``depth``: ``(H, W)`` mm, 0 = invalid. Steps: 5x5 median filter (removes flying pixels and
    speckle); nearest valid depth ``d_near`` (0.5th percentile); connected components (4-connected)
    of the pixels in ``[d_near, d_near + band_mm]``; the nearest component whose metric area
    (sum of ``(z/fx)(z/fy)`` over its pixels) is at least ``min_area_mm2``; if that component
    starts well behind ``d_near`` (the near pixels were noise) the band is re-anchored at it.
    Centre = centre of mass of the component's points within ``front_mm`` of its nearest depth,
    then ``mean_shift_iters`` mean-shift steps over the component's points within a sphere of
    radius ``radius_mm`` (default ``0.4 * cube_mm``): the shift climbs to the densest nearby
    surface (palm + fingers) and does not run down the forearm the way a plain centre of mass
    of the whole blob does.

    ``prev_centre_mm`` (3,): the previous frame's centre; if given (and finite), the component
    with the most pixels within ``cube_mm / 2`` of its projection is preferred (the start of the
    mean shift is chosen as without a hint: starting from the previous centre lets the centre
    drift down the arm frame after frame).
    """
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    nan3 = np.full(3, np.nan)
    z = cv2.medianBlur(depth, 5)
    valid = (z >= min_depth_mm) & (z <= max_depth_mm) & (depth > 0)
    if not valid.any():
        return nan3
    pix_area_scale = 1.0 / (camera.fx * camera.fy)

    prev_uvz = None
    prev_radius_px = 0.0
    if prev_centre_mm is not None:
        p = np.asarray(prev_centre_mm, dtype=np.float64)
        if np.all(np.isfinite(p)) and p[2] > 0:
            uv = camera.project(p)
            prev_uvz = np.array([uv[0], uv[1], p[2]])
            prev_radius_px = camera.fx * 0.5 * cube_mm / p[2]

    zv = z[valid]
    k = max(0, int(0.005 * zv.size) - 1)
    d_near = float(np.partition(zv, k)[k]) - 20.0  # include the few pixels in front of it
    mask = None
    for _ in range(4):
        mask, d_comp = _choose_component(
            z, valid, d_near, band_mm, min_area_mm2, pix_area_scale, prev_uvz, prev_radius_px
        )
        if mask is None:
            # nothing sizeable in this band: move the band past it
            farther = zv[zv > d_near + band_mm]
            if farther.size == 0:
                return nan3
            k = max(0, int(0.005 * farther.size) - 1)
            d_near = float(np.partition(farther, k)[k]) - 20.0
            continue
        if d_comp - d_near > 0.2 * band_mm:
            # the band was anchored on noise in front of the blob: re-anchor on the blob
            d_near = d_comp - 10.0
            continue
        break
    if mask is None:
        return nan3

    rows, cols = np.nonzero(mask)
    zc = z[rows, cols].astype(np.float64)
    pts = camera.backproject(np.stack([cols, rows], axis=-1).astype(np.float64), zc)
    exits = _exit_pixels(z, valid, mask)[rows, cols]
    if exits.sum() >= max(8, 0.002 * len(rows)):
        # the blob is attached to something (an arm leaving the image or the band): the hand is
        # its free end, so start from the points farthest from where it is attached
        dist = np.linalg.norm(pts - pts[exits].mean(axis=0), axis=1)
        centre = pts[dist >= np.percentile(dist, 98)].mean(axis=0)
    else:
        front = zc <= zc.min() + front_mm
        centre = pts[front].mean(axis=0)
    r2 = (0.4 * cube_mm if radius_mm is None else radius_mm) ** 2
    for _ in range(mean_shift_iters):
        inside = np.sum((pts - centre) ** 2, axis=1) <= r2
        if not inside.any():
            break
        new = pts[inside].mean(axis=0)
        if np.sum((new - centre) ** 2) < 0.25:
            centre = new
            break
        centre = new
    return centre


def _segments(n: int, breaks: _Seq[int] | None) -> list[tuple[int, int]]:
    cuts = sorted({int(b) for b in (breaks or []) if 0 < int(b) < n})
    edges = [0, *cuts, n]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def smooth_centres(
    centres_mm: np.ndarray,
    sequence_breaks: _Seq[int] | None = None,
    *,
    median_frames: int = 5,
    sigma_frames: float = 1.0,
    smooth: bool = True,
) -> np.ndarray:
    """Fill NaN gaps by linear interpolation (constant at segment ends) and smooth over time.

    ``centres_mm``: ``(N, 3)``; rows with any NaN are missing. Each segment between
    ``sequence_breaks`` is processed on its own: a running median of ``median_frames`` (removes
    single-frame outliers), then a Gaussian of ``sigma_frames``. A segment with no valid row stays
    NaN. Returns a new ``(N, 3)`` float64 array.
    """
    c = np.array(centres_mm, dtype=np.float64, copy=True)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centres must be (N, 3), got {c.shape}")
    out = np.full_like(c, np.nan)
    for a, b in _segments(len(c), sequence_breaks):
        seg = c[a:b]
        ok = np.all(np.isfinite(seg), axis=1)
        if not ok.any():
            continue
        t = np.arange(b - a)
        filled = np.stack([np.interp(t, t[ok], seg[ok, j]) for j in range(3)], axis=1)
        if smooth and len(filled) > 2:
            m = min(median_frames, len(filled) if len(filled) % 2 else len(filled) - 1)
            if m >= 3:
                filled = ndimage.median_filter(filled, size=(m, 1), mode="nearest")
            if sigma_frames > 0:
                filled = ndimage.gaussian_filter1d(filled, sigma_frames, axis=0, mode="nearest")
        out[a:b] = filled
    return out


def locate_hands(
    sequence: DepthSequence,
    report: BadFrameReport | None = None,
    smooth: bool = True,
    cube_mm: float = 220.0,
    progress: bool = False,
    **locate_kwargs,
) -> np.ndarray:
    """Hand centres ``(N, 3)`` mm for every frame of ``sequence``.

    Each frame is located with :func:`locate_hand` using the previous frame's centre (within the
    same segment) as a hint; frames without a hand and bad frames (``FrameError``, recorded in
    ``report``; raised if ``report`` is None) are NaN before gap filling. Then
    :func:`smooth_centres` interpolates gaps and (if ``smooth``) smooths, cut at
    ``sequence.sequence_breaks``. Rows stay NaN only in segments where no frame had a hand.
    """
    n = len(sequence)
    raw = np.full((n, 3), np.nan)
    breaks = set(int(b) for b in sequence.sequence_breaks)
    prev = None
    it = sequence.iter_depth(range(n), report=report)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, total=n, desc="locating hand", unit="frame")
    last = -2
    for i, depth in it:
        if i in breaks or i != last + 1:
            prev = None  # new segment, or the previous frame was bad
        c = locate_hand(
            depth, sequence.camera, cube_mm=cube_mm, prev_centre_mm=prev, **locate_kwargs
        )
        if np.all(np.isfinite(c)) and prev is not None and np.linalg.norm(c - prev) > cube_mm:
            # the hint led astray or the hand jumped: retry without it
            c = locate_hand(depth, sequence.camera, cube_mm=cube_mm, **locate_kwargs)
        raw[i] = c
        prev = c if np.all(np.isfinite(c)) else None
        last = i
    return smooth_centres(raw, sorted(breaks), smooth=smooth)


# ---------------------------------------------------------------------------------------------
# crop geometry
# ---------------------------------------------------------------------------------------------
def crop_boxes(
    centres_mm: np.ndarray, camera: CameraIntrinsics, cube_mm: float = 220.0, size: int = 128
) -> np.ndarray:
    """Image boxes ``(..., 4)`` float64 ``[u_left, v_top, sx, sy]`` for centres ``(..., 3)`` mm.

    ``sx = fx * cube_mm / z_c / size`` (image px per crop px), box centred on the projection of
    the centre. NaN centres give NaN boxes.
    """
    c = np.asarray(centres_mm, dtype=np.float64)
    uv = camera.project(c)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(c[..., 2] > 0, c[..., 2], np.nan)
        sx = camera.fx * cube_mm / z / size
        sy = camera.fy * cube_mm / z / size
    u_left = uv[..., 0] + 0.5 - 0.5 * size * sx
    v_top = uv[..., 1] + 0.5 - 0.5 * size * sy
    return np.stack([u_left, v_top, sx, sy], axis=-1)


def crop_to_image(xy: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Crop pixels ``(..., 2)`` -> image pixels ``(..., 2)`` for boxes ``(..., 4)`` (broadcast)."""
    xy = np.asarray(xy, dtype=np.float64)
    b = np.asarray(boxes, dtype=np.float64)
    u = b[..., 0] + (xy[..., 0] + 0.5) * b[..., 2] - 0.5
    v = b[..., 1] + (xy[..., 1] + 0.5) * b[..., 3] - 0.5
    return np.stack([u, v], axis=-1)


def image_to_crop(uv: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Image pixels ``(..., 2)`` -> crop pixels ``(..., 2)``; exact inverse of :func:`crop_to_image`."""
    uv = np.asarray(uv, dtype=np.float64)
    b = np.asarray(boxes, dtype=np.float64)
    x = (uv[..., 0] - b[..., 0] + 0.5) / b[..., 2] - 0.5
    y = (uv[..., 1] - b[..., 1] + 0.5) / b[..., 3] - 0.5
    return np.stack([x, y], axis=-1)


def crop_depth(
    depth: np.ndarray,
    camera: CameraIntrinsics,
    centre_mm: np.ndarray,
    cube_mm: float = 220.0,
    size: int = 128,
) -> np.ndarray:
    """Normalized ``(size, size)`` float32 crop of ``depth (H, W)`` mm around ``centre_mm (3,)``.

    Nearest-neighbour resampling of the box from :func:`crop_boxes` (outside the image = no
    depth), then ``(d - z_c) / (cube_mm / 2)`` with the background rules in the module docstring
    (no depth / behind / far in front = +1, just in front = -1). A NaN centre gives all +1.
    """
    c = np.asarray(centre_mm, dtype=np.float64)
    if not np.all(np.isfinite(c)) or c[2] <= 0:
        return np.ones((size, size), np.float32)
    u_left, v_top, sx, sy = crop_boxes(c, camera, cube_mm, size)
    # dst (x, y) -> src (u, v) = (sx * x + u0, sy * y + v0)
    m = np.array(
        [[sx, 0.0, u_left + 0.5 * sx - 0.5], [0.0, sy, v_top + 0.5 * sy - 0.5]], dtype=np.float64
    )
    d = cv2.warpAffine(
        np.asarray(depth, dtype=np.float32),
        m,
        (size, size),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    half = 0.5 * cube_mm
    zc = float(c[2])
    out = np.clip((d - zc) / half, -1.0, 1.0).astype(np.float32)
    background = (d <= 0) | (d > zc + half) | (d < zc - 2.0 * half)
    out[background] = 1.0
    return out


def compute_crops(
    sequence: DepthSequence,
    centres_mm: np.ndarray,
    out_path: str | Path | None = None,
    cube_mm: float = 220.0,
    size: int = 128,
    report: BadFrameReport | None = None,
    progress: bool = False,
    chunk_frames: int = 256,
) -> np.ndarray:
    """Normalized crops ``(N, size, size)`` float16 for every frame (see :func:`crop_depth`).

    With ``out_path`` the crops are written to a ``.npy`` file chunk by chunk (a fresh writable
    mapping of ``chunk_frames`` frames at a time, flushed and dropped, so resident memory stays
    flat however long the sequence) and returned as ``np.load(out_path, mmap_mode="r")``. Without
    it an in-memory array is returned. Bad frames (``FrameError``, recorded in ``report``; raised
    if ``report`` is None) and NaN centres stay all +1.
    """
    n = len(sequence)
    centres = np.asarray(centres_mm, dtype=np.float64)
    if centres.shape != (n, 3):
        raise ValueError(f"centres must be ({n}, 3), got {centres.shape}")
    frame_shape = (size, size)
    if out_path is None:
        out = np.ones((n, *frame_shape), np.float16)
        target = out
        offset = None
    else:
        out_path = Path(out_path)
        out_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = out_path.with_name(out_path.name + ".tmp.npy")
        header = np.lib.format.open_memmap(
            tmp, mode="w+", dtype=np.float16, shape=(n, *frame_shape)
        )
        offset = int(header.offset)
        del header
        target = None
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, desc="cropping", unit="frame")
    frame_bytes = size * size * 2
    for a in range(0, n, chunk_frames):
        b = min(n, a + chunk_frames)
        if out_path is not None:
            target = np.memmap(
                tmp,
                dtype=np.float16,
                mode="r+",
                offset=offset + a * frame_bytes,
                shape=(b - a, *frame_shape),
            )
            base = a
        else:
            base = 0
        buf = np.ones((b - a, *frame_shape), np.float16)
        for i in range(a, b):
            if not np.all(np.isfinite(centres[i])):
                continue
            try:
                depth = sequence.depth(i)
            except FrameError as err:
                if report is None:
                    raise
                report.errors.append(err)
                continue
            buf[i - a] = crop_depth(depth, sequence.camera, centres[i], cube_mm, size)
        target[a - base : b - base] = buf
        if out_path is not None:
            target.flush()
            del target
            target = None
        if bar is not None:
            bar.update(b - a)
    if bar is not None:
        bar.close()
    if out_path is None:
        return out
    tmp.replace(out_path)
    return np.load(out_path, mmap_mode="r")
