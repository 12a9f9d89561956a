"""Tests of handanno_core.lift.model_refit: the click-noise estimate and the hand-model refit of
lifted references on depth rendered from the capsule model."""

from __future__ import annotations

import numpy as np
import pytest

from handanno_core.annotation import FrameAnnotation
from handanno_core.crops import crop_boxes, crop_depth
from handanno_core.lift.model_refit import (
    RefitSettings,
    denoised_clicks,
    estimate_click_noise,
    refit_references,
)
from handanno_core.skeleton import MSRA21, SKELETONS
from tests.test_handmodel import CAM, _model, _pose, _render


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.5])
def test_click_noise_estimate_inverts_the_residual_model(sigma):
    st = RefitSettings()
    s = np.sqrt(st.probe_floor_px**2 + (st.probe_slope * sigma) ** 2)
    residual = np.linalg.norm(np.random.default_rng(0).normal(0, s, (4000, 2)), axis=1)
    assert estimate_click_noise(residual, st) == pytest.approx(sigma, abs=0.15)
    assert estimate_click_noise(np.array([np.nan])) == 0.0


def _frames(sigma: float, seed: int = 0):
    """Three rendered poses, their clicks (2D noise sigma px) and lifted poses 4 mm off."""
    rng = np.random.default_rng(seed)
    truth = np.stack(
        [_pose("open"), _pose("spread", (25.0, -10.0, 5.0)), _pose("open", (-30.0, 15.0, 0.0))]
    )
    model = _model(truth[0])
    crops = np.stack([crop_depth(_render(model, x), CAM, x.mean(axis=0)) for x in truth])
    centres = truth.mean(axis=1)
    boxes = np.stack([crop_boxes(c, CAM) for c in centres])
    anns = []
    for x in truth:
        a = FrameAnnotation.empty(21)
        a.uv_px[:] = CAM.project(x) + rng.normal(0, sigma, (21, 2)) if sigma else CAM.project(x)
        anns.append(a)
    lifted = truth + rng.normal(0, 4.0, truth.shape)
    return truth, model, crops, boxes, centres, anns, lifted


def _refit(model, crops, boxes, centres, anns, lifted, **kw):
    return refit_references(
        lifted, anns, crops, boxes, centres, CAM, MSRA21, model.bone_lengths_mm, cube_mm=220.0,
        **kw,
    )  # fmt: skip


@pytest.mark.parametrize("sigma", [0.0, 2.0])
def test_refit_moves_lifted_references_towards_the_truth(sigma):
    truth, model, crops, boxes, centres, anns, lifted = _frames(sigma)
    res = _refit(model, crops, boxes, centres, anns, lifted)
    before = np.linalg.norm(lifted - truth, axis=-1).mean()
    after = np.linalg.norm(res.joints_mm - truth, axis=-1).mean()
    assert not res.kept.any()
    assert after < 0.5 * before, (before, after)
    # bones are the model's, exactly
    assert np.allclose(MSRA21.bone_lengths(res.joints_mm), model.bone_lengths_mm, atol=1e-6)
    # the estimated noise follows the clicks' noise; more noise, less weight on the clicks
    if sigma == 0.0:
        assert res.noise_px < 0.7
    else:
        assert 1.0 < res.noise_px < 3.0
        exact = _refit(model, crops, boxes, centres, anns, lifted, noise_px=0.0)
        assert exact.uv_weight > res.uv_weight


def test_the_pose_prior_weighs_in_as_the_clicks_lose_weight():
    """The refit's pose prior has the clicks' share of the noise: none for exact clicks, most of
    ``FitWeights.prior`` at 2 px."""
    from dataclasses import replace

    from handanno_core.handmodel import FitWeights

    truth, model, crops, boxes, centres, anns, lifted = _frames(2.0)
    no_prior = FitWeights(prior=0.0)
    for noise, same in ((0.0, True), (2.0, False)):
        with_prior = _refit(model, crops, boxes, centres, anns, lifted, noise_px=noise)
        without = _refit(
            model, crops, boxes, centres, anns, lifted, noise_px=noise, fit_weights=no_prior
        )
        assert np.array_equal(with_prior.joints_mm, without.joints_mm) == same, noise
    strong = _refit(
        model, crops, boxes, centres, anns, lifted, noise_px=2.0,
        fit_weights=replace(FitWeights(), prior=30.0),
    )  # fmt: skip
    moved = np.linalg.norm(strong.joints_mm - with_prior.joints_mm, axis=-1).max()
    assert moved > 0.1, moved


