"""The frame each propagated result came from (``results.npz`` ``source``): stored by the
pipeline, kept by a partial re-propagation outside the recomputed frames, read back after reopening,
shown by the app and the CLI, and filled from the selection's parent for an old file without it."""

from __future__ import annotations

import numpy as np
import pytest

from app.control.live import LiveResults
from app.control.review import frame_text
from handanno_core import pipeline
from handanno_core.results import NO_SOURCE, RESULTS_FILE, ResultsError, Stage, read_results
from handanno_core.session import Session, atomic_save_npz

N = 20


@pytest.fixture(scope="module", autouse=True)
def plain_model_fit():
    """The module's propagations without the per-finger hypotheses: on this 20-frame sequence
    they repair the forward chain's fingers, and then no frame keeps the backward chain, which is
    what the tests need (``test_propagate`` does the same for its both-ways test)."""
    from handanno_core.propagate import PropagationSettings

    make = PropagationSettings.from_session.__func__
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(
            PropagationSettings,
            "from_session",
            classmethod(lambda cls, s, **o: make(cls, s, **({"finger_hypotheses": False} | o))),
        )
        yield


@pytest.fixture(scope="module")
def fast_session(tmp_path_factory, plain_model_fit):
    """A session on a fast-motion sequence (the suite's fast speed, as ``test_propagate.fast_data``)
    with references 0 and N-1, the selection's forest the forward chain, lifted joints from ground
    truth, propagated with the hand model both ways (forward and backward candidates)."""
    from handanno_core import suite, synth

    root = tmp_path_factory.mktemp("source")
    motion = synth.synthesize_motion(
        N, 3, speed_mm=suite.FAST_SPEED_MM, hold_frames=suite.FAST_HOLD_FRAMES
    )
    data = synth.write_sequence(
        root / "data", motion.model, motion.joints_mm, motion.rotation, seed=3, progress=False,
        workers=1,
    )  # fmt: skip
    session = pipeline.new_session(root / "sess", data, format="msra", overwrite=True)
    refs = [0, N - 1]
    parent = [-1 if f in refs else f - 1 for f in range(N)]
    session.set_selection({"strategy": "chain", "reference_frames": refs, "parent": parent})
    gt = session.open_sequence().ground_truth.joints_mm
    lifted = np.full_like(gt, np.nan)
    lifted[refs] = gt[refs]
    session.save_results(lifted_mm=lifted)
    session.set_bone_lengths(session.skeleton.estimate_bone_lengths(gt))
    session.model.settings.aligner = "dis"
    # the backward chain computed for every frame (``candidate_level`` 0), not only where the
    # forward chain's fit is poor: whether any frame is poor here depends on how well the hand
    # model fits, and the first test needs a frame that kept the backward chain
    from handanno_core.propagate import PropagationSettings

    make = PropagationSettings.from_session
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(
            PropagationSettings,
            "from_session",
            classmethod(lambda cls, s, **o: make(s, **({"candidate_level": 0.0} | o))),
        )
        pipeline.propagate(session, quiet=True, use_model=True)
    session.close()
    return root / "sess"


def test_a_frame_that_kept_the_backward_chain_stores_and_shows_it(fast_session, capsys):
    from app.cli import main

    with Session.open(fast_session) as session:
        res = session.load_results()
        parent = session.parent
        src = res["source"]
        assert src.dtype == np.int64
        inner = np.arange(1, N - 1)
        # every propagated frame came from a temporal neighbour; the references from nowhere
        assert np.all((src[inner] == inner - 1) | (src[inner] == inner + 1))
        assert src[0] == src[N - 1] == NO_SOURCE
        backward = inner[src[inner] == inner + 1]
        assert len(backward), "no frame kept the backward chain on this sequence"
        f = int(backward[0])
        assert parent[f] == f - 1 != src[f]
        # the app's review panel shows the kept source, not the selection's parent
        live = LiveResults(session)
        try:
            assert live.source(f) == f + 1
            _, stage = live.frame(f)
            text = frame_text(f, stage, False, live.source(f), None)
            assert f"propagated from frame {f + 1}" in text
            assert f"from frame {f - 1}" not in text
            assert "propagated from" not in frame_text(0, 1, True, live.source(0), None)
            # a running job's fresh result: its source is unknown until the job's results are saved
            joints, _ = live.frame(f)
            live.put(f, joints, None, Stage.PROPAGATED)
            assert live.source(f) == NO_SOURCE
            live.reload()
            assert live.source(f) == f + 1
        finally:
            live.stop_ranking()
    # the CLI says so too
    assert main(["info", str(fast_session), "--frame", str(f), "--frame", "0"]) in (0, None)
    out = capsys.readouterr().out
    assert f"propagated from frame {f + 1}, not the selection's parent {f - 1}" in out
    assert "frame 0: reference" in out
    assert f"{len(backward)} kept another chain than the selection's parent" in out


