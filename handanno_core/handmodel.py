"""A personalized articulated hand model (one capsule per bone plus palm capsules) and its fit to
one frame's own depth (articulated ICP), after Tagliasacchi et al., "Robust Articulated-ICP for
Real-Time Hand Tracking" (SGP 2015) and Tkach et al., "Sphere-Meshes for Real-Time Hand Modeling
and Tracking" (SIGGRAPH Asia 2016), with what those trackers lack: exact bone lengths from the
lift and verified reference poses.

**Model** (:class:`HandModel`): capsule ``c`` spans joints ``pairs[c] = (a, b)`` from
``X_a + s0_c (X_b − X_a)`` to ``X_a + s1_c (X_b − X_a)`` with radius ``radii[c]`` mm. Every bone is
a capsule; a fingertip bone ends one radius before the tip joint (``s1 = 1 − r/L``) so its cap
reaches the tip, which lies on the surface; the knuckle line adds capsules between neighbouring
MCPs. Bone lengths come from the lift; radii from the references' point clouds
(:func:`estimate_radii`: iteratively reweighted fit of each observed point's distance to its
capsule's axis segment); the palm's shape (distances between the root's children) from the
references' lifted poses, and the thumb base's place in the palm's frame
(:meth:`Skeleton.palm_rotation`;
the palm distances hold it only weakly, it lies near the wrist with every MCP on one side) from
their median. Ground truth is never used.

**Pose**: :class:`Kinematics`, a root position (3) plus one unit direction per bone updated on the
sphere through a 2-D tangent step, joints ``X_k = root + Σ_{b on path to k} L_b·u_b``: bones are
exact by construction. Joint angles are not separate parameters; the prior below keeps them
inside the skeleton's limits and the palm term keeps the palm rigid.

**Per-frame energy** (:func:`frame_energy`), each residual weighted by √λ in the stated unit:

``E = λ_data  mean_i ρ_W(‖p_i − q_i‖ − r)      observed hand point to the nearest capsule surface, mm
    + λ_free  mean_s ρ_H(free-space violation)   front-facing capsule samples: in front of the
                                                observed surface (mm) or off the silhouette (px → mm)
    + λ_angle ½ Σ (angle outside limits)²        skeleton.angle_limits(), degrees
    + λ_palm  ½ Σ (‖X_a − X_b‖ − d_ab)²          palm shape from the references, mm
    + λ_palm  ½ Σ ‖X_t − X_root − R c_t‖²         thumb base in the palm's frame R, mm
    + λ_pose  Σ_k w_k ρ_H(‖X_k − Y_k‖)           closeness to a given pose (temporal / start), mm
    + λ_uv    ½ Σ_k w_k ‖π(X_k) − uv_k‖²         weak pull to propagated 2D positions, px
    + λ_prior ½ ‖W (φ(X) − μ)‖²                   the session's pose prior, dimensionless``

The pose prior (:mod:`handanno_core.pose_prior`: a Gaussian over the bone directions ``φ`` in the
joints' frames, learned from real recorded hands) is made the session's own by
:func:`personalize` (mean moved to the references', their spread added to its covariance). It
decides what the depth leaves open, a finger the camera does not see, from how the visible ones
sit; its rows are forward differences over the tangent parameters (:func:`_prior_jacobian`).

Observed points (:func:`observe`) come from the normalized crops (no extra depth reads), a few
hundred per frame; forearm points are ignored (:func:`_forearm`: behind a plane 25 mm past the
wrist along the wrist -> knuckles axis, or nearest to the wrist end of a capsule at the root). Model samples are 4 positions × 3 angles per capsule on the surface
facing the camera; each is projected into the crop: on a hand pixel it must not lie more than
``free_margin_mm`` in front of the observed depth; off the silhouette it is pulled to the nearest
hand pixel (distance transform, as in Tagliasacchi et al.) or past the image's border, where it
costs nothing (the sensor saw nothing there).

**Solver** (:func:`fit_frames`): Levenberg-Marquardt on all given frames at once (independent
frames: batched 43×43 systems, :func:`handanno_core.lm.levenberg_marquardt_batched` with
``active_rows``: only frames still running are evaluated, normal equations are built only for
frames whose pose moved, a frame stops after ``max_rejects`` rejected steps), correspondences and
IRLS weights re-found at every evaluation. Jacobians are analytic (point-to-segment distances,
projection), each residual row depending on two joints: rows are summed in joint space (3J×3J,
one ``np.bincount``) and mapped to θ once (:func:`_assemble`). The joint-angle prior is
differentiated forward over the tangent parameters of the bones its violated angles depend on
(:func:`angle_jacobian`, shared with :mod:`handanno_core.refine`). A step is accepted per frame
only if it lowers that frame's energy. Cost: ``benchmarks/bench_handmodel.py`` (README).

**Per-finger hypotheses** (:func:`refit_fingers`, the classic remedy of model-based trackers for a
finger stuck in the wrong basin, curled where the depth shows it extended): the energy is nearly
separable per finger, so each finger of a fitted pose is set in turn to a grid of flexions
(:data:`FINGER_FLEXIONS`, fractions of the joints' limits) and to the angles of caller-given
poses (:func:`finger_targets`), scored by the same energy; the best of each finger are
recombined and refitted once, and the result is kept only where its energy is lower.

**Reference starts** (:func:`pose_library`, :func:`library_starts`): where several fingers are
wrong at once (a fist closing faster than the flow follows), one finger at a time does not lower
the energy; the session's verified poses, the most different ones, turned into the frame's palm,
are whole-hand starts (semi-automatic annotation has them, a tracker does not).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from scipy.ndimage import distance_transform_edt, minimum_filter

from . import lm
from .camera import CameraIntrinsics
from .crops import DEFAULT_CROP, crop_to_image, image_to_crop
from .pose_prior import PosePrior, session_prior
from .pose_prior import pose_prior as packaged_pose_prior
from .skeleton import Skeleton

__all__ = [
    "FitResult",
    "FitWeights",
    "FrameObservations",
    "Priors",
    "HandModel",
    "Kinematics",
    "build_model",
    "estimate_radii",
    "fit_frames",
    "finger_chains",
    "finger_hypotheses",
    "finger_grid",
    "depth_energies",
    "reference_level",
    "finger_targets",
    "frame_energy",
    "frame_energy_rows",
    "rows_normal_equations",
    "grid_flexions",
    "observe",
    "personalize",
    "pose_energies",
    "pose_library",
    "library_starts",
    "refit_fingers",
]


# ------------------------------------------------------------------------------------------------
# kinematic parameterization (shared with refine)
# ------------------------------------------------------------------------------------------------
class Kinematics:
    """Root + unit bone directions with fixed lengths; joints and their Jacobian per frame.

    Parameters per frame θ = (root step (3), tangent step (2) per bone): ``num_params = 3 + 2B``.
    """

    def __init__(self, skeleton: Skeleton, bone_lengths_mm: np.ndarray):
        self.parents = skeleton.parent_array
        self.bones = skeleton.bones
        self.root = skeleton.root
        j = skeleton.num_joints
        b = len(self.bones)
        self.lengths = np.asarray(bone_lengths_mm, dtype=np.float64)
        if self.lengths.shape != (b,) or not np.all(np.isfinite(self.lengths)):
            raise ValueError(f"bone_lengths_mm must be ({b},) finite, got {self.lengths.shape}")
        bone_of_child = np.full(j, -1)
        bone_of_child[self.bones[:, 1]] = np.arange(b)
        self.bone_of_child = bone_of_child
        # ancestor[k, b] = 1 if bone b lies on the path root -> k
        anc = np.zeros((j, b))
        for k in range(j):
            q = k
            while self.parents[q] >= 0:
                anc[k, bone_of_child[q]] = 1.0
                q = self.parents[q]
        self.ancestor_lengths = anc * self.lengths[None, :]  # (J, B)
        self.num_params = 3 + 2 * b

    def joints(self, root: np.ndarray, u: np.ndarray) -> np.ndarray:
        """root (N,3) mm, u (N,B,3) unit -> joints (N,J,3) mm."""
        return root[:, None, :] + np.einsum("kb,nbc->nkc", self.ancestor_lengths, u)

    @staticmethod
    def tangents(u: np.ndarray) -> np.ndarray:
        """Orthonormal tangent bases (N,B,3,2) of the unit vectors u (N,B,3)."""
        a = np.zeros_like(u)
        use_x = np.abs(u[..., 0]) < 0.9
        a[use_x, 0] = 1.0
        a[~use_x, 1] = 1.0
        t1 = _unit(_cross(u, a))
        return np.stack([t1, _cross(u, t1)], axis=-1)

    def jacobian(self, u: np.ndarray) -> np.ndarray:
        """dX/dθ (N, J·3, P) with θ = (root, tangent steps of each bone)."""
        n, b = u.shape[:2]
        j = self.ancestor_lengths.shape[0]
        t = self.tangents(u)
        m = np.empty((n, j, 3, self.num_params))
        m[..., :3] = np.eye(3)
        # dX_k/dδ_b = L_kb · T_b (the joint moves with every bone above it), written in place
        np.multiply(
            self.ancestor_lengths[None, :, None, :, None],
            t.transpose(0, 2, 1, 3)[:, None],
            out=m[..., 3:].reshape(n, j, 3, b, 2),
        )
        return m.reshape(n, j * 3, self.num_params)

    def retract(self, root, u, step: np.ndarray):
        """Apply a step (N, P) to (root, u): root += step[:3]; u <- normalize(u + T·δ)."""
        n, b = u.shape[:2]
        t = self.tangents(u)
        delta = step[:, 3:].reshape(n, b, 2)
        v = u + np.einsum("nbcd,nbd->nbc", t, delta)
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        return root + step[:, :3], v

    def fit(self, target: np.ndarray, iterations: int = 8):
        """Least-squares fit of (root, u) to joints (N,J,3) with fixed bone lengths (per frame GN;
        a frame stops after a step below 1e-7, so its result does not depend on the others)."""
        root = target[:, self.root].copy()
        bv = target[:, self.bones[:, 1]] - target[:, self.bones[:, 0]]
        norm = np.linalg.norm(bv, axis=-1, keepdims=True)
        u = np.where(norm > 1e-9, bv / np.maximum(norm, 1e-9), np.array([0.0, 0.0, 1.0]))
        rows = np.arange(target.shape[0])
        for _ in range(iterations):
            r = (self.joints(root[rows], u[rows]) - target[rows]).reshape(len(rows), -1)
            m = self.jacobian(u[rows])
            h = np.matmul(m.transpose(0, 2, 1), m) + 1e-6 * np.eye(self.num_params)
            g = np.einsum("nrp,nr->np", m, r)
            step = -np.linalg.solve(h, g[..., None])[..., 0]
            root[rows], u[rows] = self.retract(root[rows], u[rows], step)
            rows = rows[np.max(np.abs(step), axis=1) >= 1e-7]
            if len(rows) == 0:
                break
        return root, u


class _AngleMeter:
    """:meth:`Skeleton.joint_angles` evaluated one chain level at a time (all fingers at once):
    the same definition (lateral axis transported along each finger), 3 vectorized steps instead of
    one Python step per joint; the fit calls it 2B+1 times per iteration."""

    def __init__(self, skeleton: Skeleton):
        self.skeleton = skeleton
        par = skeleton.parent_array
        joints = skeleton.angle_joints
        self.children = skeleton.angle_children
        pos = {int(k): i for i, k in enumerate(joints)}
        level = np.zeros(len(joints), dtype=int)
        for i, k in enumerate(joints):
            q = int(par[k])
            while q >= 0:
                level[i] += q in pos
                q = int(par[q])
        self.levels = [
            np.flatnonzero(level == v) for v in range(level.max() + 1 if len(level) else 0)
        ]
        self.joints = joints
        self.parents = par[joints]
        self.parent_pos = np.array([pos.get(int(p), -1) for p in self.parents], dtype=np.int64)

    def __call__(self, poses: np.ndarray, axes: bool = False):
        """Flexion, abduction (..., A) degrees, as :meth:`Skeleton.joint_angles` (right hand);
        with ``axes`` also the flexion axes (..., A, 3) (unit; flexion turns a joint's child
        bone about its axis, right-handed)."""
        along, towards, side, lat_all = self._components(poses)
        flex = np.degrees(np.arctan2(towards, along))
        abd = np.degrees(np.arctan2(side, np.hypot(along, towards)))
        return (flex, abd, lat_all) if axes else (flex, abd)

    def directions(self, poses: np.ndarray, only: np.ndarray | None = None) -> np.ndarray:
        """(..., A, 3) unit bone directions in the joints' frames, as
        :meth:`Skeleton.bone_directions` (right hand). ``only`` (A,) bool: compute just those
        angle joints (they must include each one's angle-joint ancestors); the others are 0."""
        along, towards, side, _ = self._components(poses, only)
        return _unit(np.stack([along, towards, side], axis=-1))

    def _components(self, poses: np.ndarray, only: np.ndarray | None = None):
        """The child bone of every angle joint along the incoming bone, towards the palm and
        lateral (..., A) mm each, and the lateral axes (..., A, 3) (``only``: those of
        :meth:`directions`; 0 elsewhere)."""
        x = np.asarray(poses, dtype=np.float64)
        normal = self.skeleton.palm_normal(x)[..., None, :]
        lat_all = np.zeros(x.shape[:-2] + (len(self.joints), 3))
        along_all = np.zeros(x.shape[:-2] + (len(self.joints),))
        towards_all = np.zeros_like(along_all)
        side_all = np.zeros_like(along_all)
        for lv, idx in enumerate(self.levels):
            if only is not None:
                idx = idx[only[idx]]
                if not len(idx):
                    continue
            k, p, c = self.joints[idx], self.parents[idx], self.children[idx]
            a = _unit(x[..., k, :] - x[..., p, :])
            if lv == 0:
                n_perp = _unit(normal - np.sum(normal * a, axis=-1, keepdims=True) * a)
                lateral = _cross(a, n_perp)
            else:
                lp = lat_all[..., self.parent_pos[idx], :]
                lateral = _unit(lp - np.sum(lp * a, axis=-1, keepdims=True) * a)
            lat_all[..., idx, :] = lateral
            n_perp = _cross(lateral, a)
            b = x[..., c, :] - x[..., k, :]
            along_all[..., idx] = np.sum(b * a, axis=-1)
            towards_all[..., idx] = np.sum(b * n_perp, axis=-1)
            side_all[..., idx] = np.sum(b * lateral, axis=-1)
        return along_all, towards_all, side_all, lat_all


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _wrist_axis(x: np.ndarray, root: int, chain: np.ndarray) -> np.ndarray:
    """``(..., 3)`` unit wrist -> knuckles axis of poses ``x`` (..., J, 3): from the ``root`` to
    the mean of the palm ``chain`` (:func:`_palm_chain`); what is behind the wrist along it is
    forearm (:func:`_forearm`, :func:`wrist_planes`)."""
    return _unit(x[..., chain, :].mean(axis=-2) - x[..., root, :])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (np.cross's axis handling costs more than the math)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _per_skeleton(cache: dict, skeleton: Skeleton, build):
    """``build(skeleton)``, computed once per skeleton object and kept in ``cache``: keyed by
    identity (a Skeleton holds arrays, so it does not hash), the object kept beside its value so
    that a reused ``id`` of another skeleton cannot hit."""
    hit = cache.get(id(skeleton))
    if hit is None or hit[0] is not skeleton:
        hit = cache[id(skeleton)] = (skeleton, build(skeleton))
    return hit[1]


_METERS: dict[int, tuple[Skeleton, _AngleMeter]] = {}


def _meter(skeleton: Skeleton) -> _AngleMeter:
    return _per_skeleton(_METERS, skeleton, _AngleMeter)


def angle_violation(skeleton: Skeleton, x: np.ndarray) -> np.ndarray:
    """(..., 2A) degrees outside the flexion/abduction limits of ``skeleton.angle_limits()``."""
    flex, abd = _meter(skeleton)(x)
    fl, al = skeleton.angle_limits()
    v = np.concatenate(
        [
            np.maximum(flex - fl[:, 1], 0) + np.maximum(fl[:, 0] - flex, 0),
            np.maximum(abd - al[:, 1], 0) + np.maximum(al[:, 0] - abd, 0),
        ],
        axis=-1,
    )
    return np.nan_to_num(v)


def angle_jacobian(
    skeleton: Skeleton,
    kin: Kinematics,
    root,
    u,
    h: float = 1e-4,
    v0=None,
    own_bones: bool = False,
    bones: np.ndarray | None = None,
):
    """Violations (m,2A) and d(violation)/dθ (m,2A,P) at the frames' parameters (root, u).

    Forward differences over the tangent parameters of the bones the violated angles depend on
    (angles do not depend on the root; an angle depends on the bones from the root to its child
    joint and to the palm joints): at most 2B extra pose evaluations per frame, typically a
    finger's, perturbed in all frames (the union over the frames, or ``bones`` when given: a
    caller splitting frames into chunks passes the union of all of them). A perturbed bone moves
    only the joints below it, by ``L·Δu``. ``v0``: the violations (m,2A) when the caller has
    them. ``own_bones``: each frame's Jacobian keeps only the columns of its own violated angles'
    bones (else a non-violated angle within ``h`` of its limit can get a row from another
    frame's bones), so a frame's result does not depend on the frames evaluated with it: the
    hand-model fit (:func:`fit_frames`) batches independent frames.
    """
    x0 = kin.joints(root, u)
    if v0 is None:
        v0 = angle_violation(skeleton, x0)
    jac = np.zeros((len(u), v0.shape[1], kin.num_params))
    own = _own_bones(skeleton, v0)
    if bones is None:
        bones = np.flatnonzero(np.any(own, axis=0))
    if len(bones) == 0:
        return v0, jac
    cols, xs = _tangent_steps(kin, x0, u, bones, h)
    v1 = angle_violation(skeleton, xs.reshape((-1,) + x0.shape[1:])).reshape(len(u), len(cols), -1)
    d = (v1 - v0[:, None, :]) / h
    if own_bones:
        d = np.where(own[:, cols // 2, None], d, 0.0)
    jac[:, :, 3 + cols] = d.transpose(0, 2, 1)
    return v0, jac


def _tangent_steps(kin: Kinematics, x0, u, bones: np.ndarray, h: float):
    """The tangent parameters of ``bones`` (2nb,) (θ minus the root's 3) and the joints (m,2nb,J,3)
    with each of them stepped by ``h`` from the frames' joints ``x0`` (m,J,3) at directions ``u``
    (m,B,3): a stepped bone moves only the joints below it, by ``L·Δu``."""
    cols = np.stack([2 * bones, 2 * bones + 1], axis=1).ravel()
    t = kin.tangents(u[:, bones])  # (m,nb,3,2)
    idx = np.arange(len(cols))
    ub = u[:, cols // 2]  # (m, 2nb, 3)
    du = _unit(ub + h * t[:, idx // 2, :, idx % 2].transpose(1, 0, 2)) - ub
    xs = x0[:, None] + kin.ancestor_lengths[:, cols // 2].T[None, :, :, None] * du[:, :, None]
    return cols, xs


def pose_prior_residuals(model: HandModel, x: np.ndarray) -> np.ndarray:
    """(..., 3A) the residuals ``W (phi - mu)`` of the model's pose prior at joints ``x``
    (..., J, 3) mm (a right hand): its energy is half their squared norm."""
    phi = _meter(model.skeleton).directions(x)
    return model.pose_prior.residuals(np.nan_to_num(phi.reshape(*phi.shape[:-2], -1)))


def _prior_jacobian(model: HandModel, kin: Kinematics, root, u, r0, h: float = 1e-5):
    """d(prior residuals)/dθ (m,3A,P) at the frames' parameters (root, u), where the residuals
    are ``r0`` (m,3A): forward differences over every bone's tangent parameters (the directions
    do not depend on the root). A step of a bone that moves no palm-normal joint changes only
    its own finger's directions (:func:`_prior_groups`), so only those are measured again:
    the same differences as measuring all, for less."""
    x0 = kin.joints(root, u)
    meter = _meter(model.skeleton)
    w = model.pose_prior.sqrt_precision
    jac = np.zeros((len(u), r0.shape[-1], kin.num_params))
    phi0 = None
    for bones, only in _prior_groups(model.skeleton):
        cols, xs = _tangent_steps(kin, x0, u, bones, h)
        if only is None:
            r1 = pose_prior_residuals(model, xs)
            jac[:, :, 3 + cols] = ((r1 - r0[:, None]) / h).transpose(0, 2, 1)
            continue
        if phi0 is None:
            phi0 = np.nan_to_num(meter.directions(x0))
        pos = np.flatnonzero(only)
        phi1 = np.nan_to_num(meter.directions(xs, only)[..., pos, :])  # (m, 2nb, F, 3)
        d = (phi1 - phi0[:, None, pos]).reshape(len(u), len(cols), -1) / h
        dims = (3 * pos[:, None] + np.arange(3)).ravel()
        jac[:, :, 3 + cols] = (d @ w[:, dims].T).transpose(0, 2, 1)
    return jac


_PRIOR_GROUPS: dict[int, tuple[Skeleton, list]] = {}


def _prior_groups(skeleton: Skeleton) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """The skeleton's bones in groups ``(bones, only)`` for :func:`_prior_jacobian`: a step of
    any of ``bones`` changes the bone directions of the angle joints ``only`` (A,) bool alone
    (one finger: the joints below the bone move, the palm normal does not), or, ``only`` None,
    of every angle joint (the bone's child is one of the palm normal's joints). Bones that move
    no angle joint's directions are left out."""
    return _per_skeleton(_PRIOR_GROUPS, skeleton, _build_prior_groups)


def _build_prior_groups(skeleton: Skeleton) -> list[tuple[np.ndarray, np.ndarray | None]]:
    palm = set(int(k) for k in (skeleton.palm_joints or ()))
    aj, children = skeleton.angle_joints, skeleton.angle_children
    everything = [b for b, (_, c) in enumerate(skeleton.bones) if int(c) in palm]
    groups = [(np.array(everything, dtype=np.int64), None)] if everything else []
    for chain in finger_chains(skeleton):
        # a finger's joints: its angle joints and their children (its first joint is a root's
        # child, the bone to it moves the whole finger)
        joints = set(int(k) for k in aj[chain]) | set(int(k) for k in children[chain])
        own = [b for b, (_, c) in enumerate(skeleton.bones) if int(c) in joints - palm]
        if own:
            only = np.zeros(len(aj), dtype=bool)
            only[chain] = True
            groups.append((np.array(own, dtype=np.int64), only))
    return groups


def violated_bones(skeleton: Skeleton, v0: np.ndarray) -> np.ndarray:
    """Bones (indices) the violated angles of any frame of ``v0`` (m,2A) depend on: the bones
    :func:`angle_jacobian` perturbs."""
    return np.flatnonzero(np.any(_own_bones(skeleton, v0), axis=0))


def _own_bones(skeleton: Skeleton, v0: np.ndarray) -> np.ndarray:
    """(m,B) bool: the bones each frame's violated angles (``v0`` (m,2A) > 0) depend on."""
    return (v0 > 0).astype(np.float64) @ _angle_bones(skeleton) > 0


_ANGLE_BONES: dict[int, tuple[Skeleton, np.ndarray]] = {}


def _angle_bones(skeleton: Skeleton) -> np.ndarray:
    """(2A, B) bool: violation row ``a`` (flexion rows, then abduction rows) depends on bone ``b``
    (bones on the paths from the root to the angle's child joint and to the palm joints)."""
    return _per_skeleton(_ANGLE_BONES, skeleton, _build_angle_bones)


def _build_angle_bones(skeleton: Skeleton) -> np.ndarray:
    par = skeleton.parent_array
    bone_of_child = np.full(skeleton.num_joints, -1)
    bone_of_child[skeleton.bones[:, 1]] = np.arange(len(skeleton.bones))

    def path(k: int) -> np.ndarray:
        on = np.zeros(len(skeleton.bones), dtype=bool)
        while par[k] >= 0:
            on[bone_of_child[k]] = True
            k = int(par[k])
        return on

    palm = np.zeros(len(skeleton.bones), dtype=bool)
    for k in skeleton.palm_joints or ():
        palm |= path(int(k))
    rows = np.array([path(int(c)) | palm for c in skeleton.angle_children]).reshape(-1, len(palm))
    return np.concatenate([rows, rows])


# ------------------------------------------------------------------------------------------------
# the model
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class HandModel:
    """Capsules of a hand, personalized (all lengths in mm).

    ``pairs`` (C, 2) joints each capsule spans; ``radii`` (C,); ``tip`` (C,) bool, capsule ends one
    radius before its second joint (fingertip bones); ``wrist`` (C,) bool, capsule starts at the
    root (points beyond its root end are forearm); ``bone_lengths_mm`` (B,);
    ``palm_pairs`` (Q, 2) joints whose distance ``palm_dist_mm`` (Q,) is kept (palm shape).
    """

    skeleton: Skeleton
    bone_lengths_mm: np.ndarray
    pairs: np.ndarray
    radii: np.ndarray
    tip: np.ndarray
    palm_pairs: np.ndarray
    palm_dist_mm: np.ndarray
    #: the session's pose prior (:func:`handanno_core.pose_prior.session_prior` of the
    #: references' poses, set by :func:`personalize`) and its weight relative to
    #: ``FitWeights.prior`` (smaller for a hand that moves more widely than the recordings)
    pose_prior: PosePrior | None = None
    pose_prior_weight: float = 1.0
    #: (A, 3) mm: where :attr:`palm_anchor_joints` are held in the palm's frame, the references'
    #: median (set by :func:`personalize`; None: no term)
    palm_anchor_mm: np.ndarray | None = None

    @cached_property
    def finger_of(self) -> np.ndarray:
        """(C,) the root child each capsule's chain starts at (-1 for capsules at the root)."""
        sk = self.skeleton
        a, b = np.asarray(self.pairs, dtype=np.int64).reshape(-1, 2).T
        along = (a != sk.root) & (sk.parent_array[b] == a)  # a bone below the root's children
        return np.where(along, sk.finger_bases[a], -1)

    @cached_property
    def collision_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Capsule pairs (Q,), (Q,) of different fingers (ordered both ways)."""
        f = self.finger_of
        ia, ik = np.nonzero((f[:, None] >= 0) & (f[None, :] >= 0) & (f[:, None] != f[None, :]))
        return ia, ik

    @cached_property
    def palm_chain(self) -> np.ndarray:
        return _palm_chain(self.skeleton)

    @cached_property
    def palm_anchor_joints(self) -> np.ndarray:
        """(A,) root children off the knuckle line (the thumb's CMC), held in the palm's frame
        (``palm_anchor_mm``). The palm distances hold them only weakly: such a joint lies near
        the wrist with every MCP on one side, so it swings about the knuckle line at nearly
        constant distances."""
        sk = self.skeleton
        if sk.palm_joints is None:
            return np.zeros(0, dtype=np.int64)
        return np.setdiff1d(sk.children(sk.root), self.palm_chain).astype(np.int64)

    @cached_property
    def wrist(self) -> np.ndarray:
        return self.pairs[:, 0] == self.skeleton.root

    @cached_property
    def fractions(self) -> tuple[np.ndarray, np.ndarray]:
        """(s0, s1) (C,) of each capsule's end points along its joint pair."""
        s0 = np.zeros(len(self.pairs))
        s1 = np.ones(len(self.pairs))
        kin_len = self._pair_lengths()
        s1 = np.where(self.tip, 1.0 - self.radii / np.maximum(kin_len, 1e-6), s1)
        return s0, np.maximum(s1, 0.05)

    def _pair_lengths(self) -> np.ndarray:
        """(C,) bone length of bone capsules (NaN for the others)."""
        sk = self.skeleton
        out = np.full(len(self.pairs), np.nan)
        par = sk.parent_array
        is_bone = par[self.pairs[:, 1]] == self.pairs[:, 0]
        boc = np.full(sk.num_joints, -1)
        boc[sk.bones[:, 1]] = np.arange(len(sk.bones))
        out[is_bone] = self.bone_lengths_mm[boc[self.pairs[is_bone, 1]]]
        return out

    def capsules(self, x: np.ndarray):
        """Capsule end points A, B (..., C, 3) mm for joints ``x (..., J, 3)``."""
        s0, s1 = self.fractions
        xa, xb = x[..., self.pairs[:, 0], :], x[..., self.pairs[:, 1], :]
        d = xb - xa
        return xa + s0[:, None] * d, xa + s1[:, None] * d


def palm_anchor_offsets(model: HandModel, x: np.ndarray) -> np.ndarray:
    """``(..., A, 3)`` mm: the anchored joints (``HandModel.palm_anchor_joints``) of poses ``x``
    (..., J, 3) relative to the wrist, in the palm's frame (:meth:`Skeleton.palm_coordinates`)."""
    return model.skeleton.palm_coordinates(x)[..., model.palm_anchor_joints, :]


def _palm_chain(skeleton: Skeleton) -> np.ndarray:
    """The root's children from the index to the little finger (MCPs), or empty."""
    if skeleton.palm_joints is None:
        return np.zeros(0, dtype=np.int64)
    _, first, last = skeleton.palm_joints
    kids = np.sort(skeleton.children(skeleton.root))
    i, k = np.searchsorted(kids, first), np.searchsorted(kids, last)
    return kids[min(i, k) : max(i, k) + 1]


def _default_radii(skeleton: Skeleton, pairs: np.ndarray) -> np.ndarray:
    """``(C,)`` mm: each capsule's default radius, the skeleton's surface offset of the bone's
    parent joint (12 mm at the root and for the knuckle-line capsules after the bones)."""
    offsets = np.asarray(skeleton.surface_offsets_mm, dtype=np.float64)
    default = np.where(pairs[:, 0] == skeleton.root, 12.0, offsets[pairs[:, 0]])
    default[len(skeleton.bones) :] = 12.0
    return np.clip(default, 4.0, 20.0)


def build_model(
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray,
    radii_mm: np.ndarray | None = None,
    palm_dist_mm: np.ndarray | None = None,
) -> HandModel:
    """The capsule layout for ``skeleton`` with default radii (the skeleton's surface offsets of each
    bone's parent joint; 12 mm for palm capsules); palm distances from the skeleton's template
    pose geometry are unknown, so ``palm_dist_mm`` NaN means "no palm term" until
    :func:`personalize` measures them."""
    sk = skeleton
    if not sk.has_finger_segments:
        raise ValueError(
            f"the hand model needs fingers of three bones; layout {sk.name} has none "
            "(Skeleton.has_finger_segments): run without the model"
        )
    lengths = np.asarray(bone_lengths_mm, dtype=np.float64)
    bones = sk.bones
    mcps = _palm_chain(sk)
    extra = np.stack([mcps[:-1], mcps[1:]], axis=1) if len(mcps) > 1 else np.zeros((0, 2), int)
    pairs = np.concatenate([bones, extra]).astype(np.int64)
    default = _default_radii(sk, pairs)
    radii = default if radii_mm is None else np.asarray(radii_mm, dtype=np.float64)
    tip = np.isin(pairs[:, 1], np.asarray(sk.fingertips, dtype=np.int64))
    tip[len(bones) :] = False
    kids = np.sort(sk.children(sk.root))
    pp = np.array([(a, b) for i, a in enumerate(kids) for b in kids[i + 1 :]], dtype=np.int64)
    pp = pp.reshape(-1, 2)
    dist = np.full(len(pp), np.nan) if palm_dist_mm is None else np.asarray(palm_dist_mm, float)
    if radii.shape != (len(pairs),):
        raise ValueError(f"radii_mm must be ({len(pairs)},), got {radii.shape}")
    return HandModel(sk, lengths, pairs, radii, tip, pp, dist)


# ------------------------------------------------------------------------------------------------
# observations of a frame
# ------------------------------------------------------------------------------------------------
@dataclass
class FrameObservations:
    """What the fit sees of ``n`` frames (from their normalized crops).

    ``points`` (n, M, 3) mm observed hand points, ``valid`` (n, M) bool; ``depth`` (n, S, S) mm
    observed depth per crop pixel (NaN off the hand); ``nearest`` (n, S, S) int32 flat crop index
    of the nearest hand pixel or pixel past the image's border (distance transform); ``boxes``
    (n, 4) crop boxes.
    """

    points: np.ndarray
    valid: np.ndarray
    depth: np.ndarray
    nearest: np.ndarray
    boxes: np.ndarray

    def take(self, idx) -> FrameObservations:
        return FrameObservations(
            self.points[idx], self.valid[idx], self.depth[idx], self.nearest[idx], self.boxes[idx]
        )

    def thinned(self, points: int | None) -> FrameObservations:
        """These frames seeing about ``points`` of their observed points (every k-th; None: all),
        for ranking many candidate poses, which needs fewer points than a fit."""
        if not points:
            return self
        k = max(1, self.points.shape[1] // int(points))
        return FrameObservations(
            self.points[:, ::k], self.valid[:, ::k], self.depth, self.nearest, self.boxes
        )

    @staticmethod
    def allocate(n: int, size: int, max_points: int | None = None) -> FrameObservations:
        """``n`` frames of crops ``size`` px seeing nothing yet (no points, NaN depth), up to
        ``max_points`` points each (None: :data:`OBSERVED_POINTS`); :func:`observe` fills them."""
        m = OBSERVED_POINTS if max_points is None else int(max_points)
        return FrameObservations(
            np.zeros((n, m, 3)), np.zeros((n, m), dtype=bool),
            np.full((n, size, size), np.nan, dtype=np.float32),
            np.zeros((n, size, size), dtype=np.int32), np.zeros((n, 4)),
        )  # fmt: skip

    @staticmethod
    def concatenate(parts: list[FrameObservations]) -> FrameObservations:
        """The frames of ``parts`` (non-empty), in order."""
        return FrameObservations(
            *(np.concatenate([getattr(o, f) for o in parts]) for f in _OBS_FIELDS)
        )


_OBS_FIELDS = ("points", "valid", "depth", "nearest", "boxes")


#: observed hand points per frame (:func:`observe`), for personalization and, by default
#: (``FitWeights.points``), for the per-frame fit
OBSERVED_POINTS = 512

#: :func:`wrist_planes`: pixels more than this far behind a pose's wrist (along its wrist ->
#: knuckles axis) are not sampled as points. The fit ignores every point behind the wrist
#: (:func:`_forearm`; since stop 49 up to ``-FitWeights.forearm_behind_mm`` past it), and on the
#: suite's tune part about half of the sampled points lay behind it;
#: the margin leaves room for the pose the plane comes from (a lifted reference, the propagated
#: initialization) being off at the wrist (20 mm chosen on the tune part; 40 mm, with
#: propagation's points cut as well, was tried: HISTORY.md, stop 45).
FOREARM_SAMPLING_MARGIN_MM = 20.0


def wrist_planes(
    skeleton: Skeleton, joints_mm: np.ndarray, margin_mm: float = FOREARM_SAMPLING_MARGIN_MM
) -> np.ndarray:
    """``(..., 4)`` per pose of ``joints_mm`` (..., J, 3) mm the plane :func:`observe` samples in
    front of: the unit wrist -> knuckles axis ``a`` (3) and the offset ``a . wrist - margin_mm``
    (mm); a point ``p`` lies behind it when ``a . p`` is below the offset. NaN rows (a pose with
    missing joints, a layout without a palm): no plane."""
    x = np.asarray(joints_mm, dtype=np.float64)
    out = np.full(x.shape[:-2] + (4,), np.nan)
    chain = _palm_chain(skeleton)
    if not len(chain):
        return out
    wrist = x[..., skeleton.root, :]
    out[..., :3] = _wrist_axis(x, skeleton.root, chain)
    out[..., 3] = np.sum(out[..., :3] * wrist, axis=-1) - float(margin_mm)
    out[~np.all(np.isfinite(out), axis=-1)] = np.nan
    return out


def observe(
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    *,
    cube_mm: float = DEFAULT_CROP.cube_mm,
    max_points: int | None = None,
    out: FrameObservations | None = None,
    planes: np.ndarray | None = None,
) -> FrameObservations:
    """Observations of frames from their crops ``(n, S, S)`` (normalized, background ±1); written
    into ``out`` (``n`` frames, e.g. a slice of a longer sequence's) and returned when given.

    Hand pixels are the crop values strictly inside (-1, 1); up to ``max_points`` of them, evenly
    spaced in raster order, become 3D points ``(crop px -> image px, depth z_c + v·cube/2)``
    (None: :data:`OBSERVED_POINTS`). Pixels clamped to -1 (surface in front of the cube, depth
    unknown) are silhouette (``nearest``) with the cube's frontmost depth ``z_c - cube``
    (``depth``), but give no points. ``planes`` ``(n, 4)`` (:func:`wrist_planes` of a pose per
    frame; NaN rows and None: none): hand pixels behind their frame's plane (its forearm) stay
    silhouette and depth but give no points, so the points the fit uses fall on the hand; a
    plane with every pixel behind it (a pose off the hand) is ignored.
    """
    max_points = OBSERVED_POINTS if max_points is None else int(max_points)
    n, s = crops.shape[0], crops.shape[-1]
    boxes = np.asarray(boxes, dtype=np.float64).reshape(n, 4)
    zc = np.asarray(centres_mm, dtype=np.float64).reshape(n, 3)[:, 2]
    half = 0.5 * cube_mm
    if planes is not None:
        planes = np.asarray(planes, dtype=np.float64).reshape(n, 4)
    if out is None:
        out = FrameObservations.allocate(n, s, max_points)
    elif out.points.shape != (n, max_points, 3) or out.depth.shape != (n, s, s):
        raise ValueError(
            f"out holds {out.points.shape} points and {out.depth.shape} depth, "
            f"not ({n}, {max_points}, 3) and ({n}, {s}, {s})"
        )
    else:  # whatever it held: nothing seen yet
        out.points[:], out.valid[:], out.depth[:], out.nearest[:] = 0.0, False, np.nan, 0
    out.boxes[:] = boxes
    points, valid, depth, nearest = out.points, out.valid, out.depth, out.nearest
    grid = np.arange(s * s, dtype=np.int32).reshape(s, s)
    for i in range(n):
        crop = np.asarray(crops[i], dtype=np.float32)
        fg = np.abs(crop) < 0.999
        # -1 is surface somewhere between z_c - cube and z_c - cube/2 (a finger pointing at the
        # camera): the model may lie there, but a made-up depth would drag it
        front = crop <= -0.999
        silhouette = fg | front
        flat = np.flatnonzero(fg)
        if not silhouette.any() or not np.isfinite(zc[i]):
            nearest[i] = grid
            continue
        # nearest surface within 3x3 crop px: a model sample is "in front" only if it is in front
        # of every surface it could project onto after resampling (no false violations at edges)
        surface = np.where(fg, zc[i] + half * crop, np.where(front, zc[i] - 2.0 * half, np.inf))
        d = minimum_filter(surface, size=3, mode="nearest")
        depth[i] = np.where(np.isfinite(d), d, np.nan)
        if len(flat):  # a hand wholly in front of the cube is silhouette without points
            pts = None  # every hand pixel's point, where a plane needs them all
            if planes is not None and np.all(np.isfinite(planes[i])):
                pts = _pixel_points(flat, crop, boxes[i], zc[i], half, camera)
                front_of = pts @ planes[i, :3] >= planes[i, 3]
                if np.any(front_of):
                    flat, pts = flat[front_of], pts[front_of]
            take = np.linspace(0, len(flat) - 1, min(max_points, len(flat))).round().astype(int)
            take = np.unique(take)
            k = len(take)
            points[i, :k] = (
                pts[take]
                if pts is not None
                else _pixel_points(flat[take], crop, boxes[i], zc[i], half, camera)
            )
            valid[i, :k] = True
        # past the image's border the hand may be: the nearest place a model sample may lie
        beyond = _beyond_image(s, boxes[i], camera)
        _, ind = distance_transform_edt(~(silhouette | beyond), return_indices=True)
        nearest[i] = ind[0] * s + ind[1]
    return out


def _in_image(coord_px: np.ndarray, side_px: int) -> np.ndarray:
    """Bool mask: image coordinates ``coord_px`` (one axis, any shape) that fall on one of the
    image's ``side_px`` pixels along that axis (NaN: False)."""
    return (coord_px >= -0.5) & (coord_px <= side_px - 0.5)


def _in_view(uv_px: np.ndarray, camera) -> np.ndarray:
    """Bool mask ``(...)``: image points ``uv_px`` (..., 2) that fall on one of the image's
    pixels (:func:`_in_image` along both axes)."""
    return _in_image(uv_px[..., 0], camera.width) & _in_image(uv_px[..., 1], camera.height)


def _beyond_image(size: int, box: np.ndarray, camera) -> np.ndarray:
    """``(S, S)`` bool: the pixels of a ``size`` x ``size`` crop with box ``box`` (4,) that lie
    outside the camera's image (the crop shows no depth there: the sensor saw nothing). A crop
    box is axis-aligned, so a column's u and a row's v decide it."""
    ax = np.arange(size, dtype=np.float64)
    uv = crop_to_image(np.stack([ax, ax], axis=-1), box)  # (S, 2): column u, row v
    return ~_in_image(uv[:, 1], camera.height)[:, None] | ~_in_image(uv[:, 0], camera.width)[None]


def _pixel_points(flat, crop, box, z_c: float, half: float, camera) -> np.ndarray:
    """``(K, 3)`` mm camera points of the crop pixels ``flat`` (K,) (flat indices into the S x S
    ``crop``, normalized depth): the image pixel the crop sampled (nearest) at depth
    ``z_c + half * value``."""
    s = crop.shape[-1]
    xy = np.stack([flat % s, flat // s], axis=-1).astype(np.float64)
    uv = np.rint(crop_to_image(xy, box))
    z = z_c + half * crop.reshape(-1)[flat].astype(np.float64)
    return camera.backproject(uv, z)


# ------------------------------------------------------------------------------------------------
# weights and priors
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FitWeights:
    """Weights λ of the per-frame model energy (see the module docstring for units).

    ``data``/``free_space`` multiply the *mean* robust cost over a frame's points/samples, so a
    frame's energy does not scale with the number of hand pixels.
    """

    data: float = 100.0
    data_scale_mm: float = 8.0  #: scale of the robust point-to-surface loss (12 before; tune part)
    data_robust: str = "welsch"  #: "welsch" (redescending) or "huber"
    free_space: float = 50.0
    free_huber_mm: float = 5.0
    free_margin_mm: float = 3.0  #: a model sample may lie this far in front of the observed surface
    free_tolerance_px: float = 1.0  #: ... or this far (image px) off the silhouette
    angle: float = (
        0.1  #: per degree² outside the limits (0.01 let a thumb tip fold into its own capsule)
    )
    palm: float = 1.0
    #: points near the root end of a palm capsule (foot at t <= forearm_t) and less than
    #: forearm_margin_mm past the wrist towards the fingers are taken as forearm and ignored
    forearm_t: float = 0.6
    forearm_margin_mm: float = 40.0
    #: points more than this far behind the wrist (along the wrist -> knuckles axis) are forearm
    #: whatever their nearest capsule (an egocentric forearm fills half the crop). Negative: the
    #: wrist's own bulk past the joint centre belongs to the arm too; an arm nearer the camera
    #: than the hand hides the wrist behind it, and those points, taken as palm, pulled the
    #: palm's wrist end towards the camera (the three forearm values chosen on the suite's tune
    #: part, HISTORY.md stop 49; 0.35 / 25 / 0 before)
    forearm_behind_mm: float = -25.0
    collision: float = 1.0  #: per mm² of interpenetration of capsules of different fingers
    collision_slack_mm: float = 1.0
    pose: float = 0.02  #: per mm² per joint to the prior pose Y (temporal closeness / start)
    pose_huber_mm: float = 20.0
    uv: float = 0.002  #: per px² per joint to the prior 2D positions
    #: times the model's pose prior (half the squared Mahalanobis distance of the bone
    #: directions, :mod:`handanno_core.pose_prior`; none without ``HandModel.pose_prior``);
    #: chosen on the tune part from 1, 3, 10 (README, stop 33)
    prior: float = 3.0
    iterations: int = 12
    max_rejects: int = 3  #: a frame stops after this many rejected LM steps in a row
    #: observed points per frame of the per-frame fit in propagation and refinement (the nearest
    #: capsule of every point is most of the fit's cost); personalization and the references'
    #: level always observe :data:`OBSERVED_POINTS`. 256 saved ~8 % of a bench's CPU but cost
    #: accuracy on the tune part (5 % forest, final mean: smooth 1.59 -> 1.66 mm, shape-fast
    #: 11.50 -> 12.86, fpha-1 11.71 -> 12.24), so 512 stays
    points: int = OBSERVED_POINTS


@dataclass
class Priors:
    """Per-frame priors (n frames): ``pose`` (n,J,3) mm with weights ``pose_w`` (n,J) (0 = none);
    ``uv`` (n,J,2) image px with ``uv_w`` (n,J)."""

    pose: np.ndarray | None = None
    pose_w: np.ndarray | None = None
    uv: np.ndarray | None = None
    uv_w: np.ndarray | None = None

    def take(self, idx) -> Priors:
        def t(a):
            return None if a is None else a[idx]

        return Priors(t(self.pose), t(self.pose_w), t(self.uv), t(self.uv_w))


# ------------------------------------------------------------------------------------------------
# robust helpers
# ------------------------------------------------------------------------------------------------
def _huber(r_abs, delta):
    inside = r_abs <= delta
    cost = np.where(inside, 0.5 * r_abs**2, delta * (r_abs - 0.5 * delta))
    return cost, np.where(inside, 1.0, delta / np.maximum(r_abs, 1e-12))


def _welsch(r_abs, scale):
    e = np.exp(-((r_abs / scale) ** 2))
    return 0.5 * scale**2 * (1.0 - e), e


# ------------------------------------------------------------------------------------------------
# energy
# ------------------------------------------------------------------------------------------------
_SAMPLE_T = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0])
_SAMPLE_PHI = np.radians([-45.0, 0.0, 45.0])


def _forearm(model: HandModel, x, points, cidx, t, w: FitWeights) -> np.ndarray:
    """(n,M) bool: points taken as forearm (ignored) for joints ``x`` (n,J,3): more than
    ``forearm_behind_mm`` behind the wrist along the wrist -> knuckles axis, or nearest to the
    root end (foot ``t`` <= ``forearm_t``) of a capsule at the root and less than
    ``forearm_margin_mm`` past the wrist."""
    root = model.skeleton.root
    axis = _wrist_axis(x, root, model.palm_chain)
    along = np.einsum("nmx,nx->nm", points - x[:, None, root], axis)
    near = model.wrist[cidx] & (t <= w.forearm_t) & (along < w.forearm_margin_mm)
    return near | (along < -w.forearm_behind_mm)


def _nearest_capsule(points, a, b, radii):
    """For points (n,M,3) and capsules A, B (n,C,3): index (n,M), t (n,M), distance to the axis
    segment (n,M) mm, signed surface distance (n,M) of the nearest capsule surface.

    The nearest capsule is chosen in float32 (coordinates relative to the frame's mean capsule
    end, where float32 resolves distances to ~1e-4 mm; 2-3x faster than float64 over all M·C
    pairs); t and the distances of the chosen capsule are then computed in float64."""
    c_count = a.shape[1]
    origin = a.mean(axis=1, keepdims=True)
    p32 = (points - origin).astype(np.float32)
    a32 = (a - origin).astype(np.float32)
    d = b - a
    d32 = d.astype(np.float32)
    dd = np.maximum(np.einsum("ncx,ncx->nc", d32, d32), np.float32(1e-9))[:, None, :]
    prod = np.matmul(p32, np.concatenate([d32, a32], axis=1).transpose(0, 2, 1))  # (n,M,2C)
    pd = prod[..., :c_count] - np.einsum("ncx,ncx->nc", a32, d32)[:, None, :]
    t = np.clip(pd / dd, 0.0, 1.0)
    pa2 = (
        np.einsum("nmx,nmx->nm", p32, p32)[..., None]
        - 2.0 * prod[..., c_count:]
        + np.einsum("ncx,ncx->nc", a32, a32)[:, None, :]
    )
    dist2 = np.maximum(pa2 - t * (2.0 * pd - t * dd), 0.0)
    c = np.argmin(np.sqrt(dist2) - radii.astype(np.float32), axis=-1)
    ai = np.take_along_axis(a, c[..., None], 1)
    di = np.take_along_axis(d, c[..., None], 1)
    pa = points - ai
    ti = np.einsum("nmx,nmx->nm", pa, di) / np.maximum(np.einsum("nmx,nmx->nm", di, di), 1e-9)
    ti = np.clip(ti, 0.0, 1.0)
    dist = np.linalg.norm(pa - ti[..., None] * di, axis=-1)
    return c, ti, dist, dist - radii[c]


_XYZ = np.arange(3)


class _Accumulator:
    """Residual rows of the Gauss-Newton normal equations, each depending on (at most) two joints,
    collected per frame; :func:`_assemble` sums them in joint space and maps them to θ."""

    def __init__(self, n: int, j: int, compact: bool = False):
        self.n = n
        self.compact = compact
        self.rows: list[tuple] = []
        self.joint_h = np.zeros((n, j, 3, 3))
        self.joint_g = np.zeros((n, j, 3))

    def add_points(self, ja, jb, ca, cb, grad, w, r):
        """Residuals ``r`` (n,R) at points ``s = ca·X_ja + cb·X_jb + const`` with ∂r/∂s ``grad``
        (n,R,3) and IRLS weights ``w`` (n,R) (0 = unused); ja, jb, ca, cb broadcast to (n,R).
        With ``compact`` (the rows are assembled at once, not kept row-wise by the batched LM)
        rows unused in every frame (most collision and free-space samples) are dropped here;
        :func:`_assemble` skips the unused rows of a frame anyway, in the same order."""
        shape = w.shape
        used = np.any(w != 0, axis=0) if self.compact else None
        if used is not None and not used.all():
            if not used.any():
                return
            cols = np.flatnonzero(used)
            ja, jb, ca, cb, w, r = (
                np.broadcast_to(v, shape)[:, cols] for v in (ja, jb, ca, cb, w, r)
            )
            grad = np.broadcast_to(grad, shape + (3,))[:, cols]
            shape = w.shape
        ja, jb = np.broadcast_to(ja, shape), np.broadcast_to(jb, shape)
        ca, cb = np.broadcast_to(ca, shape), np.broadcast_to(cb, shape)
        j6 = np.concatenate([grad * ca[..., None], grad * cb[..., None]], axis=-1)  # (n,R,6)
        idx = np.concatenate([3 * ja[..., None] + _XYZ, 3 * jb[..., None] + _XYZ], axis=-1)
        self.rows.append((idx, j6, np.broadcast_to(w, shape), np.broadcast_to(r, shape)))

    def add_joint(self, w3, g3):
        """Per-joint x-space blocks ``w3`` (n,J,3,3) and gradients ``g3`` (n,J,3)."""
        self.joint_h += w3
        self.joint_g += g3

    def state(self) -> tuple:
        """The rows as arrays with a leading frame axis: joint-coordinate indices (n,R,6),
        ∂r/∂x at them (n,R,6), weights (n,R), residuals (n,R), joint blocks (n,J,3,3), (n,J,3)."""
        n = self.n
        if not self.rows:
            return (np.zeros((n, 0, 6), np.int64), np.zeros((n, 0, 6)), np.zeros((n, 0)),
                    np.zeros((n, 0)), self.joint_h, self.joint_g)  # fmt: skip
        return (
            *(np.concatenate([r[i] for r in self.rows], axis=1) for i in range(4)),
            self.joint_h,
            self.joint_g,
        )


def _assemble(state: tuple, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H (n,P,P), g (n,P)) in θ of an :meth:`_Accumulator.state`: summed in joint space
    (3J×3J, one ``np.bincount``) and mapped through dX/dθ ``m`` (n,3J,P): ``H = mᵀ H_x m``."""
    idx, j6, w, res, joint_h, joint_g = state
    n, j = joint_h.shape[:2]
    d = 3 * j
    f, k = np.nonzero(w)  # rows with weight only
    hx = np.zeros(n * d * d)
    gx = np.zeros(n * d)
    if len(f):
        idx, j6, res = idx[f, k], j6[f, k], res[f, k]
        jw = j6 * w[f, k][:, None]
        hflat = (f * d * d)[:, None, None] + idx[:, :, None] * d + idx[:, None, :]
        hx = np.bincount(hflat.ravel(), (jw[:, :, None] * j6[:, None, :]).ravel(), n * d * d)
        gx = np.bincount(((f * d)[:, None] + idx).ravel(), (jw * res[:, None]).ravel(), n * d)
    hx = hx.reshape(n, j, 3, j, 3)
    ar = np.arange(j)
    hx[:, ar, :, ar, :] += joint_h.transpose(1, 0, 2, 3)
    gx = gx.reshape(n, d) + joint_g.reshape(n, d)
    mt = m.transpose(0, 2, 1)
    return mt @ hx.reshape(n, d, d) @ m, np.matmul(mt, gx[..., None])[..., 0]


def _normal_equations(model, kin, root, u, weights, state, v0, prior_r=None):
    """θ-space (H, g) of the energy whose rows ``state``, angle violations ``v0`` (n,2A) (or
    None) and pose-prior residuals ``prior_r`` (n,3A) (or None) were collected at (root (n,3),
    u (n,B,3))."""
    h, g = _assemble(state, kin.jacobian(u))
    if prior_r is not None and prior_r.size:
        jac_p = _prior_jacobian(model, kin, root, u, prior_r)
        lam = _prior_weight(model, weights)
        h += lam * np.matmul(jac_p.transpose(0, 2, 1), jac_p)
        g += lam * np.einsum("nrp,nr->np", jac_p, prior_r)
    if v0 is not None and v0.size:
        hit = np.flatnonzero(np.any(v0 > 0, axis=1))
        if len(hit):
            _, jac_a = angle_jacobian(
                model.skeleton, kin, root[hit], u[hit], v0=v0[hit], own_bones=True
            )
            h[hit] += weights.angle * np.matmul(jac_a.transpose(0, 2, 1), jac_a)
            g[hit] += weights.angle * np.einsum("nap,na->np", jac_a, v0[hit])
    return h, g


def _prior_weight(model: HandModel, weights: FitWeights) -> float:
    """The pose prior's weight in the fit (0: no prior)."""
    if model.pose_prior is None:
        return 0.0
    return weights.prior * model.pose_prior_weight


def frame_energy(
    model: HandModel,
    kin: Kinematics,
    root: np.ndarray,
    u: np.ndarray,
    obs: FrameObservations,
    camera: CameraIntrinsics,
    weights: FitWeights,
    priors: Priors | None = None,
    want_jac: bool = False,
    diagnostics: bool = True,
):
    """Energy of ``n`` frames at (root (n,3), u (n,B,3)).

    Returns ``(energy (n,), terms {name: (n,)}, x (n,J,3), extra)``; with ``want_jac`` ``extra`` =
    (H (n,P,P), g (n,P)) Gauss-Newton normal equations in θ, else per-capsule diagnostics
    ``{"capsule_data_mm": (n,C) mean |point residual| (NaN: no points), "capsule_free": (n,C)
    fraction of samples violating free space, "capsule_points": (n,C) observed points whose
    nearest capsule it is}`` (an empty dict without ``diagnostics``).
    """
    e, terms, x, extra = _energy(
        model, kin, root, u, obs, camera, weights, priors, want_jac, diagnostics, compact=True
    )
    if want_jac:
        extra = _normal_equations(model, kin, root, u, weights, *extra)
    return e, terms, x, extra


def frame_energy_rows(model: HandModel, kin: Kinematics, root, u, obs, camera, weights) -> tuple:
    """:func:`frame_energy` ``(n,)`` of ``n`` frames at (root (n,3), u (n,B,3)) with
    :class:`FrameObservations` ``obs``, the camera's intrinsics and :class:`FitWeights`, and its
    residual rows (opaque): :func:`rows_normal_equations` makes the θ-space normal equations of
    them, so that a solver takes them only at the evaluations it keeps (the same numbers as
    ``frame_energy(..., want_jac=True)``)."""
    e, _, _, rows = _energy(model, kin, root, u, obs, camera, weights, None, True, False, True)
    return e, rows


def rows_normal_equations(
    model: HandModel, kin: Kinematics, root, u, weights: FitWeights, rows: tuple
) -> tuple[np.ndarray, np.ndarray]:
    """``(H (n,P,P), g (n,P))`` of :func:`frame_energy_rows`'s ``rows`` taken at (root, u)."""
    return _normal_equations(model, kin, root, u, weights, *rows)


def _energy(
    model, kin, root, u, obs, camera, weights, priors, want_jac, diagnostics, compact=False
):
    """:func:`frame_energy` with, under ``want_jac``, the residual rows (an
    :meth:`_Accumulator.state`) and the angle violations (n,2A) (None: no angle term) in place
    of the normal equations, which :func:`_normal_equations` builds from them (``compact``: rows
    unused in every frame left out, see :meth:`_Accumulator.add_points`)."""
    w = weights
    x = kin.joints(root, u)
    n, j = x.shape[:2]
    a, b = model.capsules(x)
    s0, s1 = model.fractions
    pa, pb = model.pairs[:, 0], model.pairs[:, 1]
    c_count = len(model.pairs)
    terms = {}
    acc = _Accumulator(n, j, compact) if want_jac else None

    # ---------------- data: observed point -> nearest capsule surface
    pts = obs.points
    cidx, t, dist, sd = _nearest_capsule(pts, a, b, model.radii)
    forearm = _forearm(model, x, pts, cidx, t, w)
    use = obs.valid & ~forearm
    cnt = np.maximum(use.sum(axis=1), 1)
    if w.data_robust == "huber":
        cost, wr = _huber(np.abs(sd), w.data_scale_mm)
    else:
        cost, wr = _welsch(np.abs(sd), w.data_scale_mm)
    lam = w.data / cnt
    terms["data"] = lam * np.sum(np.where(use, cost, 0.0), axis=1)
    ai = np.take_along_axis(a, cidx[..., None], 1)
    bi = np.take_along_axis(b, cidx[..., None], 1)
    q = ai + t[..., None] * (bi - ai)
    nvec = (pts - q) / np.maximum(dist, 1e-9)[..., None]
    tau = s0[cidx] + t * (s1[cidx] - s0[cidx])
    if want_jac:
        wgt = np.where(use, lam[:, None] * wr, 0.0)
        acc.add_points(pa[cidx], pb[cidx], 1.0 - tau, tau, -nvec, wgt, sd)
    elif diagnostics:
        absr = np.where(use, np.abs(sd), 0.0)
        onehot = (cidx[..., None] == np.arange(c_count)) & use[..., None]
        num = onehot.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cap_data = np.einsum("nmc,nm->nc", onehot, absr) / num
        cap_data[num == 0] = np.nan

    # ---------------- free space: camera-facing samples must lie on the observed hand, not in front
    axis = b - a
    mid = 0.5 * (a + b)
    e = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9)
    v = -mid / np.linalg.norm(mid, axis=-1, keepdims=True)
    vp = v - np.sum(v * e, axis=-1, keepdims=True) * e
    vp /= np.maximum(np.linalg.norm(vp, axis=-1, keepdims=True), 1e-9)
    side = _cross(e, vp)
    dirs = (
        np.cos(_SAMPLE_PHI)[:, None, None, None] * vp
        + np.sin(_SAMPLE_PHI)[:, None, None, None] * side
    )
    dirs = dirs.transpose(1, 2, 0, 3)  # (n,C,K_phi,3)
    tt = np.repeat(_SAMPLE_T, len(_SAMPLE_PHI))  # (K,)
    dirs = np.tile(dirs, (1, 1, len(_SAMPLE_T), 1))  # (n,C,K,3)
    smp = (
        a[:, :, None]
        + tt[None, None, :, None] * axis[:, :, None]
        + model.radii[:, None, None] * dirs
    )
    k_count = len(tt)
    smp = smp.reshape(n, c_count * k_count, 3)
    uv = camera.project(smp)
    xy = image_to_crop(uv, obs.boxes[:, None, :])
    s_px = obs.depth.shape[-1]
    ix = np.clip(np.rint(np.nan_to_num(xy[..., 0], nan=-1.0)), 0, s_px - 1).astype(np.int64)
    iy = np.clip(np.rint(np.nan_to_num(xy[..., 1], nan=-1.0)), 0, s_px - 1).astype(np.int64)
    flat = iy * s_px + ix
    inside = (
        np.all(np.isfinite(xy), axis=-1)
        & (np.abs(xy[..., 0] - ix) <= 0.5)
        & (np.abs(xy[..., 1] - iy) <= 0.5)
    )
    dmap = obs.depth.reshape(n, -1)
    d_obs = np.take_along_axis(dmap, flat, 1)
    on_hand = inside & np.isfinite(d_obs)
    front = np.where(on_hand, np.maximum(d_obs - w.free_margin_mm - smp[..., 2], 0.0), 0.0)
    near = np.take_along_axis(obs.nearest.reshape(n, -1), flat, 1)
    target_uv = crop_to_image(
        np.stack([near % s_px, near // s_px], axis=-1).astype(np.float64), obs.boxes[:, None, :]
    )
    mm_per_px = smp[..., 2] / camera.fx
    # past the image's border the sensor saw nothing: a sample there is neither on the hand nor
    # off it (a hand partly out of view is not pulled into the image)
    off = ~on_hand & _in_view(uv, camera)
    duv = np.where(off[..., None], uv - target_uv, 0.0)
    duv = np.nan_to_num(duv)
    # a sample within ``free_tolerance_px`` image px of the silhouette is not penalized
    dn = np.linalg.norm(duv, axis=-1)
    duv *= (np.maximum(dn - w.free_tolerance_px, 0.0) / np.maximum(dn, 1e-9))[..., None]
    off_mm = np.maximum(dn - w.free_tolerance_px, 0.0) * mm_per_px
    viol = np.where(off, off_mm, front)
    fcost, fw = _huber(viol, w.free_huber_mm)
    lam_f = w.free_space / (c_count * k_count)
    terms["free_space"] = lam_f * np.sum(fcost, axis=1)
    if want_jac:
        cap = np.repeat(np.arange(c_count), k_count)
        ta = np.tile(tt, c_count)
        tau_s = s0[cap] + ta * (s1[cap] - s0[cap])
        ca = np.broadcast_to(1.0 - tau_s, (n, len(cap)))
        cb = np.broadcast_to(tau_s, (n, len(cap)))
        ja = np.broadcast_to(pa[cap], (n, len(cap)))
        jb = np.broadcast_to(pb[cap], (n, len(cap)))
        # in front of the surface: residual d_obs - margin - z (> 0), d/ds = -e_z
        gz = np.zeros((n, len(cap), 3))
        gz[..., 2] = -1.0
        wf = lam_f * fw
        acc.add_points(ja, jb, ca, cb, gz, np.where(on_hand & (front > 0), wf, 0.0), front)
        # off the silhouette: residual (mm) per image axis, d/ds = mm_per_px · ∂π/∂s
        pj = camera.projection_jacobian(smp) * mm_per_px[..., None, None]
        for axis_i in (0, 1):
            r_ax = duv[..., axis_i] * mm_per_px
            acc.add_points(ja, jb, ca, cb, pj[..., axis_i, :], np.where(off, wf, 0.0), r_ax)
    elif diagnostics:
        cap_free = (viol > 1.0).reshape(n, c_count, k_count).mean(axis=-1)

    # ---------------- collisions: capsules of different fingers must not interpenetrate
    terms["collision"] = np.zeros(n)
    fa, fk = model.collision_pairs
    if w.collision > 0 and len(fa):
        ts = np.array([0.0, 0.5, 1.0])
        tau_s = s0[fa, None] + ts * (s1[fa, None] - s0[fa, None])  # (Q,3)
        sp = a[:, fa, None] + ts[:, None] * (b[:, fa] - a[:, fa])[:, :, None]  # (n,Q,3,3)
        ak, bk = a[:, fk, None], b[:, fk, None]
        dk = bk - ak
        tq = np.clip(
            np.sum((sp - ak) * dk, axis=-1) / np.maximum(np.sum(dk * dk, axis=-1), 1e-9), 0, 1
        )
        qp = ak + tq[..., None] * dk
        dv = sp - qp
        dist = np.linalg.norm(dv, axis=-1)
        pen = np.maximum(
            model.radii[fa, None] + model.radii[fk, None] - w.collision_slack_mm - dist, 0
        )
        terms["collision"] = w.collision * 0.5 * np.sum(pen**2, axis=(1, 2))
        if want_jac:
            nv = (dv / np.maximum(dist, 1e-9)[..., None]).reshape(n, -1, 3)
            wc = np.where(pen > 0, w.collision, 0.0).reshape(n, -1)
            r = pen.reshape(n, -1)
            tau_q = (s0[fk, None] + tq * (s1[fk, None] - s0[fk, None])).reshape(n, -1)
            tau_s = np.broadcast_to(tau_s, (n,) + tau_s.shape).reshape(n, -1)
            ia = np.broadcast_to(pa[fa, None], (n, len(fa), 3)).reshape(n, -1)
            ib = np.broadcast_to(pb[fa, None], (n, len(fa), 3)).reshape(n, -1)
            ka = np.broadcast_to(pa[fk, None], (n, len(fa), 3)).reshape(n, -1)
            kb = np.broadcast_to(pb[fk, None], (n, len(fa), 3)).reshape(n, -1)
            acc.add_points(ia, ib, 1.0 - tau_s, tau_s, -nv, wc, r)
            acc.add_points(ka, kb, 1.0 - tau_q, tau_q, nv, wc, r)

    # ---------------- palm shape
    terms["palm"] = np.zeros(n)
    ok = np.isfinite(model.palm_dist_mm)
    if w.palm > 0 and np.any(ok):
        qa, qb = model.palm_pairs[ok, 0], model.palm_pairs[ok, 1]
        dv = x[:, qa] - x[:, qb]
        ln = np.linalg.norm(dv, axis=-1)
        r = ln - model.palm_dist_mm[ok]
        terms["palm"] = w.palm * 0.5 * np.sum(r**2, axis=1)
        if want_jac:
            unit = dv / np.maximum(ln, 1e-9)[..., None]
            acc.add_points(qa, qb, 1.0, -1.0, unit, np.full((n, len(qa)), w.palm), r)
    if w.palm > 0 and model.palm_anchor_mm is not None and len(model.palm_anchor_joints):
        # X_a - X_root - R c_a, R the palm's frame of this pose (held fixed in the Jacobian)
        ja = model.palm_anchor_joints
        rot = model.skeleton.palm_rotation(x)  # (n, 3, 3)
        want = np.einsum("nkc,ac->nak", rot, model.palm_anchor_mm)
        v = (x[:, ja] - x[:, model.skeleton.root, None] - want).reshape(n, -1)  # (n, 3A)
        terms["palm"] = terms["palm"] + w.palm * 0.5 * np.sum(v**2, axis=1)
        if want_jac:
            rows = np.repeat(ja, 3)
            unit = np.broadcast_to(np.tile(np.eye(3), (len(ja), 1)), (n, 3 * len(ja), 3))
            acc.add_points(rows, model.skeleton.root, 1.0, -1.0, unit, np.full(v.shape, w.palm), v)

    # ---------------- priors: pose (temporal closeness / start) and 2D
    terms["pose"] = np.zeros(n)
    terms["uv"] = np.zeros(n)
    if priors is not None and priors.pose is not None and w.pose > 0:
        dvec = np.nan_to_num(x - priors.pose)
        pw = np.where(np.all(np.isfinite(priors.pose), axis=-1), priors.pose_w, 0.0)
        pc, pirls = _huber(np.linalg.norm(dvec, axis=-1), w.pose_huber_mm)
        terms["pose"] = w.pose * np.sum(pw * pc, axis=1)
        if want_jac:
            ww = w.pose * pw * pirls
            acc.add_joint(ww[..., None, None] * np.eye(3), ww[..., None] * dvec)
    if priors is not None and priors.uv is not None and w.uv > 0:
        pj = camera.projection_jacobian(x)
        res = np.nan_to_num(camera.project(x) - priors.uv)
        uw = np.where(np.all(np.isfinite(priors.uv), axis=-1), priors.uv_w, 0.0)
        terms["uv"] = w.uv * 0.5 * np.sum(uw * np.sum(res**2, axis=-1), axis=1)
        if want_jac:
            ww = (w.uv * uw)[..., None, None]
            acc.add_joint(
                ww * np.einsum("nkac,nkad->nkcd", pj, pj),
                ww[..., 0] * np.einsum("nkac,nka->nkc", pj, res),
            )

    # ---------------- joint-angle limits
    terms["angle"] = np.zeros(n)
    v0 = None
    if w.angle > 0 and model.skeleton.flexion_limits_deg is not None:
        v0 = angle_violation(model.skeleton, x)
        terms["angle"] = w.angle * 0.5 * np.sum(v0**2, axis=1)

    # ---------------- pose prior (the session's)
    terms["prior"] = np.zeros(n)
    prior_r = None
    lam_p = _prior_weight(model, w)
    if lam_p > 0:
        prior_r = pose_prior_residuals(model, x)
        terms["prior"] = lam_p * 0.5 * np.sum(prior_r**2, axis=1)

    energy = sum(terms.values())
    if want_jac:
        return energy, terms, x, (acc.state(), v0, prior_r)
    if diagnostics:
        return (
            energy,
            terms,
            x,
            {
                "capsule_data_mm": cap_data,
                "capsule_free": cap_free,
                "capsule_points": num,
            },
        )
    return energy, terms, x, {}


# ------------------------------------------------------------------------------------------------
# the fit
# ------------------------------------------------------------------------------------------------
@dataclass
class FitResult:
    """``joints_mm`` (n,J,3), ``energy`` (n,) final, ``energy_start`` (n,) at the start, ``terms``
    per term (n,), ``root``/``u`` the parameters, ``iterations`` run."""

    joints_mm: np.ndarray
    energy: np.ndarray
    energy_start: np.ndarray
    terms: dict
    root: np.ndarray
    u: np.ndarray
    iterations: int


def fit_frames(
    model: HandModel,
    start_mm: np.ndarray,
    obs: FrameObservations,
    camera: CameraIntrinsics,
    *,
    weights: FitWeights | None = None,
    priors: Priors | None = None,
    iterations: int | None = None,
    kin: Kinematics | None = None,
) -> FitResult:
    """Fit the model to ``n`` frames independently from poses ``start_mm`` (n,J,3) mm.

    Levenberg-Marquardt per frame (batched), each step accepted only if it lowers that frame's
    energy; stops when no frame improves by more than 1e-4 relative.
    """
    w = weights or FitWeights()
    kin = kin or Kinematics(model.skeleton, model.bone_lengths_mm)
    root, u = kin.fit(np.asarray(start_mm, dtype=np.float64))

    def evaluate(pose, rows) -> _FrameFit:
        pri = None if priors is None else priors.take(rows)
        e, t, xj, (state, v0, prior_r) = _energy(
            model, kin, *pose, obs.take(rows), camera, w, pri, True, False
        )
        none = np.zeros((len(e), 0))
        return _FrameFit(
            e, t, xj, state, none if v0 is None else v0, none if prior_r is None else prior_r
        )

    def normal_equations(pose, ev: _FrameFit) -> lm.BatchedNormalEquations:
        h, g = _normal_equations(model, kin, *pose, w, ev.state, ev.v0, ev.prior_r)
        return lm.BatchedNormalEquations(h, g, np.einsum("npp->np", h) + 1e-6)

    first = evaluate((root, u), np.arange(len(root)))
    fit = lm.levenberg_marquardt_batched(
        evaluate,
        (root, u),
        normal_equations=normal_equations,
        retract=lambda pose, step: kin.retract(*pose, step),
        max_iter=iterations or w.iterations,
        lam0=1e-3,
        up=10.0,
        down=0.3,
        floor=1e-7,
        rtol=1e-4,
        max_lam=1e4,
        max_rejects=w.max_rejects,
        first=first,
        active_rows=True,
    )
    ev = fit.evaluation
    return FitResult(ev.x, ev.cost, first.cost.copy(), ev.terms, *fit.x, fit.iterations)


#: flexions a finger is set to by :func:`refit_fingers`: (first joint, each further joint) as
#: fractions of the joints' flexion ranges (``Skeleton.angle_limits()``), from extended to curled
FINGER_FLEXIONS = tuple((a, b) for a in (0.05, 0.3, 0.55, 0.8) for b in (0.05, 0.3, 0.55, 0.8))

#: observed points per frame candidate poses are ranked on (:func:`refit_fingers`,
#: :func:`library_starts`' callers; the nearest capsule of every point is most of the cost)
RANKING_POINTS = 256

#: rows of candidate poses whose energy is evaluated at once (each holds an (M, 2C) float32 block)
RANKING_CHUNK = 256


def finger_chains(skeleton: Skeleton) -> list[np.ndarray]:
    """Per finger (chain below a child of the root), the positions in ``skeleton.angle_joints`` of
    its angle joints, proximal first (fingers without angle joints are left out)."""
    base = skeleton.finger_bases
    order = np.argsort(skeleton.topological_order)  # a joint's place: proximal first
    groups: dict[int, list[tuple[int, int]]] = {}
    for i, k in enumerate(skeleton.angle_joints):
        groups.setdefault(int(base[k]), []).append((int(order[k]), i))
    return [np.array([i for _, i in sorted(g)], dtype=np.int64) for _, g in sorted(groups.items())]


def grid_flexions(skeleton: Skeleton, fractions=FINGER_FLEXIONS) -> np.ndarray:
    """(K, A) flexion targets, degrees: per ``(first, further)`` pair of ``fractions`` of each
    joint's flexion range, the first joint of every finger at ``first``, the others at
    ``further``."""
    fl, _ = skeleton.angle_limits()
    first = np.zeros(len(fl), dtype=bool)
    first[[int(c[0]) for c in finger_chains(skeleton)]] = True
    q = np.asarray(fractions, dtype=np.float64).reshape(-1, 2)
    frac = np.where(first[None], q[:, :1], q[:, 1:])
    return fl[:, 0] + frac * (fl[:, 1] - fl[:, 0])


#: fractions of the first finger joints' abduction ranges tried with every flexion pair by
#: :func:`finger_grid` (a finger that slid onto its neighbour is an abduction away from its points)
FINGER_ABDUCTIONS = (0.1, 0.5, 0.9)


def finger_grid(
    skeleton: Skeleton, flexions=FINGER_FLEXIONS, abductions=FINGER_ABDUCTIONS
) -> tuple[np.ndarray, np.ndarray]:
    """Hypotheses of :func:`refit_fingers` over flexion and abduction: flexion targets (K, A) and
    abduction targets (K, A) degrees, every :func:`grid_flexions` row with every finger's first
    joint at each of ``abductions`` (fractions of its abduction range; the other joints' abduction
    NaN: kept). K = len(flexions) * len(abductions)."""
    g = grid_flexions(skeleton, flexions)
    _, ab = skeleton.angle_limits()
    first = np.array([int(c[0]) for c in finger_chains(skeleton)], dtype=np.int64)
    flex, abd = [], []
    for a in abductions:
        t = np.full_like(g, np.nan)
        t[:, first] = ab[first, 0] + float(a) * (ab[first, 1] - ab[first, 0])
        flex.append(g)
        abd.append(t)
    return np.concatenate(flex), np.concatenate(abd)


def finger_targets(
    skeleton: Skeleton, poses: np.ndarray, owner: np.ndarray, n: int, fractions=FINGER_FLEXIONS
) -> tuple[np.ndarray, np.ndarray]:
    """Hypotheses of :func:`refit_fingers` for ``n`` frames: flexion and abduction targets (n,K,A)
    degrees, the grid :func:`grid_flexions` (abduction kept: NaN) followed by the angles of each
    frame's own candidate poses ``poses`` (S,J,3) (``owner`` (S,): the frame each belongs to;
    e.g. the references before and after it); a frame with fewer poses than the most gets NaN
    (keep: the fit itself) in the remaining slots."""
    g = grid_flexions(skeleton, fractions)
    owner = np.asarray(owner, dtype=np.int64)
    counts = np.bincount(owner, minlength=n)
    k = int(counts.max()) if len(owner) else 0
    fl_p, ab_p = _meter(skeleton)(np.asarray(poses, dtype=np.float64))
    order = np.argsort(owner, kind="stable")
    slot = np.arange(len(owner)) - np.concatenate([[0], np.cumsum(counts)[:-1]])[owner[order]]
    pf = np.full((n, k, g.shape[1]), np.nan)
    pa = np.full_like(pf, np.nan)
    pf[owner[order], slot] = fl_p[order]
    pa[owner[order], slot] = ab_p[order]
    flex = np.concatenate([np.broadcast_to(g, (n,) + g.shape), pf], axis=1)
    return flex, np.concatenate([np.full((n,) + g.shape, np.nan), pa], axis=1)


def _rotate(v: np.ndarray, axis: np.ndarray, deg: np.ndarray) -> np.ndarray:
    """Unit ``v`` (..., 3) turned by ``deg`` (...) about unit ``axis`` (..., 3) (Rodrigues)."""
    t = np.radians(deg)[..., None]
    c, s = np.cos(t), np.sin(t)
    return v * c + _cross(axis, v) * s + axis * np.sum(axis * v, axis=-1, keepdims=True) * (1 - c)


def finger_hypotheses(
    skeleton: Skeleton,
    kin: Kinematics,
    root: np.ndarray,
    u: np.ndarray,
    flexion_deg: np.ndarray,
    abduction_deg: np.ndarray | None = None,
) -> np.ndarray:
    """Bone directions (n, F, K, B, 3) of the poses (root (n,3), u (n,B,3)) with one finger ``F``
    (:func:`finger_chains`) at a time set to the flexions ``flexion_deg`` (K, A) or (n, K, A)
    degrees (:meth:`Skeleton.joint_angles`' angle joints; NaN: keep) and, at the finger's first
    joint, the abductions ``abduction_deg`` (same shape; None or NaN: keep). The subtree below
    each of the finger's angle joints is turned about that joint's flexion axis, distal joints
    first, then the first joint's about its abduction axis (the other fingers and the root
    unchanged; bones stay exact; the resulting angles match the targets up to the coupling of
    flexion and abduction)."""
    n = len(u)
    x = kin.joints(root, u)
    flex, abd, lateral = _meter(skeleton)(x, axes=True)
    par = skeleton.parent_array
    aj = skeleton.angle_joints
    incoming = _unit(x[:, aj] - x[:, par[aj]])  # (n,A,3)
    normal = _cross(lateral, incoming)  # flexion direction: abduction turns about it
    tf = np.broadcast_to(flexion_deg, (n,) + np.shape(flexion_deg)[-2:])
    ta = None if abduction_deg is None else np.broadcast_to(abduction_deg, tf.shape)
    chains = finger_chains(skeleton)
    children = skeleton.angle_children
    out = np.broadcast_to(u[:, None, None], (n, len(chains), tf.shape[1]) + u.shape[1:]).copy()
    below = {}
    for pos in range(len(aj)):  # bones in the subtree below each angle joint
        sub = [int(children[pos])]
        for k in skeleton.topological_order:
            if par[k] in sub:
                sub.append(int(k))
        below[pos] = kin.bone_of_child[np.asarray(sub)]
    for f, chain in enumerate(chains):
        view = out[:, f]  # (n,K,B,3), a view
        for i in range(len(chain) - 1, -1, -1):
            pos = int(chain[i])
            bones = below[pos]
            delta = np.nan_to_num(tf[:, :, pos] - flex[:, None, pos])  # (n,K)
            view[:, :, bones] = _rotate(
                view[:, :, bones], lateral[:, None, None, pos], delta[..., None]
            )
            if i == 0 and ta is not None:
                d_ab = np.nan_to_num(ta[:, :, pos] - abd[:, None, pos])
                view[:, :, bones] = _rotate(
                    view[:, :, bones], normal[:, None, None, pos], -d_ab[..., None]
                )
    return out


def refit_fingers(
    model: HandModel,
    fit: FitResult,
    obs: FrameObservations,
    camera: CameraIntrinsics,
    *,
    weights: FitWeights | None = None,
    priors: Priors | None = None,
    kin: Kinematics | None = None,
    flexion_deg: np.ndarray | None = None,
    abduction_deg: np.ndarray | None = None,
    rows: np.ndarray | None = None,
    score_points: int | None = RANKING_POINTS,
) -> FitResult:
    """Per-finger hypotheses for fits ``fit`` of ``n`` frames stuck in a finger's local minimum
    (a finger curled where the depth shows it extended, or the reverse).

    The hand energy is nearly separable per finger (each finger's capsules explain their own
    points): every finger of every frame is set in turn to each hypothesis
    (:func:`finger_hypotheses`; ``flexion_deg`` (K,A) or (n,K,A), default
    :func:`grid_flexions`, with ``abduction_deg`` alike) and scored by the frame's energy (same
    weights and priors as the fit); each finger takes its best hypothesis where that lowers the
    frame's energy below the fit's, the fingers are recombined into one pose, and one more
    Levenberg-Marquardt fit (:func:`fit_frames`) runs from it. A frame keeps its new fit only
    if that fit's energy is lower than ``fit.energy``, else it keeps ``fit`` unchanged (rows
    are independent, as in :func:`fit_frames`). Hypotheses are ranked on about
    ``score_points`` of the observed points (None: all), the refit uses all of them.
    ``rows``: the frames to try (None: all); ``obs``
    and ``priors`` are those of all ``n`` frames. Returns the merged :class:`FitResult`
    (``energy_start`` and ``iterations`` of ``fit``)."""
    w = weights or FitWeights()
    kin = kin or Kinematics(model.skeleton, model.bone_lengths_mm)
    sel = np.arange(len(fit.energy)) if rows is None else np.asarray(rows, dtype=np.int64)
    chains = finger_chains(model.skeleton)
    if len(sel) == 0 or not chains:
        return fit
    flexion_deg = grid_flexions(model.skeleton) if flexion_deg is None else flexion_deg

    def pick(a):
        return a if a is None or np.ndim(a) == 2 else np.asarray(a)[sel]

    hyp = finger_hypotheses(
        model.skeleton, kin, fit.root[sel], fit.u[sel], pick(flexion_deg), pick(abduction_deg)
    )
    nf, nk = hyp.shape[1:3]
    # scored on fewer observed points than the fit uses, the fit's own pose first so that the
    # comparison uses the same points
    sub = obs.thinned(score_points)
    owner = np.concatenate([sel, np.repeat(sel, nf * nk)])
    flat = np.concatenate([fit.u[sel], hyp.reshape((-1,) + hyp.shape[3:])])
    energy = candidate_energies(model, kin, fit.root[owner], flat, sub, owner, camera, w, priors)
    current, energy = energy[: len(sel)], energy[len(sel) :].reshape(len(sel), nf, nk)
    best = np.argmin(energy, axis=2)  # (m,F)
    better = np.take_along_axis(energy, best[..., None], 2)[..., 0] < current[:, None]
    # past the image's border the depth shows nothing, so it cannot choose among hypotheses of a
    # finger that lies there: a finger with no joint on the image stays as fitted (swung anywhere
    # out of view it costs nothing, and it was)
    on_image = _in_view(camera.project(fit.joints_mm[sel]), camera)
    moved = [model.skeleton.angle_children[chain] for chain in chains]
    better &= np.stack([on_image[:, joints].any(axis=1) for joints in moved], axis=1)
    hit = np.flatnonzero(np.any(better, axis=1))
    if len(hit) == 0:
        return fit
    todo = sel[hit]
    u = fit.u[todo].copy()
    for f, chain in enumerate(chains):
        bones = kin.bone_of_child[model.skeleton.angle_children[chain]]
        take = better[hit, f]
        chosen = hyp[hit, f, best[hit, f]]  # (h,B,3)
        u[np.ix_(take, bones)] = chosen[np.ix_(take, bones)]
    again = fit_frames(
        model, kin.joints(fit.root[todo], u), obs.take(todo), camera, weights=w,
        priors=None if priors is None else priors.take(todo), kin=kin,
    )  # fmt: skip
    keep = again.energy < fit.energy[todo]
    rows_k = todo[keep]
    out = FitResult(
        fit.joints_mm.copy(), fit.energy.copy(), fit.energy_start,
        {k: v.copy() for k, v in fit.terms.items()}, fit.root.copy(), fit.u.copy(),
        fit.iterations,
    )  # fmt: skip
    out.joints_mm[rows_k] = again.joints_mm[keep]
    out.energy[rows_k] = again.energy[keep]
    for k in out.terms:
        out.terms[k][rows_k] = again.terms[k][keep]
    out.root[rows_k] = again.root[keep]
    out.u[rows_k] = again.u[keep]
    return out


def pose_library(skeleton: Skeleton, poses_mm: np.ndarray, size: int) -> np.ndarray:
    """Up to ``size`` of the verified poses ``poses_mm`` (K,J,3) mm, the most different ones
    (farthest-point sampling on the mean joint distance, starting from the pose nearest all
    others), each in its palm's frame (:meth:`Skeleton.palm_coordinates`): (L,J,3) mm.
    Poses with NaN are left out; a skeleton without palm joints has no library (L = 0)."""
    x = np.asarray(poses_mm, dtype=np.float64)
    x = x[np.all(np.isfinite(x), axis=(1, 2))]
    if not len(x) or skeleton.palm_joints is None or size <= 0:
        return np.zeros((0,) + x.shape[1:])
    local = skeleton.palm_coordinates(x)
    dist = np.linalg.norm(local[:, None] - local[None], axis=-1).mean(axis=-1)  # (K,K)
    chosen = [int(np.argmin(dist.mean(axis=1)))]
    near = dist[chosen[0]].copy()
    while len(chosen) < min(size, len(x)) and near.max() > 0:
        k = int(np.argmax(near))
        chosen.append(k)
        near = np.minimum(near, dist[k])
    return local[np.asarray(chosen)]


def pose_energies(
    model: HandModel,
    kin: Kinematics,
    poses_mm: np.ndarray,
    obs: FrameObservations,
    owner: np.ndarray,
    camera: CameraIntrinsics,
    weights: FitWeights,
) -> np.ndarray:
    """Energy (:func:`frame_energy`, no priors) ``(S,)`` of candidate poses ``poses_mm``
    (S,J,3) mm, pose ``s`` in frame ``owner[s]`` of ``obs``, for ranking starts before fitting
    the best."""
    root, u = kin.fit(np.asarray(poses_mm, dtype=np.float64))
    return candidate_energies(model, kin, root, u, obs, owner, camera, weights)


def candidate_energies(model, kin, root, u, obs, owner, camera, weights, priors=None):
    """Energy ``(S,)`` of ``S`` candidates at (root (S,3), u (S,B,3)), candidate ``s`` in frame
    ``owner[s]`` of ``obs`` (and of ``priors``), :data:`RANKING_CHUNK` at a time (memory): the
    ranking of :func:`refit_fingers` and :func:`pose_energies`, and
    :func:`handanno_core.ambiguity.finger_ambiguity`."""
    out = np.empty(len(owner))
    for a in range(0, len(owner), RANKING_CHUNK):
        r = slice(a, a + RANKING_CHUNK)
        of = owner[r]
        out[r] = _energy(
            model, kin, root[r], u[r], obs.take(of), camera, weights,
            None if priors is None else priors.take(of), False, False,
        )[0]  # fmt: skip
    return out


def library_starts(skeleton: Skeleton, library: np.ndarray, poses_mm: np.ndarray) -> np.ndarray:
    """Every pose of a :func:`pose_library` ``library`` (L,J,3) turned into the palm of each of
    ``poses_mm`` (n,J,3) mm (its root and :meth:`Skeleton.palm_rotation`): (n,L,J,3) mm, candidate
    starts that keep a frame's hand where it is and try the articulation of every verified pose
    (several fingers at once, which :func:`refit_fingers` cannot)."""
    x = np.asarray(poses_mm, dtype=np.float64)
    rot = skeleton.palm_rotation(x)  # (n,3,3): palm axes as columns
    return x[:, skeleton.root][:, None, None] + np.einsum("ljc,ndc->nljd", library, rot)


@dataclass
class _FrameFit:
    """Per-frame energy ``cost`` (n,), ``terms``, joints ``x`` (n,J,3), the residual rows
    ``state`` (:meth:`_Accumulator.state`), angle violations ``v0`` (n,2A) and pose-prior
    residuals ``prior_r`` (n,3A) ((n,0): no such term)."""

    cost: np.ndarray
    terms: dict
    x: np.ndarray
    state: tuple
    v0: np.ndarray
    prior_r: np.ndarray


# ------------------------------------------------------------------------------------------------
# personalization
# ------------------------------------------------------------------------------------------------
#: an estimated capsule radius stays within these multiples of its default (:func:`_default_radii`):
#: a segment seen by only a few stray points (a finger mostly hidden behind the knuckles) otherwise
#: grows, each iteration claiming more of its neighbours' points, and a model personalized after a
#: review round explained every frame worse (benchmarks/HISTORY.md, stop 54). Wide enough that no
#: first pass of the suite reaches it.
RADIUS_RANGE = (0.5, 1.6)


def estimate_radii(
    model: HandModel,
    joints_mm: np.ndarray,
    obs: FrameObservations,
    *,
    iterations: int = 6,
    scale_mm: float = 4.0,
    min_points: int = 30,
    bounds_mm: tuple[float, float] = (3.0, 25.0),
    weights: FitWeights | None = None,
) -> np.ndarray:
    """Capsule radii (C,) mm from posed frames ``joints_mm`` (K,J,3) and their observations.

    Each observed point is assigned to the nearest capsule surface under the current radii; a
    capsule's radius is then the Welsch-weighted mean (scale ``scale_mm``) of its points' distance
    to its axis segment, using only points whose foot lies strictly inside the segment
    (``0.1 < t < 0.9``, away from the joints where capsules overlap) and not on the forearm (as
    the fit's data term, ``weights``). Repeated ``iterations`` times; capsules with fewer than
    ``min_points`` points keep their radius. Every radius stays within ``bounds_mm`` and within
    :data:`RADIUS_RANGE` times its default.
    """
    w = weights or FitWeights()
    radii = model.radii.copy()
    default = _default_radii(model.skeleton, model.pairs)
    lo = np.maximum(bounds_mm[0], RADIUS_RANGE[0] * default)
    hi = np.minimum(bounds_mm[1], RADIUS_RANGE[1] * default)
    x = np.asarray(joints_mm, dtype=np.float64)
    keep = np.all(np.isfinite(x), axis=(1, 2))
    x = x[keep]
    obs = obs.take(np.flatnonzero(keep))
    if len(x) == 0:
        return radii
    c_count = len(radii)
    for _ in range(iterations):
        cur = replace(model, radii=radii)
        a, b = cur.capsules(x)
        cidx, t, dist, sd = _nearest_capsule(obs.points, a, b, radii)
        ok = obs.valid & (t > 0.1) & (t < 0.9) & ~_forearm(cur, x, obs.points, cidx, t, w)
        ci, dd = cidx[ok], dist[ok]
        enough = np.bincount(ci, minlength=c_count) >= min_points
        r = radii.copy()
        for _ in range(5):  # IRLS of every capsule's radius at once
            wts = np.exp(-(((dd - r[ci]) / scale_mm) ** 2))
            num = np.bincount(ci, wts * dd, minlength=c_count)
            r = num / np.maximum(np.bincount(ci, wts, minlength=c_count), 1e-9)
        new = np.where(enough, np.clip(r, lo, hi), radii)
        if np.max(np.abs(new - radii)) < 0.01:
            radii = new
            break
        radii = new
    return radii


def personalize(
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray,
    reference_joints_mm: np.ndarray,
    obs: FrameObservations,
) -> HandModel:
    """The hand model of a sequence: bone lengths (from the lift), radii fitted to the references'
    point clouds, palm distances and the thumb base's place in the palm's frame = medians over
    the references' lifted poses (K,J,3), and the
    pose prior of the skeleton's layout (if packaged) made the session's own from those poses
    (:func:`handanno_core.pose_prior.session_prior`)."""
    model = build_model(skeleton, bone_lengths_mm)
    x = np.asarray(reference_joints_mm, dtype=np.float64)
    fin = np.all(np.isfinite(x), axis=(1, 2))
    if np.any(fin):
        dv = x[fin][:, model.palm_pairs[:, 0]] - x[fin][:, model.palm_pairs[:, 1]]
        model = replace(model, palm_dist_mm=np.median(np.linalg.norm(dv, axis=-1), axis=0))
        if len(model.palm_anchor_joints):
            off = np.median(palm_anchor_offsets(model, x[fin]), axis=0)
            model = replace(model, palm_anchor_mm=off)
        learned = packaged_pose_prior(skeleton)
        if learned is not None:
            own, weight = session_prior(learned, skeleton, x[fin], 1.0, widen=True)
            model = replace(model, pose_prior=own, pose_prior_weight=weight)
    return replace(model, radii=estimate_radii(model, x, obs))


def observe_references(
    skeleton: Skeleton,
    reference_joints_mm: np.ndarray,
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    *,
    cube_mm: float = DEFAULT_CROP.cube_mm,
) -> FrameObservations:
    """:func:`observe` of the references' crops ``(K, S, S)``, boxes ``(K, 4)`` and centres
    ``(K, 3)`` mm, with the points drawn in front of their poses' wrists ``reference_joints_mm``
    (K, J, 3) mm (:func:`wrist_planes`): what every personalization and reference level reads."""
    return observe(
        np.asarray(crops, dtype=np.float32),
        np.asarray(boxes, dtype=np.float64),
        np.asarray(centres_mm, dtype=np.float64),
        camera,
        cube_mm=cube_mm,
        planes=wrist_planes(skeleton, reference_joints_mm),
    )


def personalize_from_crops(
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray,
    reference_joints_mm: np.ndarray,
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    *,
    cube_mm: float = DEFAULT_CROP.cube_mm,
) -> tuple[HandModel, FrameObservations]:
    """:func:`personalize` from the references' crops ``(K, S, S)``, boxes ``(K, 4)`` and centres
    ``(K, 3)`` mm (:func:`observe_references`); returns the model and the observations."""
    obs = observe_references(
        skeleton, reference_joints_mm, crops, boxes, centres_mm, camera, cube_mm=cube_mm
    )
    model = personalize(
        skeleton,
        np.asarray(bone_lengths_mm, dtype=np.float64),
        np.asarray(reference_joints_mm, dtype=np.float64),
        obs,
    )
    return model, obs


def depth_energies(
    model: HandModel,
    joints_mm: np.ndarray,
    obs: FrameObservations,
    camera: CameraIntrinsics,
    weights: FitWeights | None = None,
    chunk: int | None = None,
) -> np.ndarray:
    """How well the model explains each of K poses ``joints_mm`` (K,J,3) mm in its frame
    (``obs`` of those K frames): the data + free-space energy (:func:`frame_energy`, ``weights``
    default :class:`FitWeights`), (K,); ``chunk`` frames at a time (memory), None: all at once."""
    kin = Kinematics(model.skeleton, model.bone_lengths_mm)
    w = weights or FitWeights()
    k = len(joints_mm)
    step = max(k if chunk is None else int(chunk), 1)
    out = np.empty(k)
    for a in range(0, k, step):
        rows = np.arange(a, min(a + step, k))
        part = obs if step >= k else obs.take(rows)
        _, terms, _, _ = frame_energy(
            model, kin, *kin.fit(joints_mm[rows]), part, camera, w, diagnostics=False
        )
        out[rows] = terms["data"] + terms["free_space"]
    return out


def reference_level(
    model: HandModel,
    joints_mm: np.ndarray,
    obs: FrameObservations,
    camera: CameraIntrinsics,
    weights: FitWeights | None = None,
) -> float:
    """How well the model explains verified poses: the median over the references (K,J,3) mm of
    :func:`depth_energies` at their poses. A fitted frame far above it is a fit that failed (hand
    on the wrong surface, wrong minimum)."""
    return float(np.median(depth_energies(model, joints_mm, obs, camera, weights)))


def personalize_hands(
    skeleton: Skeleton,
    lengths_mm: np.ndarray,
    hand: np.ndarray | None,
    joints_mm: np.ndarray,
    obs: FrameObservations,
    camera: CameraIntrinsics,
    given: HandModel | None = None,
) -> tuple[list[HandModel], np.ndarray]:
    """One hand model per bone-length set ``lengths_mm`` (H, B) mm and its :func:`reference_level`
    (H,): row ``h`` personalized (:func:`personalize`) from the K references (``joints_mm``
    (K, J, 3) mm, ``obs`` their :func:`observe_references`) whose ``hand`` (K,) is ``h``, from all
    of them where none is or ``hand`` is None; ``given``: that model for every row instead."""
    models, levels = [], []
    for h, lengths in enumerate(np.asarray(lengths_mm, dtype=np.float64)):
        own = np.arange(len(joints_mm))
        if hand is not None:
            own = np.flatnonzero(np.asarray(hand) == h)
            own = own if len(own) else np.arange(len(joints_mm))
        model = (
            given
            if given is not None
            else personalize(skeleton, lengths, joints_mm[own], obs.take(own))
        )
        models.append(model)
        levels.append(reference_level(model, joints_mm[own], obs.take(own), camera))
    return models, np.asarray(levels)


#: A fit whose level (data + free-space energy over :func:`reference_level`) is above this does
#: not explain its frame's depth and is no evidence: propagation's guard keeps the flowed pose
#: (``propagate.PropagationSettings.model_fail_ratio``) and recovery keeps the earlier estimate
#: (``recover.RecoverySettings.accept_level``). Not lower: the model explains some recorded poses
#: poorly even where they are right (tune-icvl's ground truth over whole stretches), while a hand
#: fitted over another surface stays above it (the guard's test in ``tests/test_handmodel.py``).
#: Chosen on the suite's tune part (README, stop 46).
UNEXPLAINED_LEVEL = 8.0
