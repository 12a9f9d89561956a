"""Reference-frame selection: which frames a person annotates, and where every other frame is
propagated from.

Every strategy returns a :class:`Selection`: the reference frames and, for every other frame, its
**parent** (the frame it is propagated from). The parents form a forest rooted at the references,
so the propagation order is data, not code.

Distances are cosine distances ``1 - x_i . x_j`` between L2-normalized descriptors
(:func:`handanno_core.descriptors.compute_descriptors`), in [0, 2].

Strategies
----------
``chain``
    The thesis (Eq. 1-2): the greedy nearest-neighbour chain over cosine distance from frame 0;
    frame 0 is a reference and a chain frame becomes a new reference when its distance to the
    **previous reference** exceeds ``rho`` (as the thesis text states; the fork tests consecutive
    steps instead). Parent = previous frame in the chain.
``chain-step``
    The public fork's variant, with its off-by-one fixed (as in its commit f8e87e6): the same chain,
    a new reference at the first frame after every chain step longer than ``rho``.
``coverage``
    Oberweger et al. (CVPR 2016): lazy greedy maximization of the submodular coverage
    ``#{i : min_s d(s, i) < rho}``, capped by the budget. Parent = nearest reference (by descriptor),
    i.e. every tree has depth 1. ``rho`` is a raw cosine distance here, not O's min-max-normalized
    one. Balls are read from the kNN lists (the ``coverage_k`` nearest frames), so a ball with more
    members than that is truncated: exact at small N, an approximation for very dense regions.
``uniform``
    Every k-th frame in time (centred in its interval, at least one per segment between
    ``sequence_breaks``). Parent = the temporal neighbour towards the nearest reference in time.
    With ``rho=R``, R is the spacing in frames.
``forest`` (ours)
    Greedy k-centre (farthest-point) on **graph geodesic distances** of a kNN graph (each frame to
    its ``graph_k`` nearest, plus the temporal neighbours i-1, i+1 unless a sequence break lies
    between them), so references bound every frame's *path length* to its reference. Parent = next
    hop on the shortest path to the nearest reference (a multi-source Dijkstra shortest-path
    forest): no frame sits at the end of a long greedy tour, and the trees are shallow and
    independent (parallel propagation). With ``rho=R``: add references until every frame is within
    geodesic distance R.
    Edge weight = cosine distance (times ``temporal_weight`` for temporal edges) + ``hop_cost``.
    Defaults (``graph_k=5, temporal_weight=0.1, hop_cost=0.002``) come from a sweep on the
    synthetic 3040-frame benchmark (benchmarks/bench_select.py): consecutive video frames are the
    best propagation sources (smaller parent->child pose change than appearance neighbours), so
    temporal edges are made cheap, while kNN edges still let a revisited pose reach
    a reference recorded elsewhere in the video; the hop cost keeps trees shallow.

Budget
------
Exactly one of ``ref_fraction=F`` (number of references = ``round(F * N)``; ``chain`` and
``coverage`` bisect their threshold, ``chain-step``, ``uniform`` and ``forest`` take the top K
directly; ``chain`` tops up with the frames farthest from their reference in the rare case the
bisection cannot hit K exactly) or ``rho=R`` (a raw threshold) must be given.

Scale: no N x N matrix is ever held; exact kNN comes from blocked matrix products
(:func:`knn`), and the chain's "nearest not-yet-visited frame" walks the sorted kNN lists with a
blocked scan of the unvisited frames as fallback (O(N k) plus occasional O(N D) scans).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import forest

STRATEGIES = ("chain", "chain-step", "coverage", "uniform", "forest")
# chosen on the benchmark suite's tune part (README, "Default selection strategy"): uniform beat the
# forest there on 5 of 7 sequences and on the mean, as on the report part
DEFAULT_STRATEGY = "uniform"
BUDGET_TOLERANCE = 0.02  # |K - round(F N)| <= 2 % of round(F N)


# --------------------------------------------------------------------------------------------
# Result type
# --------------------------------------------------------------------------------------------


@dataclass
class Selection:
    """Reference frames and the propagation forest.

    ``reference_frames``: (K,) int64, sorted. ``parent``: (N,) int64, -1 exactly at references.
    ``threshold``: the rho used (found by bisection for a budget), None where not applicable.
    """

    strategy: str
    reference_frames: np.ndarray
    parent: np.ndarray
    threshold: float | None = None

    def __post_init__(self) -> None:
        self.reference_frames = np.sort(np.asarray(self.reference_frames, dtype=np.int64))
        self.parent = np.asarray(self.parent, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.parent)

    def to_dict(self) -> dict[str, Any]:
        return {
            "strategy": self.strategy,
            "reference_frames": [int(i) for i in self.reference_frames],
            "parent": [int(p) for p in self.parent],
            "threshold": None if self.threshold is None else float(self.threshold),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Selection:
        return cls(
            strategy=d["strategy"],
            reference_frames=np.asarray(d["reference_frames"], dtype=np.int64),
            parent=np.asarray(d["parent"], dtype=np.int64),
            threshold=d.get("threshold"),
        )

    def validate(self) -> None:
        """Raise ValueError unless parents form a forest rooted exactly at the references."""
        forest.validate(self.parent, self.reference_frames)

    def roots(self) -> np.ndarray:
        """(N,) int64: the reference at the root of each frame's tree (:func:`forest.roots`)."""
        return forest.roots(self.parent)

    def depths(self) -> np.ndarray:
        """(N,) int64: number of propagation steps from each frame's root reference (0 at refs)."""
        return forest.depths(self.parent)


