import numpy as np
import pytest

from handanno_core.select import (
    STRATEGIES,
    KnnGraph,
    Selection,
    coverage_curve,
    forest_stats,
    knn,
    knn_graph_matrix,
    nn_chain,
    plot_coverage,
    plot_embedding,
    pose_distance_mm,
    select_references,
)


def _normalize(x):
    x = np.asarray(x, np.float64)
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def video_descriptors(n, d=48, seed=0):
    """Descriptors of a video-like sequence: a smooth random walk in a 3-D latent space mapped
    through random cosine features (nearby in time = nearby in appearance, with revisits)."""
    rng = np.random.default_rng(seed)
    z = np.cumsum(rng.standard_normal((n, 3)) * 0.05, axis=0)
    w = rng.standard_normal((3, d))
    b = rng.uniform(0, 2 * np.pi, d)
    x = np.cos(z @ w + b) + 0.05 * rng.standard_normal((n, d))
    x -= x.mean(axis=1, keepdims=True)
    return _normalize(x)


@pytest.fixture(scope="module")
def video():
    return video_descriptors(1000)


@pytest.fixture(scope="module")
def video_graph(video):
    return knn(video, 200)


def brute_chain(x, start):
    n = len(x)
    s = x @ x.T
    visited = np.zeros(n, bool)
    order = [start]
    visited[start] = True
    for _ in range(n - 1):
        row = np.where(visited, -np.inf, s[order[-1]])
        nxt = int(np.argmax(row))
        order.append(nxt)
        visited[nxt] = True
    return np.array(order)


# ------------------------------------------------------------------------------ kNN


@pytest.mark.parametrize("n,k,block", [(300, 5, 64), (120, 40, 50), (50, 49, 1024)])
def test_knn_blocked_equals_brute_force(n, k, block):
    x = video_descriptors(n, seed=n)
    g = knn(x, k, block=block)
    s = x.astype(np.float64) @ x.T.astype(np.float64)
    np.fill_diagonal(s, -np.inf)
    ref = np.argsort(-s, axis=1, kind="stable")[:, :k]
    np.testing.assert_array_equal(g.indices, ref)
    np.testing.assert_allclose(g.distances, 1 - np.take_along_axis(s, ref, axis=1), atol=1e-5)
    assert np.all(np.diff(g.distances, axis=1) >= 0)
    assert not np.any(g.indices == np.arange(n)[:, None])


# ------------------------------------------------------------------------------ chain


def _arc(n, seed=0, d=16):
    """Points on a circular arc (gaps 0.01 + 3e-4 i rad, growing; span < pi) in d dims."""
    i = np.arange(n)
    theta = 0.01 * i + 1.5e-4 * i**2
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((d, 2)))
    pts = np.stack([np.cos(theta), np.sin(theta)], axis=1) @ q.T
    return _normalize(pts)


def test_chain_order_on_shuffled_curve():
    n = 100
    pts = _arc(n)
    rng = np.random.default_rng(1)
    perm = rng.permutation(n)  # frame f holds arc point perm[f]
    m = 40  # start in the middle: walk to the dense end, then jump back (fallback scan)
    f0 = int(np.flatnonzero(perm == m)[0])
    perm[[0, f0]] = perm[[f0, 0]]  # frame 0 holds arc point m
    x = pts[perm]
    order, steps = nn_chain(x, k=3)
    expected_points = np.concatenate([np.arange(m, -1, -1), np.arange(m + 1, n)])
    np.testing.assert_array_equal(perm[order], expected_points)
    np.testing.assert_allclose(
        steps, 1 - np.einsum("ij,ij->i", x[order[:-1]], x[order[1:]]), atol=1e-5
    )


def test_chain_matches_brute_force_on_video(video):
    x = video[:400]
    order, _ = nn_chain(x, k=4)  # small k: many fallback scans
    np.testing.assert_array_equal(order, brute_chain(x, 0))


def test_chain_rule_is_distance_to_previous_reference(video):
    sel = select_references(video, "chain", rho=0.05)
    order, _ = nn_chain(video)
    is_ref = np.zeros(len(video), bool)
    is_ref[sel.reference_frames] = True
    assert is_ref[order[0]]
    ref = order[0]
    for f in order[1:]:
        d = 1 - video[f] @ video[ref]
        assert is_ref[f] == (d > 0.05 + 1e-6) or abs(d - 0.05) < 1e-5
        if is_ref[f]:
            ref = f
        else:
            assert sel.parent[f] >= 0


def test_chain_step_references_follow_the_jumps(video):
    sel = select_references(video, "chain-step", rho=0.03)
    order, steps = nn_chain(video)
    expected = np.sort(np.concatenate([[order[0]], order[1:][steps > 0.03]]))
    np.testing.assert_array_equal(sel.reference_frames, expected)
    pos = np.empty(len(order), int)
    pos[order] = np.arange(len(order))
    nonref = sel.parent >= 0
    assert np.all(pos[sel.parent[nonref]] == pos[nonref] - 1)


# ------------------------------------------------------------------------------ budget, forest


