"""Could anything the references carry place the worst joints the depth does not show?

Evaluation only (ground truth labels the joints and gives the oracle palm). For every joint of a
finished bench session's final result more than ``--threshold`` mm (default 40) from the ground
truth in a non-reference frame, and hidden there (:func:`handanno_core.sampling.visible_by_depth`
of the true pose: past the image's border or behind a nearer surface, the bench's rule), the
joint is placed again by what the annotated references say about its finger:

- ``interpolated``: the finger's shape (each joint relative to its finger's first joint, in the
  palm's frame, :meth:`Skeleton.palm_coordinates`) interpolated linearly in time between the
  lifted poses of the two references around the frame (the nearest one past either end, none
  across a sequence break), placed on the frame's estimated palm (its root, rotation and finger
  bases). This uses only what a user has.
- ``interpolated_true_palm``: the same shape placed on the true palm (true root, rotation and
  finger bases): an oracle for everything but the finger's own articulation.
- ``nearest_true_palm``: the nearer reference's finger shape on the true palm.
- ``any_reference_true_palm``: per joint the lowest error over every reference's finger shape on
  the true palm (an oracle choice: is the joint's finger, at this frame, like any annotated one?).
- ``median_reference_true_palm``: per joint the median error over every reference's finger shape
  on the true palm (what a reference picked without knowing the truth typically gives).
- ``best``: per joint the lowest error of the engine's and the placements above (not the
  median).

A joint that stays over the threshold under ``best`` is one that neither the engine nor any of
these readings of the references places within it.

``--replace-unshown``: what the readings would do as a rule, without ground truth choosing. Every
joint of a non-reference frame that the frame's depth does not show at its *estimated* position
(the same rule; a joint counts as not shown when any joint between it and its finger's first joint
is not) takes the finger shape of a reading, placed on the estimated palm: ``interpolated`` (as
above) or ``shown_anchors`` (interpolated between the nearest frames where the estimate shows that
joint's chain, or references). Per session: the mean joint error, the joints over the threshold and
the worst joint, for the engine and both rules.

    .venv/bin/python benchmarks/bench_hidden_bound.py W/*/uniform-0.05 --json out.json

(``W``: a ``handanno bench --work-dir``.)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from handanno_core.bench import shown_by_depth
from handanno_core.session import Session
from handanno_core.skeleton import Skeleton

ESTIMATES = (
    "engine",
    "interpolated",
    "interpolated_true_palm",
    "nearest_true_palm",
    "any_reference_true_palm",
    "median_reference_true_palm",
    "best",
)
#: the rules of ``--replace-unshown``
READINGS = ("interpolated", "shown_anchors")


def finger_shapes(skeleton: Skeleton, poses_mm: np.ndarray) -> np.ndarray:
    """``(..., J, 3)`` mm: every joint relative to its finger's first joint, in the palm's frame."""
    local = skeleton.palm_coordinates(poses_mm)
    return local - local[..., skeleton.finger_bases, :]


def place_shapes(
    skeleton: Skeleton, shapes_mm: np.ndarray, palm_poses_mm: np.ndarray
) -> np.ndarray:
    """Poses ``(..., J, 3)`` mm: finger shapes ``(..., J, 3)`` put on the palm (root, rotation,
    finger bases) of ``palm_poses_mm`` ``(..., J, 3)``. Inverse of :func:`finger_shapes` where
    the shapes are the palm poses' own."""
    x = np.asarray(palm_poses_mm, dtype=np.float64)
    rot = skeleton.palm_rotation(x)
    local = skeleton.palm_coordinates(x)
    placed = local[..., skeleton.finger_bases, :] + shapes_mm
    root = x[..., skeleton.root, None, :]
    return np.einsum("...jc,...kc->...jk", placed, rot) + root


def interpolate_at_anchors(
    values: np.ndarray, anchors: np.ndarray, segment: np.ndarray, nearest: bool = False
) -> np.ndarray:
    """``(N, J, 3)``: per joint, ``values`` ``(N, J, 3)`` kept at its anchor frames (``anchors``
    ``(N, J)`` bool) and, at every other frame, interpolated linearly in time between the anchors
    around it (``nearest``: the nearer one's value) of the same segment (``segment``: id per
    frame); past the segment's first or last anchor that anchor's value; NaN in a segment with no
    anchor."""
    n, num_joints = anchors.shape
    out = np.full(values.shape, np.nan)
    frames = np.arange(n)
    for s_id in np.unique(segment):
        in_seg = frames[segment == s_id]
        for j in range(num_joints):
            a = in_seg[anchors[in_seg, j]]
            if len(a) == 0:
                continue
            k = np.searchsorted(a, in_seg)  # the first anchor at or after each frame
            lo, hi = a[np.clip(k - 1, 0, len(a) - 1)], a[np.clip(k, 0, len(a) - 1)]
            span = np.maximum(hi - lo, 1)
            t = np.clip((in_seg - lo) / span, 0.0, 1.0)[:, None]
            if nearest:
                t = (t >= 0.5).astype(np.float64)
            out[in_seg, j] = (1.0 - t) * values[lo, j] + t * values[hi, j]
    return out


