"""Lift all references: bone-length and surface-offset re-estimation rounds (:func:`lift_references`)."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..annotation import AnnotationError, FrameAnnotation
from ..camera import CameraIntrinsics
from ..parallel import Runner
from ..pose_prior import pose_prior as packaged_pose_prior
from ..pose_prior import session_prior
from ..skeleton import Skeleton
from .initial import initial_bone_lengths
from .solve import SURFACE_DEPTH_MM, W_POSE, LiftResult, lift_frame, surface_depths_mm


@dataclass
class LiftSet:
    """Lifted references: ``joints_mm[f]`` ``(J, 3)``, ``confidence[f]`` ``(J,)``, bones ``(B,)`` mm."""

    joints_mm: dict[int, np.ndarray]
    confidence: dict[int, np.ndarray]
    bone_lengths_mm: np.ndarray
    results: dict[int, LiftResult] = field(default_factory=dict)
    bone_history_mm: list[np.ndarray] = field(default_factory=list)
    #: ``(J,)`` mm: the surface offsets the references were lifted with (self-calibrated)
    surface_offsets_mm: np.ndarray | None = None
    #: ``(B,)`` number of references in which both ends of each bone are annotated
    bone_votes: np.ndarray | None = None
    #: the pose prior's weight the references were lifted with (px^2; after the session's scale)
    pose_weight: float | None = None


def surface_correction(
    annotations: dict[int, FrameAnnotation],
    results: dict[int, LiftResult],
    skeleton: Skeleton,
    surface_depth_mm: float | np.ndarray,
    min_samples: int = 8,
) -> np.ndarray:
    """Per-joint correction ``(J,)`` mm of the surface offsets, from lifted references.

    For every annotated visible joint with an observed depth (and no elastic slack) the residual
    ``z_lifted - (D + o + surface_depth_mm + e)`` (``e`` the inclined bones' extra depth,
    ``LiftResult.surface_extra_mm``) is how much deeper below the observed surface the
    lift put the joint centre than the offset assumed; the correction of a joint group
    (:meth:`Skeleton.surface_groups`: same level along the chains) is the median over its samples
    (0 with fewer than ``min_samples``). Fingertips are the anchor (their offset is defined: the
    tip lies on the surface) and are never corrected: a uniform change of every offset is
    otherwise indistinguishable from a change of the hand's scale.
    """
    groups = skeleton.surface_groups()
    offsets = np.asarray(skeleton.surface_offsets_mm, dtype=np.float64)
    res_by_group: dict[int, list[np.ndarray]] = {}
    for f, r in results.items():
        ann = annotations[f]
        d = r.observed_depth_mm
        ok = ann.has_2d & ann.visible & np.isfinite(d)
        ok[r.slack_joints] = False
        resid = r.joints_mm[:, 2] - d - offsets - surface_depth_mm
        if r.surface_extra_mm is not None:  # the inclined bones' part is not the offset's
            resid = resid - r.surface_extra_mm
        for g in np.unique(groups[ok]):
            res_by_group.setdefault(int(g), []).append(resid[ok & (groups == g)])
    corr = np.zeros(skeleton.num_joints)
    for g, parts in res_by_group.items():
        vals = np.concatenate(parts)
        if g >= 0 and len(vals) >= min_samples:
            corr[groups == g] = float(np.median(vals))
    return corr


# ---------------------------------------------------------------------------------------- refs
def _lift_job(args: tuple) -> LiftResult:
    ann, depth, camera, skeleton, bones, kwargs = args
    return lift_frame(ann, depth, camera, skeleton, bones, **kwargs)


def _better(a: LiftResult, b: LiftResult) -> LiftResult:
    """The converged result with the lower objective (``a`` on ties)."""
    if a.converged != b.converged:
        return a if a.converged else b
    return b if b.objective < a.objective - 1e-9 else a


def _reestimate_bones(bones: np.ndarray, soft_lengths: np.ndarray, voted: np.ndarray,
                      tmpl: np.ndarray | None, seen: np.ndarray | None = None,
                      min_seen: int = 3, shrink: bool = False) -> np.ndarray:  # fmt: skip
    """New bone lengths ``(B,)`` mm: the median over the references of ``soft_lengths`` (F, B)
    for the ``voted`` bones; the others the template ``tmpl`` times the voted bones' median ratio
    to it (unchanged without a template or a voted bone). ``seen`` (F, B) bool: references where
    the bone was seen (:func:`_seen_bones`); a bone seen in ``min_seen`` references or more takes
    the median over those only (a hidden joint's soft length is its start length again: no data).
    ``shrink``: each voted bone's median is pulled towards the template's proportion by how
    uncertain it is (:func:`shrink_to_template`)."""
    new = bones.copy()
    if np.any(voted):
        samples = np.where(voted, soft_lengths, np.nan)
        if seen is not None:
            by_seen = voted & (seen.sum(axis=0) >= min_seen)
            samples[:, by_seen] = np.where(seen[:, by_seen], soft_lengths[:, by_seen], np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a voted bone without a finite sample
            new[voted] = np.nanmedian(samples[:, voted], axis=0)
        if tmpl is not None and shrink:
            new = shrink_to_template(new, samples, voted, tmpl)
        if tmpl is not None and not np.all(voted):
            # bones without enough evidence: template times the global scale
            scale = float(np.median(new[voted] / tmpl[voted]))
            new[~voted] = tmpl[~voted] * scale
    return new


def shrink_to_template(
    medians: np.ndarray,
    samples: np.ndarray,
    voted: np.ndarray,
    tmpl: np.ndarray,
    min_samples: int = 3,
    min_bones: int = 4,
) -> np.ndarray:
    """Bone lengths ``(B,)`` mm: each voted bone's median ``medians`` pulled towards the template
    ``tmpl`` (B,) mm times the hand's scale, by how uncertain the median is (empirical Bayes).

    ``samples`` (F, B) mm are the per-reference lengths the medians were taken over (NaN: not a
    sample). In log length, a bone's median has the sampling variance ``s²`` (its standard error,
    1.4826 MAD / sqrt(n), relative) and the hand's proportions differ from the template's by a
    variance ``τ²`` that is estimated from the same bones: the mean squared log ratio of the
    medians to the scaled template, less the mean ``s²``. The estimate is the precision-weighted
    mean ``w log(median) + (1 - w) log(scaled template)``, ``w = τ² / (τ² + s²)``: exact clicks
    (small ``s``) keep their medians, noisy clicks on a hand shaped like the template move
    towards it, and a hand shaped unlike the template (large ``τ``) keeps its own proportions.
    Nothing changes with fewer than ``min_bones`` bones of ``min_samples`` samples."""
    out = medians.copy()
    n = np.sum(np.isfinite(samples), axis=0)
    idx = np.flatnonzero(voted & (n >= min_samples) & np.isfinite(medians) & (medians > 0))
    if len(idx) < min_bones:
        return out
    x = samples[:, idx]
    med = medians[idx]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mad = np.nanmedian(np.abs(x - med), axis=0)
    s2 = (1.4826 * mad / np.sqrt(n[idx]) / med) ** 2
    prior = np.log(tmpl[idx] * float(np.median(med / tmpl[idx])))
    tau2 = max(float(np.mean((np.log(med) - prior) ** 2) - np.mean(s2)), 1e-6)
    w = tau2 / (tau2 + s2)
    out[idx] = np.exp(w * np.log(med) + (1.0 - w) * prior)
    return out


def _seen_bones(
    annotations: list[FrameAnnotation],
    results: list[LiftResult],
    skeleton: Skeleton,
    max_sin_elevation: float = 0.7,
) -> np.ndarray:
    """``(F, B)`` bool: references in which both ends of a bone are annotated visible with an
    observed depth that the lift kept (no elastic slack), and the lifted bone is not
    foreshortened (the sine of its angle to the image plane below ``max_sin_elevation``): the
    references whose soft-bone lift measures the bone's length from the data."""
    p, c = skeleton.bones[:, 0], skeleton.bones[:, 1]
    out = np.zeros((len(results), len(p)), dtype=bool)
    for i, (a, r) in enumerate(zip(annotations, results, strict=True)):
        ok = a.has_2d & a.visible & np.isfinite(r.observed_depth_mm)
        ok[r.slack_joints] = False
        v = r.joints_mm[c] - r.joints_mm[p]
        sin_el = np.abs(v[:, 2]) / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        out[i] = ok[p] & ok[c] & (sin_el < max_sin_elevation)
    return out


