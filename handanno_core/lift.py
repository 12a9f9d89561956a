"""Lift annotated reference frames from 2D to 3D (thesis Eq. 3), and estimate the bone lengths.

For one frame, :func:`lift_frame` solves, with SLSQP and analytic gradients/Jacobians,

    min_X  1/2 sum_k |pi(X_k) - uv_k|^2                       (px^2, joints with 2D)
         + 1/2 w_3d   sum_k |X_k - xyz_k|^2                    (px^2/mm^2 * mm^2, joints placed in 3D)
         + 1/2 w_surf sum_k (z_k - D_k - o_k - s)^2            (visible joints with depth)
         + 1/2 w_flat sum_k (z_k - z_parent)^2                 (hidden joints, no depth order)
         + 1/2 w_free sum_k |X_k - X0_k|^2                     (unannotated joints only)
         + 1/2 w_angle sum_r min(g_r(X), 0)^2                  (angle-range rows, mm; soft)
    s.t.   |X_c - X_p| = d_b                                   (bones, equality, mm)
           D_k + o_k <= z_k <= D_k + o_k + eps                 (visible joints with valid depth; bounds)
           D_k + o_k <= z_k                                    (occluded joints with valid depth; bounds)
           sigma_k (z_k - z_parent) >= margin                  (annotated depth order, sigma = +-1)

``D_k`` is the observed depth at the joint's 2D position (nearest valid pixel in a small window)
and ``o_k`` the skeleton's surface offset (about the finger radius, 0 at the tips).

Why the surface term: with exact 2D the one-sided depth intervals leave the whole hand free to
slide up to ``eps`` along the viewing rays, and with noisy 2D a foreshortened bone turns a pixel of
noise into centimetres of depth. The pull towards ``D_k + o_k + s`` (``w_surface`` = 0.1 px^2/mm^2,
``surface_depth_mm`` s = 3 mm: the 3x3 closest-surface reading lies that much in front of the
offset surface, median measured on the synthetic sequence) fixes visible joints near where joint
centres of a hand seen from the front lie. Hidden joints without a depth order only have a lower
bound; where the two mirror poses of a hidden finger both fit the 2D (bones nearly parallel to the
image), ``w_flat`` (0.01 px^2/mm^2) prefers the one closer to the parent's depth. Measured on 152
synthetic references (estimated bones): exact 2D, worst joint 20 -> 10 mm, mean 1.63 -> 1.68 mm;
2 px noise, mean 4.91 -> 4.87 mm.

Observed depths that no pose can meet (a visible bone whose two readings differ by more than its
length + eps) are dropped before solving: a 2D point that slips off a thin finger reads the
surface behind it, or the finger in front of it (see :func:`initial_pose`).

Joint angles follow ``skeleton.joint_angles`` exactly (same palm normal, same frame: lateral axis
from the palm normal at a finger's first joint, transported along the chain after that). The
ranges are ``skeleton.angle_ranges()``: the anatomical limits widened to what real hands were
recorded doing (robust percentiles over FPHA / NYU / ICVL motion, ``data/angle_ranges.json``).
They are *soft*: a row ``g_r >= 0`` holds inside the range, and beyond it the penalty
``w_angle/2 g_r^2`` (``g_r`` ~ bone length x sin(excess angle), mm) grows quadratically instead of a
hard wall (real hands exceed any fixed limits now and then; a wall turns that into a wrong pose
elsewhere). A flexion range of 170 degrees or more has no rows (no limit). The rows are linear in
the outgoing bone ``b`` for a fixed local frame (``a_hat``, ``n_perp``, ``lateral``):

* flexion >= fmin:  cos(fmin) b.n_perp - sin(fmin) b.a_hat >= 0   (a half-plane; range < 180 deg)
* flexion <= fmax:  sin(fmax) b.a_hat - cos(fmax) b.n_perp >= 0
* abduction in [amin, amax]:  |b| sin(amin) <= b.lateral <= |b| sin(amax)

The frame depends on the incoming bones of the chain and on the palm normal; all are
differentiated exactly (no lagged frame).

If the hard problem is infeasible or SLSQP fails (typically a 2D point on the wrong surface, so
its observed depth is wrong), the frame is re-solved in *elastic mode*: each depth interval gets a
slack with an L1 cost (an exact penalty: intervals that can be met are met). A result whose bone or
order constraints are still violated by more than 0.5 mm is returned with
``converged=False`` and halved confidence. An infeasible hard solve is recognised early: its
constraint violation stays stuck at its first value, and a callback stops it once the violation
(> 5 mm) has not dropped for 4 iterations instead of letting it run to the iteration limit
(measured: 2 px noisy references lift 20 % faster, same errors). A feasible iterate that merely ran
out of iterations is kept (not re-solved). The app's live re-lift passes ``start_elastic`` for a
frame whose previous lift needed slack, skipping the hard attempt altogether, and
``elastic_joints`` = the joints that needed it, so only those get slack variables (the others keep
hard bounds; ~15 ms instead of ~45 ms per solve, same solution where the guess is right, and a
fallback to slacks on every joint where it is not).

Speed notes: scipy's SLSQP calls LAPACK; with a multithreaded OpenBLAS on a loaded machine each call
can be 50x slower, so every solve runs inside :func:`handanno_core.blas.single_blas_thread`.
Variables are offsets from the initial pose, scaled per axis (1.5 mm units in x/y ~ 1 px, 10 mm
in z) so SLSQP's identity start Hessian is about right; constraints are in mm. The angle-limit
Jacobian is vectorized over fingers (one batch per chain level).

Bone lengths (:func:`lift_references`) are unknown in advance. They start from the skeleton's
template scaled to the annotated frames and are re-estimated from all lifted references: each
round lifts every reference with *soft* bones (a penalty towards the current estimate instead of
hard equalities), so a frame whose 2D/depth evidence cannot be met with the current length
stretches or shrinks the bone; the new estimate is the median over frames where both of the
bone's joints are annotated (at least ``min_bone_votes`` references; a bone with fewer keeps the
template times the global scale of the re-estimated bones, so a partially annotated hand of any
size gets all its bones). Rounds stop when no bone moves by more than 0.1 mm; a final lift uses
the estimate as hard constraints, from both the last soft solution and the cold start, keeping
the lower objective (the soft rounds can drift into the mirrored mode of a hidden finger).

Surface offsets are self-calibrated per session (:func:`surface_correction`): once the bones have
converged, the median over annotated visible joints of ``z_lifted - (D + o + s)`` per joint group
(same level along the chains) corrects that group's offset, and the rounds continue with the
corrected offsets (at most ``max_calibrations`` times). Fingertips are the anchor and are not
corrected: from 2D and depth alone, moving every joint deeper below the surface is the same as a
larger hand farther away (an exact scale ambiguity of the projection), so only the *relative*
depth of joint groups (a wrist or palm joint deeper inside the hand than the default, as on NYU)
is recoverable this way. The offsets used are returned in ``LiftSet.surface_offsets_mm``.

A reference whose own soft-bone lift wants an annotated bone more than 20 % (and 3 mm, and 4 robust
standard deviations of the bone's spread over the references) longer or shorter than the final
estimate is reported ``stretched`` and not ``converged`` (with a warning):
the template could only be fitted to its clicks by stretching it.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

from .annotation import AnnotationError, FrameAnnotation
from .blas import single_blas_thread
from .camera import CameraIntrinsics
from .parallel import Runner
from .skeleton import Skeleton

__all__ = [
    "LiftResult",
    "LiftSet",
    "initial_pose",
    "lift_frame",
    "lift_references",
    "observed_depth",
    "surface_correction",
    "AnnotationError",
]

# Variable scaling (measured): SLSQP starts its quasi-Newton Hessian at the identity, so each
# unit should move the objective by about the same amount. 1 px of reprojection is ~1.5 mm
# laterally at hand distance (f = 241 px, z = 350 mm), while depth is only weakly determined
# (bones, surface tie-breaker) and gets 10 mm units. This halved SLSQP iterations (50 -> 26)
# compared with uniform 10 mm units.
_SCALE_XY = 1.5  # mm per optimisation unit, x and y
_SCALE_Z = 10.0  # mm per optimisation unit, z (and elastic slacks)


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


# ---------------------------------------------------------------------------------------- depth
def observed_depth(
    depth_mm: np.ndarray, uv_px: np.ndarray, window: int = 3, near_px: int = 1
) -> np.ndarray:
    """Observed depth ``(J,)`` mm under 2D points ``(J, 2)``: the closest valid surface in the 3x3
    pixels around the rounded point (robust to sensor dropout at silhouette edges, and the same
    test the simulated annotator uses for visibility); if none, the nearest valid pixel within
    ``window`` px. NaN where none. ``near_px`` is the half-size of the block that counts as
    distance 0 (1 = 3x3; 2 = 5x5 tolerates 2D points a pixel or two off a thin finger, which would
    otherwise read the surface behind it)."""
    depth = np.asarray(depth_mm)
    h, w = depth.shape
    uv = np.asarray(uv_px, dtype=np.float64)
    out = np.full(len(uv), np.nan)
    ok = np.all(np.isfinite(uv), axis=1)
    if not np.any(ok):
        return out
    window = max(window, near_px)
    r = np.arange(-window, window + 1)
    dv, du = np.meshgrid(r, r, indexing="ij")
    dist2 = (du**2 + dv**2).ravel().astype(np.float64)
    cu = np.rint(uv[ok, 0]).astype(np.int64)
    cv = np.rint(uv[ok, 1]).astype(np.int64)
    uu = cu[:, None] + du.ravel()[None, :]
    vv = cv[:, None] + dv.ravel()[None, :]
    inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
    vals = np.zeros(uu.shape, dtype=np.float64)
    vals[inside] = depth[vv[inside], uu[inside]]
    valid = inside & np.isfinite(vals) & (vals > 0)
    # nearest valid pixel; among equally near ones the closer surface (depth breaks ties)
    cheb = np.maximum(np.abs(du), np.abs(dv)).ravel()
    ring = np.where(cheb <= near_px, 0.0, dist2)  # the (2 near_px + 1)^2 block is distance 0
    key = np.where(valid, ring[None, :] * 1e6 + vals, np.inf)
    best = np.argmin(key, axis=1)
    found = np.isfinite(key[np.arange(len(best)), best])
    res = np.where(found, vals[np.arange(len(best)), best], np.nan)
    out[np.flatnonzero(ok)] = res
    return out


def _drop_inconsistent_depths(
    d_obs: np.ndarray,
    visible: np.ndarray,
    offsets: np.ndarray,
    skeleton: Skeleton,
    lengths: np.ndarray,
    slack_mm: float,
) -> np.ndarray:
    """``d_obs`` ``(J,)`` with the wrong-looking readings of impossible visible bones set to NaN
    (rules in :func:`initial_pose`). Loops over the (few) inconsistent bones only."""
    z = d_obs + offsets
    p, c = skeleton.bones[:, 0], skeleton.bones[:, 1]
    ok = visible[p] & visible[c] & np.isfinite(z[p]) & np.isfinite(z[c])
    gap = np.where(ok, z[c] - z[p], 0.0)
    bad = np.abs(gap) > lengths + slack_mm
    if not np.any(bad):
        return d_obs
    # a reading that agrees with another visible neighbour is trusted; with no such support on
    # either side both readings are dropped; with support on both, the farther one goes
    fine = ok & ~bad
    support = np.bincount(p[fine], minlength=len(z)) + np.bincount(c[fine], minlength=len(z))
    out = d_obs.copy()
    for pp, cc, g in zip(p[bad], c[bad], gap[bad], strict=True):
        sp, sc = support[pp] > 0, support[cc] > 0
        if sp and not sc:
            out[cc] = np.nan
        elif sc and not sp:
            out[pp] = np.nan
        elif sp and sc:
            out[cc if g > 0 else pp] = np.nan
        else:
            out[[pp, cc]] = np.nan
    return out


def _template_direction(skeleton: Skeleton, joint: int, pose: np.ndarray) -> np.ndarray:
    p = skeleton.parent_array[joint]
    pp = skeleton.parent_array[p] if p >= 0 else -1
    if pp >= 0:
        d = pose[p] - pose[pp]
    else:
        d = np.nanmean(pose, axis=0) - pose[p] if np.isfinite(pose).any() else np.zeros(3)
        if not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-6:
            d = np.array([0.0, -1.0, 0.0])
    n = np.linalg.norm(d)
    return d / n if n > 1e-9 else np.array([0.0, -1.0, 0.0])


def initial_pose(
    annotation: FrameAnnotation,
    depth_mm: np.ndarray,
    camera: CameraIntrinsics,
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray | None = None,
    depth_near_px: int = 1,
    depth_check_mm: float | None = 15.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Initial joints ``(J, 3)`` mm and observed depths ``(J,)`` mm for a frame.

    Observed depths that no pose with these bone lengths can meet are dropped (NaN): for a bone
    whose both joints are visible, ``|(D_c + o_c) - (D_p + o_p)| > d_b + depth_check_mm`` means one
    reading is wrong (synthetic sequence, 2 px noise: a thumb tip reading the palm 90 mm behind, an
    index DIP reading a finger 100 mm in front). A reading backed by another consistent visible
    bone is kept and the other dropped; with no backing on either side both are dropped; with
    backing on both, the farther one. ``depth_check_mm=None`` disables the check.

    Joints with 2D are back-projected at the observed depth plus their surface offset (the median
    of the other joints' depths where there is no valid depth); joints placed in 3D start there;
    unannotated joints are hung off their parent along the parent bone's direction.
    """
    ann = annotation
    j = skeleton.num_joints
    offsets = np.asarray(skeleton.surface_offsets_mm, dtype=np.float64)
    d_obs = observed_depth(depth_mm, ann.uv_px, near_px=depth_near_px)
    has2d = ann.has_2d
    has3d = ann.has_3d
    lengths = (
        np.asarray(bone_lengths_mm, dtype=np.float64)
        if bone_lengths_mm is not None
        else np.asarray(skeleton.template_bone_lengths_mm or [40.0] * (j - 1), dtype=np.float64)
    )
    if depth_check_mm is not None:
        d_obs = _drop_inconsistent_depths(
            d_obs, ann.visible & has2d, offsets, skeleton, lengths, depth_check_mm
        )
    z = d_obs + offsets
    known = np.isfinite(z) & has2d
    ref_depths = np.concatenate([z[known], ann.xyz_mm[has3d, 2]])
    if len(ref_depths) == 0:
        valid = depth_mm[(depth_mm > 0) & np.isfinite(depth_mm)]
        ref_depths = np.array([np.median(valid)]) if valid.size else np.array([400.0])
    zmed = float(np.median(ref_depths))
    z = np.where(np.isfinite(z), z, zmed)
    # occluded joints: behind the occluder, at least near the hand's median depth
    z = np.where(has2d & ~ann.visible, np.maximum(z, zmed), z)
    pose = np.full((j, 3), np.nan)
    pose[has2d] = camera.backproject(ann.uv_px[has2d], z[has2d])
    pose[has3d] = ann.xyz_mm[has3d]
    lengths = (
        np.asarray(bone_lengths_mm, dtype=np.float64)
        if bone_lengths_mm is not None
        else np.asarray(skeleton.template_bone_lengths_mm or [40.0] * (j - 1), dtype=np.float64)
    )
    bone_of_child = np.full(j, -1)
    bone_of_child[skeleton.bones[:, 1]] = np.arange(len(skeleton.bones))
    order = skeleton.topological_order
    root = skeleton.root
    if not np.all(np.isfinite(pose[root])):
        pose[root] = (
            np.nanmean(pose, axis=0)
            if np.isfinite(pose).any()
            else camera.backproject(np.array([camera.cx, camera.cy]), np.array(zmed))
        )
    par = skeleton.parent_array
    for k in order:
        if k == root:
            continue
        p = par[k]
        length = lengths[bone_of_child[k]]
        if has3d[k]:
            continue
        if not has2d[k]:
            pose[k] = pose[p] + length * _template_direction(skeleton, k, pose)
            continue
        # on the joint's viewing ray at bone length from the (already placed) parent
        ray = np.array(
            [
                (ann.uv_px[k, 0] - camera.cx) / camera.fx,
                (ann.uv_px[k, 1] - camera.cy) / camera.fy,
                1.0,
            ]
        )
        ray /= np.linalg.norm(ray)
        rp = float(ray @ pose[p])
        disc = rp**2 - float(pose[p] @ pose[p]) + length**2
        if disc < 0:
            t = rp
        else:
            cands = np.array([rp - np.sqrt(disc), rp + np.sqrt(disc)])
            zc = cands * ray[2]
            order_k = int(ann.depth_order[k])
            ok = np.ones(2, dtype=bool)
            if order_k != 0:
                ok = order_k * (zc - pose[p, 2]) > 0
                if not ok.any():
                    ok[:] = True
            zt = z[k]
            if not ann.visible[k]:
                # hidden joint: its observed depth is only a lower bound (the occluder). Of the
                # two ray intersections take the one nearer the parent's depth (behind the
                # occluder): measured to avoid fingers folded towards the camera behind a palm
                zt = max(pose[p, 2], d_obs[k] + offsets[k] if np.isfinite(d_obs[k]) else -np.inf)
            cost = np.where(ok, np.abs(zc - zt), np.inf)
            t = float(cands[np.argmin(cost)])
        if t * ray[2] > 1.0:
            pose[k] = t * ray
    return pose, d_obs