def _open(folder: Path) -> SimpleNamespace:
    """A finished bench session's arrays; ``.session`` is open (the caller closes it)."""
    session = Session.open(folder)
    try:
        results = session.load_results()
        sequence = session.open_sequence()
        n = session.num_frames
        breaks = np.asarray(sorted(session.model.sequence_breaks), dtype=np.int64)
        return SimpleNamespace(
            session=session,
            sequence=sequence,
            skeleton=session.skeleton,
            name=f"{folder.parent.parent.name}/{folder.parent.name}/{folder.name}",
            n=n,
            gt=np.asarray(sequence.ground_truth.joints_mm, dtype=np.float64),
            final=np.asarray(results["final_mm"], dtype=np.float64),
            lifted=np.asarray(results["lifted_mm"], dtype=np.float64),
            refs=np.asarray(sorted(session.reference_frames), dtype=np.int64),
            segment=np.searchsorted(breaks, np.arange(n), side="right"),
        )
    except BaseException:
        session.close()
        raise


def session_bound(folder: Path, threshold_mm: float) -> dict:
    """The counts of the module docstring for one bench session folder."""
    d = _open(folder)
    try:
        skeleton, gt, final, lifted, refs, n = d.skeleton, d.gt, d.final, d.lifted, d.refs, d.n
        err = np.linalg.norm(final - gt, axis=-1)
        with np.errstate(invalid="ignore"):
            over = err > threshold_mm
        over[refs] = False
        frames = np.flatnonzero(over.any(axis=1))
        hidden = np.zeros_like(over)
        hidden[frames] = ~shown_by_depth(d.sequence, d.skeleton, gt, frames)
    finally:
        d.session.close()
    segment = d.segment
    shapes_ref = finger_shapes(skeleton, lifted[refs])
    at_refs = np.zeros((n, skeleton.num_joints), dtype=bool)
    at_refs[refs] = True
    shapes = np.zeros((n, skeleton.num_joints, 3))
    shapes[refs] = shapes_ref
    lin = interpolate_at_anchors(shapes, at_refs, segment)[frames]
    near = interpolate_at_anchors(shapes, at_refs, segment, nearest=True)[frames]
    placed = {
        "engine": final[frames],
        "interpolated": place_shapes(skeleton, lin, final[frames]),
        "interpolated_true_palm": place_shapes(skeleton, lin, gt[frames]),
        "nearest_true_palm": place_shapes(skeleton, near, gt[frames]),
    }
    errs = {k: np.linalg.norm(v - gt[frames], axis=-1) for k, v in placed.items()}
    each_ref = place_shapes(skeleton, shapes_ref[:, None], gt[frames][None])  # (R, F, J, 3)
    each_err = np.linalg.norm(each_ref - gt[frames][None], axis=-1)
    errs["any_reference_true_palm"] = np.nanmin(each_err, axis=0)
    errs["best"] = np.fmin.reduce(list(errs.values()))
    errs["median_reference_true_palm"] = np.nanmedian(each_err, axis=0)
    sel = (over & hidden)[frames]
    out = {
        "session": d.name,
        "frames": n,
        "joints_over": int(over.sum()),
        "hidden_over": int(sel.sum()),
        "worst_joint_mm": float(np.nanmax(np.where(np.isin(np.arange(n), refs)[:, None], 0, err))),
    }
    for k, e in errs.items():
        v = e[sel]
        with np.errstate(invalid="ignore"):
            out[f"{k}_still_over"] = int(np.sum(~(v <= threshold_mm)))
        out[f"{k}_mean_mm"] = float(np.nanmean(v)) if v.size else None
        out[f"{k}_max_mm"] = float(np.nanmax(v)) if v.size else None
    return out


