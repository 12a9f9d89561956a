"""Per-frame crop boxes (``localize.frame_cubes_mm``) and the hand held together from two
candidates (the arm's far end and the surface past it): constructed scenes where each rule must
and must not trigger."""

from __future__ import annotations

import numpy as np
import pytest

from handanno_core import localize
from handanno_core.camera import MSRA_CAMERA
from handanno_core.crops import CropSpec, compute_crops, crop_boxes, image_to_crop, locate_crops
from handanno_core.datasets.base import DepthSequence
from handanno_core.localize import (
    METHODS,
    centres_at,
    frame_cubes_mm,
    hand_geometry,
    locate_hand_geometry,
)
from handanno_core.skeleton import MSRA21

CAM = MSRA_CAMERA


def _scene(*parts) -> np.ndarray:
    """Depth map (MSRA camera) of axis-aligned rectangles ``(x0, x1, y0, y1, z)`` mm (``z`` a
    number: facing the camera; ``(z0, z1)``: a ramp from depth z0 at x0 to z1 at x1) and discs
    ``(cx, cy, r, z)`` mm facing the camera; the nearest part wins at each pixel."""
    vv, uu = np.mgrid[0 : CAM.height, 0 : CAM.width]
    depth = np.full((CAM.height, CAM.width), np.inf)
    for p in parts:
        z = p[-1]
        if isinstance(z, tuple):  # the plane z = a + b x along the pixel's ray
            b = (z[1] - z[0]) / (p[1] - p[0])
            z = (z[0] - b * p[0]) / (1.0 - b * (uu - CAM.cx) / CAM.fx)
        x = (uu - CAM.cx) * z / CAM.fx
        y = (vv - CAM.cy) * z / CAM.fy
        if len(p) == 5:
            inside = (x >= p[0]) & (x <= p[1]) & (y >= p[2]) & (y <= p[3])
        else:
            inside = (x - p[0]) ** 2 + (y - p[1]) ** 2 <= p[2] ** 2
        depth = np.where(inside & (z < depth), z, depth)
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


class FramesSequence(DepthSequence):
    """A sequence of given depth maps (MSRA camera), no ground truth."""

    format = "test"

    def __init__(self, depths):
        super().__init__("/nonexistent/frames", CAM, MSRA21)
        self.depths = list(depths)

    def __len__(self):
        return len(self.depths)

    def depth(self, index):
        return self.depths[self._check_index(index)]


def _disc_frame(radius_mm: float) -> np.ndarray:
    # a hand-sized disc, tilted a little so that its edge is not all at one depth
    vv, uu = np.mgrid[0 : CAM.height, 0 : CAM.width]
    z = 500.0 + 0.05 * (uu - CAM.cx) * 500.0 / CAM.fx
    x = (uu - CAM.cx) * z / CAM.fx
    y = (vv - CAM.cy) * z / CAM.fy
    return np.where(x**2 + y**2 <= radius_mm**2, z, 0.0).astype(np.float32)


def test_frame_cubes_grow_only_the_frames_whose_hand_does_not_fit():
    half = np.array(
        [[90.0, 80.0, 40.0], [np.nan] * 3, [140.0, 60.0, 40.0], [102.0, 50.0, 9.0], [300.0] * 3]
    )
    cubes = frame_cubes_mm(half, 220.0)
    # 2 * (90 + 8) = 196 fits; no hand keeps the cube; 2 * (140 + 8) = 296 -> 300; 2 * 110 = 220
    # fits exactly; 616 is capped at 400
    np.testing.assert_array_equal(cubes, [220.0, 220.0, 300.0, 220.0, 400.0])
    np.testing.assert_array_equal(frame_cubes_mm(half[:2], 220.0), [220.0, 220.0])


