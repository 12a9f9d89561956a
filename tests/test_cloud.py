"""handanno_core.cloud: flying-pixel filter and forearm cut at the wrist plane."""

from __future__ import annotations

import numpy as np

from handanno_core.camera import MSRA_CAMERA
from handanno_core.cloud import clean_hand_cloud, flying_pixel_mask, wrist_plane
from handanno_core.skeleton import MSRA21
from tests.forearm_scenes import FOREARM_LENGTH_MM, ForearmCase, arm_direction, render_case


def _points(depth):
    pts, _ = MSRA_CAMERA.depth_to_points(depth)
    return pts


def test_flying_pixels_between_a_finger_and_the_wall_are_flagged_surfaces_kept():
    cam = MSRA_CAMERA
    depth = np.full((cam.height, cam.width), 700.0, np.float32)  # a wall
    depth[60:180, 100:140] = 400.0  # a "finger" in front of it
    # a steep but smooth ramp (a surface seen at a grazing angle): 4 mm per pixel
    depth[60:180, 200:230] = 450.0 + 4.0 * np.arange(30)[None, :]
    # flying pixels: a 1-pixel trail right of the finger, halfway between finger and wall
    depth[60:180, 140] = 550.0
    flying = flying_pixel_mask(_points(depth), cam)
    rows, cols = np.nonzero(depth > 0)
    band = (rows >= 60) & (rows < 180)
    trail = band & (cols == 140)
    assert flying[trail].mean() > 0.9
    finger = band & (cols >= 100) & (cols < 140)
    ramp = band & (cols >= 200) & (cols < 230)
    assert flying[finger].mean() < 0.01 and flying[ramp].mean() < 0.01
    assert flying[~(trail | finger | ramp)].mean() < 0.001  # the wall
    # an isolated speck in mid air
    depth2 = np.zeros_like(depth)
    depth2[100:140, 100:140] = 400.0
    depth2[20, 20] = 380.0
    pts = _points(depth2)
    assert flying_pixel_mask(pts, cam)[np.argmin(pts[:, 2])]


def test_wrist_plane_cuts_the_forearm_and_keeps_the_hand():
    case = ForearmCase(seed=4, theta_deg=90.0, phi_deg=80.0, sleeve=False, frames=1)
    depths, joints = render_case(case)
    pts = _points(depths[0])
    j = joints[0]
    plane = wrist_plane(j, MSRA21)
    assert plane is not None
    np.testing.assert_allclose(plane[0], j[0])
    keep, t = clean_hand_cloud(pts, MSRA_CAMERA, joints_mm=j, skeleton=MSRA21, colour_by_depth=True)
    assert t is not None and len(t) == keep.sum() and t.min() == 0.0 and t.max() == 1.0
    # forearm points: near the arm axis, 40 mm or more from the wrist towards the elbow
    d = arm_direction(case.theta_deg, case.phi_deg)
    along = (pts - j[0]) @ d
    hand_d = np.min(np.linalg.norm(pts[:, None] - j[None, 1:], axis=2), axis=1)
    forearm = (along > 40.0) & (along < FOREARM_LENGTH_MM) & (hand_d > 40.0)
    hand = hand_d < 12.0
    assert forearm.sum() > 200 and hand.sum() > 200
    assert keep[forearm].mean() < 0.02
    assert keep[hand].mean() > 0.97
    # without joints only the flying-pixel filter runs: the forearm stays
    keep2, _ = clean_hand_cloud(pts, MSRA_CAMERA)
    assert keep2[forearm].mean() > 0.95
    # missing wrist: no plane
    j2 = j.copy()
    j2[0] = np.nan
    assert wrist_plane(j2, MSRA21) is None
