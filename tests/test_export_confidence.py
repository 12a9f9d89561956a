"""Export confidence: a joint that was never annotated nor estimated has confidence 0."""

from __future__ import annotations

import numpy as np

from handanno_core import pipeline
from handanno_core.export import collect
from handanno_core.synth import generate_sequence


def test_confidence_zero_for_joints_never_estimated(tmp_path):
    data = generate_sequence(tmp_path / "data", frames=6, seed=1, progress=False, workers=1)
    session = pipeline.new_session(tmp_path / "s", data)
    session.set_selection({"reference_frames": [0, 3], "parent": [-1, 0, 1, -1, 3, 4]})
    n, j = session.num_frames, session.skeleton.num_joints
    lifted = np.full((n, j, 3), np.nan)
    lifted[0] = session.open_sequence().ground_truth.joints_mm[0]
    final = np.full((n, j, 3), np.nan)
    final[1] = lifted[0] + 1.0  # a propagated frame with its own confidence
    conf = np.full((n, j), np.nan)
    conf[1] = 0.6
    session.save_results(
        lifted_mm=lifted, init_mm=np.full((n, j, 3), np.nan), final_mm=final, confidence=conf
    )
    c = collect(session)["confidence"]
    assert c.shape == (n, j)
    # reference 3 was never lifted: no joint, confidence 0 (not the 1.0 of a lifted reference)
    assert np.all(c[3] == 0.0)
    assert np.all(c[0] == 1.0)  # the lifted reference
    assert np.allclose(c[1], 0.6)
    assert np.all(c[[2, 4, 5]] == 0.0)
    # a frame whose result lacks a joint exports no joints, so no confidence either
    final[1, 7] = np.nan
    session.save_results(final_mm=final)
    data = collect(session)
    assert np.all(np.isnan(data["joints_mm"][1])) and np.all(data["confidence"][1] == 0.0)
    session.close()
