"""The safety net after localization (``localize._ending_pieces``): a finger's last segment
behind a depth step larger than the surface graph links (a finger pointing away from the
camera, its tip beyond a knuckle) is in the crop; surface that does not end next to the hand
(it runs to the image border, or is larger than a hand) does not grow it. Constructed scenes
(``tests.test_crops_per_frame._scene``, MSRA camera)."""

from __future__ import annotations

import numpy as np

from handanno_core import localize
from handanno_core.crops import crop_boxes, image_to_crop
from handanno_core.localize import MAX_HAND_AREA_MM2, hand_geometry, locate_hand_region
from tests.test_crops_per_frame import CAM, _scene

# an arm from the image's bottom border, a palm, a finger's first segment on the same surface
# (depth steps of 5-10 mm) and its last segment 45 mm nearer the camera, bent towards it (the graph links < 25 mm, the
# attachment < 30 mm), 2 pixels without depth between them in the image (a sensor's shadow):
# x0, x1, y0, y1 (mm), depth (mm)
_ARM = (-25.0, 25.0, 20.0, 300.0, 420.0)
_PALM = (-45.0, 45.0, -80.0, 20.0, 430.0)
_FINGER = (-9.0, 9.0, -120.0, -80.0, 435.0)
_TIP = (-8.0, 8.0, -165.0, -112.0, 390.0)


def _pixels(depth: np.ndarray, part: tuple) -> np.ndarray:
    """Image pixels ``(K, 2)`` (u, v) of rectangle ``part`` where it is the visible surface."""
    x0, x1, y0, y1, z = part
    vv, uu = np.nonzero(np.abs(depth - z) < 1.0)
    x = (uu - CAM.cx) * z / CAM.fx
    y = (vv - CAM.cy) * z / CAM.fy
    keep = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return np.stack([uu[keep], vv[keep]], axis=1).astype(np.float64)


def _inside(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Which pixels ``uv`` ``(K, 2)`` a crop of the frame's hand (at the cube it asks for, less
    the 8 mm margin) holds."""
    loc = locate_hand_region(depth, CAM)
    cube = localize.session_cube_mm(loc.half_extent_mm[None], 220.0)
    xy = image_to_crop(uv, crop_boxes(loc.centre_mm, CAM, cube, 128))
    lim = (cube / 2 - localize.CROP_MARGIN_MM) * 128 / cube
    return np.all(np.abs(xy - 63.5) <= lim, axis=1)


def test_a_finger_segment_behind_a_depth_step_is_in_the_crop(monkeypatch):
    """Must trigger: the last segment is a piece that ends next to the hand; every one of its
    pixels is in the crop. Without the net (as on main) the crop, placed on the arm's far end,
    cuts it."""
    depth = _scene(_ARM, _PALM, _FINGER, _TIP)
    tip = _pixels(depth, _TIP)
    assert len(tip) > 50
    assert _inside(depth, tip).all()
    g = hand_geometry(depth, CAM)
    assert g[1] > -160.0 / 390.0 and g[16] * 390.0 <= -160.0  # held, not the hand's own box
    monkeypatch.setattr(localize, "_ending_pieces", lambda pts, *a: np.zeros(len(pts), bool))
    assert not _inside(depth, tip).all()


def test_surface_that_does_not_end_next_to_the_hand_does_not_grow_its_box():
    """Must not trigger: a strip 50 mm behind the palm running from its side past the arm to
    the image's bottom border (a body or an object behind the hand, not a finger), or a plate
    larger than a hand there: nothing to hold but the hand. The same strip ending short of the
    border, or a plate within a hand's area, ends next to the hand: it is held."""
    bottom = CAM.cy / CAM.fy * 480.0  # the image's bottom border at 480 mm
    to_border = (55.0, 71.0, -20.0, bottom + 100.0, 480.0)
    tall = 1.2 * MAX_HAND_AREA_MM2 / 150.0  # a plate 150 mm wide with 1.2 x a hand's area
    plate = (55.0, 205.0, -0.5 * tall, 0.5 * tall, 480.0)
    for part in (to_border, plate):
        g = hand_geometry(_scene(_ARM, _PALM, _FINGER, part), CAM)
        assert np.all(np.isnan(g[15:19]))
    short = (55.0, 71.0, -20.0, bottom - 40.0, 480.0)
    g = hand_geometry(_scene(_ARM, _PALM, _FINGER, short), CAM)
    assert g[18] * 480.0 >= bottom - 45.0 and g[17] * 480.0 >= 66.0
    small = (55.0, 105.0, -80.0, -30.0, 480.0)
    g = hand_geometry(_scene(_ARM, _PALM, _FINGER, small), CAM)
    assert g[17] * 480.0 >= 100.0


def test_a_finger_touching_the_image_border_is_in_the_crop(monkeypatch):
    """A finger running out of the image's top border (a narrow contact: kept out of the arm's
    far end) is linked to the hand in its end part: the crop holds it to the border, with the
    margin beyond. Without that (as on main) its last 40 mm are cut."""
    top = -CAM.cy / CAM.fy * 435.0  # the image's top border at 435 mm
    finger = (-9.0, 9.0, top - 50.0, -80.0, 435.0)
    depth = _scene(_ARM, _PALM, finger)
    pixels = _pixels(depth, finger)
    assert _inside(depth, pixels).all()
    monkeypatch.setattr(localize, "_linked", lambda edges, hand, zone: np.zeros(len(hand), bool))
    assert _inside(depth, pixels).mean() < 0.9


def test_a_crop_that_already_holds_the_piece_does_not_move(monkeypatch):
    """A piece past the hand's own box but inside the crop's margin is held without moving the
    crop: the centre is the one without the net (only crops that would cut a piece move); the
    half extent holds the piece (it sizes the cube and the frame's box)."""
    piece = (55.0, 75.0, -60.0, -44.0, 480.0)
    depth = _scene(_ARM, _PALM, _FINGER, piece)
    g = hand_geometry(depth, CAM)
    assert g[17] * 480.0 >= 70.0 and g[17] > g[2]  # held, past the hand's own box
    loc = locate_hand_region(depth, CAM)
    assert _inside(depth, _pixels(depth, piece)).all()
    monkeypatch.setattr(localize, "_ending_pieces", lambda pts, *a: np.zeros(len(pts), bool))
    off = locate_hand_region(depth, CAM)
    np.testing.assert_allclose(loc.centre_mm, off.centre_mm)
    assert loc.half_extent_mm[0] > off.half_extent_mm[0]
    assert loc.centre_mm[0] + loc.half_extent_mm[0] >= 70.0 / 480.0 * loc.centre_mm[2]
