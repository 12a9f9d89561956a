"""Session data model: journal durability, undo/redo, crash recovery, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from handanno_core.annotation import FrameAnnotation
from handanno_core.camera import MSRA_CAMERA
from handanno_core.session import (
    Batch,
    DatasetSpec,
    Session,
    SessionError,
    SetDepthOrder,
    SetJoint2D,
    SetJoint3D,
    SetOutside,
    SetReference,
    SetReview,
    SetVisibility,
    resolve_session,
    safe_session_path,
)


@pytest.fixture
def session(tmp_path):
    s = Session.create(
        tmp_path / "s", DatasetSpec(path=str(tmp_path / "data"), format="msra"), 10, MSRA_CAMERA
    )
    s.set_selection(
        {
            "strategy": "uniform",
            "reference_frames": [0, 5],
            "parent": [-1, 0, 1, 2, 3, -1, 5, 6, 7, 8],
        }
    )
    return s


def test_edit_is_journaled_before_it_is_applied(session):
    entry = session.execute(SetJoint2D(frame=0, joint=4, uv_px=(100.5, 80.25)))
    lines = (session.folder / "journal.jsonl").read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["seq"] == entry.seq
    assert session.annotation(0).uv_px[4].tolist() == [100.5, 80.25]


def test_reopen_without_close_replays_every_acknowledged_edit(session):
    session.execute(SetJoint2D(frame=0, joint=1, uv_px=(10, 20)))
    session.execute(SetVisibility(frame=0, joint=1, visible=False))
    session.execute(SetDepthOrder(frame=5, joint=2, order=-1))
    # no close(): simulates a SIGKILL after the edits were acknowledged
    again = Session.open(session.folder)
    ann0, ann5 = again.annotation(0), again.annotation(5)
    assert ann0.uv_px[1].tolist() == [10, 20] and not ann0.visible[1]
    assert ann5.depth_order[2] == -1


def test_torn_last_journal_line_is_ignored_but_corrupt_middle_line_is_an_error(session):
    session.execute(SetJoint2D(frame=0, joint=1, uv_px=(1, 2)))
    path = session.folder / "journal.jsonl"
    with open(path, "ab") as f:
        f.write(
            b'{"seq": 2, "time": 1.0, "cl'
        )  # crash in the middle of a write: never acknowledged
    assert Session.open(session.folder).annotation(0).uv_px[1].tolist() == [1, 2]
    path.write_bytes(b"garbage\n" + path.read_bytes())
    with pytest.raises(SessionError, match="journal.jsonl:1: corrupt entry"):
        Session.open(session.folder)


def test_undo_redo_per_client_and_after_restart(session):
    session.execute(SetJoint2D(frame=0, joint=2, uv_px=(5, 6)), client="a")
    session.execute(SetJoint2D(frame=0, joint=3, uv_px=(7, 8)), client="b")
    session.undo("a")  # undoes a's edit only: b's joint on the same frame survives
    ann = session.annotation(0)
    assert np.isnan(ann.uv_px[2]).all() and ann.uv_px[3].tolist() == [7, 8]
    again = Session.open(session.folder)
    assert again.can_redo("a") and not again.can_redo("b")
    again.redo("a")
    assert again.annotation(0).uv_px[2].tolist() == [5, 6]
    again.undo("a")
    again.undo("a")  # nothing left for a: no-op
    assert np.isnan(again.annotation(0).uv_px[2]).all()


def test_set_3d_projects_to_2d_and_reference_batch_undoes_as_one(session):
    cmd = Batch(
        commands=[
            SetJoint3D(frame=7, joint=0, xyz_mm=(10.0, -20.0, 400.0)).model_dump(),
            SetReference(frame=7, is_reference=True, correction=True).model_dump(),
        ]
    )
    session.execute(cmd)
    assert 7 in session.reference_frames and session.model.corrections == [7]
    assert session.parent[7] == -1
    uv = session.annotation(7).uv_px[0]
    np.testing.assert_allclose(uv, MSRA_CAMERA.project(np.array([10.0, -20.0, 400.0])))
    session.undo()
    assert 7 not in session.reference_frames and session.parent[7] == 6
    ann = session.annotation(7)
    assert (ann is None or not ann.annotated.any()) and session.model.corrections == []


def test_working_out_a_batch_inverse_leaves_the_session_as_it_was(session):
    """A batch's inverse is worked out by applying its commands to a copy of the model (only the
    containers commands edit in place are copied): the session itself is untouched until the
    batch is journaled, and the inverse undoes exactly the batch."""
    session.execute(SetReview(frame=3, status="flagged"))
    before = session.model.model_dump()
    cmd = Batch(
        commands=[
            SetReference(frame=7, is_reference=True, correction=True).model_dump(),
            SetReview(frame=3, status=None).model_dump(),
            SetJoint3D(frame=7, joint=0, xyz_mm=(10.0, -20.0, 400.0)).model_dump(),
        ]
    )
    inverse = session._inverse_of(cmd)
    assert session.model.model_dump() == before
    session.execute(cmd)
    assert session.parent[7] == -1 and session.model.review == {}
    inverse.apply(session)
    after = session.model.model_dump()
    assert not session.annotation(7).annotated.any()  # undone to an empty annotation
    for key in set(before) - {"annotations", "journal_seq"}:
        assert after[key] == before[key], key


def test_invalid_edits_are_refused_and_not_journaled(session):
    with pytest.raises(ValueError, match="out of range"):
        session.execute(SetJoint2D(frame=99, joint=0, uv_px=(1, 2)))
    with pytest.raises(ValueError, match="joint 21 out of range"):
        session.execute(SetVisibility(frame=0, joint=21, visible=True))
    with pytest.raises(ValueError, match="finite"):
        session.execute(SetJoint2D(frame=0, joint=0, uv_px=(float("nan"), 1)))
    assert not (session.folder / "journal.jsonl").exists()


def test_review_status_round_trip(session):
    session.execute(SetReview(frame=3, status="flagged"))
    session.execute(SetReview(frame=3, status="accepted"))
    session.undo()
    assert session.model.review == {"3": "flagged"}


def test_missing_and_corrupt_sessions_name_the_file(tmp_path):
    with pytest.raises(SessionError, match="no such session folder"):
        Session.open(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SessionError, match="session.json: missing"):
        Session.open(tmp_path / "empty")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "session.json").write_text("{not json")
    with pytest.raises(SessionError, match="corrupt session file"):
        Session.open(tmp_path / "bad")


def test_results_are_atomic_and_partial_updates_keep_other_arrays(session):
    n, j = 10, 21
    session.save_results(init_mm=np.ones((n, j, 3)))
    session.save_results(final_mm=np.full((n, j, 3), 2.0))
    res = session.load_results()
    assert res["init_mm"].mean() == 1 and res["final_mm"].mean() == 2
    assert np.isnan(res["lifted_mm"]).all()
    assert not list(session.folder.glob(".results*"))


def test_session_names_are_confined_to_the_sessions_folder(tmp_path):
    assert safe_session_path("demo", tmp_path) == (tmp_path / "demo").resolve()
    for bad in ("../etc", "a/b", "..", "/abs", ".hidden", "a\\b"):
        with pytest.raises(SessionError):
            safe_session_path(bad, tmp_path)
    assert resolve_session("x", tmp_path) == (tmp_path / "x").resolve()
    assert resolve_session(str(tmp_path / "y"), "sessions") == tmp_path / "y"


@pytest.mark.parametrize(
    ("refs", "parent", "says"),
    [
        ([0, 5], [-1, 0, 3, 2, 3, -1, 5, 6, 7, 8], "cycle"),  # frames 2 and 3 point at each other
        ([0], [-1, 0, 1, 2, 3, -1, 5, 6, 7, 8], "-1 exactly at the references"),
    ],
)
def test_selection_that_is_not_a_forest_is_refused_and_the_old_one_kept(
    session, refs, parent, says
):
    with pytest.raises(ValueError, match=says):
        session.set_selection({"reference_frames": refs, "parent": parent})
    assert session.reference_frames.tolist() == [0, 5]
    assert session.parent.tolist() == [-1, 0, 1, 2, 3, -1, 5, 6, 7, 8]


def test_accepted_flag_is_set_cleared_by_a_click_and_restored_by_undo(session):
    session.execute(SetJoint2D(frame=0, joint=4, uv_px=(100.0, 80.0), accepted=True))
    assert session.annotation(0).accepted[4]
    session.execute(SetJoint2D(frame=0, joint=4, uv_px=(103.0, 81.0)))  # the annotator moves it
    ann = session.annotation(0)
    assert not ann.accepted[4] and ann.uv_px[4].tolist() == [103.0, 81.0]
    session.undo()  # back to the accepted guess, flag and all
    ann = session.annotation(0)
    assert ann.accepted[4] and ann.uv_px[4].tolist() == [100.0, 80.0]
    session.execute(SetJoint3D(frame=0, joint=4, xyz_mm=(10.0, 5.0, 400.0)))  # placed by hand
    assert not session.annotation(0).accepted[4]
    session.undo()
    session.execute(SetJoint2D(frame=0, joint=4, uv_px=None))  # cleared: no flag without 2D
    assert not session.annotation(0).accepted.any()
    session.undo()
    again = Session.open(session.folder)  # replayed from the journal
    assert again.annotation(0).accepted.tolist() == [k == 4 for k in range(21)]


def test_annotation_json_keeps_the_accepted_flag_and_reads_old_json_as_clicks():
    from handanno_core.annotation import AnnotationError, FrameAnnotation

    ann = FrameAnnotation.empty(21)
    ann.uv_px[:3] = [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]
    assert "accepted" not in ann.to_json()  # nothing accepted: the JSON written before the flag
    ann.accepted[[1, 7]] = True  # joint 7 has no 2D: the flag means nothing there
    data = ann.to_json()
    back = FrameAnnotation.from_json(data, 21)
    assert back.accepted.tolist() == [k == 1 for k in range(21)]
    assert back.copy().accepted.tolist() == back.accepted.tolist()
    del data["accepted"]
    assert not FrameAnnotation.from_json(data, 21).accepted.any()
    with pytest.raises(AnnotationError, match="accepted has shape"):
        FrameAnnotation.from_json({**data, "accepted": [True] * 5}, 21)


def test_a_joint_marked_outside_the_image_loses_its_placement_and_a_click_takes_the_mark(session):
    session.execute(SetJoint2D(frame=0, joint=4, uv_px=(319.0, 10.0)), client="a")
    session.execute(SetJoint3D(frame=0, joint=5, xyz_mm=(1.0, 2.0, 300.0)), client="a")
    session.execute(SetOutside(frame=0, joint=4, outside=True), client="a")
    session.execute(SetOutside(frame=0, joint=5, outside=True), client="a")
    ann = session.annotation(0)
    assert ann.outside[[4, 5]].all() and not ann.annotated[[4, 5]].any()
    assert ann.complete[[4, 5]].all() and not ann.complete[6]
    assert session.model.annotations["0"]["outside"][4] is True
    session.undo("a")  # joint 5 is placed in 3D again (2D by projection), unmarked
    ann = session.annotation(0)
    assert ann.xyz_mm[5].tolist() == [1.0, 2.0, 300.0] and not ann.outside[5]
    session.execute(SetJoint2D(frame=0, joint=4, uv_px=(300.0, 12.0)), client="a")
    ann = session.annotation(0)
    assert not ann.outside[4] and ann.uv_px[4].tolist() == [300.0, 12.0]
    session.undo("a")  # the click undone: the mark is back
    assert session.annotation(0).outside[4]
    before = {k: v for k, v in session.model.annotations["0"].items() if k != "outside"}
    assert not FrameAnnotation.from_json(before, 21).outside.any()  # written before the mark
