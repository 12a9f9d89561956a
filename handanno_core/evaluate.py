"""Error metrics against ground truth, as the anchors report them (per-joint 3D Euclidean error).

Ground truth is allowed here (and in the simulated annotator and tests/benchmarks) only.
A NaN prediction is a *missing* joint: it is excluded from the statistics and counted in
``"missing"``, never silently treated as an error of 0.
"""

from __future__ import annotations

import numpy as np


def joint_errors_mm(pred_mm: np.ndarray, gt_mm: np.ndarray) -> np.ndarray:
    """Per-joint Euclidean errors ``(N, J)`` mm of predictions ``(N, J, 3)`` against ``(N, J, 3)``.

    NaN where the prediction (or the ground truth) has a NaN coordinate.
    """
    pred = np.asarray(pred_mm, dtype=np.float64)
    gt = np.asarray(gt_mm, dtype=np.float64)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"pred {pred.shape} and gt {gt.shape} must both be (N, J, 3)")
    return np.linalg.norm(pred - gt, axis=-1)


def error_summary(
    pred_mm: np.ndarray, gt_mm: np.ndarray, frames: np.ndarray | list[int] | None = None
) -> dict:
    """Summary of :func:`joint_errors_mm` over ``frames`` (default all).

    Returns ``{"mean_mm", "median_mm", "max_mm", "frames", "missing"}``: the mean over frames and
    joints, the median of the per-joint errors, the single worst joint anywhere, the number of
    frames evaluated and the number of (frame, joint) predictions that were NaN (excluded from the
    statistics). Joints whose ground truth is NaN are ignored. Statistics are NaN when nothing is
    left to evaluate.
    """
    pred = np.asarray(pred_mm, dtype=np.float64)
    gt = np.asarray(gt_mm, dtype=np.float64)
    if frames is not None:
        idx = np.asarray(frames, dtype=np.int64)
        pred, gt = pred[idx], gt[idx]
    errors = joint_errors_mm(pred, gt)
    gt_ok = np.all(np.isfinite(gt), axis=-1)
    pred_ok = np.all(np.isfinite(pred), axis=-1)
    missing = int(np.count_nonzero(gt_ok & ~pred_ok))
    values = errors[gt_ok & pred_ok]
    if values.size == 0:
        mean = median = worst = float("nan")
    else:
        mean, median, worst = float(values.mean()), float(np.median(values)), float(values.max())
    return {
        "mean_mm": mean,
        "median_mm": median,
        "max_mm": worst,
        "frames": int(pred.shape[0]),
        "missing": missing,
    }


__all__ = ["error_summary", "joint_errors_mm"]
