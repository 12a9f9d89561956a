"""Tests of the ground-truth error metrics (handanno_core/evaluate.py)."""

from __future__ import annotations

import numpy as np
import pytest

from handanno_core.evaluate import error_summary, joint_errors_mm


def _pair() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    gt = rng.normal(0, 50, (4, 21, 3)) + [0, 0, 400]
    pred = gt.copy()
    pred[..., 0] += 3.0  # every joint 3 mm off
    pred[1, 5] += [0.0, 4.0, 0.0]  # one joint 5 mm off
    pred[2, 7, 2] += 40.0  # one joint sqrt(9 + 1600) mm off
    return pred, gt


def test_joint_errors():
    pred, gt = _pair()
    err = joint_errors_mm(pred, gt)
    assert err.shape == (4, 21)
    assert err[0, 0] == pytest.approx(3.0)
    assert err[1, 5] == pytest.approx(5.0)
    assert err[2, 7] == pytest.approx(np.hypot(3.0, 40.0))
    with pytest.raises(ValueError):
        joint_errors_mm(pred[:, :20], gt)


def test_summary_mean_median_max():
    pred, gt = _pair()
    s = error_summary(pred, gt)
    expected = (3.0 * 82 + 5.0 + np.hypot(3.0, 40.0)) / 84
    assert s["mean_mm"] == pytest.approx(expected)
    assert s["median_mm"] == pytest.approx(3.0)
    assert s["max_mm"] == pytest.approx(np.hypot(3.0, 40.0))
    assert s["frames"] == 4 and s["missing"] == 0


def test_nan_predictions_are_missing_not_zero():
    pred, gt = _pair()
    pred[0, :3] = np.nan
    pred[3, 10, 1] = np.nan
    s = error_summary(pred, gt)
    assert s["missing"] == 4
    expected = (3.0 * 78 + 5.0 + np.hypot(3.0, 40.0)) / 80
    assert s["mean_mm"] == pytest.approx(expected)  # a 0 in place of NaN would lower the mean
    assert np.isnan(joint_errors_mm(pred, gt)[0, 0])


def test_frame_subset_and_empty():
    pred, gt = _pair()
    s = error_summary(pred, gt, frames=[0, 3])
    assert s["frames"] == 2
    assert s["max_mm"] == pytest.approx(3.0)
    pred[:] = np.nan
    s = error_summary(pred, gt, frames=np.array([1]))
    assert s["missing"] == 21 and s["frames"] == 1
    assert np.isnan(s["mean_mm"]) and np.isnan(s["max_mm"])
