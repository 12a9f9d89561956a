"""Every skeleton layout the readers produce runs the whole pipeline: NYU (``nyu14``) and ICVL
(``icvl16``) fixtures written from the synthetic renderer (tests/layout_fixtures.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from handanno_core.datasets import open_sequence
from handanno_core.session import Session
from handanno_core.skeleton import get_skeleton
from tests.layout_fixtures import has_real_motion, write_icvl_fixture, write_nyu_fixture

WRITERS = {"nyu14": write_nyu_fixture, "icvl16": write_icvl_fixture}


@pytest.mark.parametrize("layout", ["msra21", "nyu14", "icvl16"])
def test_layout_has_everything_the_lift_needs(layout):
    sk = get_skeleton(layout)
    assert sk.template_bone_lengths_mm is not None and len(sk.template_bone_lengths_mm) == len(
        sk.bones
    )
    assert all(20.0 > o >= 0.0 for o in sk.surface_offsets_mm)
    assert sk.palm_joints is not None and len(sk.angle_joints) >= 5
    fl, ab = sk.angle_ranges()
    assert np.all(np.isfinite(fl)) and np.all(np.isfinite(ab))
    assert np.all(fl[:, 0] < fl[:, 1]) and np.all(ab[:, 0] < ab[:, 1])


@pytest.mark.parametrize("layout", ["nyu14", "icvl16"])
def test_fixture_ground_truth_measures_as_a_right_hand_inside_the_ranges(layout, tmp_path):
    """The fixture's layout mapping is consistent with the layout's palm normal and its learned
    ranges: the synthetic right hand's angles are mostly inside them."""
    seq = open_sequence(WRITERS[layout](tmp_path / layout, frames=6))
    assert seq.skeleton.name == layout
    v = seq.skeleton.angle_range_violation_deg(seq.ground_truth.joints_mm)
    assert np.mean(v > 0) < 0.2, v


REAL = pytest.mark.skipif(not has_real_motion(), reason="../shared/data/real-motion is absent")


@pytest.mark.parametrize(
    "layout, motion",
    [
        ("nyu14", "synthetic"),
        ("icvl16", "synthetic"),
        pytest.param("nyu14", "fpha", marks=REAL),
        pytest.param("icvl16", "fpha", marks=REAL),
    ],
)
def test_pipeline_end_to_end_on_layout(layout, motion, tmp_path, capsys):
    """new/select/annotate-from-gt/lift/propagate/refine/export on a fixture of the layout, the
    hand following synthetic motion or a real recorded trajectory (FPHA, tune side)."""
    data = WRITERS[layout](tmp_path / "data", frames=30, motion=motion)
    sessions = tmp_path / "sessions"
    base = ["--sessions-dir", str(sessions)]
    assert main(base + ["new", "s", str(data)]) == 0
    assert main(base + ["select", "s", "--strategy", "uniform", "--ref-fraction", "0.2"]) == 0
    assert main(base + ["annotate-from-gt", "s"]) == 0
    assert main(base + ["lift", "s"]) == 0
    assert main(base + ["propagate", "s"]) == 0
    assert main(base + ["refine", "s"]) == 0
    out = tmp_path / "out.json"
    assert main(["export", str(sessions / "s"), "--format", "json", "-o", str(out)]) == 0
    session = Session.open(sessions / "s")
    assert session.skeleton.name == layout
    gt = open_sequence(data).ground_truth.joints_mm
    refs = np.asarray(session.reference_frames)
    lifted = session.load_results()["lifted_mm"][refs]
    err = np.linalg.norm(lifted - gt[refs], axis=-1)
    with capsys.disabled():
        print(f"\n{layout} {motion}: lift error on {len(refs)} references {err.mean():.2f} mm mean")
    final = np.linalg.norm(session.load_results()["final_mm"] - gt, axis=-1)
    with capsys.disabled():
        print(f"{layout} {motion}: final error {final.mean():.2f} mm mean")
    assert np.all(np.isfinite(lifted)) and np.all(np.isfinite(final))
    if motion == "synthetic":
        # measured: nyu14 1.86, icvl16 1.73 mm (exact 2D, bones estimated, 6 references;
        # icvl16 with the hand-model refit, 2.06 without; nyu14 has none)
        assert err.mean() < 6.0
        # the hand model is on by default but not for nyu14 (fingers of two bones), where it
        # made the final error 2.0 -> 18.4 mm on a 60-frame fixture
        assert final.mean() < 6.0
    # on the real trajectory (FPHA Subject_1, first sequence, 30 frames) the pipeline runs end to
    # end but the lift is far off: 9.2 mm (nyu14, the wrist joints 16-36 mm) and 22.8 mm
    # (icvl16, bones estimated up to 2x too long) on the references: reported in the README,
    # not asserted
    doc = json.loads(out.read_text())
    assert len(doc["frames"]) == len(gt)
