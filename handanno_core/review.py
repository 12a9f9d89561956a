"""Review engine (no viser): which frames to show the annotator, and what a review edit does.

Used by the app's review tab (``app/control/review.py``, ``app/control/live.py``) and by the bench's
simulated review loop (:mod:`handanno_core.review_loop`).

* :func:`frame_scores` - a pure-numpy per-frame score in [0, 1] (1 = trustworthy) from the
  propagation confidence (which already contains the forward-backward flow consistency), bone-length
  anomalies, depth residuals, temporal jumps and an optional flow-inconsistency term (the app's
  ranking until now, kept as the ``"score"`` ranking of the bench).
* :func:`worst_order` / :func:`next_worst` - walk frames by increasing score.
* :func:`seed_annotation` / :func:`correction_command` - the session command of a review edit: on a
  propagated frame it is a :class:`~handanno_core.session.Batch` that makes the frame a reference
  (``correction=True``), seeds its annotation from the shown skeleton and applies the joint edit,
  all as one undo step.
* :func:`review_evidence` - per-frame evidence that a skeleton is wrong (confidence, depth and
  silhouette residuals, joints far behind the surface, the skeleton drifting off the observed hand
  centre, temporal jumps, refinement shift, angle limits incl. mirrored hands, finger order,
  bones, distance to the reference; a model-fit residual can be passed in), and
  :func:`evidence_priority` - the ``"evidence"`` ranking made of it (:data:`EVIDENCE_WEIGHTS`,
  chosen on the suite's tune part), optionally smoothed in time (:func:`smooth_in_time`,
  :data:`SMOOTH`).
* :func:`rank_priority` / :func:`pick_frames` / :func:`uniform_pick` - the frames a review round
  shows: by a ranking, never a frame already reviewed, optionally not next to one just picked
  (:data:`SUPPRESS_RADIUS`); :func:`recall_at` measures a ranking against ground truth
  (evaluation only).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .annotation import FrameAnnotation
from .camera import CameraIntrinsics
from .crops import DEFAULT_CROP
from .results import MODEL_FIT_TERMS
from .sampling import VISIBILITY_MARGIN_MM, visible_by_depth
from .session import (
    Batch,
    Command,
    Session,
    SetFrameAnnotation,
    SetJoint3D,
    SetReference,
)

#: scale of each score term: a term equal to its scale halves the score (``1 / (1 + (x/s)^2)``).
SCORE_SCALES = {"bone": 0.10, "depth_mm": 15.0, "jump_mm": 30.0, "flow_px": 3.0}
#: penalty (mm) of a joint projecting onto background / outside the hand cube.
OFF_HAND_MM = 40.0


# =============================================================================================
# scores (pure numpy)


def bone_anomaly(
    joints_mm: np.ndarray, bones: np.ndarray, bone_lengths_mm: np.ndarray
) -> np.ndarray:
    """``(N,)`` largest relative bone-length deviation per frame (0 = exact; NaN if no joints).

    ``joints_mm`` (N, J, 3) mm, ``bones`` (B, 2) (parent, child), ``bone_lengths_mm`` (B,) mm
    (or (N, B): each frame its hand's, :meth:`Session.frame_bone_lengths`).
    """
    j = np.asarray(joints_mm, dtype=np.float64)
    b = np.asarray(bones, dtype=np.int64)
    lengths = np.linalg.norm(j[:, b[:, 1]] - j[:, b[:, 0]], axis=-1)  # (N, B)
    ref = np.asarray(bone_lengths_mm, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        dev = np.abs(lengths - ref) / np.maximum(ref, 1e-6)
        out = np.max(dev, axis=1)
    out[~np.all(np.isfinite(dev), axis=1)] = np.nan
    return out


def temporal_jump(joints_mm: np.ndarray, sequence_breaks: Iterable[int] = ()) -> np.ndarray:
    """``(N,)`` mm: for each frame the largest joint displacement to its previous and to its next
    frame, and of those two the *smaller* one (a single wrong frame jumps away from both of its
    neighbours; a frame next to it only from one). Jumps across sequence breaks are ignored; NaN
    where no neighbour has joints."""
    j = np.asarray(joints_mm, dtype=np.float64)
    n = len(j)
    step = np.full(n + 1, np.nan)  # step[t] = jump between frame t-1 and t
    if n > 1:
        d = np.max(np.linalg.norm(j[1:] - j[:-1], axis=-1), axis=1)
        step[1:n] = d
    for b in sequence_breaks:
        if 0 < int(b) < n:
            step[int(b)] = np.nan
    prev, nxt = step[:n], step[1 : n + 1]
    with np.errstate(invalid="ignore"):
        out = np.fmin(prev, nxt)
    out[~np.all(np.isfinite(j), axis=(1, 2))] = np.nan
    return out


def _observed_depth(
    joints_mm: np.ndarray,
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    cube_mm: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The observed surface under each joint, read from the normalized crops: ``frames`` (M,) the
    frames with joints, ``observed`` (M, J) mm (the crop's depth at the joint's projection) and
    ``background`` (M, J) bool (the joint projects onto background or outside the crop)."""
    from .crops import image_to_crop

    j = np.asarray(joints_mm, dtype=np.float64)
    frames = np.flatnonzero(np.all(np.isfinite(j), axis=(1, 2)))
    jj = j[frames]
    uv = camera.project(jj)  # (M, J, 2)
    xy = image_to_crop(uv, np.asarray(boxes, dtype=np.float64)[frames][:, None, :])
    size = crops.shape[1]
    xy = np.where(np.isfinite(xy), xy, -1.0)  # joints at z <= 0 project nowhere: off the crop
    xi = np.rint(xy[..., 0]).astype(np.int64)
    yi = np.rint(xy[..., 1]).astype(np.int64)
    inside = (xi >= 0) & (xi < size) & (yi >= 0) & (yi < size)
    fi = np.broadcast_to(frames[:, None], xi.shape)
    vals = np.ones(xi.shape, dtype=np.float64)
    vals[inside] = np.asarray(crops[fi[inside], yi[inside], xi[inside]], dtype=np.float64)
    background = ~inside | (vals >= 0.999)
    observed = np.asarray(centres_mm, dtype=np.float64)[frames, 2][:, None] + vals * (cube_mm / 2.0)
    return frames, observed, background


def depth_residuals(
    joints_mm: np.ndarray,
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    *,
    cube_mm: float = DEFAULT_CROP.cube_mm,
    surface_offsets_mm: np.ndarray | None = None,
    behind: bool = False,
) -> np.ndarray:
    """``(N, J)`` mm: how far each joint sits *in front of* the observed surface (a joint centre
    lies on or behind it), read from the normalized crops (no depth file is opened); a joint that
    projects onto background or outside the crop costs :data:`OFF_HAND_MM`. NaN without joints.
    ``behind``: instead, how far each joint on the hand sits *behind* the surface beyond its offset
    (an occluded joint may; a whole hand behind its surface has drifted), 0 off the hand, capped at
    :data:`OFF_HAND_MM`.

    ``crops`` (N, S, S) normalized depth ``(d - z_c) / (cube_mm / 2)``, +1 = background;
    ``boxes`` (N, 4) ``[u_left, v_top, sx, sy]``; ``centres_mm`` (N, 3).
    """
    j = np.asarray(joints_mm, dtype=np.float64)
    n, nj = j.shape[:2]
    out = np.full((n, nj), np.nan)
    frames, observed, background = _observed_depth(j, crops, boxes, centres_mm, camera, cube_mm)
    if frames.size == 0:
        return out
    jj = j[frames]
    offsets = (
        0.0
        if surface_offsets_mm is None
        else np.asarray(surface_offsets_mm, dtype=np.float64)[None, :]
    )
    if behind:
        res = np.clip(jj[..., 2] - observed - offsets, 0.0, OFF_HAND_MM)
        out[frames] = np.where(background, 0.0, res)
        return out
    # A visible joint centre sits ~offset behind the surface: in front of (observed + offset) is wrong.
    res = np.maximum(observed + offsets - jj[..., 2], 0.0)
    res = np.where(background, OFF_HAND_MM, np.minimum(res, OFF_HAND_MM))
    out[frames] = res
    return out


@dataclass
class FrameScores:
    """``score`` (N,) in [0, 1], 1 = trustworthy, NaN = nothing to review (no joints); ``terms``:
    each ingredient (N,) in its own unit (``confidence`` 0..1, ``bone`` relative, ``depth_mm``,
    ``jump_mm``, ``flow_px``)."""

    score: np.ndarray
    terms: dict[str, np.ndarray] = field(default_factory=dict)


def _goodness(x: np.ndarray, scale: float) -> np.ndarray:
    """1 / (1 + (x / scale)^2), with NaN (term unavailable) -> 1."""
    g = 1.0 / (1.0 + (np.asarray(x, dtype=np.float64) / scale) ** 2)
    return np.where(np.isfinite(g), g, 1.0)


def frame_scores(
    confidence: np.ndarray,
    joints_mm: np.ndarray,
    bones: np.ndarray,
    bone_lengths_mm: np.ndarray | None,
    *,
    depth_residual_mm: np.ndarray | None = None,
    flow_error_px: np.ndarray | None = None,
    sequence_breaks: Iterable[int] = (),
    is_reference: np.ndarray | None = None,
    scales: dict[str, float] | None = None,
) -> FrameScores:
    """Combine the review evidence into one score per frame (see :class:`FrameScores`).

    ``confidence`` (N, J) in [0, 1] (propagation confidence, NaN = unknown -> 0.5);
    ``joints_mm`` (N, J, 3) the skeletons shown; ``bone_lengths_mm`` (B,) or None (no bone term);
    ``depth_residual_mm`` (N, J) from :func:`depth_residuals`; ``flow_error_px`` (N,) or (N, J)
    flow inconsistency (optional; the propagation confidence already includes its forward-backward
    consistency). Reference frames score 1. The score is the product of the per-frame confidence
    (mean and minimum over joints, averaged) and ``1 / (1 + (x / scale)^2)`` for each other term.
    """
    s = dict(SCORE_SCALES, **(scales or {}))
    joints = np.asarray(joints_mm, dtype=np.float64)
    n = len(joints)
    has = np.all(np.isfinite(joints), axis=(1, 2))
    conf = np.asarray(confidence, dtype=np.float64)
    conf = np.where(np.isfinite(conf), np.clip(conf, 0.0, 1.0), 0.5)
    c = 0.5 * (conf.mean(axis=1) + conf.min(axis=1)) if conf.size else np.ones(n)
    terms: dict[str, np.ndarray] = {"confidence": c}
    score = c.copy()
    if bone_lengths_mm is not None:
        terms["bone"] = bone_anomaly(joints, bones, bone_lengths_mm)
        score *= _goodness(terms["bone"], s["bone"])
    if depth_residual_mm is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # frames without joints: NaN
            terms["depth_mm"] = np.nanmean(np.asarray(depth_residual_mm, dtype=np.float64), axis=1)
        score *= _goodness(terms["depth_mm"], s["depth_mm"])
    terms["jump_mm"] = temporal_jump(joints, sequence_breaks)
    score *= _goodness(terms["jump_mm"], s["jump_mm"])
    if flow_error_px is not None:
        f = np.asarray(flow_error_px, dtype=np.float64)
        if f.ndim == 2:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                f = np.nanmean(f, axis=1)
        terms["flow_px"] = f
        score *= _goodness(f, s["flow_px"])
    score = np.where(has, np.clip(score, 0.0, 1.0), np.nan)
    if is_reference is not None:
        score = np.where(np.asarray(is_reference, dtype=bool) & has, 1.0, score)
    return FrameScores(score=score, terms=terms)


def session_depth_residuals(
    session, joints_mm: np.ndarray, crop_data, *, behind: bool = False
) -> np.ndarray:
    """:func:`depth_residuals` (N, J) mm of ``joints_mm`` (N, J, 3) mm against the session's crops
    ``crop_data`` = ``(crops, centres_mm, boxes)``, with the session's camera, cube and offsets
    (``behind``: the distance behind the surface instead)."""
    crops, centres, boxes = crop_data
    return depth_residuals(
        joints_mm,
        crops,
        boxes,
        centres,
        session.camera,
        cube_mm=session.model.settings.cube_mm,
        surface_offsets_mm=np.asarray(session.skeleton.surface_offsets_mm),
        behind=behind,
    )


def session_hand_models(session, joints_mm: np.ndarray, crop_data):
    """The hand models :func:`session_finger_ambiguity` scores with: one per bone-length set,
    personalized from the references' joints (``joints_mm`` (N, J, 3) mm at the session's
    reference frames) and crops ``crop_data`` = ``(crops, centres_mm, boxes)``, as propagation
    does (:func:`handanno_core.handmodel.personalize_hands`). Returns ``(models, levels (H,),
    table)`` (``table``: the session's :class:`handanno_core.hands.BoneTable`), or None without
    bone lengths, references with joints or a layout with three-bone fingers. Costly with many
    references (README, stop 48): a caller ranking repeatedly keeps it while the references and
    their joints stay the same."""
    from . import handmodel as hm
    from .hands import bone_table

    j = np.asarray(joints_mm, dtype=np.float64)
    skeleton = session.skeleton
    has = np.all(np.isfinite(j), axis=(1, 2))
    refs = np.array([f for f in session.reference_frames if has[f]], dtype=np.int64)
    if session.model.bone_lengths_mm is None or len(refs) == 0:
        return None
    if not skeleton.has_finger_segments:
        return None
    crops, centres, boxes = crop_data
    obs = hm.observe_references(
        skeleton, j[refs], crops[refs], np.asarray(boxes, dtype=np.float64)[refs],
        np.asarray(centres, dtype=np.float64)[refs], session.camera,
        cube_mm=session.model.settings.cube_mm,
    )  # fmt: skip
    table = bone_table(session.frame_bone_lengths(), len(j), len(skeleton.bones))
    hand = None if table.single else table.hand[refs]
    models, levels = hm.personalize_hands(
        skeleton, table.lengths, hand, j[refs], obs, session.camera
    )
    return models, levels, table


def session_finger_ambiguity(
    session,
    joints_mm: np.ndarray,
    crop_data,
    frames: np.ndarray | None = None,
    chunk: int = 64,
    models=None,
) -> np.ndarray:
    """:func:`handanno_core.ambiguity.finger_ambiguity` (N,) mm of the session's shown skeletons
    ``joints_mm`` (N, J, 3) mm on its crops ``crop_data`` = ``(crops, centres_mm, boxes)``, for
    ``frames`` (default: every frame with joints; NaN elsewhere), scored with ``models``
    (:func:`session_hand_models` of these joints; None: made here), observations in front of
    each pose's wrist (the forearm's points left out), ``chunk`` frames at a time (memory). All
    NaN where :func:`session_hand_models` has no models."""
    from . import handmodel as hm
    from .ambiguity import finger_ambiguity

    j = np.asarray(joints_mm, dtype=np.float64)
    out = np.full(len(j), np.nan)
    models = session_hand_models(session, j, crop_data) if models is None else models
    if models is None:
        return out
    hand_models, levels, table = models
    crops, centres, boxes = crop_data
    centres, boxes = np.asarray(centres, dtype=np.float64), np.asarray(boxes, dtype=np.float64)
    has = np.all(np.isfinite(j), axis=(1, 2))
    todo = np.flatnonzero(has) if frames is None else np.asarray(frames, dtype=np.int64)
    todo = todo[has[todo]]
    for h, (model, level) in enumerate(zip(hand_models, levels, strict=True)):
        rows = todo if table.single else todo[table.hand[todo] == h]
        for a in range(0, len(rows), chunk):
            c = rows[a : a + chunk]
            obs = hm.observe(
                crops[c], boxes[c], centres[c], session.camera,
                cube_mm=session.model.settings.cube_mm, planes=hm.wrist_planes(session.skeleton, j[c]),
            )  # fmt: skip
            out[c] = finger_ambiguity(model, j[c], obs, session.camera, level)
    return out


def session_scores(
    session: Session,
    joints_mm: np.ndarray,
    confidence: np.ndarray,
    crop_data: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    *,
    bone_lengths_mm: np.ndarray | None = None,
) -> FrameScores:
    """:func:`frame_scores` of a session's skeletons ``joints_mm`` (N, J, 3) mm with their
    ``confidence`` (N, J): the session's bone lengths (or ``bone_lengths_mm``), sequence breaks and
    references; the depth term when ``crop_data`` = ``(crops, centres_mm, boxes)`` is given
    (:func:`handanno_core.prefill.cached_crops`)."""
    skeleton = session.skeleton
    if bone_lengths_mm is None:
        bone_lengths_mm = session.frame_bone_lengths()
    is_ref = np.zeros(session.num_frames, dtype=bool)
    is_ref[session.reference_frames] = True
    residual = None if crop_data is None else session_depth_residuals(session, joints_mm, crop_data)
    return frame_scores(
        confidence,
        joints_mm,
        skeleton.bones,
        bone_lengths_mm,
        depth_residual_mm=residual,
        sequence_breaks=session.model.sequence_breaks,
        is_reference=is_ref,
    )


def worst_order(score: np.ndarray, exclude: Iterable[int] = ()) -> np.ndarray:
    """Frames with a score, by increasing score (ties by frame index), ``exclude`` left out."""
    score = np.asarray(score, dtype=np.float64)
    ok = np.isfinite(score)
    ex = np.fromiter((int(f) for f in exclude), dtype=np.int64)
    ok[ex[(ex >= 0) & (ex < len(score))]] = False
    frames = np.flatnonzero(ok)
    return frames[np.lexsort((frames, score[frames]))]


def next_worst(
    score: np.ndarray, current: int | None = None, exclude: Iterable[int] = ()
) -> int | None:
    """The next frame after ``current`` in :func:`worst_order` (the worst one if ``current`` is
    None or not in the order; None when there is nothing to review)."""
    order = worst_order(score, exclude)
    if order.size == 0:
        return None
    if current is not None:
        hit = np.flatnonzero(order == int(current))
        if hit.size and hit[0] + 1 < order.size:
            return int(order[hit[0] + 1])
        if hit.size:
            return int(order[0])  # wrapped around
    return int(order[0])


# =============================================================================================
# review edits


def seed_annotation(
    joints_mm: np.ndarray,
    camera: CameraIntrinsics,
    depth_mm: np.ndarray | None = None,
    surface_offsets_mm: np.ndarray | None = None,
    margin_mm: float = VISIBILITY_MARGIN_MM,
) -> FrameAnnotation:
    """A reference annotation from a shown skeleton ``(J, 3)`` mm: every joint placed in 3D (and its
    projection in 2D) as an accepted guess, visibility by :func:`sampling.visible_by_depth`
    against ``depth_mm`` (H, W) when given.

    Accepted, because the annotator only looked at the joints it did not move: the lift weighs
    them below a placed joint (:data:`handanno_core.lift.ACCEPTED_UV_WEIGHT`, in 2D and 3D), and
    an edit of a joint (a drag, a click) makes it the annotator's own. Seeded in 3D, not only
    2D, because a shown joint within a few pixels of the truth can read another surface's depth
    where it slips off a thin finger: lifted from 2D alone, a review correction that moved
    nothing made good frames worse (HISTORY.md, stop 39)."""
    x = np.asarray(joints_mm, dtype=np.float64)
    nj = len(x)
    ann = FrameAnnotation.empty(nj)
    ann.xyz_mm[:] = x
    ann.uv_px[:] = camera.project(x)
    ann.accepted[:] = np.all(np.isfinite(ann.uv_px), axis=1)
    if depth_mm is not None:
        off = 0.0 if surface_offsets_mm is None else surface_offsets_mm
        ann.visible[:] = visible_by_depth(x, depth_mm, camera, off, margin_mm)
    return ann


def correction_command(
    session: Session,
    frame: int,
    joint: int,
    xyz_mm: np.ndarray,
    shown_mm: np.ndarray,
    depth_mm: np.ndarray | None = None,
) -> tuple[Command, bool]:
    """The command of a review edit of ``joint`` on ``frame`` to ``xyz_mm`` (mm, camera frame).

    Returns ``(command, became_reference)``. On a frame that is already an annotated reference it is
    a single :class:`SetJoint3D`. Otherwise one :class:`Batch`: ``SetReference(is_reference=True,
    correction=True)`` (unless it is a selected reference without annotation), the frame's
    annotation seeded from ``shown_mm`` (J, 3) (:func:`seed_annotation`) and the joint edit.
    Call it under ``session.lock`` together with ``session.execute`` so that two annotators
    correcting the same frame at once cannot seed over each other's joints.
    """
    xyz = tuple(round(float(v), 2) for v in np.asarray(xyz_mm, dtype=np.float64))
    edit = SetJoint3D(frame=int(frame), joint=int(joint), xyz_mm=xyz)  # type: ignore[arg-type]
    is_ref = int(frame) in set(session.model.selection.reference_frames)
    if is_ref and session.annotation(int(frame)) is not None:
        return edit, False
    commands: list[dict[str, Any]] = []
    if not is_ref:
        commands.append(
            SetReference(frame=int(frame), is_reference=True, correction=True).model_dump()
        )
    seed = seed_annotation(shown_mm, session.camera, depth_mm, session.skeleton.surface_offsets_mm)
    commands.append(SetFrameAnnotation(frame=int(frame), annotation=seed.to_json()).model_dump())
    commands.append(edit.model_dump())
    return Batch(commands=commands), not is_ref


# =============================================================================================
# review evidence: the ingredients of the ranking, per frame (no ground truth)


def angle_violation(joints_mm: np.ndarray, skeleton) -> np.ndarray:
    """``(N,)`` degrees: the sum over joints of how far flexion and abduction leave the skeleton's
    limits (0 inside; a mirrored or left/right-swapped hand bends its fingers backwards). NaN
    without joints; zeros for a skeleton without angle limits."""
    j = np.asarray(joints_mm, dtype=np.float64)
    out = np.zeros(len(j))
    if skeleton.palm_joints is None or skeleton.flexion_limits_deg is None:
        out[~np.all(np.isfinite(j), axis=(1, 2))] = np.nan
        return out
    with np.errstate(invalid="ignore", divide="ignore"):
        flex, abd = skeleton.joint_angles(j)
        fl, al = skeleton.angle_limits()
        over = (
            np.maximum(fl[:, 0] - flex, 0)
            + np.maximum(flex - fl[:, 1], 0)
            + np.maximum(al[:, 0] - abd, 0)
            + np.maximum(abd - al[:, 1], 0)
        )
        out = over.sum(axis=1)
    out[~np.all(np.isfinite(j), axis=(1, 2))] = np.nan
    return out


def finger_order_violation(joints_mm: np.ndarray, skeleton, margin_mm: float = 5.0) -> np.ndarray:
    """``(N,)`` mm: swapped fingers. The fingers whose base lies on the segment between the palm's
    two side joints (``skeleton.palm_joints``: index and little MCP for MSRA-21; the thumb, whose
    base is off that line, is left out) keep their
    order across the palm: for each pair of adjacent fingers, how far (beyond ``margin_mm``) their
    tips cross along the palm's lateral axis, summed. NaN without joints; zeros without palm joints."""
    j = np.asarray(joints_mm, dtype=np.float64)
    n = len(j)
    bad = ~np.all(np.isfinite(j), axis=(1, 2))
    out = np.zeros(n)
    if skeleton.palm_joints is None:
        out[bad] = np.nan
        return out
    w, a, b = skeleton.palm_joints
    parents = skeleton.parent_array
    bases = [int(k) for k in np.flatnonzero(parents == w)]
    tips = []
    for k in bases:  # follow the single-child chain to its end
        t = k
        while len(skeleton.children(t)) == 1:
            t = int(skeleton.children(t)[0])
        tips.append(t)
    with np.errstate(invalid="ignore", divide="ignore"):
        axis = j[:, b] - j[:, a]
        span = np.linalg.norm(axis, axis=-1, keepdims=True)
        axis = axis / np.maximum(span, 1e-9)
        rel = j[:, bases] - j[:, a][:, None]  # (N, F, 3)
        base_pos = np.einsum("nkd,nd->nk", rel, axis)
        off_line = np.linalg.norm(rel - base_pos[..., None] * axis[:, None], axis=-1)
        tip_pos = np.einsum("nkd,nd->nk", j[:, tips] - j[:, a][:, None], axis)
        inside = (base_pos > -margin_mm) & (base_pos < span + margin_mm) & (off_line < 0.5 * span)
        inside = np.nanmean(inside[~bad], axis=0) > 0.5 if (~bad).any() else inside[0] & False
    idx = np.flatnonzero(inside)
    if idx.size >= 2:
        order = idx[np.argsort(np.nanmedian(base_pos[:, idx], axis=0))]
        cross = tip_pos[:, order[:-1]] - tip_pos[:, order[1:]]  # > 0: tips out of order
        out = np.maximum(cross - margin_mm, 0.0).sum(axis=1)
    out[bad] = np.nan
    return out


def unexplained_foreground(
    joints_mm: np.ndarray,
    crops: np.ndarray,
    boxes: np.ndarray,
    camera: CameraIntrinsics,
    bones: np.ndarray,
    *,
    radius_px: float = 6.0,
    stride: int = 4,
    frames: np.ndarray | None = None,
    chunk_frames: int = 32,
) -> np.ndarray:
    """``(N,)`` share of the hand's pixels in the crop (normalized depth < 1) farther than
    ``radius_px`` crop pixels from every projected bone: a finger the skeleton does not cover (a
    2D model-fit residual). Crop pixels are sampled every ``stride``. NaN without joints or hand.

    ``crops`` (N, S, S), ``boxes`` (N, 4) as :mod:`handanno_core.crops`; ``bones`` (B, 2).
    ``frames``: only these frames (indices; the others stay NaN), e.g. the frames whose joints
    changed. Vectorized over the hand pixels of ``chunk_frames`` frames at a time (32: the
    temporaries stay in cache); a frame's value depends on nothing else (not on the chunking,
    nor on ``frames``).
    """
    from .crops import image_to_crop

    j = np.asarray(joints_mm, dtype=np.float64)
    n = len(j)
    out = np.full(n, np.nan)
    size = crops.shape[1]
    grid = np.arange(stride // 2, size, stride)
    gy, gx = np.meshgrid(grid, grid, indexing="ij")
    pix = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float64)  # (P, 2) crop px
    b = np.asarray(bones, dtype=np.int64)
    todo = np.arange(n) if frames is None else np.unique(np.asarray(frames, dtype=np.int64))
    ok = todo[np.all(np.isfinite(j[todo]), axis=(1, 2))]
    step = max(int(chunk_frames), 1)
    for start in range(0, ok.size, step):
        chunk = ok[start : start + step]
        sampled = np.asarray(crops[chunk])[:, stride // 2 :: stride, stride // 2 :: stride]
        fg = sampled.reshape(len(chunk), -1) < 0.999  # (C, P), pixels as ``pix``
        xy = image_to_crop(
            camera.project(j[chunk]), np.asarray(boxes[chunk], dtype=np.float64)[:, None, :]
        )  # (C, J, 2)
        p0, p1 = xy[:, b[:, 0]], xy[:, b[:, 1]]  # (C, B, 2)
        d = p1 - p0
        dd = np.maximum(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1], 1e-9)  # (C, B)
        which, where = np.nonzero(fg)  # the hand pixels of the chunk: (M,) frame, (M,) pixel
        # per (hand pixel, bone), x and y apart (reductions over a length-2 axis are slow)
        qx, qy = pix[where, 0][:, None], pix[where, 1][:, None]  # (M, 1)
        x0, y0 = p0[which, :, 0], p0[which, :, 1]  # (M, B)
        dx, dy = d[which, :, 0], d[which, :, 1]
        t = np.clip(((qx - x0) * dx + (qy - y0) * dy) / dd[which], 0, 1)
        ex, ey = qx - (x0 + t * dx), qy - (y0 + t * dy)
        dist = np.sqrt(ex * ex + ey * ey).min(axis=1)  # (M,) crop px to the nearest bone
        count = np.bincount(which, minlength=len(chunk))
        far = np.bincount(which, weights=dist > radius_px, minlength=len(chunk))
        has = count > 0
        out[chunk[has]] = far[has] / count[has]
    return out


def hops_to_reference(parent: np.ndarray) -> np.ndarray:
    """``(N,)`` number of propagation steps from each frame's reference (0 at references)."""
    parent = np.asarray(parent, dtype=np.int64)
    n = len(parent)
    p = np.where(parent < 0, np.arange(n), parent)
    d = (parent >= 0).astype(np.int64)  # invariant: d[i] = steps from i up to p[i]
    for _ in range(int(np.log2(max(n, 2))) + 2):  # pointer jumping; bounded against cycles
        d = d + d[p]
        p = p[p]
    return d


def centre_drift(joints_mm: np.ndarray, centres_mm: np.ndarray, root: np.ndarray) -> np.ndarray:
    """``(N,)`` mm: how far the skeleton moved relative to the observed hand. The offset of the
    joints' mean from the hand centre the crops were cut around (``centres_mm`` (N, 3), from the
    depth alone) is compared with the same offset on the frame's reference ``root`` (N,) (its
    root in the parent forest); a propagated skeleton that slid off the hand changes it, a pose
    change only by a little. NaN without joints or centre."""
    j = np.asarray(joints_mm, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        offset = j.mean(axis=1) - np.asarray(centres_mm, dtype=np.float64)  # (N, 3)
        return np.linalg.norm(offset - offset[np.asarray(root, dtype=np.int64)], axis=-1)


def _max_joint_norm(x: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.max(np.linalg.norm(x, axis=-1), axis=-1)


def review_evidence(
    session: Session,
    results: dict[str, np.ndarray],
    crop_data: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    *,
    extra: dict[str, np.ndarray] | None = None,
    unexplained: np.ndarray | None = None,
    ambiguity: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Per-frame evidence ``{name: (N,)}`` that a frame's shown skeleton (refined, else
    propagated, else lifted) is wrong, larger = worse, NaN = unavailable. No ground truth.

    ``conf`` 1 - propagation confidence (mean and minimum over joints averaged; it contains the
    forward-backward flow consistency of the step); ``conf_min`` 1 - its minimum;
    ``depth_mm`` / ``depth_max_mm`` joints in front of the observed surface or off the hand
    (:func:`depth_residuals`, mean and max over joints; needs ``crop_data``); ``unexplained`` hand
    pixels no bone covers (:func:`unexplained_foreground`; needs ``crop_data``); ``jump_mm``
    (:func:`temporal_jump`); ``accel_mm`` largest second difference in time; ``refine_mm`` how far
    refinement moved a joint from its propagated position; ``angle_deg`` joint-angle limit
    violation (:func:`angle_violation`, also catches mirrored hands); ``swap_mm`` finger order
    (:func:`finger_order_violation`); ``bone`` bone-length anomaly of the propagated pose;
    ``hops`` propagation steps from the reference; ``gap`` frames (in time) to the reference;
    with the hand model, the propagation's own fit evidence (``results["model_fit"]``, not
    recomputed): ``model_level`` (the fit's data + free-space energy over the references'),
    ``model_data_mm`` (mean point-to-surface mm at the kept pose), ``model_free`` (share of
    free-space samples violated), ``model_rejected`` (1: the guard kept the flowed pose), see
    :data:`handanno_core.results.MODEL_FIT_TERMS`.
    ``ambiguity_mm`` how far one finger could move at little cost on the frame's depth
    (:func:`session_finger_ambiguity`; needs ``crop_data``).
    ``extra``: further terms ``{name: (N,)}`` (e.g. a model-fit residual) passed through.
    ``crop_data`` = ``(crops, centres_mm, boxes)`` (:func:`handanno_core.prefill.cached_crops`).
    ``unexplained`` / ``ambiguity``: :func:`unexplained_foreground` / :func:`session_finger_ambiguity`
    of these joints (N,) when the caller keeps them up to date itself (the app recomputes only
    frames whose joints changed); else computed here.
    """
    from .export import best_joints
    from .pipeline import root_reference

    skeleton = session.skeleton
    joints, _ = best_joints(results)
    init = np.asarray(results["init_mm"], dtype=np.float64)
    n = len(joints)
    conf = np.asarray(results["confidence"], dtype=np.float64)
    conf = np.where(np.isfinite(conf), np.clip(conf, 0.0, 1.0), 0.5)
    ev: dict[str, np.ndarray] = {
        "conf": 1.0 - 0.5 * (conf.mean(axis=1) + conf.min(axis=1)),
        "conf_min": 1.0 - conf.min(axis=1),
    }
    if crop_data is not None:
        crops, _, boxes = crop_data
        res = session_depth_residuals(session, joints, crop_data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ev["depth_mm"] = np.nanmean(res, axis=1)
            ev["depth_max_mm"] = np.nanmax(res, axis=1)
        ev["unexplained"] = (
            unexplained_foreground(joints, crops, boxes, session.camera, skeleton.bones)
            if unexplained is None
            else np.asarray(unexplained, dtype=np.float64)
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ev["behind_mm"] = np.nanmedian(
                session_depth_residuals(session, joints, crop_data, behind=True), axis=1
            )
        ev["drift_mm"] = centre_drift(joints, crop_data[1], root_reference(session.parent))
        ev["ambiguity_mm"] = (
            session_finger_ambiguity(session, joints, crop_data)
            if ambiguity is None
            else np.asarray(ambiguity, dtype=np.float64)
        )
    ev["jump_mm"] = temporal_jump(joints, session.model.sequence_breaks)
    accel = np.full(n, np.nan)
    if n > 2:
        accel[1:-1] = _max_joint_norm(joints[2:] - 2.0 * joints[1:-1] + joints[:-2])
    for b in session.model.sequence_breaks:  # no second difference across a break
        for f in (int(b) - 1, int(b)):
            if 0 <= f < n:
                accel[f] = np.nan
    ev["accel_mm"] = accel
    ev["refine_mm"] = _max_joint_norm(joints - np.where(np.isfinite(init), init, joints))
    ev["angle_deg"] = angle_violation(joints, skeleton)
    ev["swap_mm"] = finger_order_violation(joints, skeleton)
    if session.model.bone_lengths_mm is not None:
        ev["bone"] = bone_anomaly(init, skeleton.bones, session.frame_bone_lengths())
    # hops, gap (and drift_mm above) along the selection's forest, as when the weights were
    # fitted: along the candidate chain each frame kept (results "source") the ranking was no
    # better on the tune part (objective 0.466 -> 0.471, rank correlation 0.670 -> 0.664; seed
    # 0, forest 5 %, model on, 8 sessions; README "Which frame a result came from")
    parent = session.parent
    ev["hops"] = hops_to_reference(parent).astype(np.float64)
    ev["gap"] = np.abs(np.arange(n) - root_reference(parent)).astype(np.float64)
    model_fit = results.get("model_fit")
    if model_fit is not None:
        model_fit = np.asarray(model_fit, dtype=np.float64)
        for k, name in enumerate(MODEL_FIT_TERMS):
            ev[f"model_{name}"] = model_fit[:, k]
    for name, value in (extra or {}).items():
        ev[name] = np.asarray(value, dtype=np.float64)
    return ev


# =============================================================================================
# rankings: which K frames to show


#: ``{evidence name: (scale, weight)}`` of the "evidence" ranking: priority = sum of
#: ``weight * log1p(x / scale)`` (a logit). Chosen on the suite's tune part only, with the hand
#: model on (``benchmarks/bench_review_ranking.py --loso --objective-mm 10,15,20,30,40``: ``handanno
#: suite --part tune --frames-scale 0.5`` seeds 0 and 1, 14 sessions, forest 5 %, exact 2D): a
#: non-negative logistic regression of "a joint more than 10 mm off" over the non-reference
#: frames; scales = each term's median there. Leave-one-sequence-out inside the tune part it beat
#: the previous weights (chosen with the model off by coordinate ascent): mean recall@10 %
#: relative to its ceiling 0.46 -> 0.54, rank correlation with the frame error 0.43 -> 0.61; the
#: coordinate ascent did not (0.46). Terms at weight 0: depth_mm, depth_max_mm, bone, gap and the
#: model-fit terms other than model_free (the fit's residual is already a factor of the
#: propagation confidence, ``conf``; a fit without the model-fit terms did as well in the same
#: check). ``ambiguity_mm`` (:func:`session_finger_ambiguity`) joined at stop 48 with the others
#: unchanged, its weight chosen on the tune part (seeds 0-2, 5 % uniform, 24 sessions): at 4 the
#: tune objective is better at 10-15, 20, 20-40 and 10-40 mm; the bench's leave-one-sequence-out
#: check is better at 20-40 mm and worse at 10-40 mm (``benchmarks/HISTORY.md``, stop 48).
EVIDENCE_WEIGHTS: dict[str, tuple[float, float]] = {
    "conf": (0.8645, 3.1257),
    "conf_min": (1.0, 0.4363),
    "unexplained": (0.4205, 2.1346),
    "behind_mm": (3.5951, 0.9821),
    "drift_mm": (4.7774, 0.1445),
    "jump_mm": (3.3979, 0.7174),
    "accel_mm": (1.7765, 0.3567),
    "refine_mm": (4.9036, 0.8621),
    "angle_deg": (13.2785, 2.122),
    "swap_mm": (6.9528, 3.0542),
    "hops": (4.0, 1.425),
    "model_free": (0.0072, 0.382),
    "ambiguity_mm": (10.0, 4.0),
}
#: frames within this distance (in time) of a frame already picked in the same round are shown
#: only when nothing else is left: one bad stretch should not fill the list. 0 (off): on the tune
#: part radii 1, 2 and 4 all lowered recall@10 % (bad frames come in stretches).
SUPPRESS_RADIUS = 0
#: ``(radius, weight)`` of :func:`smooth_in_time` applied to the "evidence" priority; off: on the
#: tune part no radius (1-8) and weight (0.25-0.75) raised recall@10 % with these weights.
SMOOTH: tuple[int, float] = (0, 0.0)

RANKINGS = ("evidence", "score", "uniform")


def evidence_priority(
    evidence: dict[str, np.ndarray], weights: dict[str, tuple[float, float]] | None = None
) -> np.ndarray:
    """``(N,)`` priority (larger = show first) from :func:`review_evidence`: the sum over terms of
    ``weight * log1p(max(x, 0) / scale)``; a term that is missing or NaN contributes nothing (a
    model-fit residual added to ``evidence`` and ``weights`` joins without other changes)."""
    w = EVIDENCE_WEIGHTS if weights is None else weights
    n = len(next(iter(evidence.values())))
    out = np.zeros(n)
    for name, (scale, weight) in w.items():
        x = evidence.get(name)
        if x is None:
            continue
        t = np.log1p(np.maximum(np.asarray(x, dtype=np.float64), 0.0) / scale)
        out += weight * np.where(np.isfinite(t), t, 0.0)
    return out


def smooth_in_time(
    priority: np.ndarray, radius: int, weight: float, sequence_breaks: Iterable[int] = ()
) -> np.ndarray:
    """``(N,)``: ``(1 - weight) * priority + weight * (mean of priority over the frames within
    ``radius`` in time, same sequence segment)``. Bad frames come in stretches while single
    evidence terms are noisy, so a frame whose neighbours look wrong is more likely wrong. NaN
    entries stay NaN and do not enter their neighbours' means."""
    p = np.asarray(priority, dtype=np.float64)
    n = len(p)
    if radius <= 0 or weight == 0.0 or n == 0:
        return p.copy()
    ok = np.isfinite(p)
    seg = np.zeros(n, dtype=np.int64)
    for b in sequence_breaks:
        if 0 < int(b) < n:
            seg[int(b)] = 1
    seg = np.cumsum(seg)
    idx = np.arange(n)
    lo = np.maximum(idx - radius, np.searchsorted(seg, seg, side="left"))
    hi = np.minimum(idx + radius + 1, np.searchsorted(seg, seg, side="right"))
    csum = np.concatenate([[0.0], np.cumsum(np.where(ok, p, 0.0))])
    ccnt = np.concatenate([[0], np.cumsum(ok)])
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (csum[hi] - csum[lo]) / (ccnt[hi] - ccnt[lo])
    return np.where(ok, (1.0 - weight) * p + weight * mean, np.nan)


def pick_frames(
    priority: np.ndarray,
    k: int,
    *,
    exclude: Iterable[int] = (),
    radius: int = SUPPRESS_RADIUS,
    sequence_breaks: Iterable[int] = (),
) -> np.ndarray:
    """The ``k`` frames to show (``(<=k,)`` int64, in the order shown): by decreasing ``priority``
    (NaN never), ``exclude`` (frames already reviewed, references) left out, and a frame within
    ``radius`` frames of one already picked (same segment) deferred until nothing else is left."""
    p = np.asarray(priority, dtype=np.float64)
    n = len(p)
    ok = np.isfinite(p)
    ex = np.fromiter((int(f) for f in exclude), dtype=np.int64)
    ok[ex[(ex >= 0) & (ex < n)]] = False
    cand = np.flatnonzero(ok)
    cand = cand[np.lexsort((cand, -p[cand]))]
    k = min(int(k), cand.size)
    if radius <= 0 or k == 0:
        return cand[:k]
    segment = np.zeros(n, dtype=np.int64)
    for b in sequence_breaks:
        if 0 < int(b) < n:
            segment[int(b)] = 1
    segment = np.cumsum(segment)
    blocked = np.zeros(n, dtype=bool)
    picked: list[int] = []
    deferred: list[int] = []
    for f in cand:
        if len(picked) == k:
            break
        if blocked[f]:
            deferred.append(int(f))
            continue
        picked.append(int(f))
        lo, hi = max(f - radius, 0), min(f + radius + 1, n)
        blocked[lo:hi] |= segment[lo:hi] == segment[f]
    picked += deferred[: k - len(picked)]
    return np.asarray(picked, dtype=np.int64)


def uniform_pick(n: int, k: int, exclude: Iterable[int] = ()) -> np.ndarray:
    """``k`` frames evenly spread over ``0..n-1`` (the baseline: corrections without a ranking),
    skipping ``exclude``."""
    ok = np.ones(n, dtype=bool)
    ex = np.fromiter((int(f) for f in exclude), dtype=np.int64)
    ok[ex[(ex >= 0) & (ex < n)]] = False
    cand = np.flatnonzero(ok)
    k = min(int(k), cand.size)
    if k == 0:
        return cand[:0]
    return cand[np.unique(np.linspace(0, cand.size - 1, k).round().astype(np.int64))]


def rank_priority(
    ranking: str,
    session: Session,
    results: dict[str, np.ndarray],
    crop_data: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    *,
    extra: dict[str, np.ndarray] | None = None,
    unexplained: np.ndarray | None = None,
    ambiguity: np.ndarray | None = None,
) -> np.ndarray:
    """``(N,)`` priority of ``ranking`` (larger = show first; NaN = nothing to show): ``"evidence"``
    (:func:`evidence_priority`), ``"score"`` (the app's ranking until now: ``1 -``
    :func:`session_scores`), ``"uniform"`` (all equal; use :func:`uniform_pick`). ``unexplained``
    and ``ambiguity`` go to :func:`review_evidence`."""
    from .export import best_joints

    joints, _ = best_joints(results)
    has = np.all(np.isfinite(joints), axis=(1, 2))
    if ranking == "evidence":
        ev = review_evidence(
            session, results, crop_data, extra=extra, unexplained=unexplained, ambiguity=ambiguity
        )
        p = evidence_priority(ev)
        p = smooth_in_time(p, SMOOTH[0], SMOOTH[1], session.model.sequence_breaks)
    elif ranking == "score":
        p = 1.0 - session_scores(session, joints, results["confidence"], crop_data).score
    elif ranking == "uniform":
        p = np.zeros(len(joints))
    else:
        raise ValueError(f"unknown ranking {ranking!r}; choose one of {RANKINGS}")
    return np.where(has, p, np.nan)


def recall_at(
    priority: np.ndarray, bad: np.ndarray, share: float = 0.10, exclude: Iterable[int] = (), **kw
) -> float:
    """Share of the ``bad`` frames ((N,) bool, not excluded) among the ranking's first
    ``share * N`` picks (:func:`pick_frames`); NaN when no frame is bad. Evaluation only."""
    bad = np.asarray(bad, dtype=bool).copy()
    ex = np.fromiter((int(f) for f in exclude), dtype=np.int64)
    bad[ex] = False
    if not bad.any():
        return float("nan")
    top = pick_frames(priority, int(round(share * len(bad))), exclude=ex, **kw)
    return float(bad[top].sum() / bad.sum())