def test_a_partial_repropagation_updates_only_the_recomputed_sources(fast_session, tmp_path):
    """A review correction re-propagates the frames between its neighbouring references; the
    frames of the other segment keep their stored sources."""
    import shutil

    folder = tmp_path / "sess"
    shutil.copytree(fast_session, folder)
    mid, fix = N // 2, 5

    def select(refs):
        parent = [-1 if f in refs else f - 1 for f in range(N)]
        session.set_selection({"strategy": "chain", "reference_frames": refs, "parent": parent})
        lifted = session.load_results()["lifted_mm"]
        lifted[refs] = gt[refs]
        session.save_results(lifted_mm=lifted)

    with Session.open(folder) as session:
        gt = session.open_sequence().ground_truth.joints_mm
        select([0, mid, N - 1])
        pipeline.propagate(session, quiet=True, use_model=True)
        before = session.load_results()["source"]
        select([0, fix, mid, N - 1])  # frame 5 corrected: a new reference
        frames = pipeline.frames_to_repropagate(session, [fix], use_model=True)
        frames = frames[session.parent[frames] >= 0]  # as the app's review runner
        np.testing.assert_array_equal(frames, [f for f in range(1, mid) if f != fix])
        result = pipeline.propagate(session, quiet=True, use_model=True, frames=frames)
    with Session.open(folder) as session:  # reopened: what is on disk
        after = session.load_results()["source"]
    np.testing.assert_array_equal(after[frames], result.source[frames])
    assert before[fix] >= 0 and after[fix] == NO_SOURCE
    untouched = np.setdiff1d(np.arange(N), np.append(frames, fix))
    np.testing.assert_array_equal(after[untouched], before[untouched])
    assert np.all(after[mid + 1 : N - 1] >= 0)


def test_an_old_results_file_without_source_opens_with_the_selection_parent(fast_session, tmp_path):
    import shutil

    folder = tmp_path / "sess"
    shutil.copytree(fast_session, folder)
    with np.load(folder / RESULTS_FILE) as z:
        old = {k: z[k] for k in z.files if k != "source"}
    init = old["init_mm"]
    init[5] = np.nan  # a frame without a propagated result has no source either
    atomic_save_npz(folder / RESULTS_FILE, old)
    with Session.open(folder) as session:
        res = session.load_results()
        parent = session.parent
        expected = np.where(parent >= 0, parent, NO_SOURCE)
        expected[5] = NO_SOURCE
        np.testing.assert_array_equal(res["source"], expected)
        # the first save writes it; a partial results file keeps its other arrays
        session.save_results(confidence=res["confidence"])
    with np.load(folder / RESULTS_FILE) as z:
        np.testing.assert_array_equal(z["source"], expected)
    # without the session's forest (a bare read), nothing is claimed
    atomic_save_npz(tmp_path / "old.npz", old)
    bare = read_results(tmp_path / "old.npz", N, init.shape[1])
    assert np.all(bare["source"] == NO_SOURCE)
    np.testing.assert_array_equal(bare["init_mm"], init)
    # a source outside the session's frames is another session's file: a clear error
    atomic_save_npz(tmp_path / "bad.npz", old | {"source": np.full(N, N)})
    with pytest.raises(ResultsError, match=r"bad\.npz: source holds frames outside 0-19"):
        read_results(tmp_path / "bad.npz", N, init.shape[1])
