"""Dense alignment of two normalized depth crops: SIFT Flow, DIS optical flow and NCC matching.

All flows follow one convention: ``flow[y, x] = (dx, dy)`` in pixels such that
``reference(x, y) ~ moving(x + dx, y + dy)``. Pixel centres are at integer coordinates (see
DESIGN.md). Crops are ``(H, W)`` float arrays, typically the normalized depth crops of
:mod:`handanno_core.crops` (values in [-1, 1], background +1).

* :func:`sift_flow` -- SIFT Flow (C. Liu, J. Yuen, A. Torralba, "SIFT Flow: Dense Correspondence
  across Scenes and its Applications", TPAMI 33(5), 2011, doi:10.1109/TPAMI.2010.147), our own
  numpy implementation: dense SIFT descriptors (:func:`dense_sift`), a truncated-L1 data term, a
  small-displacement term and a truncated-L1 smoothness term separable in u and v, minimized
  coarse to fine by loopy min-sum belief propagation over a discrete search window per level.
  Messages use the linear-time distance transform for the truncated L1 (separable in u and v, as
  the dual-layer formulation of the paper), vectorized over all pixels with array shifts.
  Pure numpy cannot reach the C++ speed at 128x128 labels, so the matching runs at a working
  resolution (``working_size``, default 64x64) and the flow is upsampled; the final labels get
  sub-pixel precision from a parabola fit of the beliefs.
* :func:`dis_flow` -- OpenCV's DIS optical flow on the crops scaled to uint8.
* :func:`ncc_match` -- normalized cross-correlation of a patch around each query point within a
  search window (sparse: one displacement per point).

The coarse-to-fine pyramid exists once (:func:`coarse_to_fine`) and is shared by the dense flows.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

__all__ = [
    "coarse_to_fine",
    "dense_sift",
    "dis_flow",
    "ncc_match",
    "sample_flow",
    "sift_flow",
]


# ---------------------------------------------------------------------------------------------
# shared pyramid
# ---------------------------------------------------------------------------------------------
def _downsample(image: np.ndarray) -> np.ndarray:
    """Halve ``(H, W[, C])`` by 2x2 averaging (pixel centres stay consistent)."""
    h, w = image.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        shape = (h // 2, 2, w // 2, 2) + image.shape[2:]
        return image.reshape(shape).mean(axis=(1, 3), dtype=np.float32)
    out = cv2.resize(image, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
    return out.reshape(out.shape[:2] + image.shape[2:])


def upsample_flow(flow: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resize a flow ``(h, w, 2)`` px to ``shape`` (H, W), scaling the vectors by the size ratio."""
    h, w = flow.shape[:2]
    if (h, w) == tuple(shape):
        return flow.astype(np.float32, copy=True)
    out = cv2.resize(flow.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    out[..., 0] *= shape[1] / w
    out[..., 1] *= shape[0] / h
    return out


def coarse_to_fine(
    reference: np.ndarray,
    moving: np.ndarray,
    solver: Callable[[np.ndarray, np.ndarray, np.ndarray, int], np.ndarray],
    *,
    levels: int = 3,
    min_size: int = 8,
) -> np.ndarray:
    """Run ``solver`` from the coarsest pyramid level to the finest (as scikit-image's helper).

    ``reference``, ``moving``: ``(H, W[, C])``. ``solver(ref_l, mov_l, flow_init_l, level)`` gets
    the images of one level, the flow ``(h, w, 2)`` px upsampled from the coarser level (zeros at
    the top) and the level index (``levels - 1`` = coarsest, 0 = finest); it returns the refined
    flow ``(h, w, 2)``. Returns the finest flow ``(H, W, 2)`` float32 px.
    """
    pyr_ref, pyr_mov = [reference], [moving]
    for _ in range(levels - 1):
        if min(pyr_ref[-1].shape[:2]) < 2 * min_size:
            break
        pyr_ref.append(_downsample(pyr_ref[-1]))
        pyr_mov.append(_downsample(pyr_mov[-1]))
    top = len(pyr_ref) - 1
    flow = np.zeros(pyr_ref[top].shape[:2] + (2,), np.float32)
    for level in range(top, -1, -1):
        shape = pyr_ref[level].shape[:2]
        flow = upsample_flow(flow, shape)
        flow = solver(pyr_ref[level], pyr_mov[level], flow, level)
    return flow


# ---------------------------------------------------------------------------------------------
# dense SIFT
# ---------------------------------------------------------------------------------------------
def dense_sift(
    image: np.ndarray,
    *,
    cell_size: int = 2,
    num_bins: int = 8,
    clip: float = 0.2,
    as_uint8: bool = False,
) -> np.ndarray:
    """SIFT descriptor at every pixel of ``image`` ``(H, W)`` -> ``(H, W, 16 * num_bins)``.

    As in SIFT Flow (Lazebnik/Liu dense SIFT): a ``4 cell_size`` px square support (8 px for the
    default ``cell_size=2``) split into 4x4 cells; each cell holds a ``num_bins``-bin histogram of
    gradient orientations (magnitude-weighted, linear interpolation between bins, triangular
    spatial weighting). Descriptors are L2-normalized, clipped at ``clip`` and renormalized;
    flat regions give all-zero descriptors. Returns float32 with unit norm, or uint8 scaled by
    255 when ``as_uint8`` (the storage of the reference implementation).
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2:
        raise ValueError(f"dense_sift expects a 2-D image, got shape {img.shape}")
    h, w = img.shape
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    mag, ang = cv2.cartToPolar(gx, gy)  # ang in [0, 2 pi)
    pos = ang * (num_bins / (2.0 * np.pi))
    b0 = np.floor(pos).astype(np.int64)
    frac = (pos - b0).astype(np.float32)
    b0 %= num_bins
    b1 = (b0 + 1) % num_bins
    hist = np.zeros((h * w, num_bins), np.float32)
    rows = np.arange(h * w)
    hist[rows, b0.ravel()] = (mag * (1.0 - frac)).ravel()
    hist[rows, b1.ravel()] += (mag * frac).ravel()
    hist = hist.reshape(h, w, num_bins)
    # triangular spatial weight over a cell (support 2 * cell_size - 1)
    tri = np.convolve(np.ones(cell_size), np.ones(cell_size)).astype(np.float32)
    tri /= tri.sum()
    pooled = cv2.sepFilter2D(hist, -1, tri, tri, borderType=cv2.BORDER_CONSTANT)
    pooled = pooled.reshape(h, w, num_bins)
    # gather the 4x4 cells around every pixel
    offsets = np.rint((np.arange(4) - 1.5) * cell_size).astype(int)
    pad = int(np.abs(offsets).max())
    padded = np.pad(pooled, ((pad, pad), (pad, pad), (0, 0)))
    desc = np.empty((h, w, 4, 4, num_bins), np.float32)
    for i, oy in enumerate(offsets):
        for j, ox in enumerate(offsets):
            desc[:, :, i, j] = padded[pad + oy : pad + oy + h, pad + ox : pad + ox + w]
    desc = desc.reshape(h, w, 16 * num_bins)
    norm = np.linalg.norm(desc, axis=-1, keepdims=True)
    floor = 1e-3 * max(float(norm.max()), 1e-12)
    desc /= np.maximum(norm, floor)
    np.minimum(desc, clip, out=desc)
    norm = np.linalg.norm(desc, axis=-1, keepdims=True)
    desc /= np.maximum(norm, 1e-6)
    if as_uint8:
        return np.clip(np.rint(desc * 255.0), 0, 255).astype(np.uint8)
    return desc


# ---------------------------------------------------------------------------------------------
# SIFT Flow: data cost and belief propagation on one level
# ---------------------------------------------------------------------------------------------
def _data_cost(
    s1: np.ndarray, s2: np.ndarray, offset: np.ndarray, radius: int, trunc: float
) -> np.ndarray:
    """Truncated L1 descriptor cost ``(S, S, h, w)`` (label axes dv, du first) around ``offset``."""
    h, w, c = s1.shape
    size = 2 * radius + 1
    s1f = s1.reshape(h * w, c)
    s2f = s2.reshape(h * w, c)
    ys, xs = np.mgrid[0:h, 0:w]
    cost = np.empty((size, size, h, w), np.float32)
    # targets outside the image read the replicated border (crops have background there)
    for iv in range(size):
        yy = np.clip(ys + offset[..., 1] + (iv - radius), 0, h - 1)
        for iu in range(size):
            xx = np.clip(xs + offset[..., 0] + (iu - radius), 0, w - 1)
            diff = cv2.absdiff(s1f, s2f[(yy * w + xx).ravel()])
            l1 = cv2.reduce(diff, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32F).reshape(h, w)
            np.minimum(l1, trunc, out=cost[iv, iu])
    return cost


def _take(f: np.ndarray, axis: int, i: int) -> np.ndarray:
    return f[i] if axis == 0 else f[:, i]


def _l1_transform(f: np.ndarray, axis: int, alpha: float) -> None:
    """In-place lower envelope ``min_l f(l) + alpha |x - l|`` along label ``axis`` (0 or 1)."""
    n = f.shape[axis]
    for i in range(1, n):
        cur = _take(f, axis, i)
        np.minimum(cur, _take(f, axis, i - 1) + alpha, out=cur)
    for i in range(n - 2, -1, -1):
        cur = _take(f, axis, i)
        np.minimum(cur, _take(f, axis, i + 1) + alpha, out=cur)


def _label_min(f: np.ndarray, axis: int) -> np.ndarray:
    """Minimum over a short label axis as a chain of elementwise minima (fast for S ~ 5)."""
    out = _take(f, axis, 0).copy()
    for i in range(1, f.shape[axis]):
        np.minimum(out, _take(f, axis, i), out=out)
    return np.expand_dims(out, axis)


def _shift_labels(f: np.ndarray, delta: np.ndarray | None, axis: int, alpha: float) -> np.ndarray:
    """Evaluate a lower envelope at labels ``l + delta`` (``delta (h, w)`` int per pixel).

    Outside the window the envelope continues with slope ``alpha`` (exact for the L1 part)."""
    if delta is None:
        return f
    n = f.shape[axis]
    out = f.copy()
    for dv in np.unique(delta):
        if dv == 0:
            continue
        sel = delta == dv
        for i in range(n):
            src = min(max(i + int(dv), 0), n - 1)
            excess = abs(i + int(dv) - src)
            dst = _take(out, axis, i)
            np.copyto(dst, _take(f, axis, src) + alpha * excess, where=sel)
    return out


def _message(h: np.ndarray, shifts, alpha: float, d: float) -> np.ndarray:
    """Min-sum message for the truncated-L1 smoothness, separable in u (axis 1) and v (axis 0).

    ``h``: ``(S, S, h, w)`` sender belief without the receiver's message; ``shifts``: per-pixel
    label offsets (receiver window minus sender window) for u and v, or None where all zero."""
    g = h.copy()
    _l1_transform(g, 1, alpha)
    g = _shift_labels(g, shifts[0], 1, alpha)
    np.minimum(g, _label_min(h, 1) + d, out=g)
    g2 = g.copy()
    _l1_transform(g2, 0, alpha)
    g2 = _shift_labels(g2, shifts[1], 0, alpha)
    np.minimum(g2, _label_min(g, 0) + d, out=g2)
    g2 -= _label_min(_label_min(g2, 0), 1)
    return g2


def _bp_level(
    s1: np.ndarray,
    s2: np.ndarray,
    init: np.ndarray,
    level: int,
    *,
    radius_top: int,
    radius: int,
    alpha: float,
    d: float,
    gamma: float,
    iterations: int,
    top_iterations: int,
    trunc: float,
    top_level: int,
    subpixel: bool,
) -> np.ndarray:
    """One coarse-to-fine level of SIFT Flow: discrete search around ``init``, loopy BP.

    Arrays are ``(S, S, h, w)`` (label axes first, so label loops touch contiguous images)."""
    is_top = level == top_level
    r = radius_top if is_top else radius
    n_iter = top_iterations if is_top else iterations
    size = 2 * r + 1
    offset = np.rint(init).astype(np.int64)
    h, w = offset.shape[:2]
    cost = _data_cost(s1, s2, offset, r, trunc)
    lab = np.arange(-r, r + 1)
    g = gamma * 2.0**level  # the small-displacement weight grows with the level as in SIFT Flow
    cost += g * (
        np.abs(offset[None, None, :, :, 1] + lab[:, None, None, None])
        + np.abs(offset[None, None, :, :, 0] + lab[None, :, None, None])
    ).astype(np.float32)
    # messages into each pixel from its left, right, upper and lower neighbour
    m_left = np.zeros_like(cost)
    m_right = np.zeros_like(cost)
    m_up = np.zeros_like(cost)
    m_down = np.zeros_like(cost)

    # evaluating the sender's envelope at the receiver's labels: l_s = l_r + (o_r - o_s)
    def shifts(du, dv):
        return (du if np.any(du) else None, dv if np.any(dv) else None)

    du_x = offset[:, 1:, 0] - offset[:, :-1, 0]  # receiver right of sender
    dv_x = offset[:, 1:, 1] - offset[:, :-1, 1]
    du_y = offset[1:, :, 0] - offset[:-1, :, 0]  # receiver below sender
    dv_y = offset[1:, :, 1] - offset[:-1, :, 1]
    sh_right, sh_left = shifts(du_x, dv_x), shifts(-du_x, -dv_x)
    sh_down, sh_up = shifts(du_y, dv_y), shifts(-du_y, -dv_y)
    for _ in range(n_iter):
        belief = cost + m_left + m_right + m_up + m_down
        new_left = np.zeros_like(cost)
        new_left[..., 1:] = _message((belief - m_right)[..., :-1], sh_right, alpha, d)
        new_right = np.zeros_like(cost)
        new_right[..., :-1] = _message((belief - m_left)[..., 1:], sh_left, alpha, d)
        new_up = np.zeros_like(cost)
        new_up[..., 1:, :] = _message((belief - m_down)[..., :-1, :], sh_down, alpha, d)
        new_down = np.zeros_like(cost)
        new_down[..., :-1, :] = _message((belief - m_up)[..., 1:, :], sh_up, alpha, d)
        m_left, m_right, m_up, m_down = new_left, new_right, new_up, new_down
    belief = (cost + m_left + m_right + m_up + m_down).reshape(size * size, h, w)
    best = np.argmin(belief, axis=0)
    bv, bu = np.divmod(best, size)
    flow = np.stack([offset[..., 0] + bu - r, offset[..., 1] + bv - r], axis=-1).astype(np.float32)
    if subpixel:
        # Sub-pixel: a fit through the data cost aggregated over a small window (the beliefs
        # are piecewise linear near their minimum and would bias the fit).
        agg = cv2.blur(
            np.ascontiguousarray(cost.reshape(size * size, h, w).transpose(1, 2, 0)),
            (5, 5),
            borderType=cv2.BORDER_REFLECT,
        ).reshape(h, w, size, size)
        yy, xx = np.mgrid[0:h, 0:w]
        f0 = agg[yy, xx, bv, bu]
        for comp, lab_i in ((0, bu), (1, bv)):
            # both neighbouring labels must point inside the image (outside costs are flat)
            pos = (xx, yy)[comp] + offset[..., comp] + lab_i - r
            limit = (w, h)[comp]
            inner = (lab_i > 0) & (lab_i < size - 1) & (pos >= 1) & (pos <= limit - 2)
            k = np.clip(lab_i, 1, size - 2)
            if comp == 0:
                fm, fp = agg[yy, xx, bv, k - 1], agg[yy, xx, bv, k + 1]
            else:
                fm, fp = agg[yy, xx, k - 1, bu], agg[yy, xx, k + 1, bu]
            # equiangular (V-shaped) fit: an L1 cost is linear, not quadratic, near its minimum
            den = 2.0 * (np.maximum(fm, fp) - f0)
            with np.errstate(divide="ignore", invalid="ignore"):
                delta = np.where(inner & (den > 1e-6), (fm - fp) / den, 0.0)
            flow[..., comp] += np.clip(delta, -0.5, 0.5)
    return flow


def sift_flow(
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    alpha: float = 2.0,
    d: float = 40.0,
    gamma: float = 0.005,
    levels: int = 2,
    wsize: int = 2,
    topwsize: int = 4,
    iterations: int = 4,
    top_iterations: int = 8,
    working_size: int | None = 64,
    data_truncation: float = 0.5,
    cell_size: int = 2,
    subpixel: bool = True,
) -> np.ndarray:
    """SIFT Flow from ``reference`` to ``moving``, both ``(H, W)`` float -> flow ``(H, W, 2)`` px.

    ``flow[y, x] = (dx, dy)`` with ``reference(x, y) ~ moving(x + dx, y + dy)``.

    Energy (Liu et al. 2011, Eq. 3), with descriptors ``s1``, ``s2`` from :func:`dense_sift`::

        E(w) = sum_p min(|s1(p) - s2(p + w_p)|_1, t)                       (data)
             + sum_p gamma (|u_p| + |v_p|)                                 (small displacement)
             + sum_{p~q} min(alpha |u_p - u_q|, d) + min(alpha |v_p - v_q|, d)   (smoothness)

    Units: as in the reference code, descriptors are scaled to [0, 255] and the paper's
    ``alpha``, ``d`` and ``gamma`` are multiplied by 255 (``SIFTflowpara.alpha = 2*255``);
    ``data_truncation`` t is a fraction of the largest possible L1 distance (2 * 255 * sqrt(128)
    bounds it; we use ``t = data_truncation * 255 * 8``). ``gamma`` is doubled per coarser level.

    Search: ``topwsize`` labels (+-px) at the coarsest level, ``wsize`` around the upsampled flow
    below; ``top_iterations`` / ``iterations`` sweeps of synchronous loopy min-sum BP per level.
    ``working_size``: the crops are resampled to this size (px) for matching and the flow is
    upsampled back (None = full resolution). ``levels`` counts pyramid levels from the working
    resolution: the default 64 px with ``levels=2`` (64, 32) matches the two coarse levels of the
    paper's 3-level pyramid on a 128 px crop (``working_size=None, levels=3`` gives the paper's
    setting, ~15x slower in numpy). A 16x16 top level was measured to fail on hand crops (an 8 px
    descriptor covers the whole hand there).
    The finest labels are refined to sub-pixel by a parabola fit of the beliefs (``subpixel``).
    """
    ref = np.asarray(reference, dtype=np.float32)
    mov = np.asarray(moving, dtype=np.float32)
    if ref.shape != mov.shape or ref.ndim != 2:
        raise ValueError(f"sift_flow needs two equal 2-D images, got {ref.shape} and {mov.shape}")
    full_shape = ref.shape
    if working_size is not None and max(full_shape) > working_size:
        scale = working_size / max(full_shape)
        size = (max(1, round(full_shape[1] * scale)), max(1, round(full_shape[0] * scale)))
        ref = cv2.resize(ref, size, interpolation=cv2.INTER_AREA)
        mov = cv2.resize(mov, size, interpolation=cv2.INTER_AREA)
    s1 = dense_sift(ref, cell_size=cell_size, as_uint8=True)
    s2 = dense_sift(mov, cell_size=cell_size, as_uint8=True)
    flow = _sift_flow_descriptors(
        s1,
        s2,
        alpha=alpha,
        d=d,
        gamma=gamma,
        levels=levels,
        wsize=wsize,
        topwsize=topwsize,
        iterations=iterations,
        top_iterations=top_iterations,
        data_truncation=data_truncation,
        subpixel=subpixel,
    )
    return upsample_flow(flow, full_shape)


def _sift_flow_descriptors(
    s1: np.ndarray,
    s2: np.ndarray,
    *,
    alpha: float,
    d: float,
    gamma: float,
    levels: int,
    wsize: int,
    topwsize: int,
    iterations: int,
    top_iterations: int,
    data_truncation: float,
    subpixel: bool,
) -> np.ndarray:
    """SIFT Flow on precomputed uint8 descriptor images ``(h, w, 128)`` -> ``(h, w, 2)`` px."""
    # count the levels the pyramid will really have (it stops at 8 px)
    top = 0
    size = min(s1.shape[:2])
    while top < levels - 1 and size >= 16:
        size //= 2
        top += 1

    def solver(a: np.ndarray, b: np.ndarray, init: np.ndarray, level: int) -> np.ndarray:
        a8 = a if a.dtype == np.uint8 else np.clip(np.rint(a), 0, 255).astype(np.uint8)
        b8 = b if b.dtype == np.uint8 else np.clip(np.rint(b), 0, 255).astype(np.uint8)
        return _bp_level(
            a8,
            b8,
            init,
            level,
            radius_top=topwsize,
            radius=wsize,
            alpha=alpha * 255.0,
            d=d * 255.0,
            gamma=gamma * 255.0,
            iterations=iterations,
            top_iterations=top_iterations,
            trunc=data_truncation * 255.0 * 8.0,
            top_level=top,
            subpixel=subpixel and level == 0,
        )

    return coarse_to_fine(s1, s2, solver, levels=levels)


# ---------------------------------------------------------------------------------------------
# DIS optical flow and NCC matching
# ---------------------------------------------------------------------------------------------
def _to_uint8(crop: np.ndarray, lo: float = -1.0, hi: float = 1.0) -> np.ndarray:
    x = (np.asarray(crop, dtype=np.float32) - lo) * (255.0 / (hi - lo))
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


_DIS_CACHE: dict[tuple, cv2.DISOpticalFlow] = {}


def dis_flow(
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    preset: int = cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
    patch_size: int = 8,
    patch_stride: int = 3,
    finest_scale: int = 1,
    gradient_descent_iterations: int = 25,
    variational_iterations: int = 5,
    value_range: tuple[float, float] = (-1.0, 1.0),
    levels: int = 1,
) -> np.ndarray:
    """DIS optical flow (Kroeger et al., ECCV 2016) from ``reference`` to ``moving`` ``(H, W)``.

    The crops are scaled from ``value_range`` to uint8. ``finest_scale=1`` (patches matched at
    half resolution, then variational refinement at full resolution) was both faster and more
    accurate than 0 on the synthetic benchmark (``benchmarks/results/design_measurements.md``).
    Returns ``(H, W, 2)`` float32 px with the module's convention. DIS has its own internal pyramid; ``levels > 1`` additionally wraps it
    in :func:`coarse_to_fine` (each level initialized with the upsampled flow).
    """
    key = (
        preset,
        patch_size,
        patch_stride,
        finest_scale,
        gradient_descent_iterations,
        variational_iterations,
    )
    dis = _DIS_CACHE.get(key)
    if dis is None:
        dis = cv2.DISOpticalFlow_create(preset)
        dis.setPatchSize(patch_size)
        dis.setPatchStride(patch_stride)
        dis.setFinestScale(finest_scale)
        dis.setGradientDescentIterations(gradient_descent_iterations)
        dis.setVariationalRefinementIterations(variational_iterations)
        dis.setUseMeanNormalization(False)  # depth offsets are meaningful, keep them
        _DIS_CACHE[key] = dis
    a = _to_uint8(reference, *value_range)
    b = _to_uint8(moving, *value_range)

    def solver(ra: np.ndarray, mb: np.ndarray, init: np.ndarray, level: int) -> np.ndarray:
        ra8 = ra if ra.dtype == np.uint8 else np.clip(np.rint(ra), 0, 255).astype(np.uint8)
        mb8 = mb if mb.dtype == np.uint8 else np.clip(np.rint(mb), 0, 255).astype(np.uint8)
        flow = np.ascontiguousarray(init, dtype=np.float32)
        return dis.calc(ra8, mb8, flow if np.any(init) else None)

    if levels <= 1:
        return dis.calc(a, b, None)
    return coarse_to_fine(a, b, solver, levels=levels)


def ncc_match(
    reference: np.ndarray,
    moving: np.ndarray,
    points: np.ndarray,
    *,
    patch: int = 21,
    search: int = 12,
    init: np.ndarray | None = None,
    background: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Match a ``patch`` x ``patch`` window around each point by normalized cross-correlation.

    ``points``: ``(P, 2)`` px in ``reference``; ``init``: optional ``(P, 2)`` px displacement
    guesses. The patch is searched within +-``search`` px in ``moving`` (``TM_CCOEFF_NORMED``,
    sub-pixel by parabola fit). Outside the crop counts as ``background``. Returns
    ``(displacement (P, 2) px, score (P,) in [-1, 1])``.
    """
    ref = np.asarray(reference, dtype=np.float32)
    mov = np.asarray(moving, dtype=np.float32)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    guess = (
        np.zeros_like(pts) if init is None else np.asarray(init, dtype=np.float64).reshape(-1, 2)
    )
    half = patch // 2
    big = half + 2 * search + 2
    ref_p = cv2.copyMakeBorder(ref, big, big, big, big, cv2.BORDER_CONSTANT, value=background)
    mov_p = cv2.copyMakeBorder(mov, big, big, big, big, cv2.BORDER_CONSTANT, value=background)
    hi = np.array(ref.shape[::-1]) - 1
    disp = np.full_like(pts, np.nan)
    score = np.full(len(pts), -1.0)
    win = 2 * (half + search) + 1
    for k in range(len(pts)):
        p, g = pts[k], guess[k]
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(g))):
            continue
        c = np.clip(np.rint(p).astype(int), -search, hi + search)
        tpl = ref_p[
            c[1] + big - half : c[1] + big + half + 1, c[0] + big - half : c[0] + big + half + 1
        ]
        q = np.clip(np.rint(p + g).astype(int), -search, hi + search)
        x0, y0 = q[0] + big - half - search, q[1] + big - half - search
        region = mov_p[y0 : y0 + win, x0 : x0 + win]
        if float(tpl.std()) < 1e-6:
            disp[k] = g
            continue
        res = cv2.matchTemplate(region, tpl, cv2.TM_CCOEFF_NORMED)
        iy, ix = np.unravel_index(int(np.argmax(res)), res.shape)
        sub = np.zeros(2)
        if 0 < ix < res.shape[1] - 1:
            fm, f0, fp = res[iy, ix - 1], res[iy, ix], res[iy, ix + 1]
            den = fm - 2 * f0 + fp
            if den < -1e-9:
                sub[0] = np.clip(0.5 * (fm - fp) / den, -0.5, 0.5)
        if 0 < iy < res.shape[0] - 1:
            fm, f0, fp = res[iy - 1, ix], res[iy, ix], res[iy + 1, ix]
            den = fm - 2 * f0 + fp
            if den < -1e-9:
                sub[1] = np.clip(0.5 * (fm - fp) / den, -0.5, 0.5)
        # best window top-left (padded coords) -> its centre in crop coords
        centre = np.array([x0 + ix, y0 + iy], dtype=np.float64) + sub + half - big
        disp[k] = centre - c
        score[k] = float(res[iy, ix])
    return disp, score


def sample_flow(flow: np.ndarray, points: np.ndarray, *, radius: int = 1) -> np.ndarray:
    """Robust flow at sub-pixel ``points`` ``(P, 2)`` px: median of bilinear samples on a grid.

    Samples at ``points + (i, j)`` for i, j in [-radius, radius] (bilinear, border replicated)
    and returns the per-component median ``(P, 2)`` px. NaN points give NaN.
    """
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 2)
    off = np.arange(-radius, radius + 1, dtype=np.float32)
    oy, ox = np.meshgrid(off, off, indexing="ij")
    x = pts[:, 0, None] + ox.ravel()[None]
    y = pts[:, 1, None] + oy.ravel()[None]
    bad = ~np.isfinite(pts).all(axis=1)
    x[bad] = 0.0
    y[bad] = 0.0
    val = cv2.remap(
        np.ascontiguousarray(flow, dtype=np.float32),
        np.ascontiguousarray(x),
        np.ascontiguousarray(y),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    out = np.median(val, axis=1).astype(np.float64)
    out[bad] = np.nan
    return out