def _mark_stretched(res: list, soft_lengths: np.ndarray, bones: np.ndarray, sk: Skeleton,
                    stretch_tolerance: float) -> None:  # fmt: skip
    """Mark the references whose soft-bone lengths ``soft_lengths`` (F, B) mm want some bone far
    off the estimate ``bones`` (B,) mm (see :func:`lift_references`): ``stretched``, not
    ``converged``, half the confidence, the bone in the message."""
    dev = np.abs(soft_lengths - bones)
    rel = dev / bones
    # beyond the tolerance, 3 mm, and 4 robust standard deviations of the bone's spread over
    # the references (noisy clicks spread every bone; only an outlier frame is stretched)
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)  # bones nobody annotated: all NaN
        spread = 1.4826 * np.nanmedian(dev, axis=0) if len(dev) >= 5 else np.zeros(len(bones))
        wants = (rel > stretch_tolerance) & (dev > 3.0) & (dev > 4.0 * spread)
    for i, r in enumerate(res):
        if np.any(wants[i]):
            b = int(np.argmax(np.where(wants[i], rel[i], -1.0)))
            r.stretched = True
            r.converged = False
            r.confidence = r.confidence * 0.5
            r.message = (
                f"stretched: bone {sk.joint_names[sk.bones[b, 0]]}-"
                f"{sk.joint_names[sk.bones[b, 1]]} fits {soft_lengths[i, b]:.1f} mm in this "
                f"frame against {bones[b]:.1f} mm estimated; {r.message}"
            )


