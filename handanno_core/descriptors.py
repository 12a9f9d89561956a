"""Per-frame appearance descriptors of normalized hand crops, for reference-frame selection.

Input: normalized depth crops ``(N, S, S)`` float (depth relative to the hand centre in [-1, 1],
background +1), e.g. the memory-mapped ``crops.npy`` of a session. Output: ``(N, D)`` float32 with
every row L2-normalized, so the cosine distance between frames ``i`` and ``j`` is
``1 - X[i] @ X[j]`` (in [0, 2]). All-background frames give a zero row (cosine distance 1 to
everything) rather than NaN.

Two kinds:

``"hog"``
    Histogram of oriented gradients with Oberweger et al.'s parameters (CVPR 2016; O's
    ``semiautoanno.py``): window 128, block 32, block stride 16, cell 16, 9 unsigned orientation
    bins, L2-Hys block normalization -> 7 x 7 blocks x 4 cells x 9 bins = **1764-D**. OpenCV 5
    dropped ``cv2.HOGDescriptor`` (it now lives in opencv-contrib), so this is a vectorized numpy
    implementation of the same layout (centred [-1, 0, 1] gradients, bilinear interpolation between
    orientation bins, no Gaussian block window or spatial interpolation) computed on the crop mapped
    linearly to 0..255 (the scale of O's uint8 image, without its quantization; O min-max normalized
    each crop, a fixed map keeps depth steps comparable across frames). Crops of another size are
    area-resampled to 128 x 128 first.
``"downsampled"``
    The crop area-resampled to ``size x size`` (default 16 -> 256-D; 16, 24 and 32 select equally well on the synthetic benchmark, and kNN cost grows with D), mean-subtracted per frame
    before normalizing so the +1 background does not dominate the cosine (unlike the thesis fork,
    which used the raw 16384-D crops; see anchor-algorithms.md, h.12).
"""

from __future__ import annotations

import numpy as np

KINDS = ("hog", "downsampled")
#: Default descriptor, chosen by benchmarks/bench_select.py: as good as HOG for selection on the
#: synthetic benchmark (better parents for the chain), several times cheaper, 256-D instead of 1764.
DEFAULT_KIND = "downsampled"

_HOG_WIN = 128
_HOG_CELL = 16
_HOG_BINS = 9
_HOG_BLOCK_CELLS = 2  # block 32 = 2 x 2 cells, block stride 16 = 1 cell
_HOG_CLIP = 0.2  # L2-Hys clipping, as OpenCV