def test_a_frame_whose_hand_needs_a_larger_box_gets_it_and_the_other_crops_stay(tmp_path):
    """Discs of 60 mm radius, one frame of 108 mm (a larger hand, one frame: the session's cube
    does not grow for it). That frame gets its own box (every pixel of its hand inside its crop;
    the session's cube would cut it); the other frames' centres, boxes and crops are those of the
    session's cube alone, bit for bit, and every crop's depth is normalized at the session's
    cube."""
    depths = [_disc_frame(108.0 if i == 3 else 60.0) for i in range(7)]
    seq = FramesSequence(depths)
    centres, spec, box = locate_crops(seq, CropSpec(220.0, 64))
    assert spec.cube_mm == 220.0  # a one-frame spike does not size the session's cube
    assert box[3] > 220.0 and np.all(np.delete(box, 3) == 220.0)

    geometry = locate_hand_geometry(seq)
    alone, _ = centres_at(geometry, 220.0)
    np.testing.assert_array_equal(np.delete(centres, 3, 0), np.delete(alone, 3, 0))
    boxes = crop_boxes(centres, CAM, box, 64)
    np.testing.assert_array_equal(
        np.delete(boxes, 3, 0), np.delete(crop_boxes(centres, CAM, 220.0, 64), 3, 0)
    )
    crops = compute_crops(seq, centres, cube_mm=220.0, size=64, box_cubes_mm=box)
    same = compute_crops(seq, centres, cube_mm=220.0, size=64)
    np.testing.assert_array_equal(np.delete(crops, 3, 0), np.delete(same, 3, 0))
    assert not np.array_equal(crops[3], same[3])

    # frame 3's hand: every pixel of the disc inside its crop, cut at 220 mm
    vv, uu = np.nonzero(depths[3] > 0)
    uv = np.stack([uu, vv], axis=-1).astype(np.float64)

    def worst_mm(cube):
        xy = image_to_crop(uv, crop_boxes(centres[3], CAM, cube, 64))
        return float(np.abs((xy - 31.5) * cube / 64).max()) - cube / 2

    assert worst_mm(box[3]) <= 0.0 < worst_mm(220.0)
    # depth at the session's cube: the disc's centre pixel decodes to its depth either way
    v, u = CAM.height // 2, CAM.width // 2
    xy = np.rint(image_to_crop(np.array([u, v], float), crop_boxes(centres[3], CAM, box[3], 64)))
    value = float(crops[3][int(xy[1]), int(xy[0])])
    assert spec.depth_mm(value, centres[3, 2]) == pytest.approx(depths[3][v, u], abs=3.0)


# an arm from the left image border, nearer the camera than the hand (380 mm at the border, 560 mm
# at the wrist), ending in a hand-sized plate (one smooth surface) and a small patch 50 mm behind
# the plate's far end: a finger seen past a fingertip (egocentric views)
_ARM = (-400.0, -40.0, -25.0, 25.0, (380.0, 560.0))
_PLATE = (-40.0, 70.0, -45.0, 45.0, 560.0)
_PATCH = (70.0, 100.0, -15.0, 15.0, 610.0)


def test_a_small_surface_past_a_large_regions_far_end_is_held_with_it(monkeypatch):
    """Must trigger: the region (arm + plate) is far larger than what a sleeve pointing at the
    camera shows and the surface past its far end is a small share of it: the hand is both, the
    plate and the patch (own box). Before, the patch and the far end's last 40 mm were taken for
    the hand and the plate was cut."""
    depth = _scene(_ARM, _PLATE, _PATCH)
    g = hand_geometry(depth, CAM)
    assert METHODS[int(g[13])] == "arm-end" and g[14] == 1.0
    # the box (ray angles x / z) holds the plate's near half and the patch's far edge
    assert g[0] <= -30.0 / _PLATE[-1] and g[2] >= 0.95 * _PATCH[1] / _PATCH[-1]
    # the rule off (share 0): the patch alone and the far end, the plate's near half cut
    monkeypatch.setattr(localize, "BEHIND_SHARE", 0.0)
    g0 = hand_geometry(depth, CAM)
    assert g0[14] == 0.0 and g0[0] > 0.0


