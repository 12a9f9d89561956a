"""Per-frame values summarized over bins of consecutive frames (a timeline of a long session).

A 76,000-frame session cannot show one widget or plot point per frame; a timeline of ``K`` bins
shows, per bin, the worst score, the mean, how many frames are references or reviewed, and which
frame to jump to. Everything here is vectorized (``np.ufunc.reduceat``), O(N) for N frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BinSummary", "bin_edges", "summarize_bins"]


def bin_edges(n: int, bins: int, breaks=()) -> np.ndarray:
    """Edges ``(K+1,)`` of at most ``bins`` bins of near-equal size over ``n`` frames.

    Every sequence break (frame index) is also an edge, so no bin mixes two sequences (the bin
    count can then exceed ``bins`` by the number of breaks). Empty bins are dropped.
    """
    if n <= 0:
        return np.zeros(1, dtype=np.int64)
    bins = max(1, min(int(bins), n))
    edges = np.round(np.linspace(0, n, bins + 1)).astype(np.int64)
    extra = np.asarray([int(b) for b in breaks if 0 < int(b) < n], dtype=np.int64)
    return np.unique(np.concatenate([edges, extra]))


@dataclass
class BinSummary:
    """Per bin (``K`` bins, ``edges`` (K+1,)): ``count``, ``finite`` (frames with a finite value),
    ``mean``/``max``/``min`` over finite values (NaN if none), ``argmax`` (frame index of the
    max, -1 if none) and ``flagged`` (frames with ``flags`` set, when given); arrays of (K,)."""

    edges: np.ndarray
    count: np.ndarray
    finite: np.ndarray
    mean: np.ndarray
    max: np.ndarray
    min: np.ndarray
    argmax: np.ndarray
    flagged: np.ndarray


def summarize_bins(values: np.ndarray, edges: np.ndarray, flags: np.ndarray | None = None):
    """Summaries of ``values`` ``(N,)`` (NaN = no value) over the bins ``edges`` (``bin_edges``).

    ``flags`` ``(N,)`` bool (e.g. reference or reviewed frames) are counted per bin.
    Returns a :class:`BinSummary`.
    """
    v = np.asarray(values, dtype=np.float64)
    edges = np.asarray(edges, dtype=np.int64)
    if v.ndim != 1 or edges[0] != 0 or edges[-1] != len(v) or np.any(np.diff(edges) <= 0):
        raise ValueError("values must be (N,) and edges increasing from 0 to N")
    starts = edges[:-1]
    count = np.diff(edges)
    ok = np.isfinite(v)
    finite = np.add.reduceat(ok.astype(np.int64), starts)
    total = np.add.reduceat(np.where(ok, v, 0.0), starts)
    vmax = np.maximum.reduceat(np.where(ok, v, -np.inf), starts)
    vmin = np.minimum.reduceat(np.where(ok, v, np.inf), starts)
    none = finite == 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(none, np.nan, total / np.maximum(finite, 1))
    vmax = np.where(none, np.nan, vmax)
    vmin = np.where(none, np.nan, vmin)
    # the first frame of each bin reaching the bin's max
    bin_of = np.repeat(np.arange(len(starts)), count)
    hit = ok & (v == np.where(none, np.inf, vmax)[bin_of])
    first = np.full(len(starts), len(v), dtype=np.int64)
    np.minimum.at(first, bin_of[hit], np.flatnonzero(hit))
    argmax = np.where(first < len(v), first, -1)
    flagged = (
        np.add.reduceat(np.asarray(flags, dtype=np.int64), starts)
        if flags is not None
        else np.zeros(len(starts), dtype=np.int64)
    )
    return BinSummary(edges, count, finite, mean, vmax, vmin, argmax, flagged)
