"""Tests of handanno_core.ambiguity: a finger the depth pins down scores low, a finger behind an
occluder (any flexion fits the depth as well) scores high. Depth rendered from the capsule model
itself (exact ray casting, no noise), as in tests/test_handmodel.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from test_handmodel import _model, _pose, _render

from handanno_core import handmodel as hm
from handanno_core.ambiguity import finger_ambiguity
from handanno_core.camera import MSRA_CAMERA
from handanno_core.crops import crop_boxes, crop_depth
from handanno_core.pose_prior import PosePrior

CAM = MSRA_CAMERA


def _scene():
    x = _pose("open")
    model = _model(x)
    depth = _render(model, x)
    return x, model, depth


def _observe(depth: np.ndarray, x: np.ndarray) -> hm.FrameObservations:
    c = x.mean(axis=0)
    crop = crop_depth(depth, CAM, c)[None]
    return hm.observe(crop, crop_boxes(c, CAM)[None], c[None], CAM)


#: the references' level: an exact render is explained at energy 0, so any unit will do
LEVEL = 1.0


def _behind_board(depth: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``depth`` with a board 30 mm in front of the fingers over every pixel above the knuckles."""
    mcp_v = CAM.project(x[[1, 5, 9, 13]])[:, 1].max()
    occluded = depth.copy()
    rows = np.arange(depth.shape[0])[:, None] < mcp_v - 4
    occluded[np.broadcast_to(rows, depth.shape)] = float(np.nanmin(x[[1, 5, 9, 13], 2])) - 30.0
    return occluded


def test_fingers_behind_an_occluder_are_ambiguous_and_fingers_in_view_are_not():
    x, model, depth = _scene()
    in_view = finger_ambiguity(model, x[None], _observe(depth, x), CAM, LEVEL)[0]
    # whatever the fingers do behind the board, the camera sees the board
    behind = finger_ambiguity(model, x[None], _observe(_behind_board(depth, x), x), CAM, LEVEL)[0]
    # an open hand's fingertip curls 60-90 mm away from where it was at the grid's far end
    assert behind > 40.0
    assert in_view < 0.5 * behind


def test_a_pose_prior_does_not_make_a_hidden_finger_certain():
    # a prior that holds every finger tightly where the shown pose has it: with the prior in the
    # energy, every other flexion would cost far more than the references' level and the hidden
    # fingers would score as pinned down; the depth cannot tell, so the term must not change
    x, model, depth = _scene()
    obs = _observe(_behind_board(depth, x), x)
    plain = finger_ambiguity(model, x[None], obs, CAM, LEVEL)[0]
    sk = model.skeleton
    size = 3 * len(sk.angle_joints)
    prior = PosePrior(sk.name, np.zeros(size), 30.0 * np.eye(size))
    prior = replace(prior, mean=prior.features(sk, x))
    held = replace(model, pose_prior=prior, pose_prior_weight=1.0)
    assert prior.energy(sk, x) < 1e-9 < prior.energy(sk, _pose("fist"))
    with_prior = finger_ambiguity(held, x[None], obs, CAM, LEVEL)[0]
    assert plain > 40.0
    assert with_prior == plain


def test_a_pose_without_joints_has_no_ambiguity():
    x, model, depth = _scene()
    obs = _observe(depth, x)
    missing = np.full_like(x, np.nan)[None]
    both = np.concatenate([missing, x[None]])
    out = finger_ambiguity(model, both, hm.FrameObservations.concatenate([obs, obs]), CAM, 1.0)
    assert np.isnan(out[0]) and np.isfinite(out[1])
    assert np.isnan(finger_ambiguity(model, x[None], obs, CAM, float("nan"))[0])
