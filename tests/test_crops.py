"""Tests for handanno_core.crops: localization without ground truth and normalized cube crops."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from handanno_core.camera import MSRA_CAMERA, SR305_CAMERA, CameraIntrinsics
from handanno_core.crops import (
    compute_crops,
    crop_boxes,
    crop_depth,
    crop_to_image,
    image_to_crop,
    locate_hand,
    locate_hands,
    smooth_centres,
)
from handanno_core.datasets.base import BadFrameReport, DepthSequence, FrameError
from handanno_core.skeleton import MSRA21

SR305_DIR = Path("/work/shared/data/real-sr305")
if not SR305_DIR.exists():
    SR305_DIR = Path(__file__).resolve().parents[1] / "shared" / "data" / "real-sr305"

# Hand (palm + fingers, not forearm) bounding boxes (u0, v0, u1, v1) px, read off the frames by
# eye with a 50 px grid drawn on them (benchmarks/bench_crops.py writes the annotated montage).
# Each excludes the head, the torso centre and the noisy bottom-right of the body.
SR305_HAND_BOXES = {
    "20210326-230536/110.png": (195, 155, 385, 315),
    "20210326-230536/130.png": (190, 140, 370, 310),
    "20210326-230536/150.png": (210, 130, 385, 340),
    "20210326-230536/170.png": (185, 180, 330, 330),
    "20210326-230536/30.png": (200, 255, 350, 390),
    "20210326-230536/50.png": (190, 205, 350, 350),
    "20210326-230536/70.png": (210, 175, 350, 345),
    "20210326-230536/90.png": (260, 130, 385, 330),
    "20210326-231615/0.png": (205, 195, 335, 360),
    "20210326-231615/100.png": (260, 195, 390, 360),
    "20210326-231615/140.png": (255, 190, 375, 370),
    "20210326-231615/160.png": (270, 190, 410, 375),
    "20210326-231615/180.png": (265, 190, 415, 360),
    "20210326-231615/20.png": (270, 205, 400, 365),
    "20210326-231615/200.png": (280, 175, 415, 365),
    "20210326-231615/220.png": (295, 185, 415, 375),
    "20210326-231615/40.png": (245, 215, 385, 365),
    "20210326-231615/60.png": (255, 195, 395, 355),
    "20210326-231615/80.png": (250, 195, 390, 355),
}


# ------------------------------------------------------------------------------ fixtures
def render_spheres(camera: CameraIntrinsics, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Exact depth map (H, W) float32 mm of a union of spheres (ray casting), 0 = background."""
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    rays = np.stack(
        [(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], -1
    )
    a = np.sum(rays**2, -1)[..., None]  # (H, W, 1)
    b = rays @ centres.T  # (H, W, S)
    cc = np.sum(centres**2, -1) - radii**2  # (S,)
    disc = b**2 - a * cc
    with np.errstate(invalid="ignore"):
        t = np.where(disc >= 0, (b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
    z = t.min(-1)  # ray z component is 1, so t is the depth
    return np.where(np.isfinite(z), z, 0).astype(np.float32)


def _chain(p0, p1, r0, r1, n):
    s = np.linspace(0, 1, n)[:, None]
    return (1 - s) * np.asarray(p0, float) + s * np.asarray(p1, float), np.linspace(r0, r1, n)


def hand_model(palm_mm, spread=1.0, forearm_dir=(0.0, 1.0, 0.6)):
    """Spheres for palm (disc of spheres), 5 fingers and a forearm; palm centre = ``palm_mm``."""
    palm = np.asarray(palm_mm, float)
    parts_c, parts_r = [], []
    gx, gy = np.meshgrid(np.linspace(-30, 30, 5), np.linspace(-35, 35, 5))
    parts_c.append(palm + np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], -1))
    parts_r.append(np.full(gx.size, 14.0))
    for k, x in enumerate([-30, -10, 10, 30]):
        base = palm + [x, -40, 0]
        tip = base + [x * 0.5 * spread, -75 + 5 * abs(k - 1.5), -10]
        c, r = _chain(base, tip, 9, 7, 8)
        parts_c.append(c)
        parts_r.append(r)
    c, r = _chain(palm + [40, 10, 0], palm + [75 * spread, -20, -15], 10, 8, 6)  # thumb
    parts_c.append(c)
    parts_r.append(r)
    d = np.asarray(forearm_dir, float)
    d /= np.linalg.norm(d)
    c, r = _chain(palm + [0, 45, 5], palm + [0, 45, 5] + 260 * d, 24, 30, 14)  # forearm
    parts_c.append(c)
    parts_r.append(r)
    return np.concatenate(parts_c), np.concatenate(parts_r)


def msra_frame(palm_mm, camera=MSRA_CAMERA, **kw):
    return render_spheres(camera, *hand_model(palm_mm, **kw))


class SphereHandSequence(DepthSequence):
    """Moving analytic hand; some frames bad (FrameError) or empty; optional sequence breaks."""

    format = "test"

    def __init__(self, palms, bad=(), empty=(), breaks=(), camera=MSRA_CAMERA):
        super().__init__("/nonexistent/test-seq", camera, MSRA21)
        self.palms = np.asarray(palms, float)
        self.bad, self.empty, self._breaks = set(bad), set(empty), list(breaks)
        self.reads = 0

    def __len__(self):
        return len(self.palms)

    def depth(self, index):
        index = self._check_index(index)
        self.reads += 1
        if index in self.bad:
            raise FrameError(self.path / f"{index:06d}_depth.bin", index, "truncated file")
        if index in self.empty:
            return np.zeros((self.camera.height, self.camera.width), np.float32)
        return msra_frame(self.palms[index], self.camera)

    @property
    def sequence_breaks(self):
        return self._breaks


def load_sr305(name: str) -> np.ndarray:
    raw = cv2.imread(str(SR305_DIR / name), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint16, name
    return raw.astype(np.float32) * 0.125


# ------------------------------------------------------------------------------ localization
@pytest.mark.skipif(not SR305_DIR.exists(), reason="real SR305 frames not available")
@pytest.mark.parametrize("name", sorted(SR305_HAND_BOXES))
def test_sr305_centre_lies_on_hand(name):
    depth = load_sr305(name)
    c = locate_hand(depth, SR305_CAMERA)
    assert np.all(np.isfinite(c))
    u, v = SR305_CAMERA.project(c)
    u0, v0, u1, v1 = SR305_HAND_BOXES[name]
    assert u0 <= u <= u1 and v0 <= v <= v1, f"centre projects to ({u:.0f}, {v:.0f}), off the hand"
    # the centre's pixel is on a surface within 40 mm of the centre's depth ...
    d_px = depth[int(round(v)), int(round(u))]
    assert d_px > 0 and abs(d_px - c[2]) < 40.0
    # ... and that surface is among the nearest things in the frame (hand, not head/body)
    valid = depth[depth > 0]
    p5, p95 = np.percentile(valid, [5, 95])
    assert (c[2] - p5) / (p95 - p5) < 0.25
    assert np.mean(valid < c[2]) < 0.25


@pytest.mark.skipif(not SR305_DIR.exists(), reason="real SR305 frames not available")
def test_sr305_crop_shows_hand_not_body():
    depth = load_sr305("20210326-231615/20.png")  # hand barely in front of the torso
    c = locate_hand(depth, SR305_CAMERA)
    crop = crop_depth(depth, SR305_CAMERA, c)
    fg = crop < 1.0
    # a hand fills a good part of the cube's projection but not all of it (torso is behind)
    assert 0.15 < fg.mean() < 0.7
    assert fg[54:74, 54:74].mean() > 0.8  # the centre of the crop is on the hand


def test_msra_style_frame_centre_on_palm_not_forearm():
    palm = np.array([20.0, -15.0, 380.0])
    depth = msra_frame(palm)
    assert (depth > 0).mean() > 0.05
    c = locate_hand(depth, MSRA_CAMERA)
    assert np.linalg.norm(c - palm) < 35.0, c
    # the centre of mass of hand + forearm is pulled down the arm (+y); the centre is not: it is
    # on the fingers' side of the palm centre, and the whole hand (palm + fingers) is in the crop
    pts, _ = MSRA_CAMERA.depth_to_points(depth)
    assert pts.mean(0)[1] > palm[1] + 20
    assert c[1] < palm[1] + 5
    centres, radii = hand_model(palm)
    hand = centres[:-14]  # the last 14 spheres are the forearm
    box = crop_boxes(c, MSRA_CAMERA)
    xy = image_to_crop(MSRA_CAMERA.project(hand), box)
    assert np.all((xy > -0.5) & (xy < 127.5))


def test_speckle_and_flying_pixels_in_front_are_ignored():
    palm = np.array([-10.0, 5.0, 420.0])
    depth = msra_frame(palm)
    rng = np.random.default_rng(1)
    rows = rng.integers(0, depth.shape[0], 300)
    cols = rng.integers(0, depth.shape[1], 300)
    depth[rows, cols] = rng.uniform(160, 300, 300)  # isolated flying pixels far in front
    depth[5:9, 5:9] = 200.0  # a small clump (16 px = ~11 mm^2 at 200 mm): too small for a hand
    c = locate_hand(depth, MSRA_CAMERA)
    assert np.linalg.norm(c - palm) < 35.0


def test_nearest_hand_sized_blob_wins_over_farther_body():
    cam = MSRA_CAMERA
    palm = np.array([-60.0, 0.0, 450.0])
    hand_c, hand_r = hand_model(palm, forearm_dir=(0, 1, 0.2))
    body_c = np.array([[120.0, 40.0, 700.0], [120.0, 200.0, 720.0], [130, -120, 690]])
    body_r = np.array([140.0, 150.0, 90.0])
    depth = render_spheres(cam, np.concatenate([hand_c, body_c]), np.concatenate([hand_r, body_r]))
    c = locate_hand(depth, cam)
    assert np.linalg.norm(c - palm) < 35.0


def test_no_hand_gives_nan():
    cam = MSRA_CAMERA
    assert np.all(np.isnan(locate_hand(np.zeros((cam.height, cam.width), np.float32), cam)))
    tiny = np.zeros((cam.height, cam.width), np.float32)
    tiny[100:103, 100:103] = 400.0  # ~25 mm^2: noise, not a hand
    assert np.all(np.isnan(locate_hand(tiny, cam)))
    far = msra_frame([0, 0, 1800.0])  # beyond max_depth_mm
    assert np.all(np.isnan(locate_hand(far, cam)))


def test_prev_centre_hint_prefers_the_tracked_hand():
    cam = MSRA_CAMERA
    a, b = np.array([-90.0, 0.0, 450.0]), np.array([90.0, 0.0, 430.0])
    ca, ra = hand_model(a)
    cb, rb = hand_model(b)
    depth = render_spheres(cam, np.concatenate([ca, cb]), np.concatenate([ra, rb]))
    assert np.linalg.norm(locate_hand(depth, cam) - b) < 35.0  # nearest without a hint
    assert np.linalg.norm(locate_hand(depth, cam, prev_centre_mm=a + 10) - a) < 35.0


# ------------------------------------------------------------------------------ smoothing
def test_smooth_centres_fills_gaps_rejects_outliers_and_respects_breaks():
    n = 40
    t = np.arange(n, dtype=float)
    c = np.stack([t, 2 * t, 400 + 0 * t], -1)
    c[20:] += [500.0, 0, 0]  # new unrelated sequence at frame 20
    raw = c.copy()
    raw[5] = np.nan
    raw[10] = [1000.0, -1000.0, 50.0]  # single-frame outlier
    out = smooth_centres(raw, [20])
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out[5], c[5], atol=0.5)
    # the outlier is gone; neighbours are off by at most about one frame of motion (2 mm/frame)
    np.testing.assert_allclose(out[8:13], c[8:13], atol=2.5)
    # no blending across the break: last frame of segment 1, first of segment 2
    np.testing.assert_allclose(out[19], c[19], atol=1.0)
    np.testing.assert_allclose(out[20], c[20], atol=1.0)
    # all-NaN segment stays NaN; unsmoothed keeps values
    raw2 = c.copy()
    raw2[20:] = np.nan
    out2 = smooth_centres(raw2, [20], smooth=False)
    assert np.all(np.isnan(out2[20:]))
    np.testing.assert_allclose(out2[:20], c[:20])


def test_locate_hands_sequence_with_bad_and_empty_frames_and_break():
    n = 12
    palms = np.stack([np.linspace(-40, 40, n), np.zeros(n), np.full(n, 400.0)], -1)
    palms[6:] += [0, 60, 50]  # second sequence starts at 6
    seq = SphereHandSequence(palms, bad=[3], empty=[8], breaks=[6])
    report = BadFrameReport()
    centres = locate_hands(seq, report=report)
    assert centres.shape == (n, 3)
    assert report.frames == [3]
    assert np.all(np.isfinite(centres))
    err = np.linalg.norm(centres - palms, axis=1)
    assert err.max() < 40.0, err
    # frame 3 (bad) and 8 (empty) are interpolated from their neighbours
    assert err[3] < 40.0 and err[8] < 40.0
    # without a report, a bad frame raises
    with pytest.raises(FrameError):
        locate_hands(SphereHandSequence(palms[:5], bad=[2]))


# ------------------------------------------------------------------------------ geometry
def test_crop_geometry_round_trip_and_centre():
    rng = np.random.default_rng(0)
    centres = np.stack(
        [rng.uniform(-100, 100, 50), rng.uniform(-80, 80, 50), rng.uniform(250, 900, 50)], -1
    )
    for size in (128, 96):
        boxes = crop_boxes(centres, SR305_CAMERA, cube_mm=220.0, size=size)
        assert boxes.shape == (50, 4) and boxes.dtype == np.float64
        np.testing.assert_allclose(boxes[:, 2], SR305_CAMERA.fx * 220.0 / centres[:, 2] / size)
        uv_c = SR305_CAMERA.project(centres)
        np.testing.assert_allclose(image_to_crop(uv_c, boxes), (size - 1) / 2, atol=1e-9)
        xy = rng.uniform(-5, size + 5, (50, 2))
        np.testing.assert_allclose(image_to_crop(crop_to_image(xy, boxes), boxes), xy, atol=1e-9)
        # crop pixel edges -0.5 and size-0.5 are the box edges u_left-0.5 .. u_left-0.5+size*sx
        edges = crop_to_image(np.array([-0.5, -0.5]), boxes)
        np.testing.assert_allclose(edges, boxes[:, :2] - 0.5)
        # the box spans exactly the cube's width at the centre depth
        left = SR305_CAMERA.project(centres - [110.0, 0, 0])[:, 0]
        right = SR305_CAMERA.project(centres + [110.0, 0, 0])[:, 0]
        np.testing.assert_allclose(right - left, size * boxes[:, 2])
    # broadcasting one box over many points, and NaN centres
    b = crop_boxes(centres[0], SR305_CAMERA)
    assert crop_to_image(np.zeros((7, 2)), b).shape == (7, 2)
    assert np.all(np.isnan(crop_boxes(np.full((2, 3), np.nan), SR305_CAMERA)))


def test_crop_depth_values_and_background_rules():
    cam = CameraIntrinsics(fx=300, fy=300, cx=159.5, cy=119.5, width=320, height=240)
    zc = 500.0
    depth = np.full((240, 240 + 80), zc, np.float32)
    depth[:, :40] = 0.0  # no depth on the left
    depth[:20, :] = zc + 60  # inside cube, behind the centre: +60/110
    depth[20:30, :] = zc + 200  # behind the cube: background
    depth[30:40, :] = zc - 150  # just in front of the cube: clamped to -1
    depth[40:50, :] = zc - 300  # far in front: background
    centre = np.array([0.0, 0.0, zc])
    crop = crop_depth(depth, cam, centre, cube_mm=220.0, size=64)
    assert crop.shape == (64, 64) and crop.dtype == np.float32
    box = crop_boxes(centre, cam, 220.0, 64)
    img_uv = crop_to_image(np.stack(np.meshgrid(np.arange(64), np.arange(64)), -1), box)
    src = depth[
        np.clip(np.round(img_uv[..., 1]).astype(int), 0, 239),
        np.clip(np.round(img_uv[..., 0]).astype(int), 0, 319),
    ]
    inside = (img_uv[..., 1] > 0) & (img_uv[..., 1] < 239)
    # compare away from the stripes' edges (nearest-neighbour rounding can differ there)
    stable = inside & (np.abs(np.round(img_uv[..., 1]) - img_uv[..., 1]) < 0.4)
    stable &= np.abs(np.round(img_uv[..., 0]) - img_uv[..., 0]) < 0.4
    expect = np.where(src == zc, 0.0, np.nan)
    expect[src == zc + 60] = 60 / 110
    expect[src == zc + 200] = 1.0
    expect[src == zc - 150] = -1.0
    expect[src == zc - 300] = 1.0
    expect[src == 0] = 1.0
    np.testing.assert_allclose(crop[stable], expect[stable], atol=1e-6)
    assert set(np.unique(crop)) <= {-1.0, 0.0, np.float32(60 / 110), 1.0}
    assert np.all(crop[~inside] == 1.0)  # outside the image: no depth
    assert np.all(crop_depth(depth, cam, np.full(3, np.nan), size=32) == 1.0)


def test_crop_depth_places_a_point_where_image_to_crop_says():
    cam = MSRA_CAMERA
    centre = np.array([10.0, -5.0, 400.0])
    blob = centre + [45.0, -30.0, 20.0]
    depth = render_spheres(cam, blob[None], np.array([6.0]))
    crop = crop_depth(depth, cam, centre)
    ys, xs = np.nonzero(crop < 1.0)
    box = crop_boxes(centre, cam)
    expect = image_to_crop(cam.project(blob), box)
    assert np.hypot(xs.mean() - expect[0], ys.mean() - expect[1]) < 1.5
    assert np.all(np.abs(crop[ys, xs] - (blob[2] - 6 - centre[2]) / 110) < 0.1)


def test_compute_crops_memmap_bad_frames_and_matches_crop_depth(tmp_path):
    n = 7
    palms = np.stack([np.linspace(-30, 30, n), np.zeros(n), np.full(n, 380.0)], -1)
    seq = SphereHandSequence(palms, bad=[2])
    centres = palms.copy()
    centres[5] = np.nan
    report = BadFrameReport()
    out = tmp_path / "sub" / "crops.npy"
    crops = compute_crops(seq, centres, out, size=64, report=report, chunk_frames=3)
    assert out.exists() and not list(tmp_path.glob("sub/*.tmp*"))
    assert isinstance(crops, np.memmap) or crops.base is not None
    assert crops.shape == (n, 64, 64) and crops.dtype == np.float16
    assert report.frames == [2]
    assert np.all(crops[2] == 1.0) and np.all(crops[5] == 1.0)
    for i in (0, 4, 6):
        ref = crop_depth(seq.depth(i), seq.camera, centres[i], size=64)
        np.testing.assert_allclose(crops[i].astype(np.float32), ref, atol=1e-3)
        assert (crops[i] < 1).mean() > 0.1
    reloaded = np.load(out)
    np.testing.assert_array_equal(reloaded, np.asarray(crops))
    in_memory = compute_crops(seq, centres, None, size=64, report=BadFrameReport())
    np.testing.assert_array_equal(in_memory, reloaded)
    with pytest.raises(FrameError):
        compute_crops(seq, centres, None, size=64)
    with pytest.raises(ValueError):
        compute_crops(seq, centres[:3], None)


def test_synth_sequence_centres_and_crops_follow_the_hand(tmp_path):
    synth = pytest.importorskip("handanno_core.synth")
    from handanno_core.datasets import open_sequence

    synth.generate_sequence(tmp_path / "seq", frames=24, seed=3, progress=False, workers=1)
    seq = open_sequence(tmp_path / "seq")
    centres = locate_hands(seq)
    # scoring only: palm = mean of wrist and the four MCPs
    gt = seq.ground_truth.joints_mm
    palm = gt[:, [0, 1, 5, 9, 13]].mean(axis=1)
    err = np.linalg.norm(centres - palm, axis=1)
    # (part of this is a systematic ~25 mm: the visible surface is in front of the joint centres)
    assert np.median(err) < 50.0 and err.max() < 70.0, err
    # the hand projects into its crop (a spread hand's fingertips may graze the 220 mm cube's edge)
    boxes = crop_boxes(centres, seq.camera)
    xy = image_to_crop(seq.camera.project(gt), boxes[:, None, :])
    assert np.mean((xy > -0.5) & (xy < 127.5)) > 0.95
    assert np.all((xy > -10) & (xy < 137))
    crops = compute_crops(seq, centres, tmp_path / "crops.npy")
    assert ((np.asarray(crops) < 1).mean(axis=(1, 2)) > 0.05).all()


# ------------------------------------------------------------------------------ forearm at any angle
@pytest.mark.parametrize(
    "theta, sleeve",
    [(15.0, False), (45.0, True), (75.0, False), (105.0, True), (135.0, False), (165.0, True)],
)
def test_crop_holds_every_joint_whatever_the_forearm_does(theta, sleeve):
    """Forearm from pointing at the camera (15 deg, hand behind it) to pointing away (165 deg):
    every ground-truth joint (scoring only) inside the crop, x/y within the half cube less 8 mm
    (tests/forearm_scenes.py; tune-set angles and seed, see handanno_core/localize.py)."""
    from handanno_core.localize import locate_hands_with_extent, session_cube_mm
    from tests.forearm_scenes import ForearmCase, case_sequence

    seq = case_sequence(ForearmCase(1, theta, 100.0, sleeve, frames=6))
    centres, half = locate_hands_with_extent(seq)
    cube = session_cube_mm(half)
    assert 220.0 <= cube <= 400.0
    gt = seq.ground_truth.joints_mm
    xy = image_to_crop(seq.camera.project(gt), crop_boxes(centres, seq.camera, cube)[:, None])
    mm = (xy - 63.5) * cube / 128
    assert np.all(np.abs(mm) <= cube / 2 - 8.0), np.abs(mm).max(axis=(1, 2))
    # the crop's depth range holds the hand too unless the arm hides it (pointing at the camera)
    if theta >= 45.0:
        dz = gt[..., 2] - centres[:, None, 2]
        assert np.all(dz <= cube / 2)


def _joints_in_crop_mm(joints, loc, cam, session_cube_mm):
    """Joints ``(J, 2)`` in mm from the centre of the crop that ``loc`` gives, and its cube (mm)."""
    cube = session_cube_mm(loc.half_extent_mm[None])
    xy = image_to_crop(cam.project(joints), crop_boxes(loc.centre_mm, cam, cube))
    return (xy - 63.5) * cube / 128, cube


@pytest.mark.parametrize("seed, theta, phi", [(0, 50.0, 120.0), (1, 50.0, 60.0), (2, 50.0, 60.0)])
def test_fingertips_on_the_image_border_with_the_arm_nearer_stay_in_the_crop(seed, theta, phi):
    """Fingers running onto the image's top border, forearm (synth's short one) nearer the camera
    and ending inside the image: the fingertips touching the border are not the arm's way out,
    so every joint (fingertips included) is inside the crop, x/y within the half cube less 8 mm
    (before this round the crop sat on the forearm: joints 13-23 mm outside in these frames)."""
    from handanno_core.localize import locate_hand_region, session_cube_mm
    from tests.forearm_scenes import border_fingertips_frame

    cam = MSRA_CAMERA
    depth, joints = border_fingertips_frame(seed, theta, phi, cam)
    assert (depth[0] > 0).any() and not (depth[-1] > 0).any()  # hand on the top border only
    tips = list(MSRA21.fingertips)
    assert joints[0, 2] < joints[tips, 2].mean()  # the arm's end (wrist) nearer than the tips
    loc = locate_hand_region(depth, cam)
    assert loc.method == "arm-end"
    mm, cube = _joints_in_crop_mm(joints, loc, cam, session_cube_mm)
    assert np.all(np.abs(mm) <= cube / 2 - 8.0), np.abs(mm).max(axis=1)


@pytest.mark.parametrize("seed, theta, phi", [(1, 30.0, 60.0), (1, 30.0, 120.0), (2, 30.0, 120.0)])
def test_sleeve_ending_in_view_nearer_than_the_hand_puts_the_crop_on_the_hand(seed, theta, phi):
    """A sleeve pointing at the camera that ends in view, far from the sensor's near range (no
    image-border contact, too short for the free-arm rule): its wide rim is the arm's end because
    the hand shows past the far end, so every joint is inside the crop in x/y and depth (before
    this round the crop sat on the sleeve: joints 52-79 mm outside, 200-215 mm behind the cube)."""
    from handanno_core.localize import locate_hand_region, session_cube_mm
    from tests.forearm_scenes import sleeve_end_in_view_frame

    cam = MSRA_CAMERA
    depth, joints = sleeve_end_in_view_frame(seed, theta, phi, cam)
    valid = depth > 0
    assert not (valid[0].any() or valid[-1].any() or valid[:, 0].any() or valid[:, -1].any())
    assert depth[valid].min() < joints[:, 2].min() - 100.0  # the sleeve's rim is nearer
    loc = locate_hand_region(depth, cam)
    assert loc.method == "arm-end"
    mm, cube = _joints_in_crop_mm(joints, loc, cam, session_cube_mm)
    assert np.all(np.abs(mm) <= cube / 2 - 8.0), np.abs(mm).max(axis=1)
    assert np.all(joints[:, 2] - loc.centre_mm[2] <= cube / 2)


def test_smoothing_never_moves_a_centre_past_its_own_slack():
    n = 21
    c = np.zeros((n, 3))
    c[:, 2] = 400.0
    c[10, 0] = 60.0  # one frame's hand really is 60 mm to the side (a fast move)
    free = smooth_centres(c)
    assert free[10, 0] < 30.0  # unbounded, the running median removes it
    slack = np.full((n, 3), 5.0)
    bounded = smooth_centres(c, max_shift_mm=slack)
    assert np.all(np.abs(bounded - c) <= 5.0 + 1e-9)
    assert bounded[10, 0] == pytest.approx(55.0)
    # NaN slack (no hand size known) leaves the frame unbounded; gaps are still filled
    slack[10] = np.nan
    c2 = c.copy()
    c2[3] = np.nan
    out = smooth_centres(c2, max_shift_mm=slack)
    assert out[10, 0] < 30.0 and np.all(np.isfinite(out[3]))


def test_session_cube_grows_only_for_hands_that_do_not_fit():
    from handanno_core.localize import session_cube_mm

    half = np.tile([80.0, 90.0, 40.0], (200, 1))
    assert session_cube_mm(half) == 220.0  # 2 * (90 + 8) = 196 fits
    half[:, 1] = 110.0  # 2 * (110 + 8) = 236 -> 240 (10 mm steps)
    assert session_cube_mm(half) == 240.0
    half[7, 1] = 500.0  # one wild frame does not blow the cube up (a spike, not a hand) ...
    assert session_cube_mm(half) == 240.0
    half[8, 1] = 130.0  # ... but a hand larger for two frames running grows it: 2 * (130 + 8)
    assert session_cube_mm(half) == 280.0
    assert session_cube_mm(half, sequence_breaks=[8]) == 240.0  # not across a break
    assert session_cube_mm(np.full((3, 3), np.nan)) == 220.0
    assert session_cube_mm(np.tile([300.0, 300.0, 0.0], (5, 1))) == 400.0  # capped


def test_crop_spec_is_the_one_home_of_crop_geometry():
    from types import SimpleNamespace

    from handanno_core.crops import DEFAULT_CROP, CropSpec

    spec = CropSpec.of(SimpleNamespace(cube_mm=260, crop_size=64))
    assert spec == CropSpec(260.0, 64) and spec.half_mm == 130.0
    assert spec.with_cube(300).cube_mm == 300.0 and spec.cube_mm == 260.0  # frozen
    with pytest.raises(AttributeError):
        spec.cube_mm = 1.0
    vals = np.array([1.0, 0.9995, 0.5, -1.0], np.float16)
    np.testing.assert_array_equal(CropSpec.is_background(vals), [True, True, False, False])
    np.testing.assert_allclose(spec.depth_mm([0.5, -1.0], 400.0), [465.0, 270.0])
    # the functions' defaults come from the spec, and background is the spec's value
    crop = crop_depth(np.zeros((240, 320), np.float32), MSRA_CAMERA, np.array([0, 0, 300.0]))
    assert crop.shape == (DEFAULT_CROP.size,) * 2 and np.all(crop == CropSpec.BACKGROUND)


def _bar_frame(length_mm: float = 420.0, width_mm: float = 45.0, z: float = 500.0):
    """A depth map (MSRA camera) of a flat bar floating in view, both ends alike (no arm end)."""
    cam = MSRA_CAMERA
    vv, uu = np.mgrid[0 : cam.height, 0 : cam.width]
    x = (uu - cam.cx) * z / cam.fx
    y = (vv - cam.cy) * z / cam.fy
    depth = np.where((np.abs(x) <= length_mm / 2) & (np.abs(y) <= width_mm / 2), z, 0.0)
    return depth.astype(np.float32), cam


def test_free_blob_extent_does_not_grow_with_the_cube():
    """Without an arm end the extent is that of the surface within a fixed radius: locating with
    a larger cube must not report a larger hand (which would grow the session's cube again)."""
    from handanno_core.localize import FREE_EXTENT_RADIUS_MM, locate_hand_region

    depth, cam = _bar_frame()
    small = locate_hand_region(depth, cam, cube_mm=220.0)
    large = locate_hand_region(depth, cam, cube_mm=320.0)
    assert small.method == large.method == "free-blob"
    np.testing.assert_allclose(small.half_extent_mm[:2], large.half_extent_mm[:2], atol=2.0)
    assert small.half_extent_mm[0] <= FREE_EXTENT_RADIUS_MM + 5.0  # not the whole 210 mm


def test_cube_back_lies_behind_the_farthest_visible_surface_and_in_front_of_a_body():
    """A plate tilted 45 deg away (depth 450..560 mm): the hand's hidden side lies behind what the
    sensor sees, so the cube's back is HIDDEN_MAX_MM behind its farthest visible point when nothing
    is behind it; with a wall behind, BEHIND_GAP_MM in front of the wall, never less than
    HIDDEN_DEPTH_MM behind the plate."""
    from handanno_core.localize import (
        BEHIND_GAP_MM,
        HIDDEN_DEPTH_MM,
        HIDDEN_MAX_MM,
        locate_hand_region,
    )

    cam = MSRA_CAMERA
    vv, uu = np.mgrid[0 : cam.height, 0 : cam.width]
    ry = (vv - cam.cy) / cam.fy
    rx = (uu - cam.cx) / cam.fx
    z = 500.0 / (1.0 - ry)  # the plane z = 500 + y (45 deg), along each ray
    plate = (np.abs(rx * z) <= 45.0) & (np.abs(ry * z) <= 55.0)
    depth = np.where(plate, z, 0.0).astype(np.float32)
    z_far = float(np.percentile(depth[depth > 0], 99.8))
    backs = {}
    for wall in (None, z_far + 110.0, z_far + 60.0):
        d = depth if wall is None else np.where(plate, depth, wall).astype(np.float32)
        loc = locate_hand_region(d, cam, cube_mm=220.0)
        backs[wall] = loc.centre_mm[2] + 110.0
        # the nearest surface is still inside the cube (or just in front: foreground, -1)
        assert depth[depth > 0].min() >= loc.centre_mm[2] - 220.0
    assert backs[None] == pytest.approx(z_far + HIDDEN_MAX_MM, abs=8.0)
    assert backs[z_far + 110.0] == pytest.approx(z_far + 110.0 - BEHIND_GAP_MM, abs=8.0)
    assert backs[z_far + 60.0] == pytest.approx(z_far + HIDDEN_DEPTH_MM, abs=8.0)


def test_locate_crops_grows_the_cube_to_a_fixed_point():
    """A hand too large for the cube: locate_crops returns a grown spec at which locating again
    would not grow it further (a rebuilt cache gives the same crops)."""
    from handanno_core.crops import CropSpec, locate_crops
    from handanno_core.localize import locate_hands_with_extent, session_cube_mm
    from tests.forearm_scenes import ForearmCase, case_sequence

    seq = case_sequence(ForearmCase(1, 105.0, 100.0, False, frames=4))
    centres, spec, box = locate_crops(seq, CropSpec(160.0, 64))
    assert np.all(box == spec.cube_mm)  # every frame's hand fits the session's cube
    assert spec.size == 64 and 160.0 < spec.cube_mm <= 400.0
    again, half = locate_hands_with_extent(seq, cube_mm=spec.cube_mm)
    assert session_cube_mm(half, spec.cube_mm) == spec.cube_mm
    np.testing.assert_allclose(again, centres)
    same, unchanged, _ = locate_crops(seq, spec)
    assert unchanged == spec


def test_locate_crops_reads_every_frame_once_even_when_the_cube_grows():
    """The hand's geometry does not depend on the cube: growing the session's cube re-places the
    crops from it instead of locating every frame again (a second full pass at 76k frames)."""
    from handanno_core.crops import CropSpec, locate_crops
    from handanno_core.localize import locate_hands_with_extent

    palms = [[10.0 * np.sin(i / 3.0), 5.0, 330.0 + 2.0 * i] for i in range(8)]
    seq = SphereHandSequence(palms)
    centres, spec, _ = locate_crops(seq, CropSpec(120.0, 64))
    assert spec.cube_mm > 120.0  # the hand did not fit: the cube grew
    assert seq.reads == len(seq)
    again, _ = locate_hands_with_extent(seq, cube_mm=spec.cube_mm)
    np.testing.assert_allclose(again, centres)


def test_joints_in_front_of_the_cube_are_not_held_in_depth():
    """A hand whose crop centre lies too deep (the localizer took the arm's far end) projects
    inside the crop's box but in front of its cube: held in x and y, not in depth."""
    from handanno_core.crops import joints_inside_crops

    rng = np.random.default_rng(0)
    hand = rng.normal(0.0, 25.0, (2, 21, 3)) + [0.0, 0.0, 350.0]
    centres = np.array([[0.0, 0.0, 360.0], [0.0, 0.0, 476.0]])  # the second 117 mm too deep
    in_xy = joints_inside_crops(hand, centres, MSRA_CAMERA, 280.0)
    in_depth = joints_inside_crops(hand, centres, MSRA_CAMERA, 280.0, cube_mm=280.0)
    assert in_xy.tolist() == [True, True]
    assert in_depth.tolist() == [True, False]
    # a joint without a position is not counted, in depth either
    hand[1, :, 2] = np.nan
    assert joints_inside_crops(hand, centres, MSRA_CAMERA, 280.0, cube_mm=280.0).tolist() == [
        True,
        True,
    ]


def test_a_hand_merged_with_the_surface_behind_it_for_two_frames_keeps_its_neighbours_depth():
    """A hand whose depth range reaches 200 mm back for two frames (merged with a table behind
    it) would put its crop's cube behind the hand, the hand in front of the cube; a run of such
    frames as short as that is a localization slip, and the crop keeps its neighbours' depth. A
    hand that stays deep (a forearm reaching back) keeps its own centre."""
    from handanno_core.localize import DEPTH_SPIKE_FRAMES, centres_at

    # one frame's geometry row (ray-angle box, depth range, hidden depth, wrist; arm-end method)
    row = np.array([-0.066, -0.108, 0.340, 0.315, 259.5, 314.6, 130.0, 19.8, 85.4, 295.3]
                   + [np.nan] * 3 + [1.0, 0.0] + [np.nan] * 4)  # fmt: skip
    geometry = np.tile(row, (30, 1))
    cube = 280.0
    calm, _ = centres_at(geometry, cube)
    merged = geometry.copy()
    merged[[10, 11], 5] += 200.0  # the farthest surface 200 mm further back
    slipped, half = centres_at(merged, cube)
    assert np.all(half[[10, 11], 2] > cube / 2)  # the hand does not fit the cube in depth
    np.testing.assert_allclose(slipped[[10, 11]], calm[[10, 11]], atol=1.0)
    stays = geometry.copy()
    stays[10 : 10 + DEPTH_SPIKE_FRAMES, 5] += 200.0  # deep for longer than a slip
    own, _ = centres_at(stays, cube)
    assert own[12, 2] > calm[12, 2] + 100.0