def lift_references(
    annotations: dict[int, FrameAnnotation],
    depth_of: Callable[[int], np.ndarray],
    camera: CameraIntrinsics,
    skeleton: Skeleton,
    *,
    bone_lengths_mm: np.ndarray | None = None,
    pin_bone_lengths: bool = False,
    eps_mm: float = 15.0,
    angle_limits: bool = True,
    workers: int = 1,
    scheduler=None,
    progress: Callable[[int, int], None] | None = None,
    max_rounds: int = 30,
    bone_tol_mm: float = 0.1,
    soft_bone_weight: float = 0.05,
    min_bone_votes: int = 3,
    calibrate_surface: bool = True,
    offset_tol_mm: float = 0.5,
    max_calibrations: int = 3,
    stretch_tolerance: float = 0.2,
    seen_votes: bool = True,
    shrink_bones: bool = False,
    adapt_pose_prior: bool = True,
    **lift_kwargs,
) -> LiftSet:
    """Lift every annotated reference frame; estimate the bone lengths and surface offsets.

    annotations: frame -> :class:`FrameAnnotation`. depth_of(frame) -> ``(H, W)`` mm.
    bone_lengths_mm: ``(B,)`` starting lengths (default: the template times the hand scale
    measured on the annotations, :func:`initial_bone_lengths`).
    pin_bone_lengths: keep ``bone_lengths_mm`` fixed (no re-estimation; requires the lengths).
    Re-estimation rounds (see module docstring) run until no bone changes by more than
    ``bone_tol_mm`` (and no surface offset by more than ``offset_tol_mm``) or ``max_rounds``.
    A bone is re-estimated only where both its joints are annotated in at least
    ``min_bone_votes`` references; the others keep the template times the global scale of the
    re-estimated ones (median ratio to the template). seen_votes: a bone seen in
    ``min_bone_votes`` references (both ends visible with a kept reading, not foreshortened) takes
    the median over those only (module docstring). shrink_bones: each median pulled towards the
    template's proportions by its own uncertainty (:func:`shrink_to_template`).
    adapt_pose_prior: after the first round, make the pose prior the session's own
    (:func:`handanno_core.pose_prior.session_prior` of the lifted references: its mean moved to
    theirs, ``w_pose`` divided by their remaining spread; the weight used is
    ``LiftSet.pose_weight``); not with pinned bones (no rounds). calibrate_surface:
    re-estimate the depth of joint centres below the observed surface per joint group in every
    round (:func:`surface_correction`; the result is in ``LiftSet.surface_offsets_mm``).
    A reference whose own evidence (its last soft-bone lift) wants some annotated bone more than
    ``stretch_tolerance`` (fraction, and > 3 mm, and > 4 robust standard deviations of that
    bone's spread over the references) longer or shorter than the final estimate is reported
    ``stretched`` (and not ``converged``): the template could only be fitted by stretching it.
    workers > 1 lifts frames in processes, ``scheduler`` (``"tcp://HOST:PORT"``) on a Dask
    cluster (:class:`handanno_core.parallel.Runner`: each round is a map over the references, the
    bone estimate a reduction here; depth maps are sent once). progress(done, total) is called
    after every frame of every round. Returns a :class:`LiftSet` with ``bone_history_mm`` (one entry per
    round).
    """
    frames = sorted(int(f) for f in annotations)
    for f in frames:
        if not isinstance(annotations[f], FrameAnnotation):
            raise AnnotationError(f"frame {f}: expected a FrameAnnotation")
        annotations[f].validate(skeleton.num_joints, where=f"frame {f}")
    if pin_bone_lengths and bone_lengths_mm is None:
        raise ValueError("pin_bone_lengths=True needs bone_lengths_mm")
    depths = {f: np.asarray(depth_of(f)) for f in frames}
    anns = {f: annotations[f] for f in frames}
    with Runner(workers, scheduler) as runner:
        shared = {f: runner.share(depths[f]) for f in frames}
        if bone_lengths_mm is not None:
            bones = np.asarray(bone_lengths_mm, dtype=np.float64).copy()
        elif frames:
            bones = initial_bone_lengths(anns, depths, camera, skeleton)
        else:
            bones = np.asarray(skeleton.template_bone_lengths_mm, dtype=np.float64)
        history = [bones.copy()]
        sk = skeleton
        surface_depth = surface_depths_mm(sk, lift_kwargs.get("surface_depth_mm", SURFACE_DEPTH_MM))
        kw = dict(eps_mm=eps_mm, angle_limits=angle_limits, **lift_kwargs)
        kw.setdefault("w_pose", W_POSE)
        prior = packaged_pose_prior(sk) if kw.get("pose_prior") is None else kw["pose_prior"]
        adapt = adapt_pose_prior and prior is not None and kw["w_pose"] > 0
        inits: dict[int, np.ndarray] = {}
        soft_lengths = None
        votes = (
            np.stack([anns[f].annotated for f in frames])
            if frames
            else np.zeros((0, sk.num_joints), dtype=bool)
        )
        bmask = votes[:, sk.bones[:, 0]] & votes[:, sk.bones[:, 1]]  # (F, B) both ends annotated
        voted = bmask.sum(axis=0) >= min_bone_votes
        tmpl = (
            np.asarray(sk.template_bone_lengths_mm, dtype=np.float64)
            if sk.template_bone_lengths_mm is not None
            else None
        )
        calibrations = 0
        if not pin_bone_lengths and len(frames) > 0:
            for _ in range(max_rounds + max_calibrations):
                jobs = [
                    (
                        anns[f],
                        shared[f],
                        camera,
                        sk,
                        bones,
                        dict(kw, soft_bones=soft_bone_weight, init_mm=inits.get(f)),
                    )
                    for f in frames
                ]
                res = runner.map(_lift_job, jobs, progress)
                poses = np.stack([r.joints_mm for r in res])
                if adapt:
                    # once: centre the prior on this hand's own poses, and widen it by how far
                    # they still lie from it
                    kw["pose_prior"], kw["w_pose"] = session_prior(
                        prior, sk, poses, kw["w_pose"], kw.get("right_hand", True)
                    )
                    adapt = False
                soft_lengths = np.where(bmask, sk.bone_lengths(poses), np.nan)  # (F, B)
                new = _reestimate_bones(
                    bones, soft_lengths, voted, tmpl,
                    _seen_bones([anns[f] for f in frames], res, sk) if seen_votes else None,
                    min_bone_votes, shrink_bones,
                )  # fmt: skip
                change = float(np.max(np.abs(new - bones)))
                bones = new
                history.append(bones.copy())
                inits = {f: r.joints_mm for f, r in zip(frames, res, strict=True)}
                if change >= bone_tol_mm:
                    continue
                # bones converged: calibrate the surface offsets only now (while the bones are still
                # off, the residuals measure the bones' error, and offsets would absorb it)
                if not calibrate_surface or calibrations >= max_calibrations:
                    break
                corr = surface_correction(
                    anns, dict(zip(frames, res, strict=True)), sk, surface_depth
                )
                calibrations += 1
                if float(np.max(np.abs(corr))) < offset_tol_mm:
                    break
                offsets = np.asarray(sk.surface_offsets_mm) + corr
                sk = dataclasses.replace(sk, surface_offsets_mm=tuple(float(o) for o in offsets))
        res = _final_lifts(
            runner, [anns[f] for f in frames], [shared[f] for f in frames], camera, sk, bones, kw,
            [inits.get(f) for f in frames], progress,
        )  # fmt: skip
        if soft_lengths is not None:
            _mark_stretched(res, soft_lengths, bones, sk, stretch_tolerance)
        _warn_stretched(res)
        results = dict(zip(frames, res, strict=True))
        return LiftSet(
            joints_mm={f: r.joints_mm for f, r in results.items()},
            confidence={f: r.confidence for f, r in results.items()},
            bone_lengths_mm=bones,
            results=results,
            bone_history_mm=history,
            surface_offsets_mm=np.asarray(sk.surface_offsets_mm, dtype=np.float64),
            bone_votes=bmask.sum(axis=0),
            pose_weight=float(kw["w_pose"]),
        )