@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("fraction", [0.02, 0.05, 0.10])
def test_budget_met_and_forest_valid(video, video_graph, strategy, fraction):
    n = len(video)
    sel = select_references(
        video, strategy, ref_fraction=fraction, sequence_breaks=[600], graph=video_graph
    )
    target = round(fraction * n)
    assert abs(len(sel.reference_frames) - target) <= 0.02 * target
    sel.validate()
    roots = sel.roots()
    assert set(np.unique(roots)) <= set(sel.reference_frames.tolist())
    assert np.all(sel.parent[sel.reference_frames] == -1)
    assert np.all(np.delete(sel.parent, sel.reference_frames) >= 0)
    d = sel.to_dict()
    assert d["strategy"] == strategy and len(d["parent"]) == n
    assert d["reference_frames"] == sorted(d["reference_frames"])
    assert isinstance(d["reference_frames"][0], int)


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_fewer_references_as_rho_grows(video, video_graph, strategy):
    rhos = [2, 5, 10, 20, 40] if strategy == "uniform" else [0.01, 0.02, 0.04, 0.08, 0.16, 0.3]
    counts = [
        len(select_references(video, strategy, rho=r, graph=video_graph).reference_frames)
        for r in rhos
    ]
    assert all(a >= b for a, b in zip(counts[:-1], counts[1:], strict=True)), counts
    assert counts[0] > counts[-1]


def test_exactly_one_of_budget_or_rho(video):
    with pytest.raises(ValueError, match="exactly one"):
        select_references(video, "chain")
    with pytest.raises(ValueError, match="exactly one"):
        select_references(video, "chain", ref_fraction=0.05, rho=0.1)
    with pytest.raises(ValueError, match="unknown strategy"):
        select_references(video, "kmeans", ref_fraction=0.05)


def test_validate_rejects_cycles_and_bad_roots():
    Selection("x", np.array([0]), np.array([-1, 0, 1])).validate()
    with pytest.raises(ValueError, match="cycle"):
        Selection("x", np.array([0]), np.array([-1, 2, 1])).validate()
    with pytest.raises(ValueError, match="-1 exactly"):
        Selection("x", np.array([0]), np.array([-1, -1, 1])).validate()
    s = Selection("x", np.array([0, 3]), np.array([-1, 0, 1, -1, 3]), 0.1)
    np.testing.assert_array_equal(s.roots(), [0, 0, 0, 3, 3])
    np.testing.assert_array_equal(s.depths(), [0, 1, 2, 0, 1])
    assert Selection.from_dict(s.to_dict()).to_dict() == s.to_dict()


# ------------------------------------------------------------------------------ sequence breaks


def test_uniform_respects_sequence_breaks():
    n = 300
    breaks = [100, 130]
    sel = select_references(
        np.eye(n, 4, dtype=np.float32) + 1, "uniform", ref_fraction=0.05, sequence_breaks=breaks
    )
    sel.validate()
    seg = np.searchsorted(breaks, np.arange(n), side="right")
    assert set(seg[sel.reference_frames]) == {0, 1, 2}  # every segment has a reference
    child = np.flatnonzero(sel.parent >= 0)
    assert np.all(np.abs(sel.parent[child] - child) == 1)
    assert np.all(seg[sel.parent[child]] == seg[child])
    roots = sel.roots()
    assert np.all(seg[roots] == seg)


def test_forest_temporal_edges_cut_at_breaks():
    n = 50
    x = video_descriptors(n)
    empty = KnnGraph(np.zeros((n, 0), np.int32), np.zeros((n, 0), np.float32))
    g = knn_graph_matrix(x, empty, np.array([20]))
    assert g[19, 20] == 0 and g[20, 19] == 0
    assert g[18, 19] > 0 and g[20, 21] > 0 and g[21, 20] == g[20, 21]
    assert g.nnz == 2 * (n - 2)


def test_forest_on_disjoint_segments():
    # two unrelated sequences with disjoint appearance: no kNN edge links them either
    a = video_descriptors(300, seed=1)
    b = video_descriptors(200, seed=2)
    b = np.concatenate([np.zeros((200, 48), np.float32), b], axis=1)
    a = np.concatenate([a, np.zeros((300, 48), np.float32)], axis=1)
    x = np.concatenate([a, b])
    sel = select_references(x, "forest", ref_fraction=0.04, sequence_breaks=[300])
    sel.validate()
    seg = (np.arange(500) >= 300).astype(int)
    assert set(seg[sel.reference_frames]) == {0, 1}
    child = np.flatnonzero(sel.parent >= 0)
    assert np.all(seg[sel.parent[child]] == seg[child])


def test_forest_is_shallower_than_chain(video):
    f = select_references(video, "forest", ref_fraction=0.05)
    c = select_references(video, "chain", ref_fraction=0.05)
    assert f.depths().max() < c.depths().max()


# ------------------------------------------------------------------------------ diagnostics


def test_pose_distance_and_coverage_curve(tmp_path):
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(6, 21, 3)) * 30
    gt[1] = gt[0] + np.array([100.0, -50.0, 20.0])  # a pure translation of frame 0
    assert pose_distance_mm(gt[0], gt[1]) < 1e-9
    sel = Selection("x", np.array([0, 3]), np.array([-1, 0, 1, -1, 3, 4]))
    t, f = coverage_curve(gt, sel, thresholds_mm=range(0, 1000, 10))
    assert f[0] >= 3 / 6 and f[-1] == 1.0 and np.all(np.diff(f) >= 0)
    stats = forest_stats(gt, sel)
    assert stats["references"] == 2 and stats["depth_max"] == 2
    assert stats["path_mean_mm"] >= stats["root_mean_mm"] - 1e-9
    plot_coverage({"x": (t, f)}, tmp_path / "cov.png")
    assert (tmp_path / "cov.png").stat().st_size > 1000
    plot_coverage(t, f, tmp_path / "cov1.png")  # single-curve form used by the pipeline
    assert (tmp_path / "cov1.png").stat().st_size > 1000


def test_plot_embedding(tmp_path, video):
    sel = select_references(video, "forest", ref_fraction=0.05)
    plot_embedding(video, sel, tmp_path / "emb.png")
    assert (tmp_path / "emb.png").stat().st_size > 1000
