"""Tests of handanno_core.ambiguity: a finger the depth pins down scores low, a finger behind an
occluder (any flexion fits the depth as well) scores high. Depth rendered from the capsule model
itself (exact ray casting, no noise), as in tests/test_handmodel.py."""

from __future__ import annotations

import numpy as np
from test_handmodel import _model, _pose, _render

from handanno_core import handmodel as hm
from handanno_core.ambiguity import finger_ambiguity
from handanno_core.camera import MSRA_CAMERA
from handanno_core.crops import crop_boxes, crop_depth

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


def test_fingers_behind_an_occluder_are_ambiguous_and_fingers_in_view_are_not():
    x, model, depth = _scene()
    in_view = finger_ambiguity(model, x[None], _observe(depth, x), CAM, LEVEL)[0]
    # a board 30 mm in front of the fingers, over every pixel above the knuckles: whatever the
    # fingers do behind it, the camera sees the board
    mcp_v = CAM.project(x[[1, 5, 9, 13]])[:, 1].max()
    occluded = depth.copy()
    rows = np.arange(depth.shape[0])[:, None] < mcp_v - 4
    board = float(np.nanmin(x[[1, 5, 9, 13], 2])) - 30.0
    occluded[np.broadcast_to(rows, depth.shape)] = board
    behind = finger_ambiguity(model, x[None], _observe(occluded, x), CAM, LEVEL)[0]
    # an open hand's fingertip curls 60-90 mm away from where it was at the grid's far end
    assert behind > 40.0
    assert in_view < 0.5 * behind


def test_a_pose_without_joints_has_no_ambiguity():
    x, model, depth = _scene()
    obs = _observe(depth, x)
    missing = np.full_like(x, np.nan)[None]
    both = np.concatenate([missing, x[None]])
    out = finger_ambiguity(model, both, hm.FrameObservations.concatenate([obs, obs]), CAM, 1.0)
    assert np.isnan(out[0]) and np.isfinite(out[1])
    assert np.isnan(finger_ambiguity(model, x[None], obs, CAM, float("nan"))[0])