def replace_unshown(folder: Path, threshold_mm: float) -> dict:
    """``--replace-unshown`` (module docstring) for one bench session folder."""
    d = _open(folder)
    try:
        skeleton, gt, final, lifted, refs, n = d.skeleton, d.gt, d.final, d.lifted, d.refs, d.n
        shown = shown_by_depth(d.sequence, skeleton, final, np.arange(n))
    finally:
        d.session.close()
    segment = d.segment
    parents, base = skeleton.parent_array, skeleton.finger_bases
    for j in skeleton.topological_order:
        if base[j] != j:  # shown only with every joint up to its finger's first joint
            shown[:, j] &= shown[:, parents[j]]
    shown[refs] = True
    pose = final.copy()
    pose[refs] = lifted[refs]
    shapes = finger_shapes(skeleton, pose)
    at_refs = np.zeros_like(shown)
    at_refs[refs] = True
    readings = {
        "interpolated": interpolate_at_anchors(shapes, at_refs, segment),
        "shown_anchors": interpolate_at_anchors(shapes, shown, segment),
    }
    estimates = {"engine": final}
    for name, reading in readings.items():
        new_shapes = np.where(shown[..., None] | np.isnan(reading), shapes, reading)
        estimates[name] = np.where(
            shown[..., None], final, place_shapes(skeleton, new_shapes, final)
        )
    nonref = np.ones(n, dtype=bool)
    nonref[refs] = False
    out = {
        "session": d.name,
        "unshown_share": float((~shown[nonref]).mean()),
    }
    for name, est in estimates.items():
        err = np.linalg.norm(est - gt, axis=-1)
        out[f"{name}_mean_mm"] = float(np.nanmean(err))
        with np.errstate(invalid="ignore"):
            out[f"{name}_over"] = int(np.sum(err[nonref] > threshold_mm))
        out[f"{name}_worst_mm"] = float(np.nanmax(err[nonref]))
    return out


def bound_totals(rows: list[dict]) -> dict:
    """Joint counts summed over sessions; mean errors weighted by each session's joints."""
    total = {k: sum(r[k] for r in rows) for k in ("joints_over", "hidden_over")}
    weights = [r["hidden_over"] for r in rows if r["hidden_over"]]
    for k in ESTIMATES:
        total[f"{k}_still_over"] = sum(r[f"{k}_still_over"] for r in rows)
        means = [r[f"{k}_mean_mm"] for r in rows if r["hidden_over"]]
        total[f"{k}_mean_mm"] = float(np.average(means, weights=weights)) if weights else None
    return total


def replacement_totals(rows: list[dict], threshold_mm: float) -> dict:
    """Per rule: mean of the sessions' means, joints over the threshold, sessions with a joint
    over it, and (rules other than the engine) sessions with a better / worse mean."""
    total = {}
    base = np.array([r["engine_mean_mm"] for r in rows])
    for name in ("engine", *READINGS):
        means = np.array([r[f"{name}_mean_mm"] for r in rows])
        total[f"{name}_mean_of_means_mm"] = float(means.mean())
        total[f"{name}_over"] = sum(r[f"{name}_over"] for r in rows)
        total[f"{name}_sessions_worst_over"] = sum(
            r[f"{name}_worst_mm"] > threshold_mm for r in rows
        )
        if name != "engine":
            total[f"{name}_sessions_better"] = int(np.sum(means < base))
            total[f"{name}_sessions_worse"] = int(np.sum(means > base))
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sessions", nargs="+", type=Path, help="finished bench session folders")
    ap.add_argument("--threshold", type=float, default=40.0, help="mm (default 40)")
    ap.add_argument("--json", type=Path, help="write the per-session rows and the totals here")
    ap.add_argument(
        "--replace-unshown", action="store_true", help="the readings as a rule (module docstring)"
    )
    args = ap.parse_args()
    rows = []
    for folder in args.sessions:
        if args.replace_unshown:
            r = replace_unshown(folder, args.threshold)
            line = json.dumps(r)
        else:
            r = session_bound(folder, args.threshold)
            line = f"{r['session']:48s} worst {r['worst_joint_mm']:6.1f}"
            line += f"  over {r['joints_over']:3d} hidden {r['hidden_over']:3d}  still over:"
            line += "".join(f" {k} {r[f'{k}_still_over']}" for k in ESTIMATES)
        rows.append(r)
        print(line, flush=True)
    total = replacement_totals(rows, args.threshold) if args.replace_unshown else bound_totals(rows)
    print("total", json.dumps(total))
    if args.json:
        report = {"threshold_mm": args.threshold, "sessions": rows, "total": total}
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
