"""Lift one frame: :func:`lift_frame` (hard solve, elastic fallback, confidence)."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from scipy.optimize import minimize

from ..annotation import AnnotationError, FrameAnnotation
from ..blas import single_blas_thread
from ..camera import CameraIntrinsics
from ..pose_prior import PosePrior
from ..pose_prior import pose_prior as packaged_pose_prior
from ..skeleton import Skeleton
from .initial import initial_pose
from .problem import _Problem
from .surface import inclined_joints, inclined_surface_extra_mm, inclined_tips

#: weight (px^2) of the pose prior's energy in ``lift_references``, chosen on the suite's tune part
W_POSE = 0.3

#: 2D weight of an accepted guess relative to a click, about (click spread / accepted spread)^2
#: (the package docstring; 1/4 chosen over 1 and 1/16 on the suite's tune part)
ACCEPTED_UV_WEIGHT = 1.0 / 4.0


# ---------------------------------------------------------------------------------------- results
@dataclass
class LiftResult:
    """One lifted frame.

    joints_mm: ``(J, 3)`` camera frame, mm. confidence: ``(J,)`` in [0, 1] (low for unannotated
    joints and joints without valid depth). reprojection_px: ``(J,)`` distance between the lifted
    joint's projection and its 2D annotation (NaN where there is no 2D). observed_depth_mm: ``(J,)``
    depth ``D_k`` used for the joint's interval (NaN where none). bone_error_mm: largest
    ``| |X_c - X_p| - d_b |`` at the solution. elastic: the frame was solved with L1-penalised
    interval violations and some depth interval is violated by more than 0.5 mm (its observed
    depth is probably wrong: a 2D point off the finger); slack_joints: those joints ``(S,)``.
    stretched: set by :func:`lift_references` when the frame's clicks only fit with some bone
    more than 20 % off the estimated length (then ``converged`` is False).
    """

    joints_mm: np.ndarray
    confidence: np.ndarray
    converged: bool
    iterations: int
    reprojection_px: np.ndarray
    observed_depth_mm: np.ndarray
    bone_error_mm: float
    elastic: bool = False
    slack_joints: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    message: str = ""
    time_s: float = 0.0
    objective: float = float("nan")
    stretched: bool = False
    #: ``(J,)`` mm: how much deeper than ``D + o`` the visible joints' surface target and upper
    #: depth bound were put for their bones' inclination (:mod:`handanno_core.lift.surface`)
    surface_extra_mm: np.ndarray | None = None


# ---------------------------------------------------------------------------------------- lift
def _check_inputs(annotation: FrameAnnotation, skeleton: Skeleton, bone_lengths_mm) -> np.ndarray:
    if not isinstance(annotation, FrameAnnotation):
        raise AnnotationError(f"expected a FrameAnnotation, got {type(annotation).__name__}")
    annotation.validate(skeleton.num_joints)
    d = np.asarray(bone_lengths_mm, dtype=np.float64)
    if d.shape != (len(skeleton.bones),) or not np.all(np.isfinite(d)) or np.any(d <= 0):
        raise ValueError(
            f"bone_lengths_mm must be {len(skeleton.bones)} positive finite lengths, got {d!r}"
        )
    return d


#: scipy SLSQP's exit status "Iteration limit reached"
_SLSQP_ITERATION_LIMIT = 9
#: constraints (bones, rows) met to this (mm) count as met; slacks above it as used
_FEASIBLE_MM = 0.5
#: weight (px^2/mm^2) pulling unannotated joints towards their start (keeps them defined)
_W_FREE = 1e-3

#: how far (mm) a visible joint's centre lies behind ``D + o`` (``D`` the median of the front
#: surface in the 3x3 block, ``o`` the skeleton's offset), per kind of joint: root (wrist),
#: first joints off the root (knuckles, thumb CMC), finger joints, fingertips. Chosen on the
#: suite's tune part: knuckles lie a knuckle radius (~11.5 mm) below the surface against offsets
#: of 8-9 mm; 3 mm for them was best for the lift alone (bench_lift mean of means 1.90 against
#: 1.99 mm at 2 mm), 2 mm end to end (final mean of means, uniform 4.99 against 4.72 mm)
SURFACE_DEPTH_MM = (1.0, 2.0, 1.0, 1.0)


def surface_depths_mm(skeleton: Skeleton, surface_depth_mm) -> np.ndarray:
    """``(J,)`` mm: ``surface_depth_mm`` (a scalar, ``(J,)``, or 4 values for the root, its
    children, the other finger joints and the fingertips, as :data:`SURFACE_DEPTH_MM`) per joint."""
    s = np.asarray(surface_depth_mm, dtype=np.float64)
    if s.ndim == 0 or s.shape == (skeleton.num_joints,):
        return np.broadcast_to(s, (skeleton.num_joints,)).astype(np.float64)
    if s.shape != (4,):
        raise ValueError(f"surface_depth_mm: a scalar, 4 or {skeleton.num_joints} values, got {s}")
    g = skeleton.surface_groups()
    return np.select([g == 0, g == 1, g == -1], [s[0], s[1], s[3]], s[2])


@dataclass(frozen=True)
class WarmStart:
    """How the app's live re-lift starts a solve (none of it is a parameter of the problem).

    ``init_mm``: ``(J, 3)`` mm start pose (NaN rows: the annotation's own start), e.g. the previous
    solution while a joint is dragged. ``start_elastic``: solve the elastic problem first instead of
    only after the hard one failed (a frame whose previous lift needed slack: the hard solve would
    spend its iterations failing again); an elastic solution whose slacks are all zero meets every
    hard constraint and is reported as such (``elastic=False``). ``elastic_joints``: with
    ``start_elastic``, give slacks only to these joints (the previous lift's ``slack_joints``); if
    the other intervals cannot be met either, every joint gets one."""

    init_mm: np.ndarray | None = None
    start_elastic: bool = False
    elastic_joints: np.ndarray | None = None


def lift_frame(
    annotation: FrameAnnotation,
    depth: np.ndarray,
    camera: CameraIntrinsics,
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray,
    *,
    eps_mm: float = 15.0,
    angle_limits: bool = True,
    init_mm: np.ndarray | None = None,
    order_margin_mm: float = 10.0,
    w_3d: float = 1.0,
    w_surface: float = 0.1,
    surface_depth_mm: float | tuple[float, ...] = SURFACE_DEPTH_MM,
    w_flat: float = 0.01,
    w_angle: float = 1.0,
    w_angle_inner: float = 0.0,
    w_pose: float = 0.0,
    pose_prior: PosePrior | None = None,
    depth_near_px: int = 1,
    soft_bones: float | None = None,
    right_hand: bool = True,
    elastic_weight: float = 2.0,
    start_elastic: bool = False,
    elastic_joints: np.ndarray | None = None,
    max_iter: int = 200,
    tol: float = 1e-6,
    warm: WarmStart | None = None,
    incline_surface: bool = True,
    incline_min_sin: float = 0.3,
    incline_radius_factor: float = 0.85,
    incline_tips: bool = True,
    drop_slack_depths: bool = True,
    incline_hidden: bool = True,
    depth_front_band_mm: float | None = 10.0,
    accepted_uv_weight: float = ACCEPTED_UV_WEIGHT,
) -> LiftResult:
    """Lift one annotated frame to 3D (see the module docstring for the problem).

    annotation: the frame's :class:`FrameAnnotation` (J joints; validated, AnnotationError if bad).
    depth: ``(H, W)`` mm, 0 = invalid. bone_lengths_mm: ``(B,)`` mm, bone ``b`` = ``skeleton.bones[b]``.
    eps_mm: width of a visible joint's interval behind ``D + o``. angle_limits: thesis Eq. 5 limits.
    order_margin_mm: depth-order margin. w_3d: weight (px^2 per mm^2) of joints placed in 3D.
    w_surface: weight (px^2/mm^2) of the pull of visible joints towards ``D + o``.
    w_angle: weight (px^2/mm^2) of the soft rows of ``skeleton.angle_ranges()`` (``angle_limits``);
    w_angle_inner: weight of the soft rows of the narrower ``skeleton.angle_limits()``.
    w_pose: weight (px^2) of the pose prior's energy (:mod:`handanno_core.pose_prior`; ``pose_prior``,
    default the packaged one of the layout). Default 0: one frame alone has no session to make the
    prior its own, and the learned prior pulls another person's hand towards the recorded one's
    (the app's pre-fill got worse with it); :func:`lift_references` uses :data:`W_POSE`.
    accepted_uv_weight: the 2D weight of joints whose guess was accepted (``annotation.accepted``)
    relative to clicked ones (:data:`ACCEPTED_UV_WEIGHT`).
    soft_bones: if given, bones are a penalty of this weight (px^2/mm^2) instead of equalities
    (used for bone-length estimation). warm: how the app's live re-lift starts (:class:`WarmStart`);
    ``init_mm``, ``start_elastic`` and ``elastic_joints`` are shorthands for its fields.
    incline_surface: move visible finger joints' surface targets deeper where their bone is
    inclined to the viewing ray and solve again (module docstring; ``incline_min_sin`` caps
    ``1 / sin``, ``incline_radius_factor`` is the finger radius over the surface offset;
    ``incline_tips``: also fingertips whose distal segment leads away from the camera).
    Returns a :class:`LiftResult`.
    """
    t0 = time.perf_counter()
    d = _check_inputs(annotation, skeleton, bone_lengths_mm)
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth.shape}")
    x0_pose, d_obs = initial_pose(
        annotation,
        depth,
        camera,
        skeleton,
        d,
        depth_near_px=depth_near_px,
        front_band_mm=depth_front_band_mm,
    )
    if warm is None:
        warm = WarmStart(init_mm, start_elastic, elastic_joints)
    elif init_mm is not None or start_elastic or elastic_joints is not None:
        raise ValueError("pass the warm start either as warm= or as its fields, not both")
    if warm.init_mm is not None:
        init = np.asarray(warm.init_mm, dtype=np.float64)
        if init.shape != x0_pose.shape:
            raise ValueError(f"init_mm must be {x0_pose.shape}, got {init.shape}")
        x0_pose = np.where(np.isfinite(init), init, x0_pose)
    base = _Problem(
        annotation,
        d_obs,
        camera,
        skeleton,
        d,
        x0_pose,
        eps_mm=eps_mm,
        angle_limits=angle_limits,
        order_margin_mm=order_margin_mm,
        w_3d=w_3d,
        w_surface=w_surface,
        surface_depth_mm=surface_depths_mm(skeleton, surface_depth_mm),
        w_flat=w_flat,
        w_angle=w_angle,
        w_angle_inner=w_angle_inner,
        pose_prior=(
            packaged_pose_prior(skeleton) if pose_prior is None and w_pose > 0 else pose_prior
        ),
        w_pose=w_pose,
        w_free=_W_FREE,
        soft_bones=soft_bones,
        right_hand=right_hand,
        w_accepted=accepted_uv_weight,
    )
    hard_bones = soft_bones is None
    moving = inclined_joints(skeleton) | (inclined_tips(skeleton) if incline_tips else False)
    inclined = incline_surface and bool(
        np.any(moving & (base.surf_mask | (base.hid_mask if incline_hidden else False)))
    )
    extra_of = partial(
        inclined_surface_extra_mm,
        skeleton=skeleton,
        min_sin=incline_min_sin,
        radius_factor=incline_radius_factor,
        tips=incline_tips,
    )
    first = base
    if inclined and warm.init_mm is not None:
        # a warm start is a pose found before (previous round, the joint being dragged): its
        # inclined surfaces are the targets the re-solve below would move to, so start with them
        # and the re-solve is skipped wherever the solution leaves them (nearly) unchanged
        first = base.with_surface_extra(extra_of(x0_pose), incline_hidden)
    res, prob, slack_joints = _lift_attempts(
        first, x0_pose, warm, hard_bones, max_iter, tol, elastic_weight
    )
    if inclined:
        # the surface of a visible finger joint lies deeper where its bone is inclined to the
        # ray: move the targets for the pose found and solve again from it (twice at most)
        for _ in range(2):
            X = prob.pose(res.x)
            extra = extra_of(X)
            change = np.abs(np.where(base.surf_mask, extra - prob.surf_extra, 0.0))
            if incline_hidden:
                change = np.maximum(change, _hidden_bound_change(base, prob, X, extra))
            if float(np.max(change)) < 0.5:
                break
            moved = base.with_surface_extra(extra, incline_hidden)
            again = WarmStart(X, len(slack_joints) > 0, slack_joints if len(slack_joints) else None)
            r2, p2, s2 = _lift_attempts(moved, X, again, hard_bones, max_iter, tol, elastic_weight)
            if not _acceptable(r2, p2, hard_bones) and _acceptable(res, prob, hard_bones):
                break
            res, prob, slack_joints = r2, p2, s2
    if drop_slack_depths and len(slack_joints):
        # readings that no pose meets: the click lies on another surface (a finger in front, the
        # background); their pull (surface term, slackened interval) drags the joint there.
        # Solve again without them; keep that solution where it meets every other constraint
        X = prob.pose(res.x)
        free = base.without_depth(slack_joints).with_surface_extra(
            prob.surf_extra + prob.hid_extra, incline_hidden
        )
        r3, p3, _ = _lift_attempts(free, X, WarmStart(), hard_bones, max_iter, tol, elastic_weight)
        if _acceptable(r3, p3, hard_bones) and not p3.elastic:
            res, prob = r3, p3
    ok = _acceptable(res, prob, soft_bones is None)  # constraints really hold (SLSQP can claim
    # success in elastic mode with violated angle rows; report that as not converged)
    X = prob.pose(res.x)
    proj = camera.project(X)
    reproj = np.where(prob.has2d, np.linalg.norm(proj - prob.uv, axis=1), np.nan)
    bone_err = float(np.max(np.abs(skeleton.bone_lengths(X) - d)))
    conf = _confidence(annotation, d_obs, reproj, ok)
    return LiftResult(
        joints_mm=X,
        confidence=conf,
        converged=ok,
        iterations=int(res.nit),
        reprojection_px=reproj,
        observed_depth_mm=np.where(prob.has2d, d_obs, np.nan),
        bone_error_mm=bone_err,
        elastic=len(slack_joints) > 0,
        slack_joints=slack_joints,
        message=str(res.message),
        time_s=time.perf_counter() - t0,
        objective=float(res.fun),
        surface_extra_mm=prob.surf_extra.copy(),
    )


def _hidden_bound_change(
    base: _Problem, prob: _Problem, X: np.ndarray, extra: np.ndarray
) -> np.ndarray:
    """``(J,)`` mm by which moving the hidden joints' lower depth bounds to ``extra`` (J,) mm (for
    the pose ``X`` (J, 3) mm solved with ``prob``'s bounds) would change the solution's
    constraints: the new bound's violation, or how far an active bound would be released."""
    h = base.hid_mask  # (joints with a reading: finite bounds)
    out = np.zeros(len(h))
    new_lo = base.z_lo[h] + np.maximum(extra[h], 0.0)
    z = X[h, 2]
    violated = np.maximum(new_lo - z, 0.0)
    released = np.where(z - prob.z_lo[h] < 0.5, np.maximum(prob.z_lo[h] - new_lo, 0.0), 0.0)
    out[h] = np.maximum(violated, released)
    return out


def _lift_attempts(
    base: _Problem,
    x0_pose: np.ndarray,
    warm: WarmStart,
    hard_bones: bool,
    max_iter: int,
    tol: float,
    elastic_weight: float,
):
    """Solve ``base`` hard from ``x0_pose`` and, if that is infeasible or fails, elastically
    (see the module docstring). Returns ``(scipy result, problem solved, slack joints (S,))``."""
    # start inside the depth bounds
    z0 = np.clip(x0_pose[:, 2], base.z_lo, base.z_hi)
    solve = partial(_solve_from, base, x0_pose, z0, hard_bones, max_iter, tol)
    res, prob = (None, base) if warm.start_elastic else solve()
    slack_joints = np.zeros(0, dtype=np.int64)
    if res is None or not (
        _acceptable(res, prob, hard_bones)
        # a feasible iterate that only ran out of iterations is kept: elastic mode is for
        # infeasibility, and re-solving would spend as many iterations again
        or (res.status == _SLSQP_ITERATION_LIMIT and _feasible(res, prob, hard_bones))
    ):
        # infeasible or failed: the observed depth under some joint is probably wrong (2D on
        # the wrong surface). Re-solve in elastic mode from the original start.
        res2 = None
        if warm.start_elastic and warm.elastic_joints is not None and len(warm.elastic_joints):
            res2, prob2 = solve(elastic=elastic_weight, joints=warm.elastic_joints)
            if not _feasible(res2, prob2, hard_bones):
                res2 = None  # another interval cannot be met either: relax them all
        if res2 is None:
            res2, prob2 = solve(elastic=elastic_weight)
        if np.all(np.isfinite(res2.x)):
            res, prob = res2, prob2
            slack_joints = prob.el_joints[prob.slacks_mm(res.x) > _FEASIBLE_MM]
        elif res is None:
            res, prob = solve()
    return res, prob, slack_joints


def _solve_from(
    base: _Problem,
    x0_pose: np.ndarray,
    z0: np.ndarray,
    hard_bones: bool,
    max_iter: int,
    tol: float,
    elastic: float | None = None,
    joints: np.ndarray | None = None,
):
    """Solve ``base`` from ``x0_pose`` (joints without a slack moved inside their interval,
    ``z0``): with hard depth intervals, or in elastic mode (slack weight ``elastic``) with slacks
    on the intervals of ``joints`` (all when None). Returns ``(scipy result, problem solved)``."""
    if elastic is None:
        prob = base.with_start(x0_pose, z0)
    else:
        prob = base.with_start(x0_pose, z0, elastic=True, weight=elastic, joints=joints)
    return _solve(prob, hard_bones, max_iter, tol), prob


def _solve(prob: _Problem, hard_bones: bool, max_iter: int, tol: float):
    constraints = []
    if hard_bones:
        constraints.append({"type": "eq", "fun": prob.eq, "jac": prob.eq_jac})
    if prob.num_ineq():
        constraints.append({"type": "ineq", "fun": prob.ineq, "jac": prob.ineq_jac})
    with warnings.catch_warnings(), single_blas_thread():
        warnings.simplefilter("ignore", RuntimeWarning)
        return minimize(
            prob.objective,
            np.zeros(prob.n_var),
            jac=True,
            method="SLSQP",
            bounds=prob.bounds(),
            constraints=constraints,
            options={"maxiter": max_iter, "ftol": tol},
            callback=None if prob.elastic else _StallGuard(prob, hard_bones),
        )


class _StallGuard:
    """SLSQP callback that stops a hard solve whose constraint violation is stuck.

    On an infeasible frame SLSQP's linearised subproblems are inconsistent and the iterate stops
    moving: the violation stays at its first value until the iteration limit, time wasted before
    the elastic re-solve, while feasible solves reduce it below 5 mm within a few iterations
    (figures: ``benchmarks/results/design_measurements.md``). A violation above ``min_mm`` that has not
    dropped by 1 % over ``window`` iterations ends the solve (scipy's StopIteration protocol).
    """

    def __init__(self, prob: _Problem, hard_bones: bool, window: int = 4, min_mm: float = 5.0):
        self.prob, self.hard_bones = prob, hard_bones
        self.window, self.min_mm = window, min_mm
        self.history: list[float] = []

    def __call__(self, intermediate_result) -> None:
        v = _violation_mm(self.prob, intermediate_result.x, self.hard_bones)
        self.history.append(v)
        if len(self.history) > self.window and v > self.min_mm:
            before = self.history[-1 - self.window]
            if before - v < 0.01 * before:
                raise StopIteration


def _violation_mm(prob: _Problem, x: np.ndarray, hard_bones: bool) -> float:
    """Largest violation (mm) of the bone equalities and inequality rows at ``x`` (inf if NaN)."""
    if not np.all(np.isfinite(x)):
        return float("inf")
    # eq/ineq are cached per x: the SLSQP callback and the acceptance test reuse the solver's values
    v = float(np.max(np.abs(prob.eq(x)))) if hard_bones else 0.0
    if prob.num_ineq():
        v = max(v, -float(np.min(prob.ineq(x))))
    return v


def _feasible(res, prob: _Problem, hard_bones: bool) -> bool:
    """Bones and inequality rows hold to 0.5 mm at ``res.x`` (bounds hold by construction)."""
    return _violation_mm(prob, res.x, hard_bones) <= _FEASIBLE_MM


def _acceptable(res, prob: _Problem, hard_bones: bool) -> bool:
    """Feasible and SLSQP reports convergence."""
    return _feasible(res, prob, hard_bones) and bool(res.success)


def _confidence(
    ann: FrameAnnotation, d_obs: np.ndarray, reproj: np.ndarray, converged: bool
) -> np.ndarray:
    """Heuristic per-joint confidence in [0, 1].

    1.0 for a visible joint with 2D and valid depth, 0.8 if occluded, 0.5 with 2D but no valid
    depth, 0.9 for a joint placed in 3D, 0.2 for an unannotated joint; times
    ``exp(-(reprojection / 5 px)^2)`` and 0.5 when SLSQP did not converge.
    """
    has2d, has3d = ann.has_2d, ann.has_3d
    c = np.full(len(has2d), 0.2)
    c[has3d] = 0.9
    c[has2d & np.isfinite(d_obs) & ann.visible] = 1.0
    c[has2d & np.isfinite(d_obs) & ~ann.visible] = 0.8
    c[has2d & ~np.isfinite(d_obs)] = 0.5
    r = np.where(np.isfinite(reproj), reproj, 0.0)
    c = c * np.exp(-((r / 5.0) ** 2))
    if not converged:
        c *= 0.5
    return c