# ---------------------------------------------------------------------------------------- problem
def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]_x`` with ``[v]_x y = v x y``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of ``(..., 3)`` arrays (np.cross has a large per-call overhead)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


class _Problem:
    """Objective, constraints and their analytic derivatives for one frame (vectorized)."""

    def __init__(
        self,
        annotation: FrameAnnotation,
        d_obs: np.ndarray,
        camera: CameraIntrinsics,
        skeleton: Skeleton,
        bone_lengths_mm: np.ndarray,
        x0_mm: np.ndarray,
        *,
        eps_mm: float,
        angle_limits: bool,
        order_margin_mm: float,
        w_3d: float,
        w_surface: float,
        surface_depth_mm: float = 0.0,
        w_flat: float = 0.0,
        w_free: float,
        soft_bones: float | None,
        right_hand: bool,
        w_angle: float = 1.0,
        w_angle_inner: float = 0.0,
    ):
        self.cam = camera
        self.sk = skeleton
        self.j = skeleton.num_joints
        self.x0 = np.asarray(x0_mm, dtype=np.float64)
        self.bones = skeleton.bones
        self.d = np.asarray(bone_lengths_mm, dtype=np.float64)
        self.soft = soft_bones
        ann = annotation
        self.has2d = ann.has_2d
        self.uv = np.where(self.has2d[:, None], ann.uv_px, 0.0)
        self.has3d = ann.has_3d
        self.xyz = np.where(self.has3d[:, None], ann.xyz_mm, 0.0)
        self.w_3d = w_3d
        self.free = ~(self.has2d | self.has3d)
        self.w_free = w_free
        offsets = np.asarray(skeleton.surface_offsets_mm, dtype=np.float64)
        valid_d = np.isfinite(d_obs) & self.has2d
        lo = np.where(valid_d, d_obs + offsets, -np.inf)
        hi = np.where(valid_d & ann.visible, d_obs + offsets + eps_mm, np.inf)
        self.z_lo, self.z_hi = lo, hi
        self.surf_mask = valid_d & ann.visible
        self.surf_target = np.where(self.surf_mask, lo + surface_depth_mm, 0.0)
        self.w_surface = w_surface
        # hidden joints without a depth order: weak pull towards the parent's depth
        par_all = skeleton.parent_array
        fm = self.has2d & ~ann.visible & (np.asarray(ann.depth_order) == 0) & (par_all >= 0)
        self.flat_k = np.flatnonzero(fm)
        self.flat_p = par_all[self.flat_k]
        self.w_flat = w_flat
        # depth order rows
        par = skeleton.parent_array
        sel = (np.asarray(ann.depth_order) != 0) & (par >= 0)
        self.ord_k = np.flatnonzero(sel)
        self.ord_p = par[self.ord_k]
        self.ord_s = np.asarray(ann.depth_order, dtype=np.float64)[self.ord_k]
        self.margin = order_margin_mm
        # angle rows
        self.use_angles = (
            bool(angle_limits)
            and skeleton.palm_joints is not None
            and len(skeleton.angle_joints) > 0
        )
        if self.use_angles:
            k = skeleton.angle_joints
            self.ak = k
            self.ap = par[k]
            self.ac = skeleton.angle_children
            # soft rows beyond the range real hands were recorded in (weight w_angle) and,
            # optionally, a second tier beyond the narrower anatomical limits (w_angle_inner;
            # default 0: chosen on the tune set, synthetic seed 1 + FPHA Subject_1 mean)
            tiers = [(skeleton.angle_ranges(right_hand), w_angle)]
            lim = skeleton.angle_limits()
            if not right_hand:
                lim = (lim[0], -lim[1][:, ::-1])
            if w_angle_inner > 0 and not all(
                np.array_equal(a, b) for a, b in zip(lim, tiers[0][0], strict=True)
            ):
                tiers.append((lim, w_angle_inner))
            coef, weights = [], []
            for (fl, ab), w in tiers:
                # a flexion range of 170 deg or more is no limit (the two half-plane rows can
                # only express ranges under 180 deg): its rows are switched off
                on = (np.ptp(fl, axis=1) < 170.0).astype(np.float64)
                fl, ab = np.radians(fl), np.radians(ab)
                coef.append(
                    np.stack(
                        [
                            on * np.cos(fl[:, 0]),
                            on * np.sin(fl[:, 0]),
                            on * np.cos(fl[:, 1]),
                            on * np.sin(fl[:, 1]),
                            np.sin(ab[:, 0]),
                            np.sin(ab[:, 1]),
                        ]
                    )
                )
                weights.append(np.full(4 * len(k), w))
            self.angle_coef = coef  # per tier (6, A): cos/sin fmin, cos/sin fmax, sin amin/amax
            self.angle_row_w = np.concatenate(weights)
            self.palm = skeleton.palm_joints
            self.hand_sign = 1.0 if right_hand else -1.0
            self._setup_angle_levels()
        self.nfev = 0
        self.sc3 = np.array([_SCALE_XY, _SCALE_XY, _SCALE_Z])
        self._cache: dict = {}
        self.elastic = False
        self.iv_lo = np.flatnonzero(np.isfinite(lo))  # joints with a lower / upper depth bound
        self.iv_hi = np.flatnonzero(np.isfinite(hi))
        self.w_elastic = 1.0
        self.set_elastic(False)

    def set_elastic(self, on: bool, weight: float = 1.0, joints: np.ndarray | None = None) -> None:
        """Elastic mode: depth intervals become ``z >= lo - s``, ``z <= hi + s`` with slacks
        ``s >= 0`` (one per joint with an interval) costing ``weight`` px^2 per mm (exact L1
        penalty: intervals that can be met are met exactly). ``joints``: only these joints get
        slacks, the others keep their hard bounds (fewer variables and rows: measured 2.5x faster
        per SLSQP iteration with one slack instead of 21)."""
        self.elastic = on
        self.w_elastic = weight
        keep = np.arange(self.j) if joints is None else np.asarray(joints, dtype=np.int64).ravel()
        self.el_lo = np.intersect1d(self.iv_lo, keep) if on else np.zeros(0, dtype=np.int64)
        self.el_hi = np.intersect1d(self.iv_hi, keep) if on else np.zeros(0, dtype=np.int64)
        self.el_joints = np.union1d(self.el_lo, self.el_hi)
        self.slot = np.full(self.j, -1)
        self.slot[self.el_joints] = np.arange(len(self.el_joints))

    def slacks_mm(self, x: np.ndarray) -> np.ndarray:
        """``(S,)`` mm: the elastic slacks at ``x`` (empty outside elastic mode)."""
        return _SCALE_Z * np.asarray(x[3 * self.j : 3 * self.j + self.n_slack])

    @property
    def n_slack(self) -> int:
        return len(self.el_joints) if self.elastic else 0

    @property
    def n_var(self) -> int:
        return 3 * self.j + self.n_slack

    # -- variables: x (3J [+ S],) = (X - x0) / 1 cm [, slacks / 1 cm]
    def pose(self, x: np.ndarray) -> np.ndarray:
        return self.x0 + self.sc3 * x[: 3 * self.j].reshape(self.j, 3)

    def bounds(self, trust_mm: float = 150.0) -> list[tuple[float | None, float | None]]:
        txy, tz = trust_mm / _SCALE_XY, trust_mm / _SCALE_Z
        b: list[tuple[float | None, float | None]] = []
        for k in range(self.j):
            b.append((-txy, txy))
            b.append((-txy, txy))
            lo, hi = -tz, tz
            if self.slot[k] < 0:  # no slack: the depth interval is a hard bound
                if np.isfinite(self.z_lo[k]):
                    lo = max(lo, (self.z_lo[k] - self.x0[k, 2]) / _SCALE_Z)
                if np.isfinite(self.z_hi[k]):
                    hi = min(hi, (self.z_hi[k] - self.x0[k, 2]) / _SCALE_Z)
                hi = max(hi, lo)
            b.append((lo, hi))
        b.extend([(0.0, tz)] * self.n_slack)
        return b

    # -- objective
    def objective(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        self.nfev += 1
        X = self.pose(x)
        g = np.zeros((self.j, 3))
        f = 0.0
        m = self.has2d
        if np.any(m):
            Xm = X[m]
            z = np.maximum(Xm[:, 2], 1e-3)
            u = self.cam.fx * Xm[:, 0] / z + self.cam.cx
            v = self.cam.fy * Xm[:, 1] / z + self.cam.cy
            ru = u - self.uv[m, 0]
            rv = v - self.uv[m, 1]
            f += 0.5 * float(np.sum(ru**2 + rv**2))
            gx = ru * self.cam.fx / z
            gy = rv * self.cam.fy / z
            gz = -(ru * (u - self.cam.cx) + rv * (v - self.cam.cy)) / z
            g[m] += np.stack([gx, gy, gz], axis=1)
        if np.any(self.has3d):
            r = (X - self.xyz)[self.has3d]
            f += 0.5 * self.w_3d * float(np.sum(r**2))
            g[self.has3d] += self.w_3d * r
        if np.any(self.surf_mask) and self.w_surface > 0:
            r = (X[:, 2] - self.surf_target)[self.surf_mask]
            f += 0.5 * self.w_surface * float(np.sum(r**2))
            g[self.surf_mask, 2] += self.w_surface * r
        if len(self.flat_k) and self.w_flat > 0:
            r = X[self.flat_k, 2] - X[self.flat_p, 2]
            f += 0.5 * self.w_flat * float(np.sum(r**2))
            np.add.at(g[:, 2], self.flat_k, self.w_flat * r)
            np.add.at(g[:, 2], self.flat_p, -self.w_flat * r)
        if np.any(self.free) and self.w_free > 0:
            r = (X - self.x0)[self.free]
            f += 0.5 * self.w_free * float(np.sum(r**2))
            g[self.free] += self.w_free * r
        if self.soft is not None:
            c, jac = self._bone_eq(X)
            f += 0.5 * self.soft * float(np.sum(c**2))
            g += self.soft * np.einsum("b,bjk->jk", c, jac)
        if self.use_angles:
            v, jac = self._angles(X)
            short = np.minimum(v, 0.0)  # mm beyond the range (rows are >= 0 inside)
            f += 0.5 * float(np.sum(self.angle_row_w * short**2))
            g += np.einsum("r,rjk->jk", self.angle_row_w * short, jac)
        grad = (self.sc3 * g).ravel()
        if self.elastic:
            sl = x[3 * self.j :]
            f += self.w_elastic * _SCALE_Z * float(np.sum(sl))
            grad = np.concatenate([grad, np.full(len(sl), self.w_elastic * _SCALE_Z)])
        return f, grad

    # -- constraints (in mm), Jacobians w.r.t. joints (rows, J, 3)
    def _bone_eq(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, c = self.bones[:, 0], self.bones[:, 1]
        v = X[c] - X[p]
        n = np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        jac = np.zeros((len(p), self.j, 3))
        rows = np.arange(len(p))
        unit = v / n[:, None]
        jac[rows, c] = unit
        jac[rows, p] -= unit
        return n - self.d, jac

    def _cached(self, name: str, x: np.ndarray):
        """SLSQP asks for a constraint and its Jacobian at the same x: evaluate once."""
        hit = self._cache.get(name)
        if hit is not None and np.array_equal(hit[0], x):
            return hit[1]
        X = self.pose(x)
        val = self._bone_eq(X) if name == "eq" else self._ineq(X)
        self._cache[name] = (x.copy(), val)
        return val

    def eq(self, x: np.ndarray) -> np.ndarray:
        return self._cached("eq", x)[0]

    def eq_jac(self, x: np.ndarray) -> np.ndarray:
        jac = (self._cached("eq", x)[1] * self.sc3).reshape(len(self.d), -1)
        if self.n_slack:
            jac = np.hstack([jac, np.zeros((len(jac), self.n_slack))])
        return jac

    def _ineq(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        vals = []
        jacs = []
        if len(self.ord_k):
            r = len(self.ord_k)
            val = self.ord_s * (X[self.ord_k, 2] - X[self.ord_p, 2]) - self.margin
            jac = np.zeros((r, self.j, 3))
            rows = np.arange(r)
            jac[rows, self.ord_k, 2] = self.ord_s
            jac[rows, self.ord_p, 2] -= self.ord_s
            vals.append(val)
            jacs.append(jac)
        if not vals:
            return np.zeros(0), np.zeros((0, self.j, 3))
        return np.concatenate(vals), np.concatenate(jacs, axis=0)

    def _setup_angle_levels(self) -> None:
        """Constant data for :meth:`_angles`: angle joints grouped by depth along their chain
        (level 0 = a finger's first joint), the parent's angle index, and the constant
        difference-selection matrices ``D_kp = E_k - E_p`` and ``D_ck`` ``(A, 3, 3J)``."""
        j = self.j
        ak = np.asarray(self.ak)
        index_of = {int(k): i for i, k in enumerate(ak)}
        level = np.zeros(len(ak), dtype=np.int64)
        parent_idx = np.full(len(ak), -1)
        for i, p in enumerate(self.ap):  # angle joints come in topological order
            if int(p) in index_of:
                parent_idx[i] = index_of[int(p)]
                level[i] = level[parent_idx[i]] + 1
        self.a_levels = [np.flatnonzero(level == lv) for lv in range(int(level.max()) + 1)]
        self.a_parent = parent_idx
        eye = np.eye(3)

        def sel(k):
            e = np.zeros((len(k), 3, 3 * j))
            for r, kk in enumerate(k):
                e[r, :, 3 * kk : 3 * kk + 3] += eye
            return e

        self.D_kp = sel(ak) - sel(self.ap)
        self.D_ck = sel(self.ac) - sel(ak)

    def _angles(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Angle-limit rows ``(4A,)`` and their Jacobian ``(4A, J, 3)``.

        The local frame follows ``Skeleton.joint_angles``: at a finger's first joint the lateral
        axis is ``normalize(a x n)`` (palm normal ``n``); further along it is the parent joint's
        lateral axis made perpendicular to the incoming bone (transported); ``n_perp = l x a``.
        Derivatives are propagated exactly through the chain and the palm normal. Vectorized over
        fingers: one batch of small matrix products per chain level (at most 3 levels).
        """
        j = self.j
        eye = np.eye(3)
        w0, i1, l1 = self.palm
        e1 = X[i1] - X[w0]
        e2 = X[l1] - X[w0]
        mvec = _cross(e1, e2)
        mn = max(float(np.linalg.norm(mvec)), 1e-9)
        n = self.hand_sign * mvec / mn
        pm = self.hand_sign * (eye - np.outer(n, n)) / mn
        dn = np.zeros((3, j, 3))  # dn/dX
        dn[:, i1] += pm @ -_skew(e2)
        dn[:, l1] += pm @ _skew(e1)
        dn[:, w0] -= dn[:, i1] + dn[:, l1]
        dn = dn.reshape(3, 3 * j)
        a_n = len(self.ak)
        A = np.zeros((a_n, 3))
        LAT = np.zeros((a_n, 3))
        DA = np.zeros((a_n, 3, 3 * j))
        DL = np.zeros((a_n, 3, 3 * j))
        for idx in self.a_levels:
            k, p = self.ak[idx], self.ap[idx]
            u = X[k] - X[p]
            un = np.maximum(np.linalg.norm(u, axis=1), 1e-9)
            a = u / un[:, None]
            pa = (eye - a[:, :, None] * a[:, None, :]) / un[:, None, None]
            da = pa @ self.D_kp[idx]
            pi = self.a_parent[idx]
            if pi[0] >= 0:  # a level shares one kind (first joint or not): see _setup
                lp, dlp = LAT[pi], DL[pi]
                al = np.einsum("mi,mi->m", a, lp)
                w = lp - al[:, None] * a
                ma = eye - a[:, :, None] * a[:, None, :]
                mb = al[:, None, None] * eye + a[:, :, None] * lp[:, None, :]
                dw = ma @ dlp - mb @ da
            else:
                w = _cross(u, n)
                sk_u = np.zeros((len(idx), 3, 3))
                sk_u[:, 0, 1], sk_u[:, 0, 2] = -u[:, 2], u[:, 1]
                sk_u[:, 1, 0], sk_u[:, 1, 2] = u[:, 2], -u[:, 0]
                sk_u[:, 2, 0], sk_u[:, 2, 1] = -u[:, 1], u[:, 0]
                dw = -_skew(n) @ self.D_kp[idx] + sk_u @ dn
            wn = np.maximum(np.linalg.norm(w, axis=1), 1e-9)
            lat = w / wn[:, None]
            pl = (eye - lat[:, :, None] * lat[:, None, :]) / wn[:, None, None]
            A[idx], LAT[idx], DA[idx], DL[idx] = a, lat, da, pl @ dw
        npp = _cross(LAT, A)
        B = X[self.ac] - X[self.ak]
        bn = np.maximum(np.linalg.norm(B, axis=1), 1e-9)
        s1 = np.einsum("mi,mi->m", B, A)
        s2 = np.einsum("mi,mi->m", B, npp)
        s3 = np.einsum("mi,mi->m", B, LAT)
        D = self.D_ck
        g1 = np.einsum("mi,mix->mx", B, DA) + np.einsum("mi,mix->mx", A, D)
        g2 = (
            np.einsum("mi,mix->mx", _cross(A, B), DL)
            + np.einsum("mi,mix->mx", _cross(B, LAT), DA)
            + np.einsum("mi,mix->mx", npp, D)
        )
        g3 = np.einsum("mi,mix->mx", B, DL) + np.einsum("mi,mix->mx", LAT, D)
        gb = np.einsum("mi,mix->mx", B / bn[:, None], D)
        vals, jacs = [], []
        for cf0, sf0, cf1, sf1, sa0, sa1 in self.angle_coef:
            vals.append(
                np.stack([cf0 * s2 - sf0 * s1, sf1 * s1 - cf1 * s2, s3 - bn * sa0, bn * sa1 - s3])
            )
            jacs.append(
                np.stack(
                    [
                        cf0[:, None] * g2 - sf0[:, None] * g1,
                        sf1[:, None] * g1 - cf1[:, None] * g2,
                        g3 - sa0[:, None] * gb,
                        sa1[:, None] * gb - g3,
                    ]
                ).reshape(4 * a_n, j, 3)
            )
        return np.concatenate([v.ravel() for v in vals]), np.concatenate(jacs)

    def ineq(self, x: np.ndarray) -> np.ndarray:
        val = self._cached("ineq", x)[0]
        if self.elastic:
            X = self.pose(x)
            sl = _SCALE_Z * x[3 * self.j :]
            lo = X[self.el_lo, 2] - self.z_lo[self.el_lo] + sl[self.slot[self.el_lo]]
            hi = self.z_hi[self.el_hi] - X[self.el_hi, 2] + sl[self.slot[self.el_hi]]
            val = np.concatenate([val, lo, hi])
        return val

    def ineq_jac(self, x: np.ndarray) -> np.ndarray:
        jac = self._cached("ineq", x)[1]
        # (rows, J, 3) -> (rows, 3J); explicit width, since there may be no rows (elastic mode
        # with every depth bound turned into a slack row below)
        jac = (jac * self.sc3).reshape(jac.shape[0], 3 * self.j)
        if self.elastic:
            ns = self.n_slack
            jac = np.hstack([jac, np.zeros((len(jac), ns))])
            nl, nh = len(self.el_lo), len(self.el_hi)
            extra = np.zeros((nl + nh, self.n_var))
            extra[np.arange(nl), 3 * self.el_lo + 2] = _SCALE_Z
            extra[np.arange(nl), 3 * self.j + self.slot[self.el_lo]] = _SCALE_Z
            extra[nl + np.arange(nh), 3 * self.el_hi + 2] = -_SCALE_Z
            extra[nl + np.arange(nh), 3 * self.j + self.slot[self.el_hi]] = _SCALE_Z
            jac = np.vstack([jac, extra])
        return jac

    def num_ineq(self) -> int:
        n = len(self.ord_k)
        if self.elastic:
            n += len(self.el_lo) + len(self.el_hi)
        return n


# ---------------------------------------------------------------------------------------- lift
def _check_inputs(annotation: FrameAnnotation, skeleton: Skeleton, bone_lengths_mm) -> np.ndarray:
    if not isinstance(annotation, FrameAnnotation):
        raise AnnotationError(f"expected a FrameAnnotation, got {type(annotation).__name__}")
    annotation.validate(skeleton.num_joints)
    if np.any(np.isnan(annotation.uv_px).any(axis=1) & annotation.has_3d):
        pass  # 3D-only joints are fine
    d = np.asarray(bone_lengths_mm, dtype=np.float64)
    if d.shape != (len(skeleton.bones),) or not np.all(np.isfinite(d)) or np.any(d <= 0):
        raise ValueError(
            f"bone_lengths_mm must be {len(skeleton.bones)} positive finite lengths, got {d!r}"
        )
    return d


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
    surface_depth_mm: float = 3.0,
    w_flat: float = 0.01,
    w_angle: float = 1.0,
    w_angle_inner: float = 0.0,
    depth_near_px: int = 1,
    soft_bones: float | None = None,
    right_hand: bool = True,
    elastic_weight: float = 2.0,
    start_elastic: bool = False,
    elastic_joints: np.ndarray | None = None,
    max_iter: int = 200,
    tol: float = 1e-6,
) -> LiftResult:
    """Lift one annotated frame to 3D (see the module docstring for the problem).

    annotation: the frame's :class:`FrameAnnotation` (J joints; validated, AnnotationError if bad).
    depth: ``(H, W)`` mm, 0 = invalid. bone_lengths_mm: ``(B,)`` mm, bone ``b`` = ``skeleton.bones[b]``.
    eps_mm: width of a visible joint's interval behind ``D + o``. angle_limits: thesis Eq. 5 limits.
    init_mm: ``(J, 3)`` warm start (e.g. the previous solution while a joint is dragged).
    order_margin_mm: depth-order margin. w_3d: weight (px^2 per mm^2) of joints placed in 3D.
    w_surface: weight (px^2/mm^2) of the pull of visible joints towards ``D + o``.
    w_angle: weight (px^2/mm^2) of the soft rows of ``skeleton.angle_ranges()`` (``angle_limits``);
    w_angle_inner: weight of the soft rows of the narrower ``skeleton.angle_limits()``.
    soft_bones: if given, bones are a penalty of this weight (px^2/mm^2) instead of equalities
    (used for bone-length estimation). start_elastic: solve the elastic problem first instead of
    only after the hard one failed (live re-lifts of a frame whose previous lift needed slack: the
    hard solve would spend its iterations failing again); an elastic solution whose slacks are all
    zero meets every hard constraint and is reported as such (``elastic=False``).
    elastic_joints: with ``start_elastic``, give slacks only to these joints (the previous lift's
    ``slack_joints``); if the other intervals cannot be met either, every joint gets one.
    Returns a :class:`LiftResult`.
    """
    t0 = time.perf_counter()
    d = _check_inputs(annotation, skeleton, bone_lengths_mm)
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth.shape}")
    x0_pose, d_obs = initial_pose(
        annotation, depth, camera, skeleton, d, depth_near_px=depth_near_px
    )
    if init_mm is not None:
        init = np.asarray(init_mm, dtype=np.float64)
        if init.shape != x0_pose.shape:
            raise ValueError(f"init_mm must be {x0_pose.shape}, got {init.shape}")
        x0_pose = np.where(np.isfinite(init), init, x0_pose)
    prob = _Problem(
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
        surface_depth_mm=surface_depth_mm,
        w_flat=w_flat,
        w_angle=w_angle,
        w_angle_inner=w_angle_inner,
        w_free=1e-3,
        soft_bones=soft_bones,
        right_hand=right_hand,
    )
    hard_bones = soft_bones is None
    # start inside the depth bounds
    z0 = np.clip(x0_pose[:, 2], prob.z_lo, prob.z_hi)
    res = None
    if not start_elastic:
        res = _solve_hard(prob, x0_pose, z0, hard_bones, max_iter, tol)
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
        if start_elastic and elastic_joints is not None and len(elastic_joints):
            res2 = _solve_elastic(
                prob, x0_pose, z0, hard_bones, elastic_weight, max_iter, tol, elastic_joints
            )
            if not _feasible(res2, prob, hard_bones):
                res2 = None  # another interval cannot be met either: relax them all
        if res2 is None:
            res2 = _solve_elastic(prob, x0_pose, z0, hard_bones, elastic_weight, max_iter, tol)
        if np.all(np.isfinite(res2.x)):
            res = res2
            slack_joints = prob.el_joints[prob.slacks_mm(res2.x) > 0.5]
        elif res is None:
            res = _solve_hard(prob, x0_pose, z0, hard_bones, max_iter, tol)
        else:
            prob.set_elastic(False)
            prob.x0[:, 2] = z0
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
    )


#: scipy SLSQP's exit status "Iteration limit reached"
_SLSQP_ITERATION_LIMIT = 9


def _solve_hard(
    prob: _Problem, x0_pose: np.ndarray, z0: np.ndarray, hard_bones: bool, max_iter: int, tol: float
):
    """Solve with hard depth intervals (bounds) from ``x0_pose`` moved inside them (``z0``)."""
    prob.set_elastic(False)
    prob.x0 = x0_pose.copy()
    prob.x0[:, 2] = z0
    return _solve(prob, hard_bones, max_iter, tol)


def _solve_elastic(
    prob: _Problem,
    x0_pose: np.ndarray,
    z0: np.ndarray,
    hard_bones: bool,
    weight: float,
    max_iter: int,
    tol: float,
    joints: np.ndarray | None = None,
):
    """Solve with slacks on the depth intervals of ``joints`` (all when None) from ``x0_pose``;
    joints without a slack start inside their interval (``z0``)."""
    prob.set_elastic(True, weight, joints)
    prob.x0 = x0_pose.copy()
    prob.x0[:, 2] = np.where(prob.slot < 0, z0, x0_pose[:, 2])
    return _solve(prob, hard_bones, max_iter, tol)


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
    moving: the violation stays at its first value (17-22 mm, measured on live demo edits) until
    the iteration limit, 100-160 ms wasted before the elastic re-solve. Feasible solves reduce it
    below 5 mm within 5 iterations (74 of 74 measured). A violation above ``min_mm`` that has not
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
    return _violation_mm(prob, res.x, hard_bones) <= 0.5


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


# ---------------------------------------------------------------------------------------- refs
def _lift_job(args: tuple) -> LiftResult:
    ann, depth, camera, skeleton, bones, kwargs = args
    return lift_frame(ann, depth, camera, skeleton, bones, **kwargs)


def _better(a: LiftResult, b: LiftResult) -> LiftResult:
    """The converged result with the lower objective (``a`` on ties)."""
    if a.converged != b.converged:
        return a if a.converged else b
    return b if b.objective < a.objective - 1e-9 else a


def initial_bone_lengths(
    annotations: dict[int, FrameAnnotation],
    depths: dict[int, np.ndarray],
    camera: CameraIntrinsics,
    skeleton: Skeleton,
) -> np.ndarray:
    """Template bone lengths ``(B,)`` scaled to the annotated frames.

    The scale is the median over frames and bones (both joints visible with valid depth) of the
    back-projected 2D length divided by the template length, corrected upwards because a
    projected length is never longer than the bone (we take the 75th percentile of the ratios).
    """
    if skeleton.template_bone_lengths_mm is None:
        raise ValueError(
            f"skeleton {skeleton.name} has no template bone lengths; pass bone_lengths_mm"
        )
    tmpl = np.asarray(skeleton.template_bone_lengths_mm, dtype=np.float64)
    ratios = []
    offsets = np.asarray(skeleton.surface_offsets_mm)
    p, c = skeleton.bones[:, 0], skeleton.bones[:, 1]
    for f, ann in annotations.items():
        d_obs = observed_depth(depths[f], ann.uv_px)
        ok = ann.has_2d & ann.visible & np.isfinite(d_obs)
        z = np.where(ok, d_obs + offsets, np.nan)
        X = camera.backproject(np.where(ann.has_2d[:, None], ann.uv_px, 0.0), np.nan_to_num(z))
        good = ok[p] & ok[c]
        # planar (projected) length at the mean depth of the two joints
        zm = 0.5 * (z[p] + z[c])
        planar = (
            np.linalg.norm(
                (X[c, :2] / np.maximum(z[c, None], 1) - X[p, :2] / np.maximum(z[p, None], 1)),
                axis=1,
            )
            * zm
        )
        ratios.append((planar / tmpl)[good])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    r = r[np.isfinite(r) & (r > 0)]
    scale = float(np.percentile(r, 75)) if len(r) >= 5 else 1.0
    return tmpl * float(np.clip(scale, 0.5, 2.0))


def surface_correction(
    annotations: dict[int, FrameAnnotation],
    results: dict[int, LiftResult],
    skeleton: Skeleton,
    surface_depth_mm: float,
    min_samples: int = 8,
) -> np.ndarray:
    """Per-joint correction ``(J,)`` mm of the surface offsets, from lifted references.

    For every annotated visible joint with an observed depth (and no elastic slack) the residual
    ``z_lifted - (D + o + surface_depth_mm)`` is how much deeper below the observed surface the
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
        for g in np.unique(groups[ok]):
            res_by_group.setdefault(int(g), []).append(resid[ok & (groups == g)])
    corr = np.zeros(skeleton.num_joints)
    for g, parts in res_by_group.items():
        vals = np.concatenate(parts)
        if g >= 0 and len(vals) >= min_samples:
            corr[groups == g] = float(np.median(vals))
    return corr


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
    max_rounds: int = 10,
    bone_tol_mm: float = 0.1,
    soft_bone_weight: float = 0.05,
    min_bone_votes: int = 3,
    calibrate_surface: bool = True,
    offset_tol_mm: float = 0.5,
    max_calibrations: int = 3,
    stretch_tolerance: float = 0.2,
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
    re-estimated ones (median ratio to the template). calibrate_surface: re-estimate the depth of
    joint centres below the observed surface per joint group in every round
    (:func:`surface_correction`; the result is in ``LiftSet.surface_offsets_mm``).
    A reference whose own evidence (its last soft-bone lift) wants some annotated bone more than
    ``stretch_tolerance`` (fraction, and > 3 mm, and > 4 robust standard deviations of that
    bone's spread over the references) longer or shorter than the final estimate is reported
    ``stretched`` (and not ``converged``): the template could only be fitted by stretching it.
    workers > 1 lifts frames in processes, ``scheduler`` (``"tcp://HOST:PORT"``) on a Dask
    cluster (:class:`handanno_core.parallel.Runner`: each round is a map over the references, the
    bone estimate a reduction here; depth maps are sent once). progress(done, total) is called
    after every frame of every round. Returns a :class:`LiftSet` with ``bone_history_mm`` (one
    entry per round).
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
        return _lift_rounds(
            anns, depths, {f: runner.share(depths[f]) for f in frames}, runner, camera, skeleton,
            bone_lengths_mm, pin_bone_lengths, eps_mm, angle_limits, progress, max_rounds,
            bone_tol_mm, soft_bone_weight, min_bone_votes, calibrate_surface, offset_tol_mm,
            max_calibrations, stretch_tolerance, lift_kwargs,
        )  # fmt: skip


def _lift_rounds(
    anns, depths, shared, runner, camera, skeleton, bone_lengths_mm, pin_bone_lengths, eps_mm,
    angle_limits, progress, max_rounds, bone_tol_mm, soft_bone_weight, min_bone_votes,
    calibrate_surface, offset_tol_mm, max_calibrations, stretch_tolerance, lift_kwargs,
) -> LiftSet:  # fmt: skip
    """The body of :func:`lift_references` (``shared``: the depth maps' handles on the runner)."""
    frames = sorted(anns)
    if bone_lengths_mm is not None:
        bones = np.asarray(bone_lengths_mm, dtype=np.float64).copy()
    elif frames:
        bones = initial_bone_lengths(anns, depths, camera, skeleton)
    else:
        bones = np.asarray(skeleton.template_bone_lengths_mm, dtype=np.float64)
    history = [bones.copy()]
    sk = skeleton
    surface_depth = float(lift_kwargs.get("surface_depth_mm", 3.0))
    kw = dict(eps_mm=eps_mm, angle_limits=angle_limits, **lift_kwargs)
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
            soft_lengths = np.where(bmask, sk.bone_lengths(poses), np.nan)  # (F, B)
            new = bones.copy()
            if np.any(voted):
                new[voted] = np.nanmedian(soft_lengths[:, voted], axis=0)
                if tmpl is not None and not np.all(voted):
                    # bones without enough evidence: template times the global scale
                    scale = float(np.median(new[voted] / tmpl[voted]))
                    new[~voted] = tmpl[~voted] * scale
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
            corr = surface_correction(anns, dict(zip(frames, res, strict=True)), sk, surface_depth)
            calibrations += 1
            if float(np.max(np.abs(corr))) < offset_tol_mm:
                break
            offsets = np.asarray(sk.surface_offsets_mm) + corr
            sk = dataclasses.replace(sk, surface_offsets_mm=tuple(float(o) for o in offsets))
    jobs = [(anns[f], shared[f], camera, sk, bones, dict(kw, init_mm=inits.get(f))) for f in frames]
    res = runner.map(_lift_job, jobs, progress)
    if inits:
        # the soft-bone rounds can drift into the mirrored mode of a hidden finger; also solve
        # from the cold start and keep the better objective (measured: worst joint 20 -> 10 mm
        # on the synthetic sequence, at the cost of one more lift per reference)
        cold_jobs = [(a, dp, cm, sk_, b, dict(kw)) for a, dp, cm, sk_, b, _ in jobs]
        cold = runner.map(_lift_job, cold_jobs)
        res = [_better(w, c) for w, c in zip(res, cold, strict=True)]
    if soft_lengths is not None:
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
    results = dict(zip(frames, res, strict=True))
    n_stretched = sum(r.stretched for r in res)
    if n_stretched:
        warnings.warn(
            f"lift: {n_stretched} of {len(res)} references only fit by stretching the bone "
            "lengths (LiftResult.stretched); check their 2D annotations",
            stacklevel=2,
        )
    return LiftSet(
        joints_mm={f: r.joints_mm for f, r in results.items()},
        confidence={f: r.confidence for f, r in results.items()},
        bone_lengths_mm=bones,
        results=results,
        bone_history_mm=history,
        surface_offsets_mm=np.asarray(sk.surface_offsets_mm, dtype=np.float64),
        bone_votes=bmask.sum(axis=0),
    )
