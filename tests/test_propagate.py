"""Tests for handanno_core.propagate on a tiny rendered sequence (exact ground truth)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from handanno_core.crops import compute_crops, crop_boxes, crop_depth, locate_hands
from handanno_core.datasets import open_sequence
from handanno_core.datasets.base import FrameError
from handanno_core.propagate import descendants, propagate, propagation_order
from handanno_core.synth import generate_sequence

N = 24


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = generate_sequence(
        tmp_path_factory.mktemp("seq") / "s", frames=N, seed=3, progress=False, workers=1
    )
    seq = open_sequence(path)
    centres = locate_hands(seq)
    crops = compute_crops(seq, centres, None)
    boxes = crop_boxes(centres, seq.camera)
    gt = seq.ground_truth.joints_mm
    bones = seq.skeleton.estimate_bone_lengths(gt)
    return dict(seq=seq, centres=centres, crops=crops, boxes=boxes, gt=gt, bones=bones)


@pytest.fixture(scope="module")
def local_processes(data):
    """The chain forest propagated by two local processes (shared: a pool start is slow)."""
    return run(data, chain_forest(), [0, 12], workers=2)


def chain_forest() -> np.ndarray:
    """References 0 and 12; chains 1..11 and 13..23, with a branch 5 <- 2 (so 3, 4 are siblings)."""
    parent = np.arange(-1, N - 1)
    parent[0] = -1
    parent[12] = -1
    parent[5] = 2
    return parent


def run(data, parent, refs, **kw):
    seq = data["seq"]
    kw.setdefault("depth_of", seq.depth)
    return propagate(
        parent,
        {r: data["gt"][r] for r in refs},
        kw.pop("crops", data["crops"]),
        kw.pop("boxes", data["boxes"]),
        kw.pop("centres", data["centres"]),
        kw.pop("depth_of"),
        seq.camera,
        seq.skeleton,
        data["bones"],
        **kw,
    )


def errors(result, gt, frames):
    return np.linalg.norm(result.joints_mm[frames] - gt[frames], axis=-1)


class NoisyCopy:
    """Frame 1 = frame 0's depth with 0.5 mm noise on the valid pixels."""

    def __init__(self, seq):
        self.seq = seq
        d = seq.depth(0)
        rng = np.random.default_rng(0)
        self.copy = np.where(d > 0, d + rng.normal(0, 0.5, d.shape), 0).astype(np.float32)

    def __call__(self, i):
        return self.seq.depth(0) if i == 0 else self.copy


def test_near_identical_frame_gives_nearly_identical_joints(data):
    seq = data["seq"]
    depth_of = NoisyCopy(seq)
    c = data["centres"][[0, 0]]
    crops = np.stack(
        [data["crops"][0], crop_depth(depth_of(1), seq.camera, c[1]).astype(np.float16)]
    )
    res = run(
        data,
        np.array([-1, 0]),
        [0],
        crops=crops,
        boxes=data["boxes"][[0, 0]],
        centres=c,
        depth_of=depth_of,
    )
    moved = np.linalg.norm(res.joints_mm[1] - data["gt"][0], axis=-1)
    assert moved.mean() < 2.5, moved
    assert moved.max() < 8.0, moved
    # bone lengths are restored exactly (to the fit's tolerance)
    lengths = seq.skeleton.bone_lengths(res.joints_mm[1])
    np.testing.assert_allclose(lengths, data["bones"], atol=0.05)
    assert res.confidence[1].min() > 0.5
    assert res.skipped == []


def test_chain_propagation_is_accurate_and_confident_where_right(data):
    parent = chain_forest()
    res = run(data, parent, [0, 12])
    nonref = np.flatnonzero(parent >= 0)
    err = errors(res, data["gt"], nonref)
    assert np.isfinite(err).all()
    assert err.mean() < 12.0
    assert np.all((res.confidence[nonref] >= 0) & (res.confidence[nonref] <= 1))
    assert np.all(np.isnan(res.joints_mm[[0, 12]]))  # references are not recomputed
    assert res.frame_score.shape == (N,)


