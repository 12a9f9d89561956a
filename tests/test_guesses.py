"""The guesses' refit after each click (handanno_core.guesses) and the bench's interactive simulated
annotator that uses it: it stops when every guess is within the threshold, a refit pulls unplaced
joints towards the truth, and the app's live lift and the bench call the same refit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from review_session import open_review_session, synth_data

import handanno_core.guesses as guesses
from handanno_core.annotation import FrameAnnotation
from handanno_core.review_loop import interactive_fix
from handanno_core.synth import simulate_annotation

FRAMES = 12


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return synth_data(tmp_path_factory, "guesses-data", FRAMES, seed=3)


@pytest.fixture()
def session(data_dir, tmp_path):
    yield from open_review_session(tmp_path / "sess", data_dir)


def frame_inputs(session, frame: int):
    seq = session.open_sequence()
    s = session.model.settings
    return dict(
        gt=np.asarray(seq.ground_truth.joints_mm[frame], dtype=np.float64),
        depth=np.asarray(seq.depth(frame)),
        camera=session.camera,
        skeleton=session.skeleton,
        bones=np.asarray(session.model.bone_lengths_mm, dtype=np.float64),
        settings=dict(eps_mm=s.eps_mm, angle_limits=s.angle_limits),
    )


def bent_finger(skeleton, gt: np.ndarray, degrees: float) -> tuple[np.ndarray, list[int]]:
    """``gt`` (J, 3) mm with the first finger turned by ``degrees`` about its base joint (the
    pre-fill of a frame whose finger moved), and that finger's joints below its base."""
    parents = skeleton.parent_array
    base = int(np.flatnonzero(parents == 0)[0])
    chain = [base]
    while (kids := np.flatnonzero(parents == chain[-1])).size:
        chain.append(int(kids[0]))
    a = np.radians(degrees)
    axis = np.cross(gt[chain[1]] - gt[base], [0.0, 0.0, 1.0])
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k
    out = gt.copy()
    out[chain[1:]] = (gt[chain[1:]] - gt[base]) @ rot.T + gt[base]
    return out, chain[1:]


def test_interactive_annotator_stops_when_every_guess_is_within_the_threshold(session):
    x = frame_inputs(session, 5)
    cam, sk = x["camera"], x["skeleton"]
    truth = cam.project(x["gt"])
    guess = x["gt"] + np.array([12.0, -8.0, 4.0])  # the whole hand shifted: every guess off
    before = np.linalg.norm(cam.project(guess) - truth, axis=1)
    assert np.all(before > 4.0)
    spent: list[float] = []
    ann, clicks, order = interactive_fix(
        guess, x["gt"], x["depth"], cam, sk, x["bones"], **x["settings"], refit_s=spent
    )
    off = np.linalg.norm(ann.uv_px - truth, axis=1)
    assert np.all(off <= 4.0 + 1e-9)  # moved to the truth, or accepted within 4 px
    assert clicks == len(order) == len(set(order)) == len(spent)
    assert 1 <= clicks < sk.num_joints  # the refits put some joints in place before any click
    untouched = np.setdiff1d(np.arange(sk.num_joints), order)
    assert np.all(off[order] < 1e-6) and np.any(off[untouched] > 1e-3)  # accepted where drawn
    full = simulate_annotation(x["gt"], x["depth"], cam, sk)
    np.testing.assert_array_equal(ann.visible, full.visible)
    np.testing.assert_array_equal(ann.depth_order, full.depth_order)
    # nothing off: nothing clicked, every guess accepted
    ann0, clicks0, _ = interactive_fix(
        x["gt"], x["gt"], x["depth"], cam, sk, x["bones"], **x["settings"]
    )
    assert clicks0 == 0 and np.allclose(ann0.uv_px, truth)


def test_a_refit_pulls_the_unplaced_joints_towards_the_truth(session):
    x = frame_inputs(session, 7)
    cam, sk, gt = x["camera"], x["skeleton"], x["gt"]
    prefill, finger = bent_finger(sk, gt, 35.0)
    tip = finger[-1]
    full = simulate_annotation(gt, x["depth"], cam, sk)
    placed = [0, *[int(k) for k in np.flatnonzero(sk.parent_array == 0)]]  # wrist and bases
    ann = FrameAnnotation.empty(sk.num_joints)
    for k in placed:
        ann.uv_px[k], ann.visible[k], ann.depth_order[k] = full.uv_px[k], full.visible[k], 0
    first = guesses.refit_guesses(
        ann, x["depth"], cam, sk, x["bones"], prefill_mm=prefill, **x["settings"]
    )
    ann.uv_px[tip] = full.uv_px[tip]  # the bent finger's tip moved to the truth
    ann.visible[tip] = full.visible[tip]
    second = guesses.refit_guesses(
        ann, x["depth"], cam, sk, x["bones"], prefill_mm=prefill, previous_mm=first.joints_mm,
        start_elastic=bool(first.slack_joints), elastic_joints=first.slack_joints, **x["settings"],
    )  # fmt: skip
    middle = [k for k in finger if k != tip]
    err_before = np.linalg.norm(first.joints_mm[middle] - gt[middle], axis=1)
    err_after = np.linalg.norm(second.joints_mm[middle] - gt[middle], axis=1)
    assert np.all(err_before > 5.0)  # the bend was real
    assert err_after.mean() < 0.6 * err_before.mean(), (err_before, err_after)
    px_before = np.linalg.norm(
        cam.project(first.joints_mm[middle]) - cam.project(gt[middle]), axis=1
    )
    px_after = np.linalg.norm(
        cam.project(second.joints_mm[middle]) - cam.project(gt[middle]), axis=1
    )
    assert px_after.sum() < px_before.sum()
    np.testing.assert_allclose(sk.bone_lengths(second.joints_mm), x["bones"], atol=0.5)


