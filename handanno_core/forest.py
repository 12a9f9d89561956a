"""The parent forest of a selection: every frame has a parent frame it is propagated from, and the
references are the roots (parent -1).

``parent``: ``(N,)`` int, ``parent[i]`` the frame ``i`` is propagated from, ``-1`` at references.
A session without a selection reports every parent as :data:`NO_SELECTION`.

All walks are vectorized: pointer jumping for roots and depths (log2(depth) passes), a CSR
children list for walks down the trees.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "NO_SELECTION",
    "children_csr",
    "depths",
    "descendants",
    "propagation_order",
    "roots",
    "validate",
]

#: parent of every frame of a session that has no selection yet
NO_SELECTION = -2


def _passes(n: int) -> int:
    """Pointer-jumping passes that resolve any chain of length <= n (plus one to see no change)."""
    return max(1, math.ceil(math.log2(max(n, 2)))) + 2


def roots(parent: np.ndarray) -> np.ndarray:
    """``(N,)`` int64: the reference at the root of each frame's tree. ``ValueError`` on a cycle."""
    parent = np.asarray(parent, dtype=np.int64)
    n = len(parent)
    up = np.where(parent < 0, np.arange(n), parent)
    for _ in range(_passes(n)):
        nxt = up[up]
        if np.array_equal(nxt, up):
            break
        up = nxt
    if np.any(parent[up] >= 0):
        raise ValueError("parent forest has a cycle (some frame never reaches a reference)")
    return up


def depths(parent: np.ndarray) -> np.ndarray:
    """``(N,)`` int64: propagation steps from each frame's root reference (0 at references).
    ``ValueError`` on a cycle."""
    parent = np.asarray(parent, dtype=np.int64)
    n = len(parent)
    up = np.where(parent < 0, np.arange(n), parent)
    depth = (parent >= 0).astype(np.int64)
    for _ in range(_passes(n)):
        if np.all(parent[up] < 0):
            break
        depth = depth + np.where(parent[up] >= 0, depth[up], 0)
        up = np.where(parent[up] >= 0, up[up], up)
    roots(parent)
    return depth


def validate(parent: np.ndarray, reference_frames: np.ndarray) -> None:
    """``ValueError`` unless ``parent`` is a forest rooted exactly at ``reference_frames``."""
    parent = np.asarray(parent, dtype=np.int64)
    refs = np.asarray(reference_frames, dtype=np.int64)
    n = len(parent)
    if refs.size == 0:
        raise ValueError("no reference frames")
    if refs.min() < 0 or refs.max() >= n or np.unique(refs).size != refs.size:
        raise ValueError("reference frames out of range or repeated")
    is_ref = np.zeros(n, bool)
    is_ref[refs] = True
    if not np.array_equal(parent < 0, is_ref) or np.any(parent < -1):
        raise ValueError("parent must be -1 exactly at the references")
    if np.any(parent >= n):
        raise ValueError("parent index out of range")
    roots(parent)  # raises on cycles


def children_csr(parent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR children lists: the children of ``i`` are ``kids[start[i]:start[i+1]]`` (ascending)."""
    parent = np.asarray(parent, dtype=np.int64)
    n = len(parent)
    has = parent >= 0
    kids = np.flatnonzero(has)
    kids = kids[np.argsort(parent[kids], kind="stable")]
    counts = np.bincount(parent[has], minlength=n)
    start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=start[1:])
    return kids, start


def descendants(parent: np.ndarray, frames) -> np.ndarray:
    """All frames whose parent chain passes through any of ``frames`` (the frames included), sorted
    int64. After a reference (or any frame) changes, these are the frames to re-propagate."""
    parent = np.asarray(parent, dtype=np.int64)
    kids, start = children_csr(parent)
    mark = np.zeros(len(parent), dtype=bool)
    front = np.unique(np.asarray(frames, dtype=np.int64).ravel())
    mark[front] = True
    while front.size:
        nxt = np.concatenate([kids[start[i] : start[i + 1]] for i in front])
        nxt = nxt[~mark[nxt]]
        mark[nxt] = True
        front = nxt
    return np.flatnonzero(mark)


def propagation_order(parent: np.ndarray, heads) -> list[np.ndarray]:
    """Breadth-first frames below each of ``heads`` (heads excluded): one array per head, parents
    before children."""
    parent = np.asarray(parent, dtype=np.int64)
    kids, start = children_csr(parent)
    out = []
    for r in np.asarray(heads, dtype=np.int64).ravel():
        order: list[np.ndarray] = []
        front = kids[start[r] : start[r + 1]]
        while front.size:
            order.append(front)
            front = np.concatenate([kids[start[i] : start[i + 1]] for i in front])
        out.append(np.concatenate(order) if order else np.zeros(0, dtype=np.int64))
    return out