def test_parents_are_processed_before_children(data, local_processes):
    parent = chain_forest()
    seen: list[int] = []
    res = run(data, parent, [0, 12], on_result=lambda f, j, c: seen.append(f))
    assert sorted(seen) == sorted(np.flatnonzero(parent >= 0).tolist())
    done = {0, 12}
    for f in seen:
        assert parent[f] in done, (f, parent[f])
        done.add(f)
    # the same holds for the order of the parallel run's tasks
    res2 = local_processes
    pos = {f: i for i, f in enumerate(res2.order)}
    for f in res2.order:
        if parent[f] >= 0 and parent[f] not in (0, 12):
            assert pos[parent[f]] < pos[f]
    np.testing.assert_array_equal(res.joints_mm, res2.joints_mm)
    np.testing.assert_array_equal(res.confidence, res2.confidence)


def test_frame_without_depth_is_skipped_and_reported(data):
    seq = data["seq"]

    def depth_of(i):
        if i == 3:
            return np.zeros_like(seq.depth(0))
        if i == 7:
            raise FrameError("frame7.bin", 7, "truncated file")
        return seq.depth(i)

    parent = np.arange(-1, N - 1)
    parent[0] = -1
    res = run(data, parent, [0], depth_of=depth_of, frames=np.arange(1, 12))
    assert res.skipped == [3, 7]
    assert "no depth" in res.reasons[3] and "truncated" in res.reasons[7]
    assert np.all(np.isnan(res.joints_mm[[3, 7]]))
    # descendants go on from the nearest valid ancestor
    assert res.source[4] == 2 and res.source[8] == 6
    assert np.isfinite(res.joints_mm[[1, 2, 4, 5, 6, 8, 9, 10, 11]]).all()
    assert errors(res, data["gt"], [4, 8]).mean() < 20.0
    # frames outside the subset are untouched
    assert np.all(np.isnan(res.joints_mm[12:]))


def test_descendants_and_incremental_recompute(data):
    parent = chain_forest()
    assert descendants(parent, [2]).tolist() == [2, 3, 4, 5, 6, 7, 8, 9, 10, 11]
    assert descendants(parent, [4]).tolist() == [4]
    assert descendants(parent, [0, 12]).tolist() == list(range(N))
    order = propagation_order(parent, [0])[0]
    assert order[:2].tolist() == [1, 2] and set(order.tolist()) == set(range(1, 12))
    full = run(data, parent, [0, 12])
    sub = descendants(parent, [5])
    part = run(data, parent, [0, 12], frames=sub, previous=full)
    np.testing.assert_array_equal(part.joints_mm[sub], full.joints_mm[sub])
    np.testing.assert_array_equal(part.confidence[sub], full.confidence[sub])
    others = np.setdiff1d(np.arange(N), sub)
    assert np.all(np.isnan(part.joints_mm[others]))
    # from stored arrays only (a session's init_mm/confidence): close, not bit-identical
    part2 = run(
        data,
        parent,
        [0, 12],
        frames=sub,
        initial_mm=full.joints_mm,
        initial_confidence=full.confidence,
    )
    diff = np.linalg.norm(part2.joints_mm[sub] - full.joints_mm[sub], axis=-1)
    assert diff.mean() < 2.0
    # without the ancestors' joints the subset cannot be propagated: reported, not fatal
    part3 = run(data, parent, [0, 12], frames=sub)
    assert part3.skipped == sub.tolist() and "no valid ancestor" in part3.reasons[int(sub[0])]


def test_every_aligner_runs(data):
    parent = np.array([-1, 0, 1] + [-1] * (N - 3))
    for name in ("sift", "ncc"):
        res = run(data, parent, [0], aligner=name, frames=[1, 2])
        err = errors(res, data["gt"], [1, 2])
        assert np.isfinite(err).all() and err.mean() < 15.0, (name, err.mean())
    with pytest.raises(ValueError, match="aligner"):
        run(data, parent, [0], aligner="raft")