def test_the_app_and_the_bench_call_the_same_refit(session, monkeypatch):
    from app.control import jobs

    calls: list[str] = []
    real = guesses.refit_guesses

    def spy(*args, **kw):
        calls.append("refit")
        return real(*args, **kw)

    monkeypatch.setattr(guesses, "refit_guesses", spy)
    x = frame_inputs(session, 10)  # a reference, annotated by the fixture
    out = jobs.lift_for_session(session, 10, x["depth"], lift_fn=guesses.live_lift_function())
    assert calls == ["refit"] and out[0].shape == (session.skeleton.num_joints, 3)
    guess = x["gt"] + np.array([12.0, 0.0, 0.0])
    _, clicks, _ = interactive_fix(
        guess, x["gt"], x["depth"], x["camera"], x["skeleton"], x["bones"], **x["settings"]
    )
    assert clicks >= 1 and len(calls) == 1 + clicks  # one refit per click, the same function


def test_nobody_clicks_a_joint_whose_truth_is_off_the_image(session):
    """The app's clicks and accepted guesses land on the image, so the simulated annotator leaves
    a joint whose true projection is past the image's border unannotated and marks it outside
    the image (the app's O): it never clicks it (the interactive fix still ends), accepts no
    guess of it, and a review correction keeps such a joint where it was shown when that is off
    the image too, else marks it outside."""
    from handanno_core.review_loop import simulated_fix

    x = frame_inputs(session, 5)
    sk, gt = x["skeleton"], x["gt"]
    v = x["camera"].project(gt)[:, 1]
    # the same camera looking lower: the hand's 4 topmost joints project above the image
    cam = x["camera"].model_copy(update={"cy": x["camera"].cy - (np.sort(v)[4] - 2.0)})
    truth = cam.project(gt)
    off = ~cam.on_image(truth)
    assert off.sum() == 4
    full = simulate_annotation(gt, x["depth"], cam, sk, noise_px=3.0)
    assert np.isnan(full.uv_px[off]).all() and not full.visible[off].any()
    assert not full.depth_order[off].any() and cam.on_image(full.uv_px[~off]).all()
    np.testing.assert_array_equal(full.outside, off)

    guess = gt + np.array([12.0, -8.0, 4.0])
    ann, clicks, order = interactive_fix(
        guess, gt, x["depth"], cam, sk, x["bones"], **x["settings"]
    )
    assert clicks == len(order) >= 1 and not set(order) & set(np.flatnonzero(off).tolist())
    assert cam.on_image(ann.uv_px[ann.has_2d]).all()
    assert np.all(np.linalg.norm(ann.uv_px[~off] - truth[~off], axis=1) <= 4.0 + 1e-9)
    assert ann.outside[off].all() and not ann.annotated[off].any() and ann.complete.all()
    inward = gt + np.array([0.0, 30.0, 0.0])  # drawn 30 mm lower: every joint on the image
    assert cam.on_image(cam.project(inward)).all()
    ann, _, order = interactive_fix(inward, gt, x["depth"], cam, sk, x["bones"], **x["settings"])
    assert ann.outside[off].all() and not ann.annotated[off].any() and ann.complete.all()

    shown = gt + np.array([20.0, 0.0, 0.0])  # every joint ~20 px off
    fixed, moved = simulated_fix(shown, gt, x["depth"], cam, sk)
    assert moved == int((~off).sum())
    np.testing.assert_allclose(fixed.xyz_mm[off], shown[off])  # left as the app seeded it
    assert fixed.accepted[off].all() and not fixed.accepted[~off].any()
    assert cam.on_image(cam.project(shown))[off].sum() < off.sum()  # some drawn on the image
    fixed, moved = simulated_fix(inward, gt, x["depth"], cam, sk)
    assert moved == int((~off).sum()) and fixed.outside[off].all() and fixed.complete.all()
    assert not fixed.annotated[off].any() and not fixed.outside[~off].any()