def compute_descriptors(
    crops: np.ndarray,
    kind: str = DEFAULT_KIND,
    *,
    size: int = 16,
    chunk: int = 512,
    progress=None,
) -> np.ndarray:
    """Descriptors of normalized crops, rows L2-normalized (compare with cosine distance).

    Parameters
    ----------
    crops : (N, S, S) float array (may be a ``np.memmap``): normalized depth in [-1, 1],
        background +1. Read ``chunk`` frames at a time, so a memory-mapped 76k-frame array never
        has to fit in memory.
    kind : ``"downsampled"`` (default, ``size * size``-D) or ``"hog"`` (1764-D).
    size : side of the area-resampled crop for ``"downsampled"``.
    chunk : frames processed per batch.
    progress : optional ``callable(done, total)``.

    Returns
    -------
    (N, D) float32, each row of unit L2 norm (all-zero for a featureless frame).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown descriptor kind {kind!r}; expected one of {KINDS}")
    crops_shape = np.shape(crops)
    if len(crops_shape) != 3 or crops_shape[1] != crops_shape[2]:
        raise ValueError(f"crops must be (N, S, S), got {crops_shape}")
    n = crops_shape[0]
    if kind == "hog":
        dim = 7 * 7 * 4 * _HOG_BINS
        fn = _hog_batch
    else:
        if size < 1 or size > crops_shape[1]:
            raise ValueError(f"size must be in [1, {crops_shape[1]}], got {size}")
        dim = size * size
        fn = lambda c: _downsampled_batch(c, size)  # noqa: E731
    out = np.empty((n, dim), np.float32)
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        batch = np.asarray(crops[lo:hi], dtype=np.float32)
        out[lo:hi] = fn(batch)
        _release_pages(crops)
        if progress is not None:
            progress(hi, n)
    _normalize_rows(out)
    return out


def _release_pages(crops) -> None:
    """Drop the already-read pages of a read-only memory map so resident memory stays flat on
    long sequences (they are re-read from the file if touched again)."""
    mm = getattr(crops, "_mmap", None)
    if mm is None or getattr(crops, "mode", None) != "r":
        return
    try:
        import mmap

        mm.madvise(mmap.MADV_DONTNEED)
    except (AttributeError, OSError, ValueError):
        pass


def _normalize_rows(x: np.ndarray) -> None:
    """In-place L2 normalization of the rows; zero rows stay zero."""
    norm = np.sqrt(np.einsum("ij,ij->i", x, x))
    norm[norm < 1e-12] = np.inf
    x /= norm[:, None]


def _area_resample(batch: np.ndarray, size: int) -> np.ndarray:
    """(B, S, S) -> (B, size, size) by area averaging (exact block mean when S % size == 0)."""
    s = batch.shape[1]
    if s == size:
        return batch
    if s % size == 0:
        f = s // size
        return batch.reshape(len(batch), size, f, size, f).mean(axis=(2, 4))
    import cv2

    return np.stack([cv2.resize(b, (size, size), interpolation=cv2.INTER_AREA) for b in batch])


def _downsampled_batch(batch: np.ndarray, size: int) -> np.ndarray:
    small = _area_resample(batch, size).reshape(len(batch), -1)
    return small - small.mean(axis=1, keepdims=True)


def _hog_batch(batch: np.ndarray) -> np.ndarray:
    """Unnormalized-per-descriptor HOG (blocks L2-Hys normalized) of (B, S, S) crops -> (B, 1764)."""
    if batch.shape[1] != _HOG_WIN:
        batch = _area_resample(batch, _HOG_WIN)
    img = (np.clip(batch, -1.0, 1.0) + 1.0) * 127.5  # the 0..255 scale of O's uint8 image
    b = len(img)
    # Centred gradients, borders replicated (zero gradient across the border).
    gx = np.zeros_like(img)
    gy = np.zeros_like(img)
    gx[:, :, 1:-1] = img[:, :, 2:] - img[:, :, :-2]
    gy[:, 1:-1, :] = img[:, 2:, :] - img[:, :-2, :]
    mag = np.sqrt(gx * gx + gy * gy).ravel()
    nz = np.flatnonzero(mag)  # most of a crop is flat background: bin only real gradients
    mag = mag[nz]
    # Unsigned orientation in bin units [0, 9]; bin k is centred at (k + 0.5) * 20 degrees.
    ang = np.arctan2(gy.ravel()[nz], gx.ravel()[nz])
    ang = np.where(ang < 0, ang + np.float32(np.pi), ang) * np.float32(_HOG_BINS / np.pi)
    ang -= np.float32(0.5)
    lo = np.floor(ang)
    m_hi = mag * (ang - lo)
    m_lo = mag - m_hi
    bin_lo = lo.astype(np.int64)
    bin_lo[bin_lo < 0] += _HOG_BINS
    bin_hi = bin_lo + 1
    bin_hi[bin_hi >= _HOG_BINS] -= _HOG_BINS
    # Histograms by bincount over (image, cell, bin): no loop over pixels or bins.
    nc = _HOG_WIN // _HOG_CELL
    cy = np.arange(_HOG_WIN) // _HOG_CELL
    cell = (cy[:, None] * nc + cy[None, :]).astype(np.int64)  # (128, 128) cell index
    img_id, pix = np.divmod(nz, _HOG_WIN * _HOG_WIN)
    base = (img_id * (nc * nc) + cell.ravel()[pix]) * _HOG_BINS
    size = b * nc * nc * _HOG_BINS
    hist = np.bincount(base + bin_lo, m_lo, minlength=size)
    hist += np.bincount(base + bin_hi, m_hi, minlength=size)
    hist = hist.astype(np.float32).reshape(b, nc, nc, _HOG_BINS)
    # Blocks of 2 x 2 cells, stride one cell: (B, 7, 7, 2, 2, 9) -> L2-Hys per block.
    nb = nc - _HOG_BLOCK_CELLS + 1
    blocks = np.stack(
        [hist[:, i : i + nb, j : j + nb] for i in range(2) for j in range(2)], axis=3
    ).reshape(b, nb, nb, -1)
    eps = 1e-3 * _HOG_CELL * _HOG_CELL  # tiny relative to a real edge (gradients up to ~500)
    blocks = blocks / np.sqrt(np.sum(blocks * blocks, axis=-1, keepdims=True) + eps**2)
    np.minimum(blocks, _HOG_CLIP, out=blocks)
    blocks = blocks / np.sqrt(np.sum(blocks * blocks, axis=-1, keepdims=True) + 1e-12)
    return blocks.reshape(b, -1)