def test_dask_cluster_matches_local_processes(data, local_processes):
    distributed = pytest.importorskip("dask.distributed")
    parent = chain_forest()
    local = local_processes
    with distributed.LocalCluster(
        n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None
    ) as cluster:
        remote = run(data, parent, [0, 12], scheduler=cluster.scheduler_address)
    np.testing.assert_array_equal(local.joints_mm, remote.joints_mm)
    np.testing.assert_array_equal(local.confidence, remote.confidence)
    assert local.skipped == remote.skipped


def test_implausible_reference_is_reported_not_propagated(data):
    seq = data["seq"]
    parent = np.array([-1, 0, 1] + [-1] * (N - 3))
    broken = data["gt"][0] * np.array([1.0, 1.0, -1.0])  # behind the camera
    res = propagate(
        parent, {0: broken}, data["crops"], data["boxes"], data["centres"], seq.depth,
        seq.camera, seq.skeleton, data["bones"], frames=[1, 2],
    )  # fmt: skip
    assert res.skipped == [1, 2]
    assert "implausible" in res.reasons[1]


def test_hidden_joints_move_rigidly_with_the_seen_ones():
    from handanno_core.propagate import PropagationSettings, _carry_rigidly

    rng = np.random.default_rng(4)
    joints = rng.normal(0.0, 40.0, (21, 3)) + [0.0, 0.0, 400.0]
    angle = np.radians(20.0)
    rot = np.array(
        [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0, 0, 1]]
    )
    moved = (joints - joints.mean(0)) @ rot.T + joints.mean(0) + [12.0, -5.0, 8.0]
    seen = np.zeros(21, dtype=bool)
    seen[[0, 1, 5, 9, 13]] = True
    st = PropagationSettings()
    # only the seen joints' new positions are known; the hidden ones follow the same motion
    observed = np.where(seen[:, None], moved, np.nan)
    np.testing.assert_allclose(_carry_rigidly(joints, observed, seen, st), moved, atol=1e-6)
    # too few seen joints for a rotation: the mean displacement of the seen ones
    few = np.zeros(21, dtype=bool)
    few[[0, 1]] = True
    shift = (moved[few] - joints[few]).mean(0)
    np.testing.assert_allclose(_carry_rigidly(joints, observed, few, st), joints + shift)


def fast_data(folder, n: int, seed: int = 3) -> dict:
    """A rendered sequence of ``n`` frames at the suite's fast-motion speed."""
    from handanno_core import suite, synth

    motion = synth.synthesize_motion(
        n, seed, speed_mm=suite.FAST_SPEED_MM, hold_frames=suite.FAST_HOLD_FRAMES
    )
    path = synth.write_sequence(
        folder, motion.model, motion.joints_mm, motion.rotation, seed=seed, progress=False,
        workers=1,
    )  # fmt: skip
    seq = open_sequence(path)
    gt = seq.ground_truth.joints_mm
    assert np.linalg.norm(np.diff(gt, axis=0), axis=-1).mean() >= 10.0
    centres = locate_hands(seq)
    return dict(
        seq=seq, gt=gt, crops=compute_crops(seq, centres, None), centres=centres,
        boxes=crop_boxes(centres, seq.camera), bones=seq.skeleton.estimate_bone_lengths(gt),
    )  # fmt: skip


def test_model_starts_at_the_parents_velocity_or_the_reference_follow_fast_motion(tmp_path):
    """At the suite's fast-motion speed (>= 10 mm joint steps), a chain whose hand-model fit may
    start from the parent moved on at its own velocity stays on the hand; so does one that may
    start from the reference's pose turned into the flowed pose's palm (``reference_starts``);
    from the flowed pose and the parent's pose alone it loses it within a few frames."""
    from handanno_core.propagate import PropagationSettings

    n = 16
    data = fast_data(tmp_path / "fast", n)
    gt = data["gt"]
    chain = np.arange(-1, n - 1)

    def mean_error(velocity: bool, reference: int) -> float:
        st = PropagationSettings(velocity_start=velocity, reference_starts=reference)
        result = run(data, chain, [0], hand_model=True, settings=st)
        return float(errors(result, gt, np.arange(1, n)).mean())

    assert mean_error(True, 0) < 10.0 < mean_error(False, 0)
    assert mean_error(False, 8) < 10.0