def test_a_hand_past_a_sleeve_rim_stays_the_hand():
    """Must not trigger: a sleeve pointing at the camera (a 38 mm disc at 400 mm, far less than
    a hand's area) with the hand 160 mm behind it, showing past its rim: the hand is the surface
    past the rim (no own box), its box spans the hand's visible plate."""
    sleeve = (0.0, 0.0, 38.0, 400.0)
    hand = (-45.0, 45.0, -120.0, 0.0, 560.0)
    g = hand_geometry(_scene(sleeve, hand), CAM)
    assert METHODS[int(g[13])] == "arm-end" and g[14] == 0.0
    top = float(g[1] * 560.0)
    assert top <= -110.0  # the hand's far edge is in its box


def test_frames_held_together_do_not_size_the_session_cube(monkeypatch):
    """Three frames running whose hand is two candidates held together (larger than the others):
    they get their own boxes; the session's cube stays what the other frames need (before it
    grew for every frame of the session)."""
    row = localize._hand_geometry(
        np.array([[-45.0, -45.0, 500.0], [45.0, 45.0, 520.0]]), "arm-end", own_box=False
    )
    big = localize._hand_geometry(
        np.array([[-200.0, -45.0, 500.0], [45.0, 45.0, 520.0]]), "arm-end", own_box=True
    )
    geometry = np.stack([row, row, big, big, big, row, row])
    monkeypatch.setattr(localize, "locate_hand_geometry", lambda *a, **k: geometry)
    _, spec, box = locate_crops(FramesSequence([np.zeros((2, 2), np.float32)] * 7))
    assert spec.cube_mm == 220.0
    assert np.all(box[2:5] > 220.0) and np.all(box[[0, 1, 5, 6]] == 220.0)
    # the same frames without the flag: the session's cube grows for all
    geometry[2:5, 14] = 0.0
    _, spec, box = locate_crops(FramesSequence([np.zeros((2, 2), np.float32)] * 7))
    assert spec.cube_mm > 220.0 and np.all(box == spec.cube_mm)


def test_the_app_cuts_a_frames_cloud_at_its_own_box(tmp_path):
    """The app's hand cloud of a frame with its own larger box is cut at that box (else the
    fingertips the crop holds would be missing from the cloud); other frames at the session's
    cube; a cache without per-frame boxes (older sessions) at the session's cube."""
    from types import SimpleNamespace

    from app.control.frames import FrameStore
    from handanno_core.session import CROPS_META_FILE

    session = SimpleNamespace(
        folder=tmp_path,
        num_frames=3,
        model=SimpleNamespace(settings=SimpleNamespace(cube_mm=250.0)),
    )
    np.savez(
        tmp_path / CROPS_META_FILE, centres_mm=np.zeros((3, 3)), box_cubes_mm=[250.0, 310.0, 250.0]
    )
    store = FrameStore(session)
    assert [store.cube_of(i) for i in range(3)] == [250.0, 310.0, 250.0]
    np.savez(tmp_path / CROPS_META_FILE, centres_mm=np.zeros((3, 3)))
    assert [FrameStore(session).cube_of(i) for i in range(3)] == [250.0] * 3


def _deep_hand_row(z_near: float, z_far: float) -> np.ndarray:
    """A hand geometry row whose visible surface spans ``z_near..z_far`` mm in depth (90 x 120 mm
    across), nothing visible behind it (hidden side up to HIDDEN_MAX_MM)."""
    x, y, z = np.meshgrid([-45.0, 45.0], [-60.0, 60.0], np.linspace(z_near, z_far, 50))
    row = localize._hand_geometry(np.stack([x.ravel(), y.ravel(), z.ravel()], 1), "arm-end")
    row[6] = localize.HIDDEN_MAX_MM
    return row