# --------------------------------------------------------------------------------------------
# Exact kNN by blocked matrix products
# --------------------------------------------------------------------------------------------


@dataclass
class KnnGraph:
    """Exact k nearest neighbours by cosine distance, self excluded, sorted ascending.

    ``indices``: (N, k) int32; ``distances``: (N, k) float32 (cosine distance, in [0, 2]).
    """

    indices: np.ndarray
    distances: np.ndarray

    @property
    def k(self) -> int:
        return self.indices.shape[1]


def knn(descriptors: np.ndarray, k: int, *, block: int = 1024) -> KnnGraph:
    """Exact kNN of L2-normalized rows by cosine distance, without an N x N matrix.

    Similarities are computed ``block`` rows at a time (``block x N`` float32, ~300 MB at
    N = 76k). The top k of each row is found by pre-filtering with a threshold from a column
    subsample (the k-th largest of a subset is a lower bound of the k-th largest of the row),
    which is several times cheaper than ``argpartition`` over the full row, then ranking the
    few survivors exactly. Ties are broken by the smaller frame index.
    """
    x = np.ascontiguousarray(descriptors, dtype=np.float32)
    n = len(x)
    k = int(min(k, n - 1))
    if k < 1:
        return KnnGraph(np.zeros((n, 0), np.int32), np.zeros((n, 0), np.float32))
    idx = np.empty((n, k), np.int32)
    dist = np.empty((n, k), np.float32)
    # Column subsample for the threshold: about 16 candidates per wanted neighbour.
    stride = max(1, min(n // (k + 1), 16))
    sub = np.arange(0, n, stride)
    use_sub = stride >= 8 and sub.size > k + 1  # else the survivors are most of the row
    for lo in range(0, n, block):
        hi = min(n, lo + block)
        s = x[lo:hi] @ x.T  # (B, N) cosine similarity
        rows = np.arange(hi - lo)
        s[rows, np.arange(lo, hi)] = -np.inf  # exclude self
        if use_sub:
            ss = s[:, sub]
            thr = -np.partition(-ss, k - 1, axis=1)[:, k - 1]
            r, c = np.nonzero(s >= thr[:, None])
            v = s[r, c]
            # one stable sort on (row, -similarity); nonzero gives c ascending within a row
            order = np.argsort(r * 4.0 + (1.0 - v.astype(np.float64)), kind="stable")
            r, c, v = r[order], c[order], v[order]
            start = np.searchsorted(r, rows)
            take = start[:, None] + np.arange(k)
            idx[lo:hi] = c[take]
            dist[lo:hi] = 1.0 - v[take]
        else:
            part = np.sort(np.argpartition(-s, k - 1, axis=1)[:, :k], axis=1)
            pv = np.take_along_axis(s, part, axis=1)
            o = np.argsort(-pv, axis=1, kind="stable")  # ties: smaller index first
            idx[lo:hi] = np.take_along_axis(part, o, axis=1)
            dist[lo:hi] = 1.0 - np.take_along_axis(pv, o, axis=1)
    np.clip(dist, 0.0, 2.0, out=dist)
    return KnnGraph(idx, dist)


# --------------------------------------------------------------------------------------------
# Nearest-neighbour chain
# --------------------------------------------------------------------------------------------


def nn_chain(
    descriptors: np.ndarray, graph: KnnGraph | None = None, *, start: int = 0, k: int = 32
) -> tuple[np.ndarray, np.ndarray]:
    """Greedy nearest-neighbour tour over cosine distance from ``start`` (thesis Eq. 1).

    Returns ``order`` (N,) int64 (the chain) and ``steps`` (N-1,) float32 with
    ``steps[t] = d(order[t], order[t+1])``. Exact: the nearest unvisited frame is the first
    unvisited entry of the current frame's sorted kNN list; when all k are visited, a scan of
    the (periodically compacted) unvisited set finds it.
    """
    x = np.ascontiguousarray(descriptors, dtype=np.float32)
    n = len(x)
    if graph is None:
        graph = knn(x, k)
    nbr, nd = graph.indices, graph.distances
    visited = np.zeros(n, bool)
    order = np.empty(n, np.int64)
    steps = np.empty(max(n - 1, 0), np.float32)
    remaining = np.arange(n)
    x_rem = x
    cur = int(start)
    visited[cur] = True
    order[0] = cur
    n_visited_at_compact = 0
    for t in range(1, n):
        lst = nbr[cur]
        free = ~visited[lst]
        if free.any():
            a = int(free.argmax())
            nxt, d = int(lst[a]), float(nd[cur, a])
        else:
            # Fallback: blocked scan of the unvisited frames (compacted when half are stale).
            if t - n_visited_at_compact > len(remaining) // 2:
                remaining = np.flatnonzero(~visited)
                x_rem = x[remaining]
                n_visited_at_compact = t
            sims = x_rem @ x[cur]
            sims[visited[remaining]] = -np.inf
            a = int(sims.argmax())
            nxt, d = int(remaining[a]), float(1.0 - sims[a])
        order[t] = nxt
        steps[t - 1] = d
        visited[nxt] = True
        cur = nxt
    np.clip(steps, 0.0, 2.0, out=steps)
    return order, steps


def _chain_ref_positions(x_ordered: np.ndarray, rho: float) -> np.ndarray:
    """Positions in the chain where a new reference starts (distance to previous ref > rho)."""
    n = len(x_ordered)
    pos = [0]
    p = 0
    while True:
        r = x_ordered[p]
        q = p + 1
        blk = 32
        found = -1
        while q < n:
            hi = min(n, q + blk)
            d = 1.0 - x_ordered[q:hi] @ r
            ex = np.flatnonzero(d > rho)
            if ex.size:
                found = q + int(ex[0])
                break
            q = hi
            blk = min(blk * 4, 8192)
        if found < 0:
            break
        pos.append(found)
        p = found
    return np.asarray(pos, np.int64)


# --------------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------------


def budget_count(ref_fraction: float, n: int) -> int:
    """Target number of references for a fraction of N frames (at least 1)."""
    return max(1, min(n, int(round(ref_fraction * n))))


def select_references(
    descriptors: np.ndarray,
    strategy: str = DEFAULT_STRATEGY,
    *,
    ref_fraction: float | None = None,
    rho: float | None = None,
    sequence_breaks: list[int] | np.ndarray | None = None,
    graph: KnnGraph | None = None,
    chain_k: int = 32,
    graph_k: int = 5,
    coverage_k: int = 200,
    hop_cost: float = 0.002,
    temporal_weight: float = 0.1,
) -> Selection:
    """Choose reference frames and a parent (propagation source) for every other frame.

    Parameters
    ----------
    descriptors : (N, D) float, rows L2-normalized (cosine distance = 1 - dot).
    strategy : one of :data:`STRATEGIES` (see the module docstring).
    ref_fraction : target fraction of frames that become references (K = round(F N)).
    rho : raw threshold instead of a budget (cosine distance for chain/chain-step/coverage,
        geodesic path length for forest, spacing in frames for uniform).
    sequence_breaks : frames where a new unrelated sequence starts (cut temporal edges for
        ``uniform`` and ``forest``).
    graph : a precomputed :func:`knn` graph to reuse (must have at least the k the strategy
        needs: ``chain_k`` / ``graph_k`` / ``coverage_k``).
    hop_cost : ``forest`` only: constant added to every edge weight (prefers fewer hops).

    Returns
    -------
    :class:`Selection` with sorted ``reference_frames`` and ``parent`` (N,) (-1 at references).
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown strategy {strategy!r}; expected one of {STRATEGIES}")
    if (ref_fraction is None) == (rho is None):
        raise ValueError("give exactly one of ref_fraction=F (a budget) or rho=R (a threshold)")
    x = np.ascontiguousarray(descriptors, dtype=np.float32)
    if x.ndim != 2 or len(x) == 0:
        raise ValueError(f"descriptors must be a non-empty (N, D) array, got shape {x.shape}")
    n = len(x)
    if ref_fraction is not None and not (0.0 < ref_fraction <= 1.0):
        raise ValueError(f"ref_fraction must be in (0, 1], got {ref_fraction}")
    if rho is not None and not (np.isfinite(rho) and rho >= 0):
        raise ValueError(f"rho must be a finite non-negative number, got {rho}")
    target = budget_count(ref_fraction, n) if ref_fraction is not None else None
    breaks = _clean_breaks(sequence_breaks, n)

    def need_graph(k: int) -> KnnGraph:
        k = min(k, n - 1)
        if graph is not None and graph.k >= k:
            return KnnGraph(graph.indices[:, :k], graph.distances[:, :k])
        return knn(x, k)

    if n == 1:
        return Selection(strategy, np.array([0]), np.array([-1]), rho)
    if strategy in ("chain", "chain-step"):
        order, steps = nn_chain(x, need_graph(chain_k))
        if strategy == "chain":
            return _select_chain(x, order, target, rho)
        return _select_chain_step(order, steps, target, rho)
    if strategy == "coverage":
        return _select_coverage(x, need_graph(coverage_k), target, rho)
    if strategy == "uniform":
        return _select_uniform(n, breaks, target, rho)
    return _select_forest(x, need_graph(graph_k), breaks, target, rho, hop_cost, temporal_weight)


def _clean_breaks(sequence_breaks, n: int) -> np.ndarray:
    if sequence_breaks is None:
        return np.zeros(0, np.int64)
    b = np.unique(np.asarray(list(sequence_breaks), dtype=np.int64))
    return b[(b > 0) & (b < n)]


def _bisect(count_fn, target: int, lo: float, hi: float, iters: int = 50):
    """Find rho with count_fn(rho) == target, count non-increasing in rho.

    Returns (rho_low, result_low, rho_high, result_high): the tightest bracket found, with
    count(result_low) >= target >= count(result_high); both equal on an exact hit.
    """
    res_lo = count_fn(lo)
    res_hi = count_fn(hi)
    if res_lo[0] <= target:
        return lo, res_lo, lo, res_lo
    if res_hi[0] >= target:
        return hi, res_hi, hi, res_hi
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        res = count_fn(mid)
        if res[0] == target:
            return mid, res, mid, res
        if res[0] > target:
            lo, res_lo = mid, res
        else:
            hi, res_hi = mid, res
        if hi - lo < 1e-9:
            break
    return lo, res_lo, hi, res_hi


def _select_chain(x, order, target, rho) -> Selection:
    xo = x[order]

    def count(r):
        pos = _chain_ref_positions(xo, r)
        return len(pos), pos

    extra = np.zeros(0, np.int64)
    if rho is None:
        r_lo, (c_lo, pos_lo), r_hi, (c_hi, pos_hi) = _bisect(count, target, 0.0, 2.0)
        tol = BUDGET_TOLERANCE * target
        if abs(c_hi - target) <= tol or c_hi == c_lo:
            rho, pos = r_hi, pos_hi
        elif abs(c_lo - target) <= tol:
            rho, pos = r_lo, pos_lo
        else:
            # The count skipped over the target: top up the below-target result with the frames
            # farthest from the reference the rule compared them against.
            rho, pos = r_hi, pos_hi
            seg = np.searchsorted(pos, np.arange(len(order)), side="right") - 1
            d_ref = 1.0 - np.einsum("ij,ij->i", xo, xo[pos[seg]])
            d_ref[pos] = -np.inf
            extra = np.argsort(-d_ref, kind="stable")[: target - len(pos)]
    else:
        _, pos = count(rho)
    ref_pos = np.union1d(pos, extra)
    parent = np.empty(len(order), np.int64)
    parent[order[1:]] = order[:-1]
    parent[order[ref_pos]] = -1
    return Selection("chain", order[ref_pos], parent, float(rho))


def _select_chain_step(order, steps, target, rho) -> Selection:
    n = len(order)
    if rho is None:
        k = target - 1
        ranked = np.argsort(-steps, kind="stable")
        jumps = np.sort(ranked[:k])
        rho = float(steps[ranked[k]]) if k < len(steps) else 0.0
        if k == 0:
            rho = float(steps.max()) if len(steps) else 0.0
    else:
        jumps = np.flatnonzero(steps > rho)
    ref_pos = np.concatenate([[0], jumps + 1]).astype(np.int64)
    parent = np.empty(n, np.int64)
    parent[order[1:]] = order[:-1]
    parent[order[ref_pos]] = -1
    return Selection("chain-step", order[ref_pos], parent, float(rho))


# --------------------------------------------------------------------------------------------
# Coverage (Oberweger et al.)
# --------------------------------------------------------------------------------------------


def _lazy_greedy_coverage(indptr, indices, n, cap) -> list[int]:
    """Lazy greedy max coverage; ball i = indices[indptr[i]:indptr[i+1]] (contains i)."""
    uncovered = np.ones(n, bool)
    n_uncovered = n
    counts = np.diff(indptr)
    heap = [(-int(c), i) for i, c in enumerate(counts)]
    heapq.heapify(heap)
    chosen: list[int] = []
    while heap and n_uncovered > 0 and len(chosen) < cap:
        neg, i = heapq.heappop(heap)
        ball = indices[indptr[i] : indptr[i + 1]]
        gain = int(np.count_nonzero(uncovered[ball]))
        if heap and gain < -heap[0][0]:
            heapq.heappush(heap, (-gain, i))
            continue
        if gain <= 0:
            break
        chosen.append(i)
        n_uncovered -= gain
        uncovered[ball] = False
    return chosen


def _nearest_reference(x: np.ndarray, refs: np.ndarray, block: int = 4096) -> np.ndarray:
    """(N,) index into ``refs`` of each frame's nearest reference by cosine distance."""
    out = np.empty(len(x), np.int64)
    xr = x[refs]
    for lo in range(0, len(x), block):
        out[lo : lo + block] = np.argmax(x[lo : lo + block] @ xr.T, axis=1)
    return out


def _select_coverage(x, graph: KnnGraph, target, rho) -> Selection:
    n = len(x)
    nbr = np.concatenate([np.arange(n, dtype=np.int32)[:, None], graph.indices], axis=1)
    nd = np.concatenate([np.zeros((n, 1), np.float32), graph.distances], axis=1)

    def run(r, cap=n):
        keep = nd < r
        keep[:, 0] = True  # every frame covers itself
        indptr = np.concatenate([[0], np.cumsum(keep.sum(axis=1))])
        chosen = _lazy_greedy_coverage(indptr, nbr[keep], n, cap)
        return len(chosen), chosen

    if rho is None:
        hi = float(min(2.0, nd.max() + 1e-6))
        # While bisecting, stop each greedy run at K+1 picks: only "more than K?" matters.
        r_lo, (c_lo, ch_lo), r_hi, (c_hi, ch_hi) = _bisect(
            lambda r: run(r, target + 1), target, 0.0, hi, iters=40
        )
        if c_hi == target or (c_lo > target and abs(c_hi - target) <= BUDGET_TOLERANCE * target):
            rho, chosen = r_hi, ch_hi
        else:
            # Oberweger's cap: the smallest radius that needs >= K, stopped at K.
            rho, chosen = r_lo, ch_lo[:target]
            if len(chosen) < target:  # everything within one ball: rerun with the cap
                rho = r_hi
                chosen = run(r_hi)[1]
    else:
        chosen = run(rho)[1]
    refs = np.sort(np.asarray(chosen, np.int64))
    parent = refs[_nearest_reference(x, refs)]
    parent[refs] = -1
    return Selection("coverage", refs, parent, float(rho))


# --------------------------------------------------------------------------------------------
# Uniform in time
# --------------------------------------------------------------------------------------------


def _segments(n: int, breaks: np.ndarray) -> list[tuple[int, int]]:
    edges = np.concatenate([[0], breaks, [n]])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def _select_uniform(n, breaks, target, rho) -> Selection:
    segs = _segments(n, breaks)
    lengths = np.array([b - a for a, b in segs])
    if rho is None:
        # Distribute K over the segments by largest remainder, at least one each.
        k = max(target, len(segs))
        share = lengths * (k / n)
        alloc = np.maximum(1, np.floor(share).astype(int))
        while alloc.sum() < k:
            alloc[np.argmax(share - alloc)] += 1
        while alloc.sum() > k:
            cand = np.where(alloc > 1, alloc - share, -np.inf)
            alloc[np.argmax(cand)] -= 1
        alloc = np.minimum(alloc, lengths)
        threshold = float(n / k)
    else:
        spacing = max(1.0, float(rho))
        alloc = np.maximum(1, np.ceil(lengths / spacing).astype(int))
        threshold = float(rho)
    refs = []
    for (a, b), m in zip(segs, alloc, strict=True):
        step = (b - a) / m
        refs.append(a + np.floor((np.arange(m) + 0.5) * step).astype(np.int64))
    refs = np.unique(np.concatenate(refs))
    parent = _temporal_parents(n, refs, breaks)
    return Selection("uniform", refs, parent, threshold)


def _temporal_parents(n: int, refs: np.ndarray, breaks: np.ndarray) -> np.ndarray:
    """Parent = temporal neighbour towards the nearest reference in time (same segment)."""
    d_prev, d_next = _reference_distances(n, refs, breaks)
    frames = np.arange(n)
    parent = np.where(d_prev <= d_next, frames - 1, frames + 1)
    parent[d_prev == 0] = -1
    return parent


def _reference_distances(n: int, refs: np.ndarray, breaks: np.ndarray):
    """Frames ``(N,)`` to the nearest reference at or before / at or after each frame in its
    segment between ``breaks`` (``10 N`` where there is none)."""
    seg_id = np.searchsorted(breaks, np.arange(n), side="right")
    frames = np.arange(n)
    big = 10 * n
    is_ref = np.zeros(n, bool)
    is_ref[refs] = True
    prev_ref = np.maximum.accumulate(np.where(is_ref, frames, -1))
    next_ref = np.minimum.accumulate(np.where(is_ref, frames, big)[::-1])[::-1]
    d_prev = np.where(
        (prev_ref >= 0) & (seg_id[np.clip(prev_ref, 0, n - 1)] == seg_id), frames - prev_ref, big
    )
    d_next = np.where(
        (next_ref < big) & (seg_id[np.clip(next_ref, 0, n - 1)] == seg_id), next_ref - frames, big
    )
    return d_prev, d_next


def temporal_chains(n: int, refs, breaks=()) -> np.ndarray:
    """Two parent forests ``(2, N)`` over time: every frame between two references (same segment
    between ``breaks``) propagated forwards from the one before it, and backwards from the one
    after it; frames with a reference on one side only chain from that side in both. References
    are ``-1``. Propagation fits both and keeps, per frame, the chain its depth supports
    (:func:`handanno_core.propagate.propagate` with several parent forests)."""
    refs = np.asarray(refs, dtype=np.int64)
    d_prev, d_next = _reference_distances(n, refs, np.asarray(breaks, dtype=np.int64))
    frames = np.arange(n)
    big = 10 * n
    nearest = np.where(d_prev <= d_next, frames - 1, frames + 1)
    forward = np.where(d_prev < big, frames - 1, nearest)
    backward = np.where(d_next < big, frames + 1, nearest)
    out = np.stack([forward, backward])
    out[:, d_prev == 0] = -1
    return out


# --------------------------------------------------------------------------------------------
# Forest (ours): k-centre on kNN-graph geodesics, shortest-path forest
# --------------------------------------------------------------------------------------------


def knn_graph_matrix(
    x: np.ndarray,
    graph: KnnGraph,
    breaks: np.ndarray,
    *,
    temporal: bool = True,
    hop_cost: float = 0.0,
    temporal_weight: float = 1.0,
):
    """Symmetric sparse (N, N) CSR matrix of edge weights: kNN edges plus temporal edges
    (i, i+1) not crossing a sequence break; weight = cosine distance + hop_cost (> 0)."""
    import scipy.sparse as sp

    n = len(x)
    rows = [np.repeat(np.arange(n), graph.k)]
    cols = [graph.indices.reshape(-1).astype(np.int64)]
    w = [graph.distances.reshape(-1).astype(np.float64)]
    if temporal and n > 1:
        i = np.arange(n - 1)
        i = i[~np.isin(i + 1, breaks)]
        rows.append(i)
        cols.append(i + 1)
        d_t = np.clip(1.0 - np.einsum("ij,ij->i", x[i], x[i + 1]), 0.0, 2.0).astype(np.float64)
        w.append(d_t * float(temporal_weight))
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    ww = np.concatenate(w) + max(float(hop_cost), 1e-6)  # explicit zero weights are not edges
    # symmetrize, keeping the minimum weight of duplicate edges
    rr = np.concatenate([r, c])
    cc = np.concatenate([c, r])
    www = np.concatenate([ww, ww])
    key = rr * n + cc
    o = np.lexsort((www, key))
    key, www = key[o], www[o]
    first = np.concatenate([[True], key[1:] != key[:-1]])
    key, www = key[first], www[first]
    return sp.csr_matrix((www, (key // n, key % n)), shape=(n, n))


def _select_forest(x, graph: KnnGraph, breaks, target, rho, hop_cost, temporal_weight) -> Selection:
    from scipy.sparse.csgraph import dijkstra

    n = len(x)
    g = knn_graph_matrix(x, graph, breaks, hop_cost=hop_cost, temporal_weight=temporal_weight)
    d = np.full(n, np.inf)
    refs: list[int] = []
    cap = n if target is None else target
    radius = np.inf
    while len(refs) < n:
        s = int(np.argmax(d)) if refs else 0
        radius = float(d[s])
        if refs and np.isfinite(radius):
            if rho is not None and radius <= rho:
                break
            if len(refs) >= cap:
                break
        refs.append(s)
        limit = radius if np.isfinite(radius) else np.inf
        ds = dijkstra(g, directed=True, indices=s, limit=limit)
        np.minimum(d, ds, out=d)
    refs_arr = np.sort(np.asarray(refs, np.int64))
    _, pred, _ = dijkstra(
        g, directed=True, indices=refs_arr, min_only=True, return_predecessors=True
    )
    parent = pred.astype(np.int64)
    parent[parent < 0] = -1
    parent[refs_arr] = -1
    threshold = float(np.max(d)) if rho is None else float(rho)
    return Selection("forest", refs_arr, parent, threshold)


# --------------------------------------------------------------------------------------------
# Diagnostics: coverage curve (GT only), pictures
# --------------------------------------------------------------------------------------------


def pose_distance_mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Max joint distance (mm) between poses after removing each pose's centroid.

    ``a``, ``b``: (..., J, 3) mm. Returns (...,). Centroid = mean of the J joints, so global
    translation does not count (rotation does: propagation has to follow it).
    """
    a = a - a.mean(axis=-2, keepdims=True)
    b = b - b.mean(axis=-2, keepdims=True)
    return np.linalg.norm(a - b, axis=-1).max(axis=-1)


def forest_stats(gt_joints: np.ndarray, selection: Selection) -> dict[str, float]:
    """Pose-space quality of a selection (GT used only for this diagnostic).

    ``root_mean_mm``: mean over frames of the pose distance to the root reference;
    ``edge_mean_mm``: mean over non-reference frames of the parent-to-child pose distance (what
    each propagation step suffers from); ``path_mean_mm``: mean over frames of the summed edge
    distances to the root; depth statistics in propagation steps.
    """
    gt = np.asarray(gt_joints, dtype=np.float64)
    roots = selection.roots()
    root_d = pose_distance_mm(gt, gt[roots])
    nonref = selection.parent >= 0
    edge = np.zeros(len(gt))
    edge[nonref] = pose_distance_mm(gt[nonref], gt[selection.parent[nonref]])
    path = _path_sums(selection.parent, edge)
    depth = selection.depths()
    return {
        "references": int(len(selection.reference_frames)),
        "root_mean_mm": float(root_d.mean()),
        "root_p95_mm": float(np.percentile(root_d, 95)),
        "edge_mean_mm": float(edge[nonref].mean()) if nonref.any() else 0.0,
        "edge_p95_mm": float(np.percentile(edge[nonref], 95)) if nonref.any() else 0.0,
        "path_mean_mm": float(path.mean()),
        "depth_mean": float(depth.mean()),
        "depth_max": int(depth.max()),
    }


def _path_sums(parent: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """Sum of ``edge`` along each frame's path to its root (pointer jumping, O(N log depth))."""
    n = len(parent)
    acc = np.where(parent >= 0, edge, 0.0)
    up = np.where(parent >= 0, parent, np.arange(n))
    for _ in range(64):
        live = parent[up] >= 0
        if not live.any():
            break
        acc = acc + np.where(live, acc[up], 0.0)
        up = np.where(live, up[up], up)
    return acc


def coverage_curve(
    gt_joints: np.ndarray, selection: Selection, thresholds_mm=range(0, 81)
) -> tuple[np.ndarray, np.ndarray]:
    """Fraction of frames whose pose is within t mm of their root reference's pose.

    ``gt_joints``: (N, J, 3) mm. Pose distance = max joint distance after removing each pose's
    centroid (:func:`pose_distance_mm`); the reference is the one at the root of the frame's
    parent tree. Returns ``(thresholds (T,), fraction (T,))``. As O's
    ``evalReferenceFrameSelection``; GT is used only for this diagnostic.
    """
    t = np.asarray(list(thresholds_mm), dtype=np.float64)
    gt = np.asarray(gt_joints, dtype=np.float64)
    d = pose_distance_mm(gt, gt[selection.roots()])
    frac = (d[None, :] <= t[:, None] + 1e-9).mean(axis=1)
    return t, frac


def plot_coverage(
    curves_or_thresholds,
    fraction_or_path,
    path=None,
    *,
    title: str = "Reference coverage",
) -> None:
    """Write coverage curve(s) from :func:`coverage_curve` to a PNG.

    Either ``plot_coverage(thresholds, fraction, path)`` for one curve, or
    ``plot_coverage({label: (thresholds, fraction), ...}, path)`` for one labelled curve each.
    """
    if path is None:
        curves, path = curves_or_thresholds, fraction_or_path
    else:
        curves = {"": (curves_or_thresholds, fraction_or_path)}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not isinstance(curves, dict):
        curves = {"": tuple(curves)}
    fig, ax = plt.subplots(figsize=(5, 4), dpi=120)
    for label, (t, f) in curves.items():
        ax.plot(t, 100.0 * np.asarray(f), label=label or None)
    ax.set_xlabel("max joint distance to root reference (mm, centroid removed)")
    ax.set_ylabel("frames within distance (%)")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.set_title(title)
    if any(curves):
        ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def embed_2d(descriptors: np.ndarray, *, seed: int = 0) -> np.ndarray:
    """(N, 2) PCA embedding by randomized SVD of the centred descriptors (no N x D copy)."""
    x = np.asarray(descriptors, dtype=np.float32)
    mean = x.mean(axis=0)
    rng = np.random.default_rng(seed)
    omega = rng.standard_normal((x.shape[1], 10)).astype(np.float32)
    y = x @ omega - mean @ omega
    for _ in range(2):  # power iterations
        q, _ = np.linalg.qr(y)
        z = x.T @ q - np.outer(mean, q.sum(axis=0))
        y = x @ z - mean @ z
    q, _ = np.linalg.qr(y)
    b = q.T @ x - np.outer(q.sum(axis=0), mean)  # (10, D)
    _, _, vt = np.linalg.svd(b, full_matrices=False)
    v = vt[:2].T
    return x @ v - mean @ v


def plot_embedding(descriptors: np.ndarray, selection: Selection, path, *, seed: int = 0) -> None:
    """2D PCA embedding of all frames with references highlighted and parent edges faint
    (the thesis's Figures 2 and 7), written as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    e = embed_2d(descriptors, seed=seed)
    n = len(e)
    child = np.flatnonzero(selection.parent >= 0)
    if len(child) > 30000:  # keep the picture light on huge sequences
        child = np.random.default_rng(seed).choice(child, 30000, replace=False)
    fig, ax = plt.subplots(figsize=(6, 6), dpi=120)
    segs = np.stack([e[child], e[selection.parent[child]]], axis=1)
    ax.add_collection(LineCollection(segs, colors="0.5", linewidths=0.3, alpha=0.35))
    ax.scatter(e[:, 0], e[:, 1], s=2, c=np.arange(n), cmap="viridis", lw=0, alpha=0.6)
    r = selection.reference_frames
    ax.scatter(e[r, 0], e[r, 1], s=14, c="red", marker="o", lw=0.3, edgecolors="k", zorder=3)
    ax.set_title(f"{selection.strategy}: {len(r)} references of {n} frames (PCA of descriptors)")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.autoscale()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