def test_denoised_clicks_move_towards_the_refit_by_the_click_noise():
    x = _pose("open")
    a = FrameAnnotation.empty(21)
    a.uv_px[:] = CAM.project(x) + np.array([3.0, -2.0])
    a.uv_px[5] = np.nan
    a.visible[7] = False
    a.depth_order[7] = 1
    clicks = a.uv_px.copy()
    # exact clicks are the best evidence: unchanged
    assert denoised_clicks({4: a}, {4: x}, CAM, 0.0)[4] is a
    out = denoised_clicks({4: a}, {4: x}, CAM, 2.0)[4]
    move = 4.0 / (4.0 + RefitSettings().model_px ** 2)
    has = a.has_2d
    np.testing.assert_allclose(
        out.uv_px[has], clicks[has] + move * (CAM.project(x)[has] - clicks[has])
    )
    assert np.isnan(out.uv_px[5]).all()
    np.testing.assert_array_equal(a.uv_px, clicks)  # the annotation itself is not touched
    assert not out.visible[7] and out.depth_order[7] == 1
    # more noise, closer to the refit
    far = denoised_clicks({4: a}, {4: x}, CAM, 4.0)[4]
    assert np.all(
        np.linalg.norm(far.uv_px[has] - CAM.project(x)[has], axis=1)
        < np.linalg.norm(out.uv_px[has] - CAM.project(x)[has], axis=1)
    )
    # a reference without a finite refit keeps its clicks
    broken = x.copy()
    broken[3] = np.nan
    assert denoised_clicks({4: a}, {4: broken}, CAM, 2.0)[4] is a


def test_refit_keeps_placed_joints_and_lifts_that_would_break_a_depth_order():
    truth, model, crops, boxes, centres, anns, lifted = _frames(0.0)
    # frame 0: the index tip placed in 3D 6 mm off the truth stays where it was placed
    tip = MSRA21.joint_names.index("index_tip")
    anns[0].xyz_mm[tip] = truth[0, tip] + np.array([6.0, 0.0, 0.0])
    anns[0].uv_px[tip] = CAM.project(anns[0].xyz_mm[tip])
    lifted[0, tip] = anns[0].xyz_mm[tip]
    # frame 1: an annotated depth order the lift meets but the depth contradicts
    k = 8
    p = int(MSRA21.parent_array[k])
    sign = -1 if truth[1, k, 2] > truth[1, p, 2] else 1
    anns[1].depth_order[k] = sign
    lifted[1, k, 2] = lifted[1, p, 2] + sign * 30.0
    res = _refit(model, crops, boxes, centres, anns, lifted)
    assert np.linalg.norm(res.joints_mm[0, tip] - anns[0].xyz_mm[tip]) < 1.0
    assert res.kept.tolist() == [False, True, False]
    assert np.array_equal(res.joints_mm[1], lifted[1])
    # a reference without a finite lift keeps it (NaN) and the others are still refitted
    lifted[2, 3] = np.nan
    res = _refit(model, crops, boxes, centres, anns, lifted)
    assert res.kept[2] and np.isnan(res.joints_mm[2, 3]).all()


def test_only_layouts_with_finger_segments_are_refitted():
    # NYU's fingers are palm centre -> middle -> tip: the model's palm-to-middle capsule would run
    # through the palm (measured: lift error 1.9 -> 11.0 mm on the NYU fixture with the refit)
    assert {k: s.has_finger_segments for k, s in SKELETONS.items()} == {
        "msra21": True, "blender24": True, "icvl16": True, "nyu14": False,
    }  # fmt: skip


