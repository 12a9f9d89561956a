"""Pre-filled references: the frame's own results first, else one propagation step from the
nearest frame with joints, else that neighbour's joints; None when nothing has joints."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from review_session import STEP, open_review_session, synth_data

from handanno_core.datasets.base import segment_ids
from handanno_core.prefill import _nearest_known, prefill_reference, prefill_uv

FRAMES = 30


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return synth_data(tmp_path_factory, "prefill-data", FRAMES, seed=2)


@pytest.fixture()
def session(data_dir, tmp_path):
    yield from open_review_session(tmp_path / "sess", data_dir)


def errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=-1)


def test_the_frames_own_results_come_first(session):
    results = session.load_results()
    gt = session.open_sequence().ground_truth.joints_mm
    results["init_mm"][7] = gt[7] + 2.0
    results["final_mm"][7] = gt[7] + 1.0
    before = {k: v.copy() for k, v in results.items()}
    out = prefill_reference(session, 7, results)
    np.testing.assert_allclose(out, gt[7] + 1.0)
    results["final_mm"][7] = np.nan
    np.testing.assert_allclose(prefill_reference(session, 7, results), gt[7] + 2.0)
    out[:] = 0.0  # a copy: the caller may edit it
    assert np.isfinite(results["init_mm"][7]).all()
    for key in ("lifted_mm", "confidence"):
        np.testing.assert_array_equal(results[key], before[key])


def test_propagates_from_the_nearest_lifted_reference(session):
    from handanno_core.pipeline import ensure_crops

    ensure_crops(session, quiet=True)
    gt = session.open_sequence().ground_truth.joints_mm
    results = session.load_results()
    results["lifted_mm"][1:] = np.nan  # only frame 0 is lifted: the hand moves ~6 mm until 25
    frame = 25
    out = prefill_reference(session, frame, results)
    assert out.shape == (session.skeleton.num_joints, 3)
    copied = errors(gt[0], gt[frame]).mean()
    flowed = errors(out, gt[frame]).mean()
    assert flowed < 0.5 * copied, (flowed, copied)  # the flow step follows the hand
    # its bones are the session's
    np.testing.assert_allclose(
        session.skeleton.bone_lengths(out), session.model.bone_lengths_mm, rtol=0.02
    )
    uv = prefill_uv(session, out)
    np.testing.assert_allclose(uv, session.camera.project(out))
    # the results passed in are used (and not read from disk): drop the references -> None
    results["lifted_mm"][:] = np.nan
    assert prefill_reference(session, frame, results) is None


def test_without_crops_the_neighbours_joints(session):
    results = session.load_results()
    out = prefill_reference(session, 2 * STEP - 2, results)  # no crops on disk
    np.testing.assert_allclose(out, results["lifted_mm"][2 * STEP])
    with pytest.raises(ValueError, match="outside"):
        prefill_reference(session, FRAMES, results)


def test_nearest_known_stays_in_its_segment():
    has = np.zeros(20, bool)
    has[[2, 11, 19]] = True
    seg = segment_ids(20, [10])
    assert _nearest_known(8, has, seg) == 2  # 11 is nearer but across the break
    assert _nearest_known(12, has, seg) == 11
    assert _nearest_known(15, has, seg) == 11  # ties -> earlier
    assert _nearest_known(5, np.zeros(20, bool), seg) is None
    has2 = np.zeros(20, bool)
    has2[15] = True
    assert _nearest_known(3, has2, seg) == 15  # nothing in its segment: across the break


def test_bench_annotator_opens_references_prefilled(session):
    from handanno_core.pipeline import ensure_crops
    from handanno_core.review_loop import annotate_prefilled

    ensure_crops(session, quiet=True)
    refs = session.reference_frames.tolist()  # 0, 10, 20
    entries_before = len(session.folder.joinpath("journal.jsonl").read_text().splitlines())
    info = annotate_prefilled(session, quiet=True)
    assert refs[0] not in info["prefilled"]  # nothing to pre-fill it from
    # it opens with the template hand at its hand centre, as in the app
    assert info["template"] == [refs[0]] and info["clicks"][refs[0]] < 21
    assert info["prefilled"] == refs[1:]
    assert all(info["clicks"][f] < 21 for f in refs[1:])  # the guesses were mostly right
    assert info["clicks_per_reference"] == pytest.approx(np.mean(list(info["clicks"].values())))
    # one guess moved at a time, in the order recorded
    assert all(len(info["click_order"][f]) == info["clicks"][f] for f in refs[1:])
    gt = session.open_sequence().ground_truth.joints_mm
    for f in refs:
        ann = session.annotation(f)
        off = np.linalg.norm(ann.uv_px - session.camera.project(gt[f]), axis=1)
        assert np.all(off <= 4.0 + 1e-9)  # every joint within 4 px: moved, or accepted
        # the journal says which: the joints not moved are accepted guesses
        moved = np.isin(np.arange(21), info["click_order"][f])
        assert ann.accepted.tolist() == (~moved).tolist()
    lines = session.folder.joinpath("journal.jsonl").read_text().splitlines()
    assert len(lines) == entries_before + 1  # one journal entry, one undo step


def test_hand_model_snaps_the_prefill_to_the_frames_depth(session):
    from handanno_core.pipeline import ensure_crops
    from handanno_core.prefill import reference_hand_model

    ensure_crops(session, quiet=True)
    gt = session.open_sequence().ground_truth.joints_mm
    results = session.load_results()
    refs = session.reference_frames  # 0, 10, 20: lifted
    results["lifted_mm"][np.setdiff1d(np.arange(FRAMES), refs)] = np.nan
    bones = np.asarray(session.model.bone_lengths_mm)
    model = reference_hand_model(session, results["lifted_mm"], refs, bones)
    assert model is not None and np.all(np.isfinite(model.radii))
    frame = 26
    flow = prefill_reference(session, frame, results)
    snapped = prefill_reference(session, frame, results, hand_model=model)
    assert snapped.shape == flow.shape and np.all(np.isfinite(snapped))
    assert not np.allclose(snapped, flow)  # the model fit moved it
    # still a usable guess, its bones the session's
    assert errors(snapped, gt[frame]).mean() < 15.0
    np.testing.assert_allclose(session.skeleton.bone_lengths(snapped), bones, rtol=0.02)


def test_session_hand_model_needs_two_lifted_references_and_bones(session):
    from handanno_core import handmodel as hm
    from handanno_core.pipeline import ensure_crops
    from handanno_core.prefill import session_hand_model

    results = session.load_results()
    assert session_hand_model(session, 26, results) is False  # no crop cache yet
    ensure_crops(session, quiet=True)
    refs = session.reference_frames  # 0, 10, 20: lifted
    model = session_hand_model(session, 26, results)
    assert isinstance(model, hm.HandModel)
    np.testing.assert_allclose(model.bone_lengths_mm, session.model.bone_lengths_mm)
    results["lifted_mm"][refs[1:]] = np.nan  # one lifted reference: flow only
    assert session_hand_model(session, 26, results) is False
