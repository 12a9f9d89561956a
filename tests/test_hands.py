"""Several people's hands in one session: hand labels, the lift per hand, per-frame bone lengths.

Fixture: a small MSRA layout with two subjects of clearly different hands (``P0/1``, ``P0/2``
drawn with ``make_hand_model(0)``, ``P3/1`` with ``make_hand_model(3)``), as
``benchmarks/bench_scale.py --hands subject`` writes the 76k dataset.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from handanno_core import pipeline, synth
from handanno_core.datasets.msra import MSRASequence
from handanno_core.hands import bone_table
from handanno_core.session import Session, SetFrameAnnotation

FRAMES = 24
FOLDERS = (("P0", "1", 0), ("P0", "2", 0), ("P3", "1", 3))  # subject, gesture, hand seed


def _write(data: Path) -> None:
    for k, (subject, gesture, hand) in enumerate(FOLDERS):
        seed = 1000 + k
        motion = synth.synthesize_motion(FRAMES, seed, model=synth.make_hand_model(hand))
        synth.write_sequence(
            data / subject / gesture, motion.model, motion.joints_mm, motion.rotation, seed=seed,
            progress=False, workers=1,
        )  # fmt: skip


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hands") / "data"
    _write(root)
    return root


def _run(folder: Path, data: Path, *, one_hand: bool, pinned=None, window=None) -> Session:
    s = pipeline.new_session(folder, data, format="msra", one_hand=one_hand)
    pipeline.select(s, strategy="uniform", ref_fraction=0.2, figures=False, quiet=True)
    pipeline.annotate_from_gt(s, quiet=True)
    if pinned is not None:
        s.set_bone_lengths(pinned, pinned=True)
    pipeline.lift(s, quiet=True)
    pipeline.propagate(s, quiet=True)
    pipeline.refine(s, quiet=True, window=window)
    return s


@pytest.fixture(scope="module")
def runs(data, tmp_path_factory):
    """The same pipeline (20 % uniform references, exact simulated 2D) with per-hand bones and
    with ``one_hand``."""
    root = tmp_path_factory.mktemp("runs")
    per_hand = _run(root / "hands", data, one_hand=False)
    one = _run(root / "one", data, one_hand=True)
    yield per_hand, one
    per_hand.close()
    one.close()


def _true_bones(data: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(N, B)`` each frame's true bone lengths (ground truth: evaluation only) and ``(N,)`` the
    frame's hand (0: P0, 1: P3)."""
    seq = MSRASequence(data)
    gt = seq.ground_truth.joints_mm
    hand = np.repeat([0, 0, 1], FRAMES)
    return seq.skeleton.bone_lengths(gt), hand


def test_msra_reader_labels_the_subject_folders(data):
    seq = MSRASequence(data)
    assert seq.hand_labels == ["P0", "P0", "P3"]
    assert len(seq.hand_labels) == len(seq.sequence_breaks) + 1
    # a subject's own folder (gesture folders directly below): no subject to name, one hand
    assert MSRASequence(data / "P0").hand_labels is None


def test_new_session_takes_the_labels_unless_one_hand(data, tmp_path):
    with pipeline.new_session(tmp_path / "a", data) as s:
        assert s.model.hands == ["P0", "P0", "P3"]
        assert s.hand_names == ["P0", "P3"]
        assert s.hand_of_frame().tolist() == [0] * 2 * FRAMES + [1] * FRAMES
    with pipeline.new_session(tmp_path / "b", data, one_hand=True) as s:
        assert s.model.hands == [] and s.hand_of_frame().tolist() == [0] * 3 * FRAMES
    with pipeline.new_session(tmp_path / "c", data, breaks="10") as s:  # labels need their breaks
        assert s.model.hands == []


def test_cli_one_hand_option(data, tmp_path):
    from app.cli import main

    base = ["--sessions-dir", str(tmp_path)]
    assert main([*base, "new", "a", str(data)]) == 0
    assert main([*base, "new", "b", str(data), "--one-hand"]) == 0
    assert json.loads((tmp_path / "a/session.json").read_text())["hands"] == ["P0", "P0", "P3"]
    assert json.loads((tmp_path / "b/session.json").read_text())["hands"] == []


def test_lift_estimates_each_hands_bones_closer_than_one_shared_set(runs, data):
    per_hand, one = runs
    truth, hand = _true_bones(data)
    table = per_hand.model.hand_bone_lengths_mm
    assert sorted(table) == ["P0", "P3"]
    shared = np.asarray(one.model.bone_lengths_mm)
    for h, name in enumerate(("P0", "P3")):
        true_h = truth[hand == h].mean(axis=0)
        own = np.abs(np.asarray(table[name]) / true_h - 1).mean()
        common = np.abs(shared / true_h - 1).mean()
        assert own < common, (name, own, common)
    # the session-level lengths are the hands' mean (what the app shows)
    np.testing.assert_allclose(
        per_hand.model.bone_lengths_mm, np.mean([table["P0"], table["P3"]], axis=0)
    )


def test_every_stage_keeps_each_frames_own_hands_bones(runs, data):
    per_hand, _ = runs
    sk = per_hand.skeleton
    own = per_hand.frame_bone_lengths()
    assert own.shape == (3 * FRAMES, len(sk.bones))
    hand = per_hand.hand_of_frame()
    table = per_hand.model.hand_bone_lengths_mm
    np.testing.assert_array_equal(own[hand == 1][0], table["P3"])
    res = per_hand.load_results()
    # propagation: stiff soft bones (within 1 %), whatever hand the parent in the forest shows
    init = sk.bone_lengths(res["init_mm"])
    assert np.nanmax(np.abs(init / own - 1)) < 0.01
    # refinement: hard bones, the frame's own hand's
    np.testing.assert_allclose(sk.bone_lengths(res["final_mm"]), own, atol=1e-6)


