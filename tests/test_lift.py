"""Tests for handanno_core.lift: recovery, constraints, angle limits, bone estimation, robustness."""

from __future__ import annotations

import numpy as np
import pytest

from handanno_core.annotation import AnnotationError, FrameAnnotation
from handanno_core.camera import MSRA_CAMERA
from handanno_core.lift import initial_pose, lift_frame, lift_references, observed_depth
from handanno_core.lift.problem import _Problem
from handanno_core.lift.references import shrink_to_template
from handanno_core.real_motion import DEFAULT_REAL_MOTION
from handanno_core.skeleton import MSRA21

SK = MSRA21
CAM = MSRA_CAMERA
REAL_MOTION = DEFAULT_REAL_MOTION
OFF = np.asarray(SK.surface_offsets_mm)
#: the surface model these tests' sphere renderer was built with: every joint centre the offset
#: behind its sphere's surface (tips inside a sphere), read at the 3x3's closest pixel, 3 mm
#: (the lift's defaults are chosen for capsule hands with sensor noise, synth and the suite)
TOY_SURFACE = dict(surface_depth_mm=3.0, depth_front_band_mm=None)


# ------------------------------------------------------------------ fixture: poses + sphere render
def _rot(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_pose(rng: np.random.Generator, bones: np.ndarray | None = None) -> np.ndarray:
    """A right hand ``(21, 3)`` mm with angles drawn inside 90 % of the skeleton's limits, palm
    within ~50 deg of facing (or facing away from) the camera, 330-420 mm away."""
    d = np.asarray(bones if bones is not None else SK.template_bone_lengths_mm, dtype=np.float64)
    boc = np.full(SK.num_joints, -1)
    boc[SK.bones[:, 1]] = np.arange(len(SK.bones))
    X = np.zeros((SK.num_joints, 3))
    for k, ang in {1: -8.0, 5: 0.0, 9: 9.0, 13: 18.0}.items():
        a = np.radians(ang)
        X[k] = d[boc[k]] * np.array([np.sin(a), -np.cos(a), 0.0])
    t = np.array([-0.75, -0.55, 0.35])
    X[17] = d[boc[17]] * t / np.linalg.norm(t)
    fl, ab = SK.angle_limits()
    n = SK.palm_normal(X)
    lat_of: dict[int, np.ndarray] = {}
    for i, (k, c) in enumerate(zip(SK.angle_joints, SK.angle_children, strict=True)):
        p = int(SK.parent_array[k])
        a = X[k] - X[p]
        a /= np.linalg.norm(a)
        if p in lat_of:  # lateral axis transported along the chain (Skeleton.joint_angles)
            lat = lat_of[p] - (lat_of[p] @ a) * a
        else:
            lat = np.cross(a, n)
        lat /= np.linalg.norm(lat)
        lat_of[int(k)] = lat
        npp = np.cross(lat, a)
        f = np.radians(
            rng.uniform(fl[i, 0] + 0.05 * np.ptp(fl[i]), fl[i, 1] - 0.05 * np.ptp(fl[i]))
        )
        b = np.radians(rng.uniform(0.9 * ab[i, 0], 0.9 * ab[i, 1]))
        X[c] = X[k] + d[boc[c]] * (np.cos(b) * (np.cos(f) * a + np.sin(f) * npp) + np.sin(b) * lat)
    X = X @ _rot(rng).T
    n = SK.palm_normal(X)
    tilt = np.arccos(abs(n[2]))
    if tilt > np.radians(50):
        axis = np.cross(n, [0.0, 0.0, np.sign(n[2])])
        axis /= np.linalg.norm(axis)
        th = tilt - np.radians(50) * rng.uniform()
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        X = X @ (np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K).T
    X -= X.mean(axis=0)
    return X + np.array([rng.uniform(-30, 30), rng.uniform(-20, 20), rng.uniform(330, 420)])


def render(X: np.ndarray, step: float = 1.5) -> np.ndarray:
    """Depth map of spheres along the bones (radius = the joints' surface offsets; tips inside a
    cap of 0.8x the DIP radius), orthographic-per-sphere z-buffer; background 0."""
    cen, rad = [], []
    for p, c in SK.bones:
        rp = OFF[p] if p != 0 else OFF[c] + 2
        rc = OFF[c] if OFF[c] > 0 else 0.8 * OFF[p]
        m = max(2, int(np.linalg.norm(X[c] - X[p]) / step) + 1)
        t = np.linspace(0, 1, m)[:, None]
        cen.append(X[p] + t * (X[c] - X[p]))
        rad.append(rp + t[:, 0] * (rc - rp))
    cen.append(X[[0]])
    rad.append(np.array([OFF[0]]))
    cen, rad = np.concatenate(cen), np.concatenate(rad)
    h, w = CAM.height, CAM.width
    depth = np.full(h * w, np.inf)
    uv = CAM.project(cen)
    r = np.arange(-14, 15)
    dv, du = np.meshgrid(r, r, indexing="ij")
    uu = np.rint(uv[:, 0])[:, None] + du.ravel()[None]
    vv = np.rint(uv[:, 1])[:, None] + dv.ravel()[None]
    xs = (uu - CAM.cx) * cen[:, 2:3] / CAM.fx - cen[:, 0:1]
    ys = (vv - CAM.cy) * cen[:, 2:3] / CAM.fy - cen[:, 1:2]
    rho2 = xs**2 + ys**2
    inside = (rho2 < rad[:, None] ** 2) & (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
    z = cen[:, 2:3] - np.sqrt(np.maximum(rad[:, None] ** 2 - rho2, 0))
    np.minimum.at(depth, (vv * w + uu)[inside].astype(np.int64), z[inside])
    depth[~np.isfinite(depth)] = 0
    return depth.reshape(h, w).astype(np.float32)


def annotate(X, depth, noise_px=0.0, rng=None, eps=15.0) -> FrameAnnotation:
    rng = rng if rng is not None else np.random.default_rng(0)
    uv = CAM.project(X)
    D = observed_depth(depth, uv)  # closest surface in the 3x3 window, like synth's annotator
    vis = np.isfinite(D) & (X[:, 2] <= D + OFF + 10.0)
    par = SK.parent_array
    dz = X[:, 2] - X[np.maximum(par, 0), 2]
    order = np.where(dz > 10, 1, np.where(dz < -10, -1, 0)).astype(np.int8)
    order[par < 0] = 0
    if noise_px:
        uv = uv + rng.normal(0, noise_px, uv.shape)
    return FrameAnnotation(uv, vis, order, np.full((len(X), 3), np.nan))


def _check_constraints(r, ann, bones, tol=0.5):
    X = r.joints_mm
    assert np.max(np.abs(SK.bone_lengths(X) - bones)) < tol
    D = r.observed_depth_mm
    has = np.isfinite(D)
    lo = D + OFF
    assert np.all(X[has, 2] >= lo[has] - tol)
    vis = has & ann.visible
    # (the upper bound moves deeper with an inclined bone: LiftResult.surface_extra_mm)
    assert np.all(X[vis, 2] <= lo[vis] + r.surface_extra_mm[vis] + 15.0 + tol)
    par = SK.parent_array
    k = np.flatnonzero((ann.depth_order != 0) & (par >= 0))
    assert np.all(ann.depth_order[k] * (X[k, 2] - X[par[k], 2]) >= 5.0 - tol)


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(7)
    out = []
    for _ in range(6):
        X = random_pose(rng)
        depth = render(X)
        out.append((X, depth, annotate(X, depth)))
    return out


# ------------------------------------------------------------------ tests
def test_fixture_poses_respect_limits(frames):
    fl_lim, ab_lim = SK.angle_limits()
    for X, _, _ in frames:
        fl, ab = SK.joint_angles(X)
        assert np.all(fl >= fl_lim[:, 0] - 1e-6) and np.all(fl <= fl_lim[:, 1] + 1e-6)
        assert np.all(ab >= ab_lim[:, 0] - 1e-6) and np.all(ab <= ab_lim[:, 1] + 1e-6)


def test_exact_annotations_recovered_and_constraints_hold(frames):
    errs = []
    for X, depth, ann in frames:
        bones = SK.bone_lengths(X)
        r = lift_frame(ann, depth, CAM, SK, bones)
        assert r.converged, r.message
        assert r.joints_mm.shape == (21, 3) and r.confidence.shape == (21,)
        assert np.nanmax(r.reprojection_px) < 3.0
        _check_constraints(r, ann, bones)
        errs.append(np.linalg.norm(r.joints_mm - X, axis=1))
    errs = np.array(errs)
    assert errs.mean() < 2.0, errs.mean(axis=1)
    assert np.median(errs.max(axis=1)) < 8.0


def test_angle_ranges_are_soft_penalties():
    """Noisy 2D pushes towards impossible angles: the lift stays near the angle ranges (soft:
    a few degrees beyond at most) and much nearer than without them; bones stay hard."""
    rng = np.random.default_rng(3)
    worst_on, total_on, total_off = 0.0, 0.0, 0.0
    for _ in range(4):
        X = random_pose(rng)
        depth = render(X)
        ann = annotate(X, depth, noise_px=4.0, rng=rng)
        bones = SK.bone_lengths(X)
        on = lift_frame(ann, depth, CAM, SK, bones, angle_limits=True)
        off = lift_frame(ann, depth, CAM, SK, bones, angle_limits=False)
        v_on = SK.angle_range_violation_deg(on.joints_mm)
        v_off = SK.angle_range_violation_deg(off.joints_mm)
        worst_on = max(worst_on, float(v_on.max()))
        total_on += float(v_on.sum())
        total_off += float(v_off.sum())
        assert np.max(np.abs(SK.bone_lengths(on.joints_mm) - bones)) < 0.5
    assert worst_on < 10.0
    assert total_on <= total_off


def test_reversed_finger_in_2d_is_pulled_back_towards_the_ranges(frames):
    """2D clicks of an index finger bent backwards by 60 degrees at the PIP: without the
    ranges the lift follows them; with them the PIP flexion is pulled back towards its range."""
    from handanno_core.synth import gesture_library, local_pose, make_hand_model

    model = make_hand_model(0)
    params = gesture_library(model)["open"].copy()
    params[2] = -60.0  # index PIP flexion
    local = local_pose(model, params)[0]
    rot = np.diag([1.0, -1.0, -1.0])  # palm to the camera, fingers up
    X = (local - local.mean(axis=0)) @ rot.T + np.array([0.0, 0.0, 380.0])
    depth = render(X)
    ann = annotate(X, depth)
    bones = SK.bone_lengths(X)
    k = list(SK.angle_joints).index(SK.joint_names.index("index_pip"))
    on = lift_frame(ann, depth, CAM, SK, bones, angle_limits=True)
    off = lift_frame(ann, depth, CAM, SK, bones, angle_limits=False)
    v_on = SK.angle_range_violation_deg(on.joints_mm)[k]
    v_off = SK.angle_range_violation_deg(off.joints_mm)[k]
    assert v_off > 30.0  # the clicks alone give the impossible pose
    assert v_on < 0.6 * v_off, (v_on, v_off)


def test_analytic_derivatives_match_finite_differences(frames):
    X, depth, ann = frames[0]
    ann = ann.copy()
    ann.xyz_mm[3] = X[3] + 1.0
    ann.accepted[[3, 5, 9, 14]] = True  # accepted guesses: their 2D (and 3D) residuals weigh less
    bones = SK.bone_lengths(X)
    x0, d_obs = initial_pose(ann, depth, CAM, SK, bones)
    prob = _Problem(
        ann,
        d_obs,
        CAM,
        SK,
        bones,
        x0,
        eps_mm=15.0,
        angle_limits=True,
        order_margin_mm=5.0,
        w_3d=1.0,
        w_surface=0.01,
        w_free=1e-3,
        soft_bones=0.1,
        right_hand=True,
        w_accepted=0.0625,
    )
    prob = prob.with_start(x0, x0[:, 2], elastic=True)
    x = np.random.default_rng(0).normal(0, 0.5, prob.n_var)
    x[63:] = np.abs(x[63:])

    def fd(fun, h=1e-6):
        cols = []
        for i in range(len(x)):
            e = np.zeros_like(x)
            e[i] = h
            cols.append((np.atleast_1d(fun(x + e)) - np.atleast_1d(fun(x - e))) / (2 * h))
        return np.stack(cols, axis=-1)

    np.testing.assert_allclose(
        prob.objective(x)[1], fd(lambda v: prob.objective(v)[0])[0], atol=1e-4
    )
    np.testing.assert_allclose(prob.eq_jac(x), fd(prob.eq), atol=1e-5)
    np.testing.assert_allclose(prob.ineq_jac(x), fd(prob.ineq), atol=1e-5)


def test_accepted_guesses_a_few_px_off_weigh_less_than_clicks():
    """Six joints per frame 4 px off (guesses accepted as close enough): flagged as accepted,
    the clicks, depths and bones move them, and the frames lift closer to the truth than with
    the same positions taken as clicks."""
    rng = np.random.default_rng(7)
    err = {True: [], False: []}
    for i in range(6):
        X = random_pose(rng)
        depth = render(X)
        ann = annotate(X, depth)
        off = np.random.default_rng(i).choice(np.arange(1, 21), 6, replace=False)
        angle = np.random.default_rng(i).uniform(0, 2 * np.pi, len(off))
        ann.uv_px[off] += 4.0 * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        for accepted in (True, False):
            a = ann.copy()
            a.accepted[off] = accepted
            r = lift_frame(a, depth, CAM, SK, SK.bone_lengths(X))
            err[accepted].append(np.linalg.norm(r.joints_mm - X, axis=1).mean())
    assert np.mean(err[True]) < 0.95 * np.mean(err[False])


def test_an_accepted_3d_position_weighs_less_than_one_placed_by_hand():
    """A review correction seeds every joint in 3D where it was shown; the annotator accepts the
    ones it does not move. Clicked 2D at the truth and a shown 3D position 8 mm off along the
    ray: accepted, the clicks and depths pull the joint further to the truth than when the same
    position was placed by hand."""
    rng = np.random.default_rng(3)
    err = {True: [], False: []}
    for _ in range(4):
        X = random_pose(rng)
        depth = render(X)
        ann = annotate(X, depth)
        for accepted in (True, False):
            a = ann.copy()
            ray = X[[4, 8, 16]] / np.linalg.norm(X[[4, 8, 16]], axis=1, keepdims=True)
            a.xyz_mm[[4, 8, 16]] = X[[4, 8, 16]] + 8.0 * ray
            a.accepted[[4, 8, 16]] = accepted
            r = lift_frame(a, depth, CAM, SK, SK.bone_lengths(X))
            err[accepted].append(np.linalg.norm(r.joints_mm - X, axis=1)[[4, 8, 16]].mean())
    assert np.mean(err[True]) < 0.9 * np.mean(err[False]), err


def test_missing_joints_and_missing_depth_still_lift(frames):
    X, depth, ann = frames[1]
    bones = SK.bone_lengths(X)
    ann = ann.copy()
    ann.uv_px[[8, 12]] = np.nan  # two tips not annotated
    ann.depth_order[[8, 12]] = 0
    depth = depth.copy()
    u, v = np.rint(CAM.project(X[6])).astype(int)
    depth[v - 5 : v + 6, u - 5 : u + 6] = 0  # no valid depth under joint 6
    r = lift_frame(ann, depth, CAM, SK, bones)
    assert np.all(np.isfinite(r.joints_mm))
    assert np.isnan(r.observed_depth_mm[6]) and np.isnan(r.reprojection_px[8])
    assert r.confidence[8] < 0.5 and r.confidence[12] < 0.5 and r.confidence[6] < 0.8
    assert r.confidence[1] > 0.8
    assert np.max(np.abs(SK.bone_lengths(r.joints_mm) - bones)) < 0.5
    err = np.linalg.norm(r.joints_mm - X, axis=1)
    assert np.median(err) < 3.0


def test_a_hand_past_the_image_border_starts_from_the_template_hand_on_its_clicked_joints():
    """A reference whose wrist, thumb and last two fingers are off the image has no clicks there.
    Those joints start on the template hand moved rigidly onto the clicked ones, not hung off a
    wrist put at the clicked joints' mean (113 mm off for these poses before)."""
    from handanno_core import synth

    model = synth.make_hand_model(0)
    gestures = synth.gesture_library(model)
    gone = [0, 10, 11, 12, 14, 15, 16, 17, 18, 19, 20]
    for gesture, wrist_mm, gone_mm in (("relaxed", 10.0, 10.0), ("open", 50.0, 50.0)):
        for yaw in (0.0, 40.0):
            rot = synth.rotation_matrices(np.array([[yaw, 20.0, 0.0]]))
            X = synth.forward_kinematics(model, gestures[gesture][None], rot, [[0, 0, 370.0]])[0]
            depth = synth.render_frame(model, X, rot[0])
            ann = synth.simulate_annotation(X, depth, CAM, SK)
            ann.uv_px[gone], ann.depth_order[gone], ann.visible[gone] = np.nan, 0, False
            start, _ = initial_pose(ann, depth, CAM, SK, SK.bone_lengths(X))
            err = np.linalg.norm(start - X, axis=1)
            assert err[0] < wrist_mm and err[gone].mean() < gone_mm, (gesture, yaw, err.round(1))
            hung = np.isin(SK.bones[:, 1], gone)  # bones ending at a joint without a click
            np.testing.assert_allclose(SK.bone_lengths(start)[hung], SK.bone_lengths(X)[hung])


def test_joints_given_in_3d_are_kept(frames):
    X, depth, ann = frames[2]
    bones = SK.bone_lengths(X)
    ann = ann.copy()
    ann.uv_px[[3, 4]] = np.nan
    ann.xyz_mm[[3, 4]] = X[[3, 4]]
    r = lift_frame(ann, depth, CAM, SK, bones)
    assert np.linalg.norm(r.joints_mm[[3, 4]] - X[[3, 4]], axis=1).max() < 3.0


def test_warm_start_is_consistent(frames):
    X, depth, ann = frames[3]
    bones = SK.bone_lengths(X)
    r = lift_frame(ann, depth, CAM, SK, bones)
    r2 = lift_frame(ann, depth, CAM, SK, bones, init_mm=r.joints_mm)
    assert r2.iterations <= r.iterations
    assert np.abs(r2.joints_mm - r.joints_mm).max() < 1.0


def test_malformed_annotations_raise(frames):
    X, depth, ann = frames[0]
    bones = SK.bone_lengths(X)
    bad = ann.copy()
    bad.uv_px = bad.uv_px[:20]
    with pytest.raises(AnnotationError, match="shape"):
        lift_frame(bad, depth, CAM, SK, bones)
    bad = ann.copy()
    bad.uv_px[5, 0] = np.nan
    with pytest.raises(AnnotationError, match="half-NaN"):
        lift_frame(bad, depth, CAM, SK, bones)
    bad = ann.copy()
    bad.depth_order[3] = 2
    with pytest.raises(AnnotationError):
        lift_references({0: bad}, lambda f: depth, CAM, SK)
    with pytest.raises(ValueError, match="bone_lengths_mm"):
        lift_frame(ann, depth, CAM, SK, bones[:5])


def test_bone_lengths_estimated_from_exact_data():
    """Bone-length estimation converges to the true lengths on exact data (24 rendered frames,
    bones 5 % longer than the template with +-3 % per-bone variation)."""
    rng = np.random.default_rng(5)
    true = np.asarray(SK.template_bone_lengths_mm) * 1.05 * rng.uniform(0.97, 1.03, 20)
    anns, depths, poses = {}, {}, {}
    for f in range(24):
        X = random_pose(rng, true)
        depths[f] = render(X)
        anns[f] = annotate(X, depths[f])
        poses[f] = X
    # (render() puts tips inside a sphere, ~5 mm below their surface, unlike synth's capsules
    # and real fingertips: the votes of references that see a tip would measure that, so every
    # reference votes here; tests/test_lift_synth.py checks the seen votes on capsule hands)
    # two processes (CI has two cores): the same lifts as one, sooner
    res = lift_references(anns, depths.__getitem__, CAM, SK, seen_votes=False, workers=2)
    err = np.abs(res.bone_lengths_mm - true)
    start = np.abs(res.bone_history_mm[0] - true)
    # measured: mean 0.35, max 0.87 mm (from 0.97 mm mean at the scaled template)
    assert err.mean() < 0.6 and err.max() < 1.5 and err.mean() < 0.5 * start.mean(), (err, start)
    # converged: the last round moved no bone by more than the tolerance
    assert np.max(np.abs(res.bone_history_mm[-1] - res.bone_history_mm[-2])) < 0.1
    assert len(res.bone_history_mm) < 11
    e_est = np.mean([np.linalg.norm(res.joints_mm[f] - poses[f], axis=1).mean() for f in poses])
    assert e_est < 2.5
    pinned = lift_references(
        anns, depths.__getitem__, CAM, SK, bone_lengths_mm=true, pin_bone_lengths=True, workers=2
    )
    np.testing.assert_array_equal(pinned.bone_lengths_mm, true)
    e = np.mean([np.linalg.norm(pinned.joints_mm[f] - poses[f], axis=1).mean() for f in poses])
    # measured 2.04 mm with the soft learned ranges (the poses are drawn inside the narrower
    # anatomical limits, which hard walls enforced exactly: < 2.0 mm)
    assert e < 2.2


def test_uncertain_bones_shrink_towards_the_templates_proportions():
    """Empirical Bayes: a bone's median moves towards the scaled template by its own sampling
    uncertainty against the spread of the hand's proportions around the template."""
    rng = np.random.default_rng(3)
    tmpl = np.asarray(SK.template_bone_lengths_mm)
    voted = np.ones(len(tmpl), dtype=bool)
    # a hand shaped like the template, 8 references measuring every bone with 6 % noise
    true = tmpl * 1.1
    samples = true * (1.0 + rng.normal(0.0, 0.06, (8, len(tmpl))))
    med = np.median(samples, axis=0)
    out = shrink_to_template(med, samples, voted, tmpl)
    assert np.abs(out - true).mean() < 0.5 * np.abs(med - true).mean()
    # exact measurements (no spread across references): nothing to shrink
    exact = np.tile(tmpl * rng.uniform(0.8, 1.2, len(tmpl)), (8, 1))
    np.testing.assert_allclose(shrink_to_template(exact[0], exact, voted, tmpl), exact[0])
    # a hand shaped unlike the template, measured with 1 % noise, keeps its own proportions
    odd = tmpl * rng.uniform(0.8, 1.2, len(tmpl))
    s = odd * (1.0 + rng.normal(0.0, 0.01, (8, len(tmpl))))
    m = np.median(s, axis=0)
    o = shrink_to_template(m, s, voted, tmpl)
    assert np.max(np.abs(o - m) / m) < 0.005
    assert np.max(np.abs(o - odd) / odd) < 0.02
    # too few bones with enough samples to tell the spreads apart: unchanged
    few = np.full_like(samples, np.nan)
    few[:, :3] = samples[:, :3]
    np.testing.assert_array_equal(shrink_to_template(med, few, voted, tmpl), med)


def test_impossible_depth_reading_is_dropped(frames):
    """A visible tip whose 2D slipped onto a surface far behind (the palm) must not drag the
    finger back: the reading is inconsistent with the bone to its parent and is dropped."""
    X, depth, ann = frames[4]
    bones = SK.bone_lengths(X)
    vis_tips = [t for t in (4, 8, 12, 16, 20) if ann.visible[t] and ann.visible[SK.parent_array[t]]]
    assert vis_tips, "fixture frame needs a visible tip"
    t = vis_tips[0]
    depth = depth.copy()
    u, v = np.rint(CAM.project(X[t])).astype(int)
    depth[v - 1 : v + 2, u - 1 : u + 2] = X[t, 2] + 80.0  # the 3x3 under the tip reads far
    r = lift_frame(ann, depth, CAM, SK, bones)
    assert np.isnan(r.observed_depth_mm[t])
    assert np.linalg.norm(r.joints_mm[t] - X[t]) < 8.0
    assert np.linalg.norm(r.joints_mm - X, axis=1).mean() < 3.0


def test_a_joint_placed_in_3d_drops_a_depth_reading_behind_it(frames):
    """A seeded 3D joint whose pixel reads the background 40 mm behind it keeps no depth
    reading (the lift would push it there); one reading its own surface keeps it."""
    X, depth, ann = frames[0]
    ann = ann.copy()
    ann.xyz_mm[[4, 8]] = X[[4, 8]]
    u, v = np.rint(CAM.project(X[4])).astype(int)
    seen = depth.copy()
    seen[v - 2 : v + 3, u - 2 : u + 3] = X[4, 2] + 40.0
    _, d_obs = initial_pose(ann, seen, CAM, SK, SK.bone_lengths(X))
    assert np.isnan(d_obs[4]) and np.isfinite(d_obs[8])
    plain = ann.copy()
    plain.xyz_mm[:] = np.nan  # clicked only: the reading stays (the other checks decide)
    _, d_plain = initial_pose(plain, seen, CAM, SK, SK.bone_lengths(X))
    assert d_plain[4] > X[4, 2] + 30.0


def test_vectorized_angle_rows_match_skeleton_angles(frames):
    """The flexion rows are zero exactly at the limits computed by Skeleton.joint_angles."""
    X = frames[0][0]
    x0, d_obs = initial_pose(frames[0][2], frames[0][1], CAM, SK, SK.bone_lengths(X))
    prob = _Problem(
        frames[0][2],
        d_obs,
        CAM,
        SK,
        SK.bone_lengths(X),
        x0,
        eps_mm=15.0,
        angle_limits=True,
        order_margin_mm=10.0,
        w_3d=1.0,
        w_surface=0.1,
        w_free=1e-3,
        soft_bones=None,
        right_hand=True,
        w_angle_inner=1.0,
    )
    vals, _ = prob._angles(X)
    vals = vals.reshape(2, 4, -1)  # two tiers: the learned ranges, then the anatomical limits
    fl, ab = SK.joint_angles(X)
    for tier, (fl_lim, ab_lim) in zip(vals, (SK.angle_ranges(), SK.angle_limits()), strict=True):
        on = np.ptp(fl_lim, axis=1) < 170.0  # wider flexion ranges are no limit (rows off)
        assert np.all(tier[:2, ~on] == 0.0)
        # sign of each row equals the sign of the margin to its limit
        assert np.all(np.sign(tier[0, on]) == np.sign(fl - fl_lim[:, 0])[on])
        assert np.all(np.sign(tier[1, on]) == np.sign(fl_lim[:, 1] - fl)[on])
        assert np.all(np.sign(tier[2]) == np.sign(ab - ab_lim[:, 0]))
        assert np.all(np.sign(tier[3]) == np.sign(ab_lim[:, 1] - ab))


def test_inconsistent_depth_rules():
    """Backed readings are kept; an unbacked impossible pair loses both readings."""
    from handanno_core.lift.initial import _drop_inconsistent_depths

    X = random_pose(np.random.default_rng(2))
    bones = SK.bone_lengths(X)
    d = X[:, 2] - OFF  # exact readings
    vis = np.ones(21, dtype=bool)
    tip_far = d.copy()
    tip_far[4] += 90.0  # index tip reads the palm behind it; DIP backed by the PIP
    out = _drop_inconsistent_depths(tip_far, vis, OFF, SK, bones, 15.0)
    assert np.isnan(out[4]) and np.isfinite(out[[1, 2, 3]]).all()
    dip_near = d.copy()
    dip_near[3] -= 100.0  # DIP reads a finger in front; PIP hidden, so nothing backs either
    v2 = vis.copy()
    v2[2] = False
    out = _drop_inconsistent_depths(dip_near, v2, OFF, SK, bones, 15.0)
    assert np.isnan(out[3]) and np.isnan(out[4]) and np.isfinite(out[[0, 1, 5, 8]]).all()
    np.testing.assert_array_equal(_drop_inconsistent_depths(d, vis, OFF, SK, bones, 15.0), d)


def _bad_tip_depth(X, depth, tip=4, behind_mm=30.0):
    """``depth`` with the 3x3 under ``tip`` reading ``behind_mm`` behind it (2D off the finger):
    an interval no pose with these bones can meet, and too close to be dropped as impossible."""
    bad = depth.copy()
    u, v = np.rint(CAM.project(X[tip])).astype(int)
    bad[v - 1 : v + 2, u - 1 : u + 2] = X[tip, 2] + behind_mm
    return bad


def test_start_elastic_gives_the_fallback_result_directly(frames, monkeypatch):
    """Live re-lifts of a frame that needed slack start in elastic mode (skipping a hard solve
    that would fail again): same result as the hard-then-elastic fallback; on a feasible frame
    the elastic solution has no slack and is reported as a hard one."""
    X, depth, ann = frames[5]
    bones = SK.bone_lengths(X)
    bad = _bad_tip_depth(X, depth)
    fallback = lift_frame(ann, bad, CAM, SK, bones)
    direct = lift_frame(ann, bad, CAM, SK, bones, start_elastic=True)
    assert fallback.elastic and direct.elastic and list(fallback.slack_joints) == [4]
    assert direct.converged
    assert np.abs(direct.joints_mm - fallback.joints_mm).max() < 0.5
    # slacks on the joint that needed one only: one small solve, same solution
    import handanno_core.lift.solve as lift_module

    slacks_per_solve = []
    real_solve = lift_module._solve

    def spy(prob, *args):
        slacks_per_solve.append(prob.n_slack)
        return real_solve(prob, *args)

    monkeypatch.setattr(lift_module, "_solve", spy)
    # (the mechanics of one solve: no re-solves for inclined fingers or dropped readings)
    one_solve = dict(incline_surface=False, drop_slack_depths=False)
    X2, depth2, ann2 = frames[2]
    bones2 = SK.bone_lengths(X2)
    bad2 = _bad_tip_depth(X2, depth2, tip=8, behind_mm=25.0)
    wide = lift_frame(ann2, bad2, CAM, SK, bones2, start_elastic=True, **one_solve)
    assert list(wide.slack_joints) == [8]
    slacks_per_solve.clear()
    narrow = lift_frame(
        ann2, bad2, CAM, SK, bones2, start_elastic=True, elastic_joints=[8], **one_solve
    )
    assert narrow.converged and list(narrow.slack_joints) == [8] and slacks_per_solve == [1]
    assert np.abs(narrow.joints_mm - wide.joints_mm).max() < 0.05
    # ... and a wrong guess (a joint whose interval is fine) falls back to slacks on all joints
    slacks_per_solve.clear()
    guess = lift_frame(
        ann2, bad2, CAM, SK, bones2, start_elastic=True, elastic_joints=[12], **one_solve
    )
    assert guess.converged and list(guess.slack_joints) == [8]
    assert len(slacks_per_solve) == 2 and slacks_per_solve[0] == 1 and slacks_per_solve[1] > 10
    assert np.abs(guess.joints_mm - wide.joints_mm).max() < 0.05
    hard = lift_frame(ann, depth, CAM, SK, bones)
    relaxed = lift_frame(ann, depth, CAM, SK, bones, start_elastic=True)
    assert not hard.elastic and not relaxed.elastic and relaxed.converged
    assert np.abs(relaxed.joints_mm - hard.joints_mm).max() < 0.05
    _check_constraints(relaxed, ann, bones)


def test_feasible_iterate_at_iteration_limit_is_kept(frames):
    """Running out of iterations on a feasible iterate is not infeasibility: no elastic re-solve
    (which would spend as many iterations again), result flagged not converged."""
    X, depth, ann = frames[0]
    bones = SK.bone_lengths(X)
    r = lift_frame(ann, depth, CAM, SK, bones, max_iter=8)
    assert not r.elastic and not r.converged
    assert r.iterations == 8
    assert np.max(np.abs(SK.bone_lengths(r.joints_mm) - bones)) < 0.5


def test_stalled_hard_solve_stops_early(frames, monkeypatch):
    """An infeasible hard solve whose violation is stuck is stopped after a few iterations (not
    run to max_iter) before the elastic re-solve; feasible solves run to convergence."""
    import handanno_core.lift.solve as lift_module

    solves = []
    real_solve = lift_module._solve

    def spy(prob, *args):
        res = real_solve(prob, *args)
        solves.append((prob.elastic, int(res.nit), bool(res.success)))
        return res

    monkeypatch.setattr(lift_module, "_solve", spy)
    # (one solve's mechanics: no re-solves for inclined fingers or dropped readings; the closest
    # reading and one surface depth, with which this frame's elastic solve converges in 25
    # iterations instead of SLSQP's slow 320-iteration tail with the front-median reading)
    one_solve = dict(
        incline_surface=False,
        drop_slack_depths=False,
        depth_front_band_mm=None,
        surface_depth_mm=3.0,
    )
    X, depth, ann = frames[5]
    bones = SK.bone_lengths(X)
    r = lift_frame(ann, _bad_tip_depth(X, depth), CAM, SK, bones, max_iter=200, **one_solve)
    assert r.elastic and r.converged
    (hard_elastic, hard_nit, hard_ok), (second_elastic, _, _) = solves
    assert not hard_elastic and not hard_ok and hard_nit <= 10 and second_elastic
    solves.clear()
    X, depth, ann = frames[0]
    r = lift_frame(ann, depth, CAM, SK, SK.bone_lengths(X), max_iter=200, **one_solve)
    assert r.converged and not r.elastic and solves == [(False, r.iterations, True)]


# ------------------------------------------------------------------ scale, stretch, calibration
def _rendered_set(rng, true_bones, n=24, offsets=None):
    """``n`` random poses with ``true_bones``, rendered with surface ``offsets`` (default: the
    skeleton's), annotated exactly."""
    global OFF
    saved = OFF
    if offsets is not None:
        OFF = np.asarray(offsets, dtype=np.float64)
    try:
        anns, depths, poses = {}, {}, {}
        for f in range(n):
            X = random_pose(rng, true_bones)
            depths[f] = render(X)
            anns[f] = annotate(X, depths[f])
            poses[f] = X
    finally:
        OFF = saved
    return anns, depths, poses


def test_bones_from_partial_annotations_of_a_larger_hand():
    """12 of 21 joints annotated on a hand 1.3x the template (+-3 % per bone): every bone,
    annotated at both ends or not, is estimated within 5 % (global scale first, then per bone)."""
    rng = np.random.default_rng(8)
    true = np.asarray(SK.template_bone_lengths_mm) * 1.3 * rng.uniform(0.97, 1.03, 20)
    anns, depths, _ = _rendered_set(rng, true, n=16)
    keep = np.zeros(21, dtype=bool)
    keep[[0, 1, 2, 3, 4, 5, 6, 9, 13, 17, 18, 19]] = True
    for a in anns.values():
        a.uv_px[~keep] = np.nan
        a.depth_order[~keep] = 0
    # render() puts a tip at the centre of a sphere, not on the far end of its segment's cap
    # (synth's capsules, real fingertips): the tips' surface rule is left out here
    # two processes (CI has two cores): the same lifts as one, in about half the time
    res = lift_references(
        anns, depths.__getitem__, CAM, SK, incline_tips=False, seen_votes=False, workers=2,
        **TOY_SURFACE,
    )  # fmt: skip
    rel = np.abs(res.bone_lengths_mm - true) / true
    assert rel.max() < 0.05, np.round(rel, 3)
    both = keep[SK.bones[:, 0]] & keep[SK.bones[:, 1]]
    np.testing.assert_array_equal(res.bone_votes, np.where(both, 16, 0))
    # the template alone would be 30 % off
    tmpl_rel = np.abs(np.asarray(SK.template_bone_lengths_mm) - true) / true
    assert tmpl_rel.min() > 0.2


def test_a_reference_that_needs_a_stretched_bone_is_reported():
    """One reference whose index finger is clicked twice as long as in the others: the lift
    reports it stretched (not converged, halved confidence); the others are not."""
    rng = np.random.default_rng(9)
    true = np.asarray(SK.template_bone_lengths_mm) * rng.uniform(0.97, 1.03, 20)
    anns, depths, _ = _rendered_set(rng, true, n=8)
    bad = anns[3]
    uv = bad.uv_px
    for k in (2, 3, 4):  # stretch the index finger from its MCP in 2D
        uv[k] = uv[1] + 2.0 * (uv[k] - uv[1])
    bad.visible[[2, 3, 4]] = False  # no depth reading can contradict the longer finger
    with pytest.warns(UserWarning, match="stretching"):
        res = lift_references(anns, depths.__getitem__, CAM, SK, **TOY_SURFACE)
    assert res.results[3].stretched and not res.results[3].converged
    assert "stretched" in res.results[3].message
    assert not any(res.results[f].stretched for f in anns if f != 3)


def test_surface_offset_self_calibration_recovers_a_deeper_wrist():
    """The data's wrist centre lies 12 mm deeper below the observed surface than the skeleton's
    default offset says (as on NYU, where wrist and palm joints sit 26-35 mm deep): the
    calibrated offset moves towards the truth and the wrist error drops. Measured: 15 -> 19.4 mm
    against 27 mm true (a frontal wrist's depth is only weakly fixed by its bones, so the median
    residual recovers about a third of the offset error)."""
    rng = np.random.default_rng(5)
    true = np.asarray(SK.template_bone_lengths_mm)
    offsets = OFF.copy()
    offsets[0] += 12.0
    anns, depths, poses = _rendered_set(rng, true, n=24, offsets=offsets)
    # the toy poses are drawn uniformly inside the anatomical limits, not as real hands move:
    # the pose prior (tested on its own below) is off, so this measures the calibration alone
    toy = dict(TOY_SURFACE, w_pose=0.0, workers=2)  # two processes: the same lifts, sooner
    cal = lift_references(anns, depths.__getitem__, CAM, SK, **toy)
    raw = lift_references(anns, depths.__getitem__, CAM, SK, calibrate_surface=False, **toy)
    np.testing.assert_array_equal(raw.surface_offsets_mm, OFF)
    err_cal = abs(cal.surface_offsets_mm[0] - offsets[0])
    assert err_cal < 0.75 * 12.0, cal.surface_offsets_mm[0]
    # the fingers' offsets, right by construction, stay within a millimetre
    assert np.max(np.abs(cal.surface_offsets_mm[1:] - OFF[1:])) < 1.0

    def wrist_err(res):
        return np.mean([np.linalg.norm(res.joints_mm[f][0] - poses[f][0]) for f in poses])

    assert wrist_err(cal) < wrist_err(raw)


def test_elastic_lift_of_a_frame_with_few_joints_has_no_hard_rows(frames):
    """A frame with only its first joints placed, one of them occluded, re-lifted in elastic mode
    (as the app does): every depth bound becomes a slack row and angle ranges are soft penalties,
    so no hard inequality row is left; the lift must still run (it crashed reshaping the empty
    Jacobian in the app)."""
    from dataclasses import replace

    X, depth, ann = frames[5]
    bones = SK.bone_lengths(X)
    few = np.zeros(SK.num_joints, dtype=bool)
    few[:2] = True
    partial = replace(
        ann,
        uv_px=np.where(few[:, None], ann.uv_px, np.nan),
        visible=np.where(np.arange(SK.num_joints) == 0, False, ann.visible),
        depth_order=np.zeros(SK.num_joints, dtype=np.int8),
    )
    result = lift_frame(partial, depth, CAM, SK, bones, start_elastic=True, elastic_joints=[0, 1])
    assert np.all(np.isfinite(result.joints_mm))
    assert np.linalg.norm(result.joints_mm[1] - X[1]) < 15.0


def _assert_objective_gradient(prob: _Problem, pose: np.ndarray, h: float = 1e-6) -> None:
    """``prob.objective``'s gradient at ``pose`` (J, 3) mm matches central differences."""
    x = ((pose - prob.x0) / prob.sc3).ravel()
    g = prob.objective(x)[1]
    fd = np.array([
        (prob.objective(x + h * e)[0] - prob.objective(x - h * e)[0]) / (2 * h)
        for e in np.eye(len(x))
    ])  # fmt: skip
    np.testing.assert_allclose(g, fd, atol=1e-4, rtol=1e-5)


def test_angle_penalty_gradient_matches_finite_differences(frames):
    """The reverse-mode gradient of any weighted sum of the angle rows (two tiers, both hands)
    matches finite differences, and so does the objective's gradient on a pose outside the
    ranges (a finger bent backwards) and inside them (where the penalty is 0)."""
    X, depth, ann = frames[0]
    bones = SK.bone_lengths(X)
    x0, d_obs = initial_pose(ann, depth, CAM, SK, bones)
    bent = X.copy()
    bent[[7, 8]] = bent[6] + (bent[6] - bent[5]) * np.array([[1.0], [2.0]])  # straight line
    bent[[7, 8]] += (
        25.0
        * np.cross(bent[6] - bent[5], [0.0, 0.0, 1.0])[None]
        / np.linalg.norm(bent[6] - bent[5])
    )
    rng = np.random.default_rng(0)
    h = 1e-6
    for right in (True, False):
        prob = _Problem(ann, d_obs, CAM, SK, bones, x0, eps_mm=15.0, angle_limits=True,
                        order_margin_mm=10.0, w_3d=1.0, w_surface=0.1, w_free=1e-3,
                        soft_bones=None, right_hand=right, w_angle_inner=1.0)  # fmt: skip
        P = X + rng.normal(0.0, 3.0, X.shape)
        rows, fr = prob._angles(P)
        w = rng.normal(size=rows.shape)
        fd = np.zeros_like(P)
        for k in range(P.size):
            e = np.zeros(P.size)
            e[k] = h
            e = e.reshape(P.shape)
            fd.flat[k] = (w @ prob._angles(P + e)[0] - w @ prob._angles(P - e)[0]) / (2 * h)
        np.testing.assert_allclose(prob._angle_grad(fr, w), fd, atol=1e-5, rtol=1e-5)
    prob = _Problem(ann, d_obs, CAM, SK, bones, x0, eps_mm=15.0, angle_limits=True,
                    order_margin_mm=10.0, w_3d=1.0, w_surface=0.1, w_free=1e-3,
                    soft_bones=None, right_hand=True)  # fmt: skip
    for pose, outside in ((X, False), (bent, True)):
        assert np.any(prob._angles(pose)[0] < 0) == outside
        _assert_objective_gradient(prob, pose)


def test_pose_prior_gradient_matches_finite_differences(frames):
    """The objective with the pose prior (and the angle rows) has the gradient finite differences
    give, for a right and a left hand; the prior's energy is the objective's increase."""
    from handanno_core.pose_prior import pose_prior

    prior = pose_prior(SK)
    assert prior is not None
    X, depth, ann = frames[1]
    bones = SK.bone_lengths(X)
    x0, d_obs = initial_pose(ann, depth, CAM, SK, bones)
    rng = np.random.default_rng(1)
    for right in (True, False):
        kw = dict(eps_mm=15.0, angle_limits=True, order_margin_mm=10.0, w_3d=1.0, w_surface=0.1,
                  w_free=1e-3, soft_bones=None, right_hand=right)  # fmt: skip
        plain = _Problem(ann, d_obs, CAM, SK, bones, x0, **kw)
        prob = _Problem(ann, d_obs, CAM, SK, bones, x0, pose_prior=prior, w_pose=2.0, **kw)
        P = X + rng.normal(0.0, 3.0, X.shape)
        x = ((P - prob.x0) / prob.sc3).ravel()
        extra = prob.objective(x)[0] - plain.objective(x)[0]
        assert extra == pytest.approx(2.0 * prior.energy(SK, P, right), rel=1e-9)
        _assert_objective_gradient(prob, P)


def test_pose_prior_scores_a_reversed_finger_unlikely_and_mirrors_left_hands(frames):
    """The packaged prior (learned from real recorded hands) gives a finger bent backwards by 60
    degrees at its PIP a far higher energy than the same hand with the finger natural, and a
    mirrored (left) hand, measured as one, the energy of the right hand it mirrors."""
    from handanno_core.pose_prior import pose_prior

    prior = pose_prior(SK)
    X = frames[2][0]
    pip, dip, tip = 6, 7, 8  # index PIP, DIP, tip
    axis = np.cross(X[pip] - X[5], SK.palm_normal(X))
    axis /= np.linalg.norm(axis)
    flex, _ = SK.joint_angles(X)
    k = list(SK.angle_joints).index(pip)
    turn = np.radians(-60.0 - flex[k])  # to 60 degrees of hyperextension at the PIP

    def rotate(v, ang):
        return (v * np.cos(ang) + np.cross(axis, v) * np.sin(ang)
                + axis * (axis @ v) * (1 - np.cos(ang)))  # fmt: skip

    candidates = []
    for sign in (1.0, -1.0):
        bent = X.copy()
        for j in (dip, tip):
            bent[j] = X[pip] + rotate(X[j] - X[pip], sign * turn)
        candidates.append(bent)
    bent = min(candidates, key=lambda b: abs(SK.joint_angles(b)[0][k] + 60.0))
    assert SK.joint_angles(bent)[0][k] < -50.0
    natural, reversed_ = prior.energy(SK, X), prior.energy(SK, bent)
    assert reversed_ > natural + 25.0
    mirrored = X * np.array([-1.0, 1.0, 1.0])
    assert prior.energy(SK, mirrored, right_hand=False) == pytest.approx(natural, rel=1e-9)


def test_session_prior_centres_on_the_sessions_own_hand(frames):
    """The session's prior (:func:`session_prior`) moves the mean towards the session's poses,
    so they score lower under it, and its weight never exceeds the one asked for."""
    from handanno_core.pose_prior import pose_prior, session_prior

    prior = pose_prior(SK)
    poses = np.stack([X for X, _, _ in frames])
    moved, weight = session_prior(prior, SK, poses, 0.3)
    assert 0.0 < weight <= 0.3
    assert np.median(moved.energy(SK, poses)) < 0.7 * np.median(prior.energy(SK, poses))
    # 6 poses against the pseudo-count 5: the mean moves 6/11 of the way
    own = prior.features(SK, poses).mean(axis=0)
    np.testing.assert_allclose(moved.mean, (6 * own + 5 * prior.mean) / 11, atol=1e-12)


@pytest.mark.skipif(
    not (REAL_MOTION / "fpha" / "Subject_2").is_dir(), reason="shared/data/real-motion absent"
)
def test_session_prior_fits_a_person_the_prior_never_saw():
    """FPHA Subject_2 (never read when the prior was learned from Subject_1): 12 poses of a
    sequence lie far from the learned prior (the palm's shape differs), but about as close to
    the session's prior as Subject_1's poses lie to the learned one."""
    from handanno_core import real_motion as rm
    from handanno_core.pose_prior import pose_prior, session_prior, session_scale

    prior = pose_prior(SK)
    files = [f for f in rm.fpha_sequences(REAL_MOTION, "Subject_2") if f.stat().st_size > 0]
    learned, own = [], []
    for f in files[::5]:
        poses = rm.load_fpha(f)
        poses = poses[np.linspace(0, len(poses) - 1, 12).astype(int)]
        learned.append(session_scale(prior, prior.energy(SK, poses)))
        own.append(1.0 / session_prior(prior, SK, poses, 1.0)[1])
    assert np.median(learned) > 2.5
    assert np.median(own) < 1.2


@pytest.mark.skipif(
    not (REAL_MOTION / "fpha" / "Subject_1").is_dir(), reason="shared/data/real-motion absent"
)
def test_packaged_pose_prior_never_saw_the_benchmark_suites_sequences():
    """The packaged prior was learned without the suite's tune-part FPHA sequences (so a weight
    chosen there is chosen on motion it has not seen) and without Subject_2 (the report part)."""
    import json

    from handanno_core.pose_prior import default_pose_prior_path
    from handanno_core.suite import catalogue

    row = json.loads(default_pose_prior_path().read_text())["layouts"]["msra21"]
    tune = {r.motion.split(":", 1)[1] for r in catalogue(0, REAL_MOTION) if r.motion.startswith("fpha:Subject_1")}  # fmt: skip
    assert tune and tune <= set(row["held_out"])
    assert "Subject_2" not in row["source"] and "Subject_1" in row["source"]
