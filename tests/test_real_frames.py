"""Hand localization on every real frame in ../shared/data (SR305 x 19, HANDS 2017 SR300, MSRA
2015): the centre is on the hand and the crop holds every hand pixel. Skipped without the data.

Hand pixels (no ground truth here): the connected component, inside the frame's by-eye hand box
(palm and fingers, above the wrist: ``tests/real_frames.HAND_BOXES``), of the pixels within the
hand's depth band (its nearest depth in the box + 150 mm) that contains the located centre.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from handanno_core.crops import crop_boxes, crop_depth, image_to_crop
from handanno_core.localize import locate_hand_region, session_cube_mm
from tests.real_frames import DATA, HAND_BOXES, frame_names, load_frame

pytestmark = pytest.mark.skipif(DATA is None, reason="../shared/data is not available")

BAND_MM = 150.0


def hand_pixels(depth: np.ndarray, box, uv_centre) -> np.ndarray | None:
    """``(H, W)`` bool hand pixels (module docstring), or None if the centre is not on them."""
    u0, v0, u1, v1 = box
    inbox = np.zeros(depth.shape, bool)
    inbox[v0:v1, u0:u1] = True
    vals = depth[inbox & (depth > 0)]
    near = np.percentile(vals, 2)
    band = inbox & (depth >= near - 20.0) & (depth <= near + BAND_MM)
    _, labels = cv2.connectedComponents(band.astype(np.uint8), connectivity=4)
    rows, cols = np.nonzero(band)
    d2 = (cols - uv_centre[0]) ** 2 + (rows - uv_centre[1]) ** 2
    k = int(np.argmin(d2))
    if d2[k] > 8.0**2:  # no hand pixel within 8 px of the centre's projection
        return None
    return labels == labels[rows[k], cols[k]]


@pytest.mark.parametrize("name", frame_names() or ["none"])
def test_crop_holds_every_hand_pixel_and_centre_is_on_the_hand(name):
    depth, cam = load_frame(name)
    loc = locate_hand_region(depth, cam)
    assert np.all(np.isfinite(loc.centre_mm)), "no hand found"
    uv = cam.project(loc.centre_mm)
    u0, v0, u1, v1 = HAND_BOXES[name]
    assert u0 <= uv[0] <= u1 and v0 <= uv[1] <= v1, f"centre at {np.round(uv)}, off the hand box"
    hand = hand_pixels(depth, HAND_BOXES[name], uv)
    assert hand is not None, f"centre at {np.round(uv)} is not on a hand pixel"
    # the centre's depth is within the hand's depth range (not on the body behind)
    z = depth[hand]
    assert z.min() - 30.0 <= loc.centre_mm[2] <= z.max() + 30.0
    cube = session_cube_mm(loc.half_extent_mm[None], 220.0)
    box = crop_boxes(loc.centre_mm, cam, cube_mm=cube, size=128)
    rows, cols = np.nonzero(hand)
    xy = image_to_crop(np.stack([cols, rows], axis=1).astype(float), box)
    outside = np.any((xy < -0.5) | (xy > 127.5), axis=1)
    assert not outside.any(), f"{outside.sum()} of {len(xy)} hand pixels outside the crop"
    # and in the crop they are foreground (inside or just in front of the cube)
    crop = crop_depth(depth, cam, loc.centre_mm, cube_mm=cube)
    ij = np.clip(np.rint(xy).astype(int), 0, 127)
    assert np.mean(crop[ij[:, 1], ij[:, 0]] < 1.0) > 0.97
