"""The session the review tests (unit and end-to-end) start from: references every STEP-th frame,
annotated by the simulated annotator, lifted joints taken from ground truth so that the fixture is
fast (the lift is tested elsewhere), the fast DIS aligner."""

from __future__ import annotations

from pathlib import Path

import numpy as np

STEP = 10


def build_review_session(folder: Path, data: Path) -> Path:
    """A session in ``folder`` on the MSRA-layout sequence ``data``; returns ``folder``."""
    from handanno_core.pipeline import annotate_from_gt, new_session

    session = new_session(folder, data, format="msra", overwrite=True)
    refs = list(range(0, session.num_frames, STEP))
    parent = [-1 if f in refs else f - 1 for f in range(session.num_frames)]
    session.set_selection({"strategy": "uniform", "reference_frames": refs, "parent": parent})
    annotate_from_gt(session, quiet=True)
    gt = session.open_sequence().ground_truth.joints_mm
    lifted = np.full_like(gt, np.nan)
    lifted[refs] = gt[refs]
    conf = np.full(gt.shape[:2], np.nan)
    conf[refs] = 1.0
    session.save_results(lifted_mm=lifted, confidence=conf)
    session.set_bone_lengths(session.skeleton.estimate_bone_lengths(gt))
    session.model.settings.aligner = "dis"  # the fast aligner keeps these tests in their budget
    session.close()
    return folder


def synth_data(tmp_path_factory, name: str, frames: int, seed: int) -> Path:
    """A synthetic sequence of ``frames`` frames in a fresh temporary folder ``name``."""
    from handanno_core.synth import generate_sequence

    out = tmp_path_factory.mktemp(name) / "data"
    generate_sequence(out, frames=frames, seed=seed, progress=False)
    return out


def open_review_session(folder: Path, data: Path):
    """Body of a pytest fixture (``yield from``): the review session built in ``folder``, closed
    after the test."""
    from handanno_core.session import Session

    session = Session.open(build_review_session(folder, data))
    yield session
    session.close()