def test_both_directions_keep_the_chain_the_frames_depth_supports(tmp_path):
    """Fast motion between two references: every frame is carried forwards from the first and
    backwards from the second, and keeps the candidate whose hand-model fit explains its depth
    best; that beats either direction alone. A partial run from one changed frame recomputes
    its descendants in both chains. (Without the per-finger hypotheses, which rescue most of the
    frames either chain alone loses here: with them, both directions are 5.04 mm, the backward
    chain alone 5.01; without the pose prior, which keeps the forward chain's fits good
    enough here that no backward candidate is needed; and without the reference starts, which
    hold the forward chain on the hand here as well.)"""
    from handanno_core.handmodel import FitWeights
    from handanno_core.propagate import PropagationSettings
    from handanno_core.select import temporal_chains

    n = 20
    data = fast_data(tmp_path / "fast", n, seed=3)
    gt = data["gt"]
    refs = [0, n - 1]
    chains = temporal_chains(n, refs)
    assert chains[0][5] == 4 and chains[1][5] == 6
    plain = PropagationSettings(finger_hypotheses=False, reference_starts=0)
    no_prior = FitWeights(prior=0.0)
    forward = run(data, chains[0], refs, hand_model=True, fit_weights=no_prior, settings=plain)
    backward = run(data, chains[1], refs, hand_model=True, fit_weights=no_prior, settings=plain)
    both = run(data, chains, refs, hand_model=True, fit_weights=no_prior,
               settings=replace(plain, candidate_level=0))  # fmt: skip
    inner = np.arange(1, n - 1)
    steps = {0: inner, 1: n - 1 - inner}  # propagation steps from each chain's reference
    penalty = PropagationSettings().chain_step_penalty
    for i, f in enumerate(inner):
        level = [r.model_fit[f, 0] * (1 + penalty * steps[k][i]) for k, r in
                 enumerate((forward, backward))]  # fmt: skip
        k = int(level[1] < level[0])
        np.testing.assert_array_equal(both.joints_mm[f], (forward, backward)[k].joints_mm[f])
        assert both.source[f] == chains[k][f]
    mean = {name: errors(r, gt, inner).mean() for name, r in
            (("forward", forward), ("backward", backward), ("both", both))}  # fmt: skip
    assert mean["both"] < min(mean["forward"], mean["backward"]), mean
    # the backward chain is computed only where a forward fit is above candidate_level (and for
    # its ancestors): frames before the first poorly fitted one keep the forward result. The
    # level here is the forward fits' upper quartile, so that some are above it whatever the
    # references' level (by default 2x the references')
    level = float(np.quantile(forward.model_fit[inner, 0], 0.75))
    adaptive = run(data, chains, refs, hand_model=True, fit_weights=no_prior,
                   settings=replace(plain, candidate_level=level))  # fmt: skip
    bad = inner[forward.model_fit[inner, 0] > level]
    assert len(bad) and bad[0] > 1
    np.testing.assert_array_equal(adaptive.joints_mm[1 : bad[0]], forward.joints_mm[1 : bad[0]])
    np.testing.assert_array_equal(adaptive.joints_mm[bad], both.joints_mm[bad])
    partial = run(data, chains, refs, hand_model=True, fit_weights=no_prior, frames=[7], previous=both,
                  settings=replace(plain, candidate_level=0))  # fmt: skip
    np.testing.assert_array_equal(partial.joints_mm[inner], both.joints_mm[inner])
    with pytest.raises(ValueError, match="same references"):
        run(data, np.stack([chains[0], np.arange(-1, n - 1)]), refs)