def _final_lifts(runner, anns, shared, camera, sk, bones, kw, inits, progress) -> list:
    """The references lifted with the final bones (hard bone equalities), each from its last
    soft-bone pose ``inits`` (None: cold) and, where it had one, from the cold start too; the
    better objective is kept."""
    jobs = [(a, dp, camera, sk, bones, dict(kw, init_mm=i)) for a, dp, i in zip(anns, shared, inits, strict=True)]  # fmt: skip
    res = runner.map(_lift_job, jobs, progress)
    if any(i is not None for i in inits):
        # the soft-bone rounds can drift into the mirrored mode of a hidden finger; also solve
        # from the cold start and keep the better objective (one more lift per reference; see
        # benchmarks/results/design_measurements.md)
        cold_jobs = [(a, dp, cm, sk_, b, dict(kw)) for a, dp, cm, sk_, b, _ in jobs]
        cold = runner.map(_lift_job, cold_jobs)
        res = [_better(w, c) for w, c in zip(res, cold, strict=True)]
    return res


def _warn_stretched(res: list) -> None:
    n_stretched = sum(r.stretched for r in res)
    if n_stretched:
        warnings.warn(
            f"lift: {n_stretched} of {len(res)} references only fit by stretching the bone "
            "lengths (LiftResult.stretched); check their 2D annotations",
            stacklevel=3,
        )
