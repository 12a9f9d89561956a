"""Refinement in pieces (handanno_core.pieces): the plan, closeness to the whole solve, resume
from checkpoints (also after a SIGKILL of the CLI), and identical results on local processes and
on a Dask cluster for lift, propagation and refinement (handanno_core.parallel)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from handanno_core.crops import compute_crops, crop_boxes, locate_hands
from handanno_core.datasets import open_sequence
from handanno_core.pieces import plan_pieces, refine_pieces
from handanno_core.refine import refine
from handanno_core.synth import generate_sequence, simulate_annotations

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 96
BREAK = 56
REF_STEP = 8


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """96 synthetic frames with a sequence break at 56, references every 8th frame, a smooth
    time-correlated perturbation of the ground truth as initialization (~6 mm)."""
    path = tmp_path_factory.mktemp("pieces") / "seq"
    generate_sequence(path, frames=FRAMES, seed=11, progress=False, workers=1)
    seq = open_sequence(path)
    centres = locate_hands(seq)
    crops = compute_crops(seq, centres)
    refs = np.arange(0, FRAMES, REF_STEP)
    closest = refs[np.argmin(np.abs(np.arange(FRAMES)[:, None] - refs[None, :]), axis=1)]
    gt = seq.ground_truth.joints_mm
    rng = np.random.default_rng(0)
    noise = gaussian_filter1d(rng.normal(size=gt.shape), sigma=4.0, axis=0, mode="nearest")
    noise *= 6.0 / noise.std()
    noise[refs] *= 0.2
    problem = dict(
        crops=crops,
        boxes=crop_boxes(centres, seq.camera),
        centres_mm=centres,
        camera=seq.camera,
        skeleton=seq.skeleton,
        bone_lengths_mm=seq.skeleton.estimate_bone_lengths(gt),
        reference_frames=refs,
        reference_annotations=simulate_annotations(seq, refs),
        closest_reference=closest,
        sequence_breaks=[BREAK],
    )
    return {"seq": seq, "gt": gt, "init": gt + noise, "problem": problem, "refs": refs}


def test_plan_covers_every_frame_cuts_at_breaks_and_shares_exactly_the_overlap():
    pieces = plan_pieces(1000, [300, 310], window=128, overlap=16)
    covered = np.zeros(1000, dtype=int)
    for p in pieces:
        assert p.stop - p.start <= 128
        covered[p.start : p.stop] += 1
        assert not (p.start < 300 < p.stop) and not (p.start < 310 < p.stop)
    assert covered.min() == 1 and covered.max() == 2
    assert [p.index for p in pieces] == list(range(len(pieces)))
    for a, b in zip(pieces[:-1], pieces[1:], strict=True):
        if b.lead:
            assert a.stop - b.start == 16 == a.trail == b.lead
        else:
            assert a.stop == b.start and a.trail == 0
    assert [(p.start, p.stop, p.lead) for p in pieces if p.start in (300, 310)] == [
        (300, 310, 0),
        (310, 422, 0),  # 690 frames: 7 windows of <= 128, evenly spaced
    ]
    assert len(plan_pieces(50, [], window=128, overlap=16)) == 1
    with pytest.raises(ValueError, match="twice the overlap"):
        plan_pieces(100, [], window=32, overlap=16)


def test_windowed_solve_is_close_to_the_whole_solve(scene):
    gt, init, prob = scene["gt"], scene["init"], scene["problem"]
    whole = refine(init, **prob)
    pieces = refine_pieces(init, window=36, overlap=12, **prob)
    assert len(pieces.pieces) == 4  # 56 frames -> 2 windows, 40 frames -> 2 windows
    diff = np.linalg.norm(pieces.joints_mm - whole.joints_mm, axis=-1)
    err_whole = np.linalg.norm(whole.joints_mm - gt, axis=-1).mean()
    err_pieces = np.linalg.norm(pieces.joints_mm - gt, axis=-1).mean()
    err_init = np.linalg.norm(init - gt, axis=-1).mean()
    assert diff.mean() < 0.5, diff.mean()
    assert err_pieces < err_init - 1.0 and err_pieces < err_whole + 0.2, (err_pieces, err_whole)
    assert pieces.bone_violation_max_mm < 1e-9
    # one piece per sequence (window larger than either): the same problems as the whole solve
    # cut at the break, no seam
    per_seq = refine_pieces(init, window=64, overlap=12, **prob)
    assert [(p.start, p.stop) for p in per_seq.pieces] == [(0, BREAK), (BREAK, FRAMES)]
    d2 = np.linalg.norm(per_seq.joints_mm - whole.joints_mm, axis=-1)
    assert d2.mean() < 0.5, d2.mean()


def test_fixed_frames_keep_their_pose_in_every_piece_that_holds_them(scene):
    """Frames held fixed (a review round's untouched frames) come out as they went in, also
    across a seam between two windows; without the hold the data pulls a shifted stretch back."""
    init, prob = scene["init"], scene["problem"]
    first = refine_pieces(init, window=36, overlap=12, **prob).joints_mm
    held = np.arange(20, 34)  # across the seam of the first sequence's two windows
    shifted = first.copy()
    shifted[held] += np.array([12.0, 0.0, 0.0])  # rigid: still on the bones
    kept = refine_pieces(shifted, window=36, overlap=12, fixed_frames=held, **prob).joints_mm
    assert np.abs(kept[held] - shifted[held]).max() < 1e-6
    free = refine_pieces(shifted, window=36, overlap=12, **prob).joints_mm
    assert np.linalg.norm(free[held] - shifted[held], axis=-1).mean() > 1.0


def test_checkpoints_resume_exactly_and_stale_ones_are_not_used(scene, tmp_path):
    init, prob = scene["init"], dict(scene["problem"], iterations=4)
    ck = tmp_path / "ck"
    first = refine_pieces(init, window=36, overlap=12, checkpoint_dir=ck, **prob)
    files = sorted(ck.glob("piece-*.npz"))
    assert len(files) == 4 and first.resumed == []
    files[2].unlink()
    files[3].write_bytes(b"not an npz")  # a damaged checkpoint is solved again
    lines: list[str] = []
    again = refine_pieces(init, window=36, overlap=12, checkpoint_dir=ck, log=lines.append, **prob)
    assert again.resumed == [0, 1]
    assert any("resuming: 2 of 4 pieces done" in m and "from piece 2" in m for m in lines), lines
    assert any("unreadable checkpoint" in m for m in lines)
    np.testing.assert_array_equal(again.joints_mm, first.joints_mm)
    # other inputs (here bone lengths moved by 1e-9 mm): every checkpoint is stale
    prob["bone_lengths_mm"] = prob["bone_lengths_mm"] + 1e-9
    moved = refine_pieces(init, window=36, overlap=12, checkpoint_dir=ck, **prob)
    assert moved.resumed == []


@pytest.fixture(scope="module")
def propagated_session(tmp_path_factory):
    """A 72-frame synthetic session (selected, annotated from ground truth, lifted, propagated)."""
    from cli_session import propagated_cli_session

    return propagated_cli_session(tmp_path_factory.mktemp("pieces-cli"), frames=72, seed=4)


@pytest.mark.slow
def test_sigkill_during_cli_refine_resumes_from_the_last_piece_and_equals_a_full_run(
    propagated_session, tmp_path
):
    from handanno_core import pipeline
    from handanno_core.session import Session

    folder = tmp_path / "s"
    shutil.copytree(propagated_session, folder)
    cmd = [sys.executable, "-u", "-m", "app.cli", "refine", str(folder), "--window", "24"]
    cmd += ["--overlap", "6"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if line.startswith("piece 1 "):  # pieces 0 and 1 are checkpointed; piece 2 is running
            proc.send_signal(signal.SIGKILL)
            break
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "".join(seen)
    assert len(list((folder / pipeline.REFINE_PIECES_DIR).glob("piece-*.npz"))) == 2
    rerun = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert "resuming: 2 of 4 pieces done" in rerun.stdout, rerun.stdout
    assert "continuing from piece 2 (frames 33-55)" in rerun.stdout, rerun.stdout
    assert "piece 0 " not in rerun.stdout and "piece 1 " not in rerun.stdout
    assert not (folder / pipeline.REFINE_PIECES_DIR).exists()  # removed once the result is saved
    with Session.open(folder) as s:
        resumed = s.load_results()["final_mm"]
        full = pipeline.refine(s, window=24, overlap=6, save=False, resume=False, quiet=True)
    np.testing.assert_array_equal(resumed, full.joints_mm)


@pytest.mark.slow
def test_local_processes_and_a_dask_cluster_give_identical_lift_propagation_refinement(scene):
    distributed = pytest.importorskip("dask.distributed")
    from handanno_core.lift import lift_references
    from handanno_core.propagate import propagate

    seq, prob, refs = scene["seq"], dict(scene["problem"], iterations=4), scene["refs"][:4]
    anns = {int(f): prob["reference_annotations"][int(f)] for f in refs}
    parent = np.arange(FRAMES) - 1
    parent[[0, BREAK]] = -1
    bones = prob["bone_lengths_mm"]

    def lift(**kw):
        return lift_references(dict(anns), seq.depth, seq.camera, seq.skeleton, max_rounds=1, **kw)

    def prop(**kw):
        return propagate(
            parent, {0: scene["gt"][0], BREAK: scene["gt"][BREAK]}, prob["crops"], prob["boxes"],
            prob["centres_mm"], seq.depth, seq.camera, seq.skeleton, bones,
            frames=np.r_[1:16, BREAK + 1 : BREAK + 16], **kw,
        )  # fmt: skip

    def pieces(**kw):
        return refine_pieces(scene["init"], window=36, overlap=12, **prob, **kw)

    here = lift(), prop(), pieces()
    processes = lift(workers=2), prop(workers=2), pieces(workers=2)
    with distributed.LocalCluster(
        n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None
    ) as cluster:
        address = cluster.scheduler_address
        dask = lift(scheduler=address), prop(scheduler=address), pieces(scheduler=address)
    for other in (processes, dask):
        for f in refs:
            np.testing.assert_array_equal(other[0].joints_mm[f], here[0].joints_mm[f])
        np.testing.assert_array_equal(other[0].bone_lengths_mm, here[0].bone_lengths_mm)
        np.testing.assert_array_equal(other[1].joints_mm, here[1].joints_mm)
        np.testing.assert_array_equal(other[1].confidence, here[1].confidence)
        np.testing.assert_array_equal(other[2].joints_mm, here[2].joints_mm)


def test_hand_model_is_personalized_once_and_given_to_every_piece(scene, monkeypatch):
    from handanno_core import handmodel

    made = []
    personalize = handmodel.personalize
    monkeypatch.setattr(
        handmodel, "personalize", lambda *a, **k: made.append(1) or personalize(*a, **k)
    )
    prob = dict(scene["problem"], iterations=2)
    res = refine_pieces(scene["init"], window=36, overlap=12, hand_model=True, **prob)
    assert made == [1] and len(res.pieces) == 4  # one model for all pieces
    assert np.isfinite(res.joints_mm).all()
    # (frames whose model energy rose keep their initialization, bones and all, as in refine)


@pytest.mark.slow
def test_long_sessions_refine_in_pieces_by_default_short_ones_as_one_system(
    propagated_session, tmp_path, monkeypatch
):
    """The default: one whole system up to WHOLE_SOLVE_MAX_FRAMES (the same result as before
    pieces existed), pieces of DEFAULT_WINDOW beyond (here the limit is lowered to 40 frames)."""
    from handanno_core import pipeline
    from handanno_core.pieces import DEFAULT_WINDOW, PiecesResult
    from handanno_core.session import Session

    folder = tmp_path / "s"
    shutil.copytree(propagated_session, folder)
    with Session.open(folder) as s:
        assert s.num_frames == 72 <= pipeline.WHOLE_SOLVE_MAX_FRAMES
        default = pipeline.refine(s, save=False, quiet=True)
        assert not isinstance(default, PiecesResult)
        monkeypatch.setattr(pipeline, "WHOLE_SOLVE_MAX_FRAMES", 40)
        long = pipeline.refine(s, save=False, quiet=True, resume=False)
        windowed = pipeline.refine(s, save=False, quiet=True, resume=False, window=DEFAULT_WINDOW)
        assert isinstance(long, PiecesResult)
        np.testing.assert_array_equal(long.joints_mm, windowed.joints_mm)
        forced = pipeline.refine(s, save=False, quiet=True, whole=True)
        np.testing.assert_array_equal(forced.joints_mm, default.joints_mm)
        with pytest.raises(ValueError, match="whole solve"):
            pipeline.refine(s, save=False, quiet=True, whole=True, window=24)