def _noisy_cli_session(tmp_path, frames: int, seed: int):
    """A synthetic sequence, a session "s" with a quarter of its frames as references, annotated
    with 2 px clicks, all through the CLI: ``(CLI base args, sessions folder, ground truth)``."""
    from app.cli import main
    from handanno_core.datasets import open_sequence

    data, sessions = tmp_path / "data", tmp_path / "sessions"
    synth = ["synth", str(data), "--frames", str(frames), "--seed", str(seed), "--workers", "1"]
    assert main(synth) == 0
    base = ["--sessions-dir", str(sessions)]
    assert main([*base, "new", "s", str(data)]) == 0
    assert main([*base, "select", "s", "--strategy", "uniform", "--ref-fraction", "0.25"]) == 0
    assert main([*base, "annotate-from-gt", "s", "--noise-px", "2"]) == 0
    return base, sessions, open_sequence(data).ground_truth.joints_mm


def test_cli_lift_refits_by_default_and_takes_the_click_noise(tmp_path, capsys):
    from app.cli import main
    from handanno_core.session import Session

    base, sessions, gt = _noisy_cli_session(tmp_path, frames=24, seed=2)
    errors, logs, noise, infos = {}, {}, {}, {}
    for name, extra in [
        ("plain", ["--no-refit"]), ("estimated", []), ("given", ["--click-noise-px", "0"]),
    ]:  # fmt: skip
        capsys.readouterr()
        assert main([*base, "lift", "s", "--workers", "2", *extra]) == 0  # CI has two cores
        logs[name] = capsys.readouterr().out
        with Session.open(sessions / "s") as session:
            refs = session.reference_frames
            lifted = session.load_results()["lifted_mm"][refs]
            noise[name] = (session.model.lift_click_noise_px, session.model.lift_click_noise_given)
        errors[name] = float(np.linalg.norm(lifted - gt[refs], axis=-1).mean())
        assert main([*base, "info", "s"]) == 0
        infos[name] = capsys.readouterr().out
    assert "refitted" not in logs["plain"]
    assert "estimated" in logs["estimated"] and "(click noise 0.00 px, given)" in logs["given"]
    # 2 px clicks: the refit with the estimated noise beats the plain lift and trusting the
    # clicks as exact
    assert errors["estimated"] < errors["plain"], errors
    assert errors["estimated"] < errors["given"], errors
    # 2 px >= lift_denoise_min_px: a second bone estimate was tried (here the model's depth
    # energy did not favour it); clicks given as exact never try one
    assert "bones estimated again from denoised clicks" in logs["estimated"]
    assert "estimated again" not in logs["given"]
    # the session records the click noise the last lift used, and `handanno info` shows it
    assert noise["plain"] == (None, False) and "clicks:" not in infos["plain"]
    estimated, given = noise["estimated"]
    assert 1.0 < estimated < 3.0 and not given
    assert f"clicks: {estimated:.1f} px noise (estimated by the last lift)" in infos["estimated"]
    assert noise["given"] == (0.0, True)
    assert "clicks: 0.0 px noise (given to the last lift)" in infos["given"]


def test_noisy_clicks_get_a_second_bone_estimate_kept_where_the_depth_favours_it(tmp_path, capsys):
    from app.cli import main
    from handanno_core.session import Session

    base, sessions, gt = _noisy_cli_session(tmp_path, frames=30, seed=4)
    errors, logs = {}, {}
    for least in (1.0, None):
        with Session.open(sessions / "s") as session:
            session.model.settings.lift_denoise_min_px = least
            session.save()
        capsys.readouterr()
        assert main([*base, "lift", "s", "--workers", "2"]) == 0  # CI has two cores
        logs[least] = capsys.readouterr().out
        with Session.open(sessions / "s") as session:
            refs = session.reference_frames
            lifted = session.load_results()["lifted_mm"][refs]
        errors[least] = float(np.linalg.norm(lifted - gt[refs], axis=-1).mean())
    assert ": kept" in logs[1.0] and "estimated again" not in logs[None]
    # measured 1.50 against 2.14 mm
    assert errors[1.0] < 0.85 * errors[None], errors