def test_the_hidden_side_never_pushes_the_hands_front_out_of_the_crop(monkeypatch):
    """Must trigger: a hand 330 mm deep in a 290 mm cube (a forearm pointing away in its region):
    the cube's back would go 130 mm behind its farthest surface, moving the centre so deep that
    the nearest surface (the fingertips) falls more than a cube in front of it, out of the crop.
    The centre stops FRONT_MARGIN_MM short of that. Must not: a hand 60 mm deep, where the hidden
    side fits, is placed as before."""
    deep, shallow = _deep_hand_row(650.0, 980.0), _deep_hand_row(500.0, 560.0)
    z_deep = localize._box_of(deep, 290.0).centre_mm[2]
    z_shallow = localize._box_of(shallow, 290.0).centre_mm[2]
    assert z_deep - 290.0 <= deep[4] - localize.FRONT_MARGIN_MM + 1e-6  # the front stays in
    assert z_deep + 145.0 >= deep[5] + localize.HIDDEN_DEPTH_MM - 1e-6  # the back as before
    monkeypatch.setattr(localize, "FRONT_MARGIN_MM", -1e6)  # the rule off
    assert localize._box_of(deep, 290.0).centre_mm[2] - 290.0 > deep[4]  # the front was cut
    assert localize._box_of(shallow, 290.0).centre_mm[2] == z_shallow


def _curled_hand_near_the_sensor():
    """An arm floating in view (80 mm wide, 520 mm deep at its cut far end, 285 mm at the wrist)
    whose hand is the nearest part, 270 mm from the sensor: a palm and four curled fingers (8 mm
    wide, 15 mm apart) bending back to 292 mm, so the knuckles make a wide rim at the region's
    nearest depth, within 150 mm of the sensor's near range (150 mm)."""
    fingers = [(110.0, 170.0, a, a + 8.0, (270.0, 292.0)) for a in (-45.0, -22.0, 1.0, 24.0)]
    arm = (-300.0, 60.0, -40.0, 40.0, (520.0, 285.0))
    return _scene(arm, (60.0, 110.0, -45.0, 32.0, (285.0, 270.0)), *fingers)


def _short_arm_cut_by_the_near_range():
    """An arm pointing at the camera, cut by the near range at 190 mm, 100 mm long in the image,
    with its hand (palm and four fingers) at 350-360 mm: too short for the ends to vote."""
    fingers = [(110.0, 160.0, a, a + 10.0, (355.0, 360.0)) for a in (-45.0, -22.0, 1.0, 24.0)]
    arm = (-40.0, 60.0, -35.0, 35.0, (190.0, 350.0))
    return _scene(arm, (60.0, 110.0, -45.0, 34.0, (350.0, 355.0)), *fingers)


def test_an_elongated_regions_ends_vote_before_the_near_range_rim(monkeypatch):
    """Must trigger: fingers curled towards the camera near the sensor make a rim like an arm cut
    by the near range; the elongated region's ends vote (the forearm's cut end is more solid,
    the fingers make edges; the rim is one vote), so the hand is the crop, not the forearm's far
    end (which the rim alone gives: the vote switched off). Must not: an arm cut by the near
    range too short to vote keeps the rim as its attachment (the hand at its far end), exactly
    as without the vote."""
    g = hand_geometry(_curled_hand_near_the_sensor(), CAM)
    assert g[2] >= 0.95 * 170.0 / 292.0  # the fingertips
    assert g[0] > -100.0 / 400.0  # not the forearm's far end (x = -300 mm at 520 mm)
    monkeypatch.setattr(localize, "_stump_of_free_arm", lambda *a, **k: None)
    rim_only = hand_geometry(_curled_hand_near_the_sensor(), CAM)
    assert rim_only[2] < 0.0  # the rim alone: the crop on the forearm's far end
    short = hand_geometry(_short_arm_cut_by_the_near_range(), CAM)  # the rim alone
    monkeypatch.undo()
    voted = hand_geometry(_short_arm_cut_by_the_near_range(), CAM)
    np.testing.assert_array_equal(voted, short)
    assert voted[2] >= 0.95 * 160.0 / 360.0 and voted[0] > -40.0 / 190.0  # the hand, not the cut