def test_refinement_in_pieces_keeps_each_hands_bones(data, tmp_path):
    with _run(tmp_path / "p", data, one_hand=False, window=16) as s:
        sk = s.skeleton
        np.testing.assert_allclose(
            sk.bone_lengths(s.load_results()["final_mm"]), s.frame_bone_lengths(), atol=1e-6
        )


def test_pinned_bones_pin_every_hand_and_match_one_hand_bit_for_bit(data, tmp_path):
    """Pinned bones are every hand's: the per-hand path then gives exactly the one-hand result
    (lift per hand group, propagation and refinement with per-frame bones)."""
    pinned = np.asarray(MSRASequence(data).skeleton.template_bone_lengths_mm) * 1.02
    with (
        _run(tmp_path / "a", data, one_hand=False, pinned=pinned) as a,
        _run(tmp_path / "b", data, one_hand=True, pinned=pinned) as b,
    ):
        assert a.model.hands and not b.model.hands
        ra, rb = a.load_results(), b.load_results()
        for key in ("lifted_mm", "init_mm", "final_mm", "confidence"):
            np.testing.assert_array_equal(ra[key], rb[key], err_msg=key)


def test_identical_rows_run_the_one_hand_code_bit_for_bit(runs):
    """``(N, B)`` bones with one distinct row give exactly the ``(B,)`` results."""
    from handanno_core.propagate import propagate
    from handanno_core.refine import refine

    _, one = runs
    bones = one.frame_bone_lengths()
    assert bones.shape == (len(one.skeleton.bones),)
    wide = np.repeat(bones[None], one.num_frames, axis=0)
    crops, centres, boxes = pipeline.ensure_crops(one, quiet=True)
    seq = one.open_sequence()
    refs = pipeline._reference_joints(one, one.load_results())
    args = (one.parent, refs, crops, boxes, centres, seq.depth, one.camera, one.skeleton)
    model = one.model.settings.hand_model  # as the session ran (the hand model, by default)
    a, b = propagate(*args, bones, hand_model=model), propagate(*args, wide, hand_model=model)
    np.testing.assert_array_equal(a.joints_mm, b.joints_mm)
    init, problem = pipeline.refine_inputs(one, quiet=True)
    ra = refine(init, **problem, hand_model=model)
    rb = refine(init, **(problem | {"bone_lengths_mm": wide}), hand_model=model)
    np.testing.assert_array_equal(ra.joints_mm, rb.joints_mm)
    np.testing.assert_array_equal(one.load_results()["final_mm"], ra.joints_mm)


def test_old_session_without_hand_fields_opens_as_one_hand(runs, tmp_path):
    import shutil

    _, one = runs
    old = tmp_path / "old"
    shutil.copytree(one.folder, old, ignore=shutil.ignore_patterns("session.lock"))
    doc = json.loads((old / "session.json").read_text())
    doc.pop("hands")
    doc.pop("hand_bone_lengths_mm")
    (old / "session.json").write_text(json.dumps(doc))
    with Session.open(old) as s:
        assert s.hand_names == [""] and s.model.hands == []
        np.testing.assert_array_equal(s.frame_bone_lengths(), one.model.bone_lengths_mm)
        assert s.bone_lengths_of(5) == one.model.bone_lengths_mm


def test_hand_without_reference_gets_the_others_mean(data, tmp_path):
    with pipeline.new_session(tmp_path / "s", data) as s:
        pipeline.select(s, strategy="uniform", ref_fraction=0.2, figures=False, quiet=True)
        pipeline.annotate_from_gt(s, quiet=True)
        for f in s.reference_frames[s.hand_of_frame()[s.reference_frames] == 1]:
            s.execute(SetFrameAnnotation(frame=int(f), annotation=None))
        pipeline.lift(s, quiet=True)
        table = s.model.hand_bone_lengths_mm
        assert table["P3"] == table["P0"] == s.model.bone_lengths_mm


def test_bone_table_shapes():
    t = bone_table(np.array([[1.0, 2.0], [1.0, 2.0], [3.0, 4.0]]), 3, 2)
    assert (
        not t.single
        and t.of(2).tolist() == [3.0, 4.0]
        and t.frames_of(t.hand[0]).tolist() == [0, 1]
    )
    assert bone_table(np.array([1.0, 2.0]), 3, 2).single
    with pytest.raises(ValueError, match=r"\(2,\) or \(3, 2\)"):
        bone_table(np.ones((2, 2)), 3, 2)


def test_hands_option_gives_labels_and_names_a_wrong_count(data, tmp_path):
    from app.cli import main

    base = ["--sessions-dir", str(tmp_path)]
    assert main([*base, "new", "a", str(data), "--hands", "x,y,y"]) == 0
    with Session.open(tmp_path / "a") as s:
        assert s.model.hands == ["x", "y", "y"] and s.hand_names == ["x", "y"]
    labels = tmp_path / "hands.txt"
    labels.write_text("x\nx\nx\n")  # one label: one hand
    assert main([*base, "new", "b", str(data), "--hands", str(labels)]) == 0
    assert json.loads((tmp_path / "b/session.json").read_text())["hands"] == []
    with pytest.raises(Exception, match="2 hand labels for 3 sequences"):
        pipeline.new_session(tmp_path / "c", data, hands="x,y")
    assert not (tmp_path / "c").exists()
