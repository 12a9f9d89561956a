"""Propagate lifted reference poses to every frame along the selection's parent forest (step 6).

Each non-reference frame ``f`` is propagated from its parent ``s = parent[f]`` (``-1`` marks a
reference), parents always before children:

1. the parent's joints ``(J, 3)`` mm are projected to the image and mapped into the parent's crop
   (:func:`handanno_core.crops.image_to_crop`);
2. the parent crop is aligned to the frame's crop (``aligner="dis"|"sift"|"ncc"``, see
   :mod:`handanno_core.flow`) and every joint moves by the flow sampled robustly (median of
   bilinear samples in a 3x3 window), then goes back to image pixels through the frame's box;
3. depth is read from the frame's **own** depth map for joints judged visible: the joint was on
   its surface in the parent (measured from the depth map at references, carried along the
   chain) and the frame's surface at the new position (nearest valid pixel within 3 px) is
   neither far in front of (occluder) nor far behind (background) the predicted depth. A visible
   joint keeps the depth *below the surface* it had at its reference (within +-10 mm of the
   skeleton's surface offset; chosen against the fixed skeleton offset on the synthetic
   sequence, see the README's propagation results). Other joints keep the parent's depth relative to the hand centre,
   ``z_parent - c_parent + c_frame``;
4. a small Levenberg-Marquardt fit on the ``3 J`` coordinates restores the bone lengths
   (``bone_lengths_mm``, soft but stiff: residuals in units of 0.05 mm) while staying close to the
   flowed 2D positions (px, sigma = one crop pixel) and the target depths (mm, sigma 8 mm visible,
   25 mm predicted). When a joint-angle limit of the skeleton is exceeded by more than 3 deg, the
   fit is rerun with hinge residuals on flexion/abduction (sigma 2 deg).

5. with the hand model on (``hand_model=True``; this function's default is off, a session's
   ``settings.hand_model`` is on; about 3x the CPU per frame; :mod:`handanno_core.handmodel`), the
   personalized capsule model is fitted to the frame's own depth from the candidate start of lowest
   energy (the flowed pose, the parent's pose, the nearest references before and after the frame in
   time; ``model_fits`` starts) and the fit of lowest energy is kept (:func:`_model_fits`) unless
   its own evidence says it failed: its data + free-space energy above ``model_fail_ratio`` times
   the references' level (the model does not explain the frame's depth: a wrong start, the hand
   fitted to another surface) or using fewer than ``min_explained_share`` of the frame's observed
   points (the rest taken as forearm); the frame then keeps its flowed pose. With
   ``finger_hypotheses`` a fit above ``finger_level`` times the references' level is also tried
   with each finger set to a grid of flexions and to the angles it has in the frame's other starts
   (:func:`handanno_core.handmodel.refit_fingers`: a finger stuck curled where the depth shows it
   extended, or the reverse); the recombined, refitted pose is kept only if its energy is lower.
   Where the flow moved the joints ``reference_min_motion_mm`` or more, the references' most
   different poses (``reference_starts``, :func:`handanno_core.handmodel.pose_library`), each
   turned into the flowed pose's palm, are ranked on the frame's depth and the best is fitted
   without the flow's priors: it replaces the fit where its energy is lower than the fit's without
   those priors (a flow that carried several fingers the wrong way holds them there; a verified
   pose of the same hand does not). Measured by ``handanno bench --model off,on`` (README, hand
   model section).

6. several candidate forests (``parent`` of shape ``(P, N)``; a session with the hand model on
   passes its selection's forest and the two temporal chains between its references,
   :func:`handanno_core.pipeline.propagation_forests`): every frame is propagated along the first,
   and along the others where its first fit is above ``candidate_level`` times the references'
   level (with the ancestors it needs; chains a candidate shares with the first are computed
   once), and
   keeps the result whose model fit explains its own depth best, its data + free-space level
   times ``1 + chain_step_penalty`` per step from its reference (:func:`_keep_best`). A frame that
   a chain from one reference lost (fast motion, a finger flipped) is then usually held by the
   chain from the other side (the fit's level ranks frames by their error: README, stop 27).

Confidence per joint in [0, 1] multiplies the parent's confidence (errors accumulate along a
chain) with the local evidence: forward-backward flow consistency (crop px), appearance residual
of the normalized crops at the matched points (mm), the depth residual of the fit (mm) and the
bone-length violation of the flowed pose before the fit, and with the model the fit residual of
the capsules touching the joint. ``PropagationResult.frame_score`` is the
per-frame mean over joints.

Bad frames: a frame whose depth raises ``FrameError``, has no valid pixel, or has no hand centre is
skipped and reported with its reason; its descendants propagate from the nearest valid ancestor
(its crop and joints), so one dropped frame does not cut a chain.

Parallelism: subtrees hanging off frames with known joints are independent. They are packed into a
few large tasks (``_Task``); ``workers=N`` runs the tasks in a process pool, ``scheduler`` on a
Dask cluster. Crops travel as a memory-map path (an in-memory array is written to a temporary
``.npy`` once), not pickled per task. Each frame's computation depends only on its parent's result,
so every mode gives bit-identical results. A task runs generation by generation (a frame's
parent in an earlier one); the hand model is fitted to up to ``_MODEL_BATCH`` frames of a
generation at once, each frame's fit independent of its batch (:func:`_model_fits`), which
halves the model's CPU (one frame's arrays are too small for numpy to pay off). Memory: results
are ``(N, J)``-sized; flows live only while their frame is processed, crops while their batch is.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from . import handmodel as hm
from .camera import CameraIntrinsics
from .crops import DEFAULT_CROP, crop_to_image, image_to_crop
from .datasets.base import FrameError
from .flow import dis_flow, ncc_match, sample_flow, sift_flow
from .forest import depths, descendants, propagation_order
from .hands import BoneTable, bone_table
from .lm import Marquardt, NormalEquations, levenberg_marquardt, solve_dense
from .parallel import Runner
from .results import MODEL_FIT_TERMS
from .rigid import kabsch
from .sampling import bilinear, depth_at
from .skeleton import Skeleton

__all__ = [
    "ALIGNERS",
    "PropagationResult",
    "PropagationSettings",
    "descendants",
    "propagation_order",
    "propagate",
]

ALIGNERS = ("dis", "sift", "ncc")
DEFAULT_ALIGNER = "dis"


@dataclass(frozen=True)
class PropagationSettings:
    """Tunable constants of one propagation step (units in the names)."""

    cube_mm: float = DEFAULT_CROP.cube_mm  #: crop cube edge; converts normalized crop values to mm
    sample_radius: int = 1  #: flow sampled as the median over a (2r+1)^2 window (crop px)
    depth_window_px: int = 3  #: nearest valid depth pixel searched within this radius (image px)
    near_surface_mm: float = 20.0  #: parent joint counts as on its surface within this (mm)
    occlusion_mm: float = 25.0  #: surface this far in front of the prediction occludes the joint
    behind_mm: float = 40.0  #: surface this far behind the prediction is not the joint's surface
    sigma_px: float = 1.0  #: 2D residual scale, in crop px (converted to image px per frame)
    sigma_visible_mm: float = 8.0
    sigma_hidden_mm: float = 25.0
    sigma_bone_mm: float = 0.05
    angle_limits: bool = True  #: refit with joint-angle limit hinges when a limit is violated
    sigma_angle_deg: float = 2.0
    angle_trigger: float = 1.5  #: refit when a limit is exceeded by this many sigma
    angle_iterations: int = 4
    carry_band_mm: float = 10.0  #: carried depth-below-surface stays this close to the skeleton's
    #: joints hidden in the source move rigidly with the joints seen on their surface (the flow at a
    #: hidden joint's pixel is its occluder's motion); needs this many seen joints, else translation
    carry_hidden_min_seen: int = 4
    carry_hidden: bool = True
    #: the hand model also starts from the parent's pose moved on at its own velocity (parent minus
    #: grandparent) when grandparent, parent and frame are consecutive frames
    velocity_start: bool = True
    fit_iterations: int = 10
    fb_scale_px: float = 1.5  #: confidence scale of the forward-backward error (crop px)
    appearance_scale_mm: float = 25.0
    depth_scale_mm: float = 12.0
    bone_scale: float = 0.2  #: relative bone-length violation scale
    ncc_patch: int = 21
    ncc_search: int = 12
    model_fits: int = 1  #: hand-model fits per frame: the candidate starts of lowest energy
    model_scale_mm: float = 4.0  #: confidence scale of a bone's mean point-to-model residual
    model_free_scale: float = 0.5  #: confidence drop per fraction of free-space violations
    #: the fit failed when its data + free-space energy exceeds this many times the references'
    #: (median over the lifted references, :func:`handmodel.reference_level`): the frame keeps
    #: its flowed pose (:data:`handmodel.UNEXPLAINED_LEVEL`, the level recovery accepts too)
    model_fail_ratio: float = hm.UNEXPLAINED_LEVEL
    #: ... or when it uses fewer than this share of the frame's observed points: the data term
    #: ignores the points a pose takes as forearm (behind its wrist) and averages over the rest,
    #: so a pose turned until every point lies behind its wrist explains the frame at no data
    #: cost and passes the level guard (chosen on the tune part from 0.05, 0.1, 0.2, HISTORY.md
    #: stop 55); its level is reported at the guard's limit, so that another chain's fit is kept
    min_explained_share: float = 0.1
    #: with the hand model, a session's propagation (:func:`handanno_core.pipeline.propagate`)
    #: also carries every frame between two references from both of them in time
    #: (:func:`handanno_core.select.temporal_chains`) and keeps, per frame, the candidate whose fit
    #: explains the frame's depth best (about twice the propagation's CPU)
    both_ways: bool = True
    #: among candidate forests, a frame's fit level counts this fraction more per propagation step
    #: from its reference (errors grow along a chain; 0.02-0.1 alike on the tune part, pure level
    #: picked a longer chain too often on smooth motion)
    chain_step_penalty: float = 0.05
    #: the other candidates are computed only for the frames whose fit along the first forest is
    #: above this level (relative to the references', ``MODEL_FIT_TERMS`` "level"), and their
    #: ancestors; 0: for every frame. Where the first forest's fits explain the depth, its
    #: chains are kept, at no extra cost
    candidate_level: float = 2.0
    #: per-finger hypotheses (:func:`handanno_core.handmodel.refit_fingers`): where a frame's
    #: model fit explains its depth worse than ``finger_level`` times the references' level, every
    #: finger is also tried curled and extended, the best of each is recombined and refitted; the
    #: new fit is kept only if its energy is lower (README, hand model section)
    finger_hypotheses: bool = True
    finger_level: float = 1.5
    #: a fit above ``model_fail_ratio`` that the hypotheses bring below it is kept only below
    #: this many times the references' level (:func:`_guard`)
    finger_rescue_level: float = 3.0
    #: reference starts (:func:`handanno_core.handmodel.pose_library`): up to this many of the
    #: references' poses (the most different ones), each turned into the flowed pose's palm,
    #: are ranked on the frame's depth and the best is fitted without the flow's priors; it
    #: replaces the frame's fit where its energy is below the fit's without those priors (the
    #: flow that carried every finger the wrong way would otherwise hold them there). 0: off
    reference_starts: int = 8
    #: ... only where the flow moved the joints at least this far from the parent's pose (mean,
    #: mm): closer, the parent's basin holds and a lower energy elsewhere is more often a
    #: misfit of the model than a better pose (half the data term's 8 mm scale; 0-6 mm tried
    #: on the tune part, README stop 43); it also spares the fits on slow motion
    reference_min_motion_mm: float = 4.0

    @classmethod
    def from_session(cls, settings, **overrides) -> PropagationSettings:
        """Settings for a session's propagation: its ``Settings.cube_mm`` (the crops' cube, which
        the crop stage may have grown) plus ``overrides``; every other constant at its default."""
        return cls(**({"cube_mm": float(settings.cube_mm)} | overrides))


@dataclass
class PropagationResult:
    """Propagated joints. Rows not computed (references, skipped, outside ``frames``) are NaN.

    ``joints_mm``: ``(N, J, 3)`` mm; ``confidence``: ``(N, J)`` in [0, 1]; ``skipped``: frames
    that could not be propagated, with ``reasons[frame]``; ``source``: ``(N,)`` the frame each
    frame was actually propagated from (``-1`` where not computed); ``seconds``: wall time;
    ``order``: frames in the order their results arrived (parents before children).
    """

    joints_mm: np.ndarray
    confidence: np.ndarray
    skipped: list[int] = field(default_factory=list)
    reasons: dict[int, str] = field(default_factory=dict)
    source: np.ndarray | None = None
    seconds: float = 0.0
    order: list[int] = field(default_factory=list)
    #: ``(N, J)`` mm each joint's depth below the observed surface where it was placed on it
    below_surface_mm: np.ndarray | None = None
    #: ``(N, T)`` the hand-model fit's own evidence per frame (NaN without the model or where
    #: not computed), columns :data:`handanno_core.results.MODEL_FIT_TERMS`
    model_fit: np.ndarray | None = None

    @property
    def frame_score(self) -> np.ndarray:
        """``(N,)`` mean joint confidence per frame (NaN where not computed)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmean(self.confidence, axis=1)


# ---------------------------------------------------------------------------------------------
# forest helpers
# ---------------------------------------------------------------------------------------------
# ---------------------------------------------------------------------------------------------
# the per-frame step (runs in workers)
# ---------------------------------------------------------------------------------------------
@dataclass
class _Context:
    """Everything a worker needs; small when pickled (crops travel by path)."""

    crops_path: str | None
    crops_offset: int
    crops_shape: tuple[int, ...]
    crops_dtype: str
    boxes: np.ndarray
    centres_mm: np.ndarray
    depth_of: Callable[[int], np.ndarray]
    camera: CameraIntrinsics
    skeleton: Skeleton
    bones: BoneTable  #: each frame's bone lengths
    aligner: str
    aligner_kwargs: dict
    settings: PropagationSettings
    crops_array: np.ndarray | None = None  # in-process only
    hand_models: list[hm.HandModel] | None = None  #: one per row of ``bones.lengths``
    fit_weights: hm.FitWeights | None = None
    model_refs: np.ndarray | None = None  #: (K,) reference frames, sorted
    model_ref_joints: np.ndarray | None = None  #: (K, J, 3) their lifted joints
    model_levels: np.ndarray | None = None  #: per model, the references' data + free energy
    #: (L, J, 3) mm: the most different references' poses in their palm's frame
    #: (:func:`handmodel.pose_library`)
    model_library: np.ndarray | None = None

    def crops(self) -> np.ndarray:
        if self.crops_array is not None:
            return self.crops_array
        key = (self.crops_path, self.crops_offset)
        arr = _CROPS_CACHE.get(key)
        if arr is None:
            arr = np.memmap(
                self.crops_path,
                dtype=np.dtype(self.crops_dtype),
                mode="r",
                offset=self.crops_offset,
                shape=self.crops_shape,
            )
            _CROPS_CACHE.clear()
            _CROPS_CACHE[key] = arr
        return arr

    def __getstate__(self):
        state = dict(self.__dict__)
        state["crops_array"] = None
        return state

    def with_model(self, models: tuple | None, known: dict, reference_joints) -> _Context:
        """This context with the hand models to fit and their reference energy levels (``models``
        from :func:`_hand_models`, one per bone-length set; None: off) and the references they
        start from (the usable ones, sorted, with their lifted joints)."""
        if models is None:
            return self
        refs = np.asarray(sorted(f for f in known if f in reference_joints), dtype=np.int64)
        joints = np.stack([known[int(f)][0] for f in refs]) if len(refs) else None
        library = None
        if joints is not None and self.settings.reference_starts > 0:
            library = hm.pose_library(self.skeleton, joints, self.settings.reference_starts)
        return dataclasses.replace(
            self, hand_models=models[0], model_levels=models[1], model_refs=refs,
            model_ref_joints=joints, model_library=library,
        )  # fmt: skip


_CROPS_CACHE: dict[tuple, np.ndarray] = {}


@dataclass
class _Task:
    """A group of subtrees: ``frames`` in topological order with their ``sources`` (parents);
    ``seeds[frame] = (joints (J,3), confidence (J,), visible (J,) bool | None)`` for the frames
    the subtrees hang off (references or frames kept from a previous run)."""

    frames: np.ndarray
    sources: np.ndarray
    seeds: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray | None]]


def _align(ctx: _Context, crop_s: np.ndarray, crop_f: np.ndarray, xy_s: np.ndarray):
    """Displacement ``(J, 2)`` crop px of points ``xy_s`` and forward-backward error ``(J,)``."""
    st = ctx.settings
    if ctx.aligner == "ncc":
        kw = dict(patch=st.ncc_patch, search=st.ncc_search) | ctx.aligner_kwargs
        disp, _ = ncc_match(crop_s, crop_f, xy_s, **kw)
        back, _ = ncc_match(crop_f, crop_s, xy_s + disp, init=-disp, **kw)
        return disp, np.linalg.norm(disp + back, axis=1)
    fn = sift_flow if ctx.aligner == "sift" else dis_flow
    fwd = fn(crop_s, crop_f, **ctx.aligner_kwargs)
    disp = sample_flow(fwd, xy_s, radius=st.sample_radius)
    del fwd
    bwd = fn(crop_f, crop_s, **ctx.aligner_kwargs)
    back = sample_flow(bwd, xy_s + disp, radius=st.sample_radius)
    return disp, np.linalg.norm(disp + back, axis=1)


class _FitEval(NamedTuple):
    """Residual groups (2D u, 2D v, depth, bone, angle), bone vectors and lengths, cost."""

    res: tuple[np.ndarray, ...]
    vec: np.ndarray
    ln: np.ndarray
    cost: float


def _fit_blocks(x, ev: _FitEval, camera, sigma_uv, inv_z, bones, sigma_bone):
    """``JᵀJ`` ``(3J, 3J)`` and ``Jᵀr`` ``(3J,)`` of the 2D, depth and bone residuals of
    :func:`_fit`, assembled from 3x3 blocks per joint and per bone."""
    r_u, r_v, r_z, r_b, _ = ev.res
    j = len(x)
    fx, fy = camera.fx, camera.fy
    idx = np.arange(j)
    bp, bc = bones[:, 0], bones[:, 1]
    z = np.maximum(x[:, 2], 1.0)
    s = 1.0 / (z * sigma_uv)
    pu = np.zeros((j, 3))
    pv = np.zeros((j, 3))
    pu[:, 0], pu[:, 2] = fx * s, -fx * x[:, 0] / z * s
    pv[:, 1], pv[:, 2] = fy * s, -fy * x[:, 1] / z * s
    blocks = np.zeros((j, j, 3, 3))
    blocks[idx, idx] = pu[:, :, None] * pu[:, None, :] + pv[:, :, None] * pv[:, None, :]
    blocks[idx, idx, 2, 2] += inv_z**2
    grad = pu * r_u[:, None] + pv * r_v[:, None]
    grad[:, 2] += inv_z * r_z
    unit = ev.vec / (np.maximum(ev.ln, 1e-9)[:, None] * sigma_bone)
    uu = unit[:, :, None] * unit[:, None, :]
    np.add.at(blocks, (bc, bc), uu)
    np.add.at(blocks, (bp, bp), uu)
    np.add.at(blocks, (bp, bc), -uu)
    np.add.at(blocks, (bc, bp), -uu)
    np.add.at(grad, bc, unit * r_b[:, None])
    np.add.at(grad, bp, -unit * r_b[:, None])
    return blocks.transpose(0, 2, 1, 3).reshape(3 * j, 3 * j), grad.ravel()


def _fit(
    x0: np.ndarray,
    uv: np.ndarray,
    sigma_uv: float,
    z_t: np.ndarray,
    sigma_z: np.ndarray,
    camera: CameraIntrinsics,
    bones: np.ndarray,
    lengths: np.ndarray,
    sigma_bone: float,
    iterations: int,
    angles: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """Levenberg-Marquardt on the ``(J, 3)`` joints (mm) with residuals: 2D reprojection (px /
    ``sigma_uv``), depth (mm / ``sigma_z``) and bone length (mm / ``sigma_bone``); a handful of
    iterations from the back-projected start.

    The normal equations are assembled from the Jacobian's sparse structure (3x3 blocks per
    joint and per bone) without BLAS: tiny multi-threaded BLAS calls stall badly on a loaded
    machine.

    ``angles(poses (..., J, 3)) -> (..., A)`` hinge residuals of the joint-angle limits (0 inside
    the limits): when given, they are appended with a forward-difference Jacobian (one batched
    call over the 3J perturbed poses, kept from the first iteration)."""
    j = len(x0)
    n = 3 * j
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    bp, bc = bones[:, 0], bones[:, 1]
    inv_z = 1.0 / np.broadcast_to(np.asarray(sigma_z, dtype=np.float64), (j,))
    na = 0 if angles is None else int(angles(x0).shape[-1])
    eps = 1e-3 * np.eye(n).reshape(n, j, 3) if na else None
    jac_a = None

    def residuals(x) -> _FitEval:
        z = np.maximum(x[:, 2], 1.0)
        r_u = (fx * x[:, 0] / z + cx - uv[:, 0]) / sigma_uv
        r_v = (fy * x[:, 1] / z + cy - uv[:, 1]) / sigma_uv
        r_z = (x[:, 2] - z_t) * inv_z
        vec = x[bc] - x[bp]
        ln = np.sqrt(np.einsum("ij,ij->i", vec, vec))
        r_b = (ln - lengths) / sigma_bone
        r_a = angles(x) if na else np.zeros(0)
        cost = float(
            np.einsum("i,i->", r_u, r_u)
            + np.einsum("i,i->", r_v, r_v)
            + np.einsum("i,i->", r_z, r_z)
            + np.einsum("i,i->", r_b, r_b)
            + np.einsum("i,i->", r_a, r_a)
        )
        return _FitEval((r_u, r_v, r_z, r_b, r_a), vec, ln, cost)

    def normal_equations(x, ev: _FitEval) -> NormalEquations:
        nonlocal jac_a
        r_a = ev.res[4]
        jtj, g = _fit_blocks(x, ev, camera, sigma_uv, inv_z, bones, sigma_bone)
        if na:
            if jac_a is None:  # kept from the first iteration
                jac_a = ((angles(x[None] + eps) - r_a) / 1e-3).T  # (A, 3J)
            jtj = jtj + np.einsum("ai,aj->ij", jac_a, jac_a)
            g = g + np.einsum("ai,a->i", jac_a, r_a)
        return NormalEquations(jtj, g, np.diag(jtj).copy() + 1e-9)

    fit = levenberg_marquardt(
        residuals,
        x0.copy(),
        normal_equations=normal_equations,
        solve=solve_dense,
        damping=Marquardt(lam=1e-4, up=10.0, down=0.1, floor=1e-9),
        max_iter=iterations,
        max_tries=5,
        rtol=1e-8,
        atol=1e-12,
    )
    return fit.x


def _angle_hinge(sk: Skeleton, sigma_deg: float) -> Callable[[np.ndarray], np.ndarray]:
    """Residuals ``(..., 2A)``: flexion/abduction outside the skeleton's limits, in sigma units
    (:func:`handmodel.angle_violation`: :meth:`Skeleton.joint_angles` vectorized over the chain
    levels, the fit calls it 3J+1 times per refit)."""

    def hinge(poses: np.ndarray) -> np.ndarray:
        return hm.angle_violation(sk, poses) / sigma_deg

    return hinge


def _surface_offsets_at_source(ctx: _Context, frame: int, joints: np.ndarray) -> np.ndarray:
    """Per joint, depth below the observed surface (mm) in a seed frame; NaN where the joint is
    not near its surface (reads the frame's depth)."""
    offsets = np.asarray(ctx.skeleton.surface_offsets_mm)
    try:
        depth = ctx.depth_of(frame)
    except FrameError:
        return np.full(len(joints), np.nan)
    surf = depth_at(
        depth, ctx.camera.project(joints), window=ctx.settings.depth_window_px, near_px=0
    )
    delta = joints[:, 2] - surf
    with np.errstate(invalid="ignore"):
        near = np.abs(delta - offsets) < ctx.settings.near_surface_mm
    return np.where(near, delta, np.nan)


class _ModelInput(NamedTuple):
    """One frame's hand-model fit input (:func:`_model_fits`): its parent ``src``, the flowed
    pose ``x_flow`` (J,3) mm, the parent's pose ``joints_s`` (J,3) mm, the flowed 2D ``uv_f``
    (J,2) px, the forward-backward flow error ``fb`` (J,) crop px and the frame's crop (S,S)."""

    src: int
    frame: int
    x_flow: np.ndarray
    joints_s: np.ndarray
    uv_f: np.ndarray
    fb: np.ndarray
    crop_f: np.ndarray
    joints_gs: np.ndarray | None = None  #: the parent's own source, for the velocity start


class _Flowed(NamedTuple):
    """A frame after the flow and the bone fit (:func:`_flow_step`), before the hand model: the
    hand model's input and what the confidence needs (all per joint, ``(J,)`` unless stated)."""

    model_in: _ModelInput
    conf_s: np.ndarray
    visible: np.ndarray
    z_t: np.ndarray
    z_obs: np.ndarray
    below: np.ndarray
    app_res: np.ndarray  #: appearance residual at the matched points, mm
    bone_viol: np.ndarray  #: relative bone-length violation of the flowed pose before the fit


def _flow_step(
    ctx: _Context,
    src: int,
    frame: int,
    joints_s: np.ndarray,
    conf_s: np.ndarray,
    delta_s: np.ndarray,
    joints_gs: np.ndarray | None = None,
) -> _Flowed:
    """Steps 1-4 for ``joints_s`` of frame ``src`` to ``frame``. ``delta_s`` (J,) mm: each
    joint's depth below the observed surface in the source (NaN = not on its surface);
    ``joints_gs`` (J,3) mm the source's own source when the three frames are consecutive (the
    hand model's velocity start) or None. Raises ``_Skip``."""
    st = ctx.settings
    cam = ctx.camera
    sk = ctx.skeleton
    box_s, box_f = ctx.boxes[src], ctx.boxes[frame]
    c_s, c_f = ctx.centres_mm[src], ctx.centres_mm[frame]
    if not (np.all(np.isfinite(box_f)) and np.all(np.isfinite(c_f))):
        raise _Skip("no hand centre")
    try:
        depth = ctx.depth_of(frame)
    except FrameError as err:
        raise _Skip(f"bad frame: {err}") from None
    if not np.any(depth > 0):
        raise _Skip("no depth (all zero)")
    crops = ctx.crops()
    crop_s = np.asarray(crops[src], dtype=np.float32)
    crop_f = np.asarray(crops[frame], dtype=np.float32)
    offsets = np.asarray(sk.surface_offsets_mm, dtype=np.float64)

    uv_s = cam.project(joints_s)
    xy_s = image_to_crop(uv_s, box_s)
    disp, fb = _align(ctx, crop_s, crop_f, xy_s)
    disp = np.where(np.isfinite(disp), disp, 0.0)
    xy_f = xy_s + disp
    uv_f = crop_to_image(xy_f, box_f)

    # the joint keeps its depth below the surface from the source (the reference's lift), kept
    # within +-carry_band_mm of the skeleton's offset
    surf = depth_at(depth, uv_f, window=st.depth_window_px, near_px=0)
    vis_s = np.isfinite(delta_s)
    below = np.where(
        vis_s,
        np.clip(np.nan_to_num(delta_s), offsets - st.carry_band_mm, offsets + st.carry_band_mm),
        offsets,
    )
    z_obs = surf + below
    z_pred = joints_s[:, 2] - c_s[2] + c_f[2]
    visible = (
        vis_s
        & np.isfinite(z_obs)
        & (z_obs > z_pred - st.occlusion_mm)
        & (z_obs < z_pred + st.behind_mm)
    )
    if st.carry_hidden and np.any(~vis_s) and np.any(visible):
        # the flow at a hidden joint's pixel is its occluder's motion: move hidden joints with the
        # joints seen on their surface instead
        carried = _carry_rigidly(joints_s, cam.backproject(uv_f, z_obs), visible, st)
        uv_f, z_pred = _replace_hidden(vis_s, uv_f, z_pred, carried, cam)
        xy_f = image_to_crop(uv_f, box_f)
    z_t = np.where(visible, z_obs, z_pred)
    x0 = cam.backproject(uv_f, z_t)
    bones = sk.bones
    lengths = ctx.bones.of(frame)
    len0 = np.linalg.norm(x0[bones[:, 1]] - x0[bones[:, 0]], axis=1)
    sigma_z = np.where(visible, st.sigma_visible_mm, st.sigma_hidden_mm)
    sigma_uv = st.sigma_px * 0.5 * float(box_f[2] + box_f[3])
    x = _fit(
        x0, uv_f, sigma_uv, z_t, sigma_z, cam, bones, lengths, st.sigma_bone_mm, st.fit_iterations
    )
    if st.angle_limits and sk.palm_joints is not None and len(sk.angle_joints):
        hinge = _angle_hinge(sk, st.sigma_angle_deg)
        if np.any(hinge(x) > st.angle_trigger):  # a limit is clearly violated: refit with hinges
            x = _fit(
                x, uv_f, sigma_uv, z_t, sigma_z, cam, bones, lengths, st.sigma_bone_mm,
                st.angle_iterations, angles=hinge,
            )  # fmt: skip
    # matched points should show the same centre-relative depth in both crops
    app_s = bilinear(crop_s, xy_s[:, 0], xy_s[:, 1])
    app_res = np.abs(app_s - bilinear(crop_f, xy_f[:, 0], xy_f[:, 1])) * (0.5 * st.cube_mm)
    bone_viol = np.zeros(len(x))
    bone_viol[bones[:, 1]] = np.abs(len0 - lengths) / np.maximum(lengths, 1e-6)
    return _Flowed(
        _ModelInput(src, frame, x, joints_s, uv_f, fb, crop_f, joints_gs),
        conf_s, visible, z_t, z_obs, below, app_res, bone_viol,
    )  # fmt: skip


def _finish(ctx: _Context, fl: _Flowed, x: np.ndarray, model_conf: np.ndarray | None):
    """The frame's result ``(joints (J,3), confidence (J,), depth below the surface (J,))`` from
    its final pose ``x`` (the flowed one, or the hand model's) and the model's confidence factor
    (None without the model)."""
    st = ctx.settings
    depth_res = np.where(fl.visible, np.abs(x[:, 2] - fl.z_t), st.depth_scale_mm * 0.6)
    local = (
        np.exp(-0.5 * (fl.model_in.fb / st.fb_scale_px) ** 2)
        * np.exp(-0.5 * (fl.app_res / st.appearance_scale_mm) ** 2)
        * np.exp(-0.5 * (depth_res / st.depth_scale_mm) ** 2)
        * np.exp(-0.5 * (fl.bone_viol / st.bone_scale) ** 2)
    )
    if model_conf is not None:
        local = local * model_conf
    conf = np.clip(fl.conf_s * local, 0.0, 1.0)
    # a joint is "on its surface" in this frame if the fit kept it there
    vis_f = fl.visible & (np.abs(x[:, 2] - fl.z_obs) < st.near_surface_mm)
    return x, conf, np.where(vis_f, fl.below, np.nan)


def _carry_rigidly(joints_s, seen_f, seen, st) -> np.ndarray:
    """``joints_s`` (J,3) mm moved by the rigid motion taking the ``seen`` (J,) source joints to
    their positions ``seen_f`` (J,3) mm in the frame (Kabsch), or by their mean displacement when
    fewer than ``st.carry_hidden_min_seen`` are seen or they are nearly collinear."""
    a, b = joints_s[seen], seen_f[seen]
    fit = kabsch(a, b) if len(a) >= st.carry_hidden_min_seen else None
    if fit is None:
        return joints_s + (b.mean(axis=0) - a.mean(axis=0))
    rot, ca, cb = fit
    return (joints_s - ca) @ rot.T + cb


def _replace_hidden(seen, uv, z, carried, camera):
    """``uv`` (J,2) px and ``z`` (J,) mm with the joints not ``seen`` (J,) taken from ``carried``
    (J,3) mm."""
    return np.where(seen[:, None], uv, camera.project(carried)), np.where(seen, z, carried[:, 2])


def _model_fits(ctx: _Context, items: list[_ModelInput]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Fit the hand model to each frame's own depth from several starts; keep the lowest energy.

    Starts: the flowed pose ``x_flow`` (J,3), the parent's pose ``joints_s``, the parent moved on
    at its own velocity (``2 joints_s - joints_gs``, where the grandparent, parent and frame are
    consecutive frames) and the lifted poses of the nearest references before and after the frame
    in time, each (but the velocity start) moved by the difference of the hand centres. All share
    one energy (priors: closeness to the flowed pose, the flowed 2D ``uv_f`` weighted by the
    flow's forward-backward consistency ``fb``), so the energies compare;
    the ``model_fits`` starts of lowest energy are fitted and the best fit is kept.
    Guard: a fit whose data + free-space energy exceeds ``model_fail_ratio`` times the
    references' (``ctx.model_levels``) failed, and the frame keeps ``x_flow``.
    Returns per item the joints (J,3), a per-joint confidence factor (J,) from the fit residuals
    of the capsules touching each joint at the returned pose (mean point-to-surface mm, fraction of
    free-space violations) and the frame's evidence ``(T,)``
    (:data:`handanno_core.results.MODEL_FIT_TERMS`).

    The frames are independent and fitted together, one batch per hand model (the batched LM
    treats every row on its own, so a frame's result does not depend on the others in its batch:
    bit-identical to fitting it alone, whatever the grouping; about half the CPU of one-by-one
    fits, whose cost is mostly numpy's per-call overhead on one frame's arrays).
    """
    hands = np.array(
        [0 if ctx.bones.hand is None else int(ctx.bones.hand[it.frame]) for it in items], int
    )
    out: list = [None] * len(items)
    for h in np.unique(hands):
        idx = np.flatnonzero(hands == h)
        for k, res in zip(
            idx, _model_fits_one_hand(ctx, int(h), [items[i] for i in idx]), strict=True
        ):
            out[k] = res
    return out


def _guard(st: PropagationSettings, plain: float, fitted: float, ref: float) -> tuple[bool, float]:
    """The guard: a fit whose data + free-space level (relative to the references') is above
    ``model_fail_ratio`` failed. A plain fit above it that the finger hypotheses bring below it
    passes only below ``finger_rescue_level``: fingers rearranged over another surface lower the
    level 2-4x (a 35-55 mm ball in the tests: from 9-33x to 4.1-8x), so without this limit the
    guard would accept a hand fitted over an object. It costs accuracy where real hands were
    rescued to 3-5x (tune-icvl, 5 % uniform, final mean: 4.33 mm without the limit, 5.03 with
    2 or 3; tune-shape-fast 5.92 with 3, 6.17 with 2). ``plain``: the level before the
    hypotheses (relative); ``fitted``: the data + free-space energy after them; ``ref``: the
    references' level. Returns (failed, the energy the evidence reports: the judged plain fit's
    where a rescue was refused)."""
    if st.model_fail_ratio <= 0:
        return False, fitted
    limit = st.model_fail_ratio
    if st.finger_hypotheses and plain > limit:
        limit = min(limit, st.finger_rescue_level)
    failed = bool(fitted > limit * ref)
    return failed, max(fitted, plain * ref) if failed and st.finger_hypotheses else fitted


def _starts(ctx: _Context, items: list[_ModelInput]) -> tuple[np.ndarray, np.ndarray]:
    """The candidate starts of :func:`_model_fits` (S,J,3) mm and the item each belongs to (S,)."""
    refs = ctx.model_refs
    starts, owner = [], []
    for i, it in enumerate(items):
        c_f = ctx.centres_mm[it.frame]
        own = [it.x_flow, it.joints_s + (c_f - ctx.centres_mm[it.src])]
        if it.joints_gs is not None and ctx.settings.velocity_start:
            own.append(2.0 * it.joints_s - it.joints_gs)
        if refs is not None and len(refs):
            pos = int(np.searchsorted(refs, it.frame))
            for k in {max(pos - 1, 0), min(pos, len(refs) - 1)}:
                if int(refs[k]) != it.src:
                    own.append(ctx.model_ref_joints[k] + (c_f - ctx.centres_mm[refs[k]]))
        starts += own
        owner += [i] * len(own)
    return np.stack(starts), np.asarray(owner, dtype=np.int64)


def _model_fits_one_hand(ctx: _Context, h: int, items: list[_ModelInput]):
    """:func:`_model_fits` for frames of one hand model ``ctx.hand_models[h]``."""
    st = ctx.settings
    model = ctx.hand_models[h]
    cam = ctx.camera
    frames = np.array([it.frame for it in items], dtype=np.int64)
    c_f = ctx.centres_mm[frames]
    starts, owner = _starts(ctx, items)
    j = starts.shape[1]
    w = ctx.fit_weights or hm.FitWeights()
    # every crop point observed, not only those in front of a start's wrist (observe's planes):
    # where every start lost the hand (fast motion, the first frame after a reference) that cut
    # took the hand's own points away (tests/test_propagate.py, the reference starts' test)
    obs_f = hm.observe(
        np.stack([it.crop_f for it in items]), ctx.boxes[frames], c_f, cam, cube_mm=st.cube_mm,
        max_points=w.points,
    )  # fmt: skip
    x_flow = np.stack([it.x_flow for it in items])
    fb_w = np.exp(
        -0.5 * (np.nan_to_num(np.stack([it.fb for it in items]), nan=1e3) / st.fb_scale_px) ** 2
    )
    pri_f = hm.Priors(
        pose=x_flow,
        pose_w=np.ones((len(items), j)),
        uv=np.stack([it.uv_f for it in items]),
        uv_w=fb_w,
    )
    kin = hm.Kinematics(ctx.skeleton, model.bone_lengths_mm)
    e0 = hm.frame_energy(
        model, kin, *kin.fit(starts), obs_f.take(owner), cam, w, pri_f.take(owner),
        diagnostics=False,
    )[0]  # fmt: skip
    best = np.concatenate(
        [
            np.flatnonzero(owner == i)[np.argsort(e0[owner == i])[: max(1, st.model_fits)]]
            for i in range(len(items))
        ]
    )
    fit = hm.fit_frames(
        model,
        starts[best],
        obs_f.take(owner[best]),
        cam,
        weights=w,
        priors=pri_f.take(owner[best]),
        kin=kin,
    )
    # the plain fit's level (data + free space relative to the references'), per fitted row
    lvl = (fit.terms["data"] + fit.terms["free_space"]) / ctx.model_levels[h]
    tried = np.flatnonzero(lvl > st.finger_level) if st.finger_hypotheses else []
    if len(tried):
        # each fitted row's fingers also tried at the angles of its frame's every start
        flex, abd = hm.finger_targets(ctx.skeleton, starts, owner, len(items))
        fit = hm.refit_fingers(
            model, fit, obs_f.take(owner[best]), cam, weights=w, priors=pri_f.take(owner[best]),
            kin=kin, flexion_deg=flex[owner[best]], abduction_deg=abd[owner[best]], rows=tried,
        )  # fmt: skip
    lib, lib_row = _library_fit(ctx, model, kin, items, obs_f, w)
    x = np.empty((len(items), j, 3))
    root = np.empty((len(items), 3))
    u = np.empty((len(items),) + fit.u.shape[1:])
    level = np.empty(len(items))
    rejected = np.zeros(len(items), dtype=bool)
    for i in range(len(items)):
        rows = np.flatnonzero(owner[best] == i)
        k = rows[int(np.argmin(fit.energy[rows]))]
        x[i], root[i], u[i] = fit.joints_mm[k], fit.root[k], fit.u[k]
        level[i] = fit.terms["data"][k] + fit.terms["free_space"][k]
        plain = lvl[k]
        r = lib_row[i]
        if r >= 0 and lib.energy[r] < fit.energy[k] - fit.terms["pose"][k] - fit.terms["uv"][k]:
            x[i], root[i], u[i] = lib.joints_mm[r], lib.root[r], lib.u[r]
            level[i] = lib.terms["data"][r] + lib.terms["free_space"][r]
            plain = level[i] / ctx.model_levels[h]  # a plain fit, not a rescue
        rejected[i], level[i] = _guard(st, plain, level[i], ctx.model_levels[h])
        if rejected[i]:
            # the fit does not explain the frame's depth: keep the flowed pose
            _keep_flowed_pose(kin, x_flow, [i], (x, root, u))
    _, _, _, diag = hm.frame_energy(model, kin, root, u, obs_f, cam, w, pri_f)
    few = _few_points(st, obs_f, diag) & ~rejected
    if few.any():
        # the second guard: the fit explains almost none of the frame's points
        _keep_flowed_pose(kin, x_flow, few, (x, root, u))
        level[few] = np.maximum(level[few], st.model_fail_ratio * ctx.model_levels[h])
        rejected |= few
        _, _, _, diag = hm.frame_energy(model, kin, root, u, obs_f, cam, w, pri_f)
    touch = np.zeros((j, len(model.pairs)), dtype=bool)
    touch[model.pairs[:, 0], np.arange(len(model.pairs))] = True
    touch[model.pairs[:, 1], np.arange(len(model.pairs))] = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res_j = np.nan_to_num(
            np.nanmax(np.where(touch, diag["capsule_data_mm"][:, None, :], np.nan), axis=2),
            nan=0.0,
        )
    free_j = np.max(np.where(touch, diag["capsule_free"][:, None, :], 0.0), axis=2)
    conf = np.exp(-0.5 * (res_j / st.model_scale_mm) ** 2) * np.clip(
        1.0 - st.model_free_scale * free_j, 0.0, 1.0
    )
    res, free, points = diag["capsule_data_mm"], diag["capsule_free"], diag["capsule_points"]
    with np.errstate(invalid="ignore", divide="ignore"):
        evidence = np.stack(
            [
                level / ctx.model_levels[h],
                np.nansum(res * points, axis=1) / points.sum(axis=1),
                free.mean(axis=1),
                rejected.astype(float),
            ],
            axis=1,
        )
    return list(zip(x, conf, evidence, strict=True))


def _few_points(st: PropagationSettings, obs, diag) -> np.ndarray:
    """``(n,)`` bool, the second guard of :func:`_model_fits_one_hand`: fits that use fewer than
    ``st.min_explained_share`` of their frame's observed points ``obs`` (``diag``: the fits'
    :func:`handmodel.frame_energy` diagnostics)."""
    share = diag["capsule_points"].sum(axis=1) / np.maximum(obs.valid.sum(axis=1), 1)
    return share < st.min_explained_share


def _keep_flowed_pose(kin, x_flow: np.ndarray, rows, pose) -> None:
    """Rows ``rows`` of ``pose`` = (x (n,J,3) mm, root (n,3), u (n,B,3)), changed in place, take
    the flowed pose ``x_flow`` (n,J,3) mm back (a guard rejected their fit)."""
    x, root, u = pose
    x[rows] = x_flow[rows]
    root[rows], u[rows] = kin.fit(x_flow[rows])


def _library_fit(
    ctx: _Context, model, kin, items: list[_ModelInput], obs, weights
) -> tuple[hm.FitResult | None, np.ndarray]:
    """The reference starts' fit of the items the flow moved at least
    ``reference_min_motion_mm`` from their parent's pose: per such frame, the pose of
    ``ctx.model_library`` turned into the flowed pose's palm (:func:`handmodel.library_starts`)
    that explains its depth best (ranked on :data:`handmodel.RANKING_POINTS` points), fitted
    without the flow's priors. Returns the fit (None: no frame) and per item its row in it (-1:
    not tried)."""
    row = np.full(len(items), -1)
    if ctx.model_library is None or not len(ctx.model_library):
        return None, row
    moved = np.array([np.linalg.norm(it.x_flow - it.joints_s, axis=1).mean() for it in items])
    tried = np.flatnonzero(moved >= ctx.settings.reference_min_motion_mm)
    if not len(tried):
        return None, row
    row[tried] = np.arange(len(tried))
    x_flow = np.stack([items[i].x_flow for i in tried])
    obs = obs.take(tried)
    starts = hm.library_starts(ctx.skeleton, ctx.model_library, x_flow)  # (n,L,J,3)
    n, nl = starts.shape[:2]
    flat = starts.reshape((n * nl,) + starts.shape[2:])
    owner = np.repeat(np.arange(n), nl)
    ranked = obs.thinned(hm.RANKING_POINTS)
    energy = hm.pose_energies(model, kin, flat, ranked, owner, ctx.camera, weights)
    pick = np.argmin(energy.reshape(n, nl), axis=1)
    fit = hm.fit_frames(
        model, starts[np.arange(n), pick], obs, ctx.camera, weights=weights, kin=kin
    )
    return fit, row


class _Skip(Exception):
    pass


@dataclass
class _TaskResult:
    """One task's rows: ``frames`` (M,), the frame each was propagated from ``sources`` (M,) (-1
    where skipped), ``joints`` (M, J, 3) mm, ``confidence`` (M, J), ``below`` (M, J) mm depth
    below the surface (NaN off it), ``skipped`` ``{frame: reason}`` and ``model_fit`` (M, T)
    (:data:`MODEL_FIT_TERMS`)."""

    frames: np.ndarray
    sources: np.ndarray
    joints: np.ndarray
    confidence: np.ndarray
    below: np.ndarray
    skipped: dict[int, str]
    model_fit: np.ndarray


def _run_task(ctx: _Context, task: _Task, emit: Callable | None = None):
    """Propagate one task (a :class:`_TaskResult`).

    OpenCV runs single-threaded here: one task = one core (parallelism comes from tasks)."""
    import cv2

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _run_task_inner(ctx, task, emit)
    finally:
        cv2.setNumThreads(threads)


def _run_task_inner(ctx: _Context, task: _Task, emit: Callable | None):
    """The task's frames generation by generation (a frame's parent is in an earlier one), each
    generation in chunks of :data:`_MODEL_BATCH` frames: flow and bone fit per frame, the hand
    model fitted to the chunk's frames at once (:func:`_model_fits`), then each frame's result."""
    j = ctx.skeleton.num_joints
    m = len(task.frames)
    out_j = np.full((m, j, 3), np.nan)
    out_c = np.full((m, j), np.nan)
    out_b = np.full((m, j), np.nan)
    out_m = np.full((m, len(MODEL_FIT_TERMS)), np.nan)
    used_src = np.full(m, -1, dtype=np.int64)
    skipped: dict[int, str] = {}
    state: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    alias: dict[int, int] = {}  # skipped frame -> nearest valid ancestor
    came_from: dict[int, int] = {}  # computed frame -> the frame it was propagated from
    for f, (jj, cc, vv) in task.seeds.items():
        if vv is None:
            vv = _surface_offsets_at_source(ctx, f, jj)
        state[f] = (jj, cc, vv)

    def skip(f: int, s: int, reason: str) -> None:
        skipped[f] = reason
        alias[f] = s
        if emit is not None:
            emit(f, None, None)

    gen = _generations(task)
    for g in np.unique(gen):
        wave = np.flatnonzero(gen == g)
        for a in range(0, len(wave), _MODEL_BATCH):
            flowed: list[tuple[int, int, _Flowed]] = []
            for k in wave[a : a + _MODEL_BATCH]:
                f = int(task.frames[k])
                s = int(task.sources[k])
                s = alias.get(s, s)
                if s not in state:
                    skip(f, s, f"no valid ancestor (parent {int(task.sources[k])} has no joints)")
                    continue
                try:
                    flowed.append(
                        (
                            int(k),
                            s,
                            _flow_step(ctx, s, f, *state[s], _grandparent(state, came_from, f, s)),
                        )
                    )
                except _Skip as err:
                    skip(f, s, str(err))
            if ctx.hand_models is not None and flowed:
                fits = _model_fits(ctx, [fl.model_in for _, _, fl in flowed])
            else:
                no_fit = np.full(len(MODEL_FIT_TERMS), np.nan)
                fits = [(fl.model_in.x_flow, None, no_fit) for _, _, fl in flowed]
            for (k, s, fl), (x, model_conf, evidence) in zip(flowed, fits, strict=True):
                out_m[k] = evidence
                x, conf, vis = _finish(ctx, fl, x, model_conf)
                f = fl.model_in.frame
                state[f] = (x, conf, vis)
                came_from[f] = s
                out_j[k], out_c[k], out_b[k], used_src[k] = x, conf, vis, s
                if emit is not None:
                    emit(f, x, conf)
    return _TaskResult(task.frames, used_src, out_j, out_c, out_b, skipped, out_m)


def _grandparent(state: dict, came_from: dict[int, int], f: int, s: int) -> np.ndarray | None:
    """The joints (J,3) of ``s``'s own source when it, ``s`` and ``f`` are consecutive frames in
    one direction (the velocity start of :func:`_model_fits`), else None."""
    g = came_from.get(s)
    if g is None or g not in state or abs(f - s) != 1 or f - s != s - g:
        return None
    return state[g][0]


#: frames of one generation whose hand-model fits run as one batch (memory: a few MB per frame)
_MODEL_BATCH = 64


def _generations(task: _Task) -> np.ndarray:
    """``(M,)`` each task frame's distance from the seeds (1 below a seed); ``task.frames`` are in
    topological order."""
    level: dict[int, int] = {}
    gen = np.zeros(len(task.frames), dtype=np.int64)
    for k, (f, s) in enumerate(zip(task.frames, task.sources, strict=True)):
        gen[k] = level[int(f)] = level.get(int(s), 0) + 1
    return gen


# ---------------------------------------------------------------------------------------------
# planning and the public entry point
# ---------------------------------------------------------------------------------------------
def _plan(
    parent: np.ndarray,
    known: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray | None]],
    todo: np.ndarray,
    n_tasks: int,
) -> tuple[list[_Task], dict[int, str]]:
    """Pack the subtrees to compute into ``n_tasks`` balanced tasks (each in topological order)."""
    n = len(parent)
    in_todo = np.zeros(n, dtype=bool)
    in_todo[todo] = True
    in_todo[list(known)] = False
    problems: dict[int, str] = {}
    # a frame in todo whose parent is not in todo hangs off a known frame (or is orphaned)
    heads = np.flatnonzero(in_todo & ~((parent >= 0) & in_todo[np.maximum(parent, 0)]))
    sub_parent = np.where(in_todo, parent, -1)
    groups: list[tuple[int, np.ndarray]] = []  # (seed frame, frames in BFS order)
    by_seed: dict[int, list[np.ndarray]] = {}
    for h, below in zip(heads, propagation_order(sub_parent, heads), strict=True):
        p = int(parent[h])
        if p < 0 or p not in known:
            sub = np.concatenate([[h], below])
            why = "reference without joints" if p < 0 else f"parent {p} has no joints"
            for f in sub:
                problems[int(f)] = f"no valid ancestor ({why})"
            continue
        by_seed.setdefault(p, []).append(np.concatenate([[h], below]).astype(np.int64))
    for seed, parts in by_seed.items():
        groups.append((seed, np.concatenate(parts)))
    covered = np.zeros(n, dtype=bool)
    for _, g in groups:
        covered[g] = True
    for f in np.flatnonzero(in_todo & ~covered):
        problems.setdefault(int(f), "parent chain has a cycle or reaches no reference")
    # greedy balancing, largest subtree first
    groups.sort(key=lambda g: -len(g[1]))
    n_tasks = max(1, min(n_tasks, len(groups)))
    bins: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(n_tasks)]
    loads = np.zeros(n_tasks)
    for g in groups:
        b = int(np.argmin(loads))
        bins[b].append(g)
        loads[b] += len(g[1])
    tasks = []
    for b in bins:
        if not b:
            continue
        frames = np.concatenate([g[1] for g in b])
        seeds = {}
        for seed, _ in b:
            seeds[seed] = known[seed]
        # sources: the parent of each frame (the seed for subtree heads)
        tasks.append(_Task(frames=frames, sources=parent[frames].copy(), seeds=seeds))
    return tasks, problems


def propagate(
    parent: np.ndarray,
    reference_joints: dict[int, np.ndarray],
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    depth_of: Callable[[int], np.ndarray],
    camera: CameraIntrinsics,
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray,
    *,
    aligner: str = DEFAULT_ALIGNER,
    workers: int = 1,
    scheduler=None,
    frames=None,
    progress: Callable[[int, int], None] | None = None,
    on_result: Callable[[int, np.ndarray, np.ndarray], None] | None = None,
    initial_mm: np.ndarray | None = None,
    initial_confidence: np.ndarray | None = None,
    previous: PropagationResult | None = None,
    reference_confidence: dict[int, np.ndarray] | None = None,
    aligner_kwargs: dict | None = None,
    settings: PropagationSettings | None = None,
    tasks_per_worker: int = 2,
    hand_model: bool | hm.HandModel = False,
    fit_weights: hm.FitWeights | None = None,
) -> PropagationResult:
    """Propagate reference poses to the frames of the parent forest.

    Parameters
    ----------
    parent : ``(N,)`` int, ``-1`` at references (the selection's parent forest), or ``(P, N)``
        candidate forests with the same references: every frame is propagated along each (see
        step 6 of the module docstring and ``PropagationSettings.candidate_level``).
    reference_joints : ``{frame: (J, 3) mm}`` lifted references.
    crops : ``(N, S, S)`` normalized crops (memmap preferred), ``boxes`` ``(N, 4)``
        ``[u_left, v_top, sx, sy]``, ``centres_mm`` ``(N, 3)`` (see :mod:`handanno_core.crops`).
    depth_of : ``frame -> (H, W) float32 mm``; may raise ``FrameError``. Must be picklable for
        ``workers > 1`` or ``scheduler``.
    bone_lengths_mm : ``(J - 1,)`` mm, the bone lengths the propagated poses keep, or
        ``(N, J - 1)`` mm, each frame's own (several people's hands, :mod:`handanno_core.hands`):
        a frame keeps its own lengths whatever hand its parent shows.
    aligner : ``"dis"`` (default, measured best), ``"sift"`` (SIFT Flow) or ``"ncc"``.
    workers : local processes (1 = in this process). scheduler : ``"tcp://HOST:PORT"`` of a Dask
        distributed scheduler (or a ``dask.distributed.Client``); overrides ``workers``.
    frames : frames to recompute (default: all non-references). Their ancestors outside
        ``frames`` must have joints: references, or rows of ``previous`` (a
        :class:`PropagationResult`; bit-identical to a full run) or of ``initial_mm`` /
        ``initial_confidence`` (arrays as stored in a session; the joints' depth below the
        surface is then re-measured from the depth map, so results differ slightly).
        Use :func:`descendants` to get the frames below a changed reference.
    progress : ``progress(done, total)`` in frames; on_result : ``on_result(frame, joints, conf)``
        for each computed frame, in the main process, parents before children.
    hand_model : ``True`` personalizes a :class:`handmodel.HandModel` from the references
        (bone lengths, radii from their crops; one per bone-length set, from its own frames'
        references) and fits it to every propagated frame's own depth
        (see :func:`_model_fits`); a ``HandModel`` is used as given; ``False`` turns it off.

    Returns a :class:`PropagationResult`; rows outside ``frames`` are NaN.
    """
    t0 = time.perf_counter()
    parents = np.asarray(parent, dtype=np.int64)
    if parents.ndim == 1:
        parents = parents[None]
    if parents.ndim != 2 or len(parents) == 0:
        raise ValueError(f"parent must be (N,) or (P, N), got shape {parents.shape}")
    n = parents.shape[1]
    if aligner not in ALIGNERS:
        raise ValueError(f"unknown aligner {aligner!r}; choose one of {ALIGNERS}")
    if crops.shape[0] != n or boxes.shape[0] != n or len(centres_mm) != n:
        raise ValueError("parent, crops, boxes and centres must have the same number of frames")
    if np.any((parents[1:] < 0) != (parents[0] < 0)):
        raise ValueError("candidate parent forests must have the same references (-1 entries)")
    settings = settings or PropagationSettings()
    bones = bone_table(bone_lengths_mm, n, len(skeleton.bones))
    known, bad_refs = _reference_seeds(reference_joints, skeleton, bones, reference_confidence)
    todos = _candidate_todos(parents, frames)
    remote = scheduler is not None or workers > 1
    n_workers = _DASK_TASK_SLOTS if scheduler is not None else max(workers, 1)
    models = _hand_models(
        hand_model, known, reference_joints, crops, boxes, centres_mm, camera, skeleton,
        bones, settings,
    )  # fmt: skip
    single = len(parents) == 1
    total = sum(len(t) for t in todos)
    runs: list[PropagationResult] = []
    with _crops_for_workers(crops, remote) as crops_file:
        ctx = _Context(
            *crops_file,
            crops_shape=tuple(crops.shape),
            crops_dtype=str(crops.dtype),
            boxes=np.asarray(boxes, dtype=np.float64),
            centres_mm=np.asarray(centres_mm, dtype=np.float64),
            depth_of=depth_of,
            camera=camera,
            skeleton=skeleton,
            bones=bones,
            aligner=aligner,
            aligner_kwargs=dict(aligner_kwargs or {}),
            settings=settings,
            crops_array=None if remote else crops,
            fit_weights=fit_weights,
        ).with_model(models, known, reference_joints)
        for k, (par, todo) in enumerate(zip(parents, todos, strict=True)):
            if k and settings.candidate_level > 0:
                todo = _needed_by(par, runs[0], todo, settings.candidate_level)
                todos[k] = todo
            seeds = dict(known)
            if runs:  # the first candidate's frames seed the chains the others share with it
                _previous_seeds(seeds, todo, runs[0], None, None, skeleton.num_joints)
            if frames is not None:
                _previous_seeds(
                    seeds, todo, previous, initial_mm, initial_confidence, skeleton.num_joints
                )
            tasks, problems = _plan(par, seeds, todo, n_workers * tasks_per_worker if remote else 1)
            _name_bad_references(problems, bad_refs, par)
            done_before = sum(len(t) for t in todos[: len(runs)])
            out = _Collector.empty(
                n, skeleton.num_joints, problems, tasks,
                None if progress is None else _offset_progress(progress, done_before, total),
                on_result if single else None,
            )  # fmt: skip
            if remote:
                with Runner(workers, scheduler, fresh_processes=True) as runner:
                    runner.each(_run_task, tasks, out.add_remote, runner.share(ctx, broadcast=True))
            else:
                _run_local(ctx, tasks, out)
            runs.append(out.result(0.0))
    if progress is not None and not single:
        progress(total, total)  # the other candidates may have needed fewer frames
    if single:
        runs[0].seconds = time.perf_counter() - t0
        return runs[0]
    steps = np.stack([depths(p) for p in parents])
    return _keep_best(
        runs, 1.0 + settings.chain_step_penalty * steps, on_result, time.perf_counter() - t0
    )


def _needed_by(parent: np.ndarray, first: PropagationResult, todo: np.ndarray, level: float):
    """The frames of ``todo`` that a frame fitted above ``level`` along the first forest (its
    ``first.model_fit`` level) needs in the forest ``parent`` (N,): the frame and its ancestors."""
    lv = np.nan_to_num(first.model_fit[:, 0], nan=0.0)
    need = np.zeros(len(parent), dtype=bool)
    front = np.intersect1d(np.flatnonzero(lv > level), todo)
    while front.size:
        need[front] = True
        up = parent[front]
        front = up[(up >= 0) & ~need[np.maximum(up, 0)]]
    return todo[need[todo]]


def _offset_progress(progress: Callable[[int, int], None], offset: int, total: int):
    """``progress`` of one candidate's run reported as part of all candidates' frames."""
    return lambda done, _total: progress(offset + done, total)


def _same_chain(parents: np.ndarray, k: int) -> np.ndarray:
    """``(N,)`` bool: frames whose whole parent chain in forest ``k`` is the one in forest 0."""
    p0 = parents[0]
    same = parents[k] == p0
    while True:
        nxt = same & ((p0 < 0) | same[np.maximum(p0, 0)])
        if np.array_equal(nxt, same):
            return same
        same = nxt


def _candidate_todos(parents: np.ndarray, frames) -> list[np.ndarray]:
    """Frames to compute in each candidate forest ``parents`` (P, N): the first computes every
    non-reference frame (or ``frames``, and with several candidates their descendants in each),
    the others only the frames whose chain differs from the first's."""
    nonref = parents[0] >= 0
    if frames is None:
        wanted = nonref
    else:
        given = np.unique(np.asarray(frames, dtype=np.int64).ravel())
        wanted = np.zeros(parents.shape[1], dtype=bool)
        if len(parents) == 1:
            wanted[given] = True
        else:
            for par in parents:
                wanted[descendants(par, given)] = True
        wanted &= nonref
    todos = [np.flatnonzero(wanted)]
    for k in range(1, len(parents)):
        todos.append(np.flatnonzero(wanted & ~_same_chain(parents, k)))
    return todos


def _keep_best(
    runs: list[PropagationResult],
    level_factor: np.ndarray,
    on_result: Callable[[int, np.ndarray, np.ndarray], None] | None,
    seconds: float,
) -> PropagationResult:
    """Per frame, the candidate whose hand-model fit explains the frame's own depth best: the
    lowest data + free-space level (:data:`handanno_core.results.MODEL_FIT_TERMS`) times
    ``level_factor`` ``(P, N)`` (the chain-length penalty); without the model the highest mean
    confidence. ``source`` says which parent each frame kept."""
    first = runs[0]
    computed = np.stack([np.all(np.isfinite(r.joints_mm), axis=(1, 2)) for r in runs])
    level = np.stack([r.model_fit[:, 0] for r in runs]) * level_factor
    score = np.stack([r.frame_score for r in runs])
    key = np.where(np.isfinite(level), level, np.inf)
    no_model = ~np.any(np.isfinite(key) & computed, axis=0)
    key = np.where(no_model[None], -np.nan_to_num(score, nan=-np.inf), key)
    key = np.where(computed, key, np.inf)
    pick = np.argmin(key, axis=0)  # ties and frames nobody computed: the first candidate
    rows = np.arange(len(pick))
    out = PropagationResult(
        joints_mm=np.stack([r.joints_mm for r in runs])[pick, rows],
        confidence=np.stack([r.confidence for r in runs])[pick, rows],
        source=np.stack([r.source for r in runs])[pick, rows],
        below_surface_mm=np.stack([r.below_surface_mm for r in runs])[pick, rows],
        model_fit=np.stack([r.model_fit for r in runs])[pick, rows],
        seconds=seconds,
        order=list(first.order),
    )
    reasons = {}
    for r in runs:
        for f, why in r.reasons.items():
            if not computed[:, f].any():
                reasons.setdefault(f, why)
    out.skipped = sorted(reasons)
    out.reasons = reasons
    if on_result is not None:
        for f in first.order:
            if computed[pick[f], f]:
                on_result(f, out.joints_mm[f], out.confidence[f])
    return out


_Seeds = dict[int, tuple[np.ndarray, np.ndarray, np.ndarray | None]]

#: tasks are planned for this many workers when running on a Dask scheduler
_DASK_TASK_SLOTS = 4
#: local runs report progress every this many frames
_PROGRESS_EVERY = 16
#: a reference whose bone lengths are off by more than this fraction is not propagated from
_BONE_PLAUSIBILITY = 0.5


def _reference_seeds(
    reference_joints: dict[int, np.ndarray],
    skeleton: Skeleton,
    bones: BoneTable,
    reference_confidence: dict[int, np.ndarray] | None,
) -> tuple[_Seeds, dict[int, str]]:
    """Seeds ``{frame: (joints (J,3), confidence (J,), None)}`` of the usable references, and
    ``{frame: reason}`` for the implausible ones (references with NaN joints are left out)."""
    j = skeleton.num_joints
    known: _Seeds = {}
    bad_refs: dict[int, str] = {}
    for f, jj in reference_joints.items():
        jj = np.asarray(jj, dtype=np.float64)
        if jj.shape != (j, 3):
            raise ValueError(f"reference {f}: joints must be ({j}, 3), got {jj.shape}")
        if not np.all(np.isfinite(jj)):
            continue
        lengths = bones.of(int(f))
        rel = np.abs(skeleton.bone_lengths(jj) - lengths) / np.maximum(lengths, 1e-6)
        if np.any(jj[:, 2] <= 0) or np.max(rel) > _BONE_PLAUSIBILITY:
            bad_refs[int(f)] = (
                "reference joints implausible (behind the camera or bones off by >50%)"
            )
            continue
        conf = (
            np.ones(j) if reference_confidence is None else reference_confidence.get(f, np.ones(j))
        )
        known[int(f)] = (jj, np.asarray(conf, dtype=np.float64), None)
    return known, bad_refs


def _previous_seeds(
    known: _Seeds,
    todo: np.ndarray,
    previous: PropagationResult | None,
    initial_mm: np.ndarray | None,
    initial_confidence: np.ndarray | None,
    j: int,
) -> None:
    """Add to ``known`` the frames outside ``todo`` that have joints from a previous run."""
    if previous is not None:
        initial_mm = previous.joints_mm
        initial_confidence = previous.confidence
    if initial_mm is None:
        return
    keep = np.ones(len(initial_mm), dtype=bool)
    keep[todo] = False
    for f in np.flatnonzero(keep & np.all(np.isfinite(initial_mm), axis=(1, 2))):
        if int(f) in known:
            continue
        conf = (
            np.asarray(initial_confidence[f], dtype=np.float64)
            if initial_confidence is not None
            else np.ones(j)
        )
        below = None
        if previous is not None and previous.below_surface_mm is not None:
            below = np.asarray(previous.below_surface_mm[f], dtype=np.float64)
        known[int(f)] = (
            np.asarray(initial_mm[f], dtype=np.float64),
            np.nan_to_num(conf, nan=0.5),
            below,
        )


def _name_bad_references(problems: dict[int, str], bad_refs: dict[int, str], parent) -> None:
    """Name the real cause for the subtrees below an implausible reference."""
    if not bad_refs:
        return
    n = len(parent)
    for f in list(problems):
        r, steps = f, 0
        while parent[r] >= 0 and steps < n:  # bounded: the forest may hold a cycle
            r, steps = int(parent[r]), steps + 1
        if r in bad_refs:
            problems[f] = f"reference {r}: {bad_refs[r]}"


def _hand_models(
    hand_model, known, reference_joints, crops, boxes, centres_mm, camera, skeleton,
    bones: BoneTable, settings: PropagationSettings,
) -> tuple[list[hm.HandModel], np.ndarray] | None:  # fmt: skip
    """The hand models to fit, one per row of ``bones.lengths`` (``hand_model=True``: each
    personalized from the usable references with those bones, else from all of them), and each
    one's reference level (:func:`handmodel.reference_level`; inf without references)."""
    if hand_model is False or hand_model is None:
        return None
    refs = sorted(f for f in known if f in reference_joints)
    given = isinstance(hand_model, hm.HandModel)
    if not refs:
        return (
            ([hand_model] * len(bones.lengths), np.full(len(bones.lengths), np.inf))
            if given
            else None
        )
    ref_frames = np.asarray(refs, dtype=np.int64)
    ref_joints = np.stack([known[f][0] for f in refs])
    obs = hm.observe_references(
        skeleton, ref_joints, crops[ref_frames], np.asarray(boxes)[ref_frames],
        np.asarray(centres_mm)[ref_frames], camera, cube_mm=settings.cube_mm,
    )  # fmt: skip
    return hm.personalize_hands(
        skeleton, bones.lengths, None if bones.single else bones.hand[ref_frames], ref_joints, obs,
        camera, given=hand_model if given else None,
    )  # fmt: skip


@contextmanager
def _crops_for_workers(crops: np.ndarray, remote: bool):
    """``(path, offset)`` of the crops as a file the workers can map (``(None, 0)`` in process):
    a memmap's own file, else a temporary ``.npy`` written once and removed afterwards."""
    if not remote:
        yield None, 0
        return
    if isinstance(crops, np.memmap) and crops.filename is not None:
        yield str(crops.filename), int(crops.offset)
        return
    with tempfile.TemporaryDirectory(prefix="handanno-crops-") as tmpdir:
        tmp = Path(tmpdir) / "crops.npy"
        mm = np.lib.format.open_memmap(tmp, mode="w+", dtype=crops.dtype, shape=crops.shape)
        mm[:] = crops
        offset = int(mm.offset)
        del mm
        yield str(tmp), offset


@dataclass
class _Collector:
    """The result arrays, filled task by task (remote) or frame by frame (local)."""

    joints: np.ndarray
    confidence: np.ndarray
    below: np.ndarray
    model_fit: np.ndarray
    source: np.ndarray
    reasons: dict[int, str]
    total: int
    progress: Callable[[int, int], None] | None
    on_result: Callable[[int, np.ndarray, np.ndarray], None] | None
    order: list[int] = field(default_factory=list)
    done: int = 0

    @classmethod
    def empty(cls, n, j, problems, tasks, progress, on_result) -> _Collector:
        return cls(
            joints=np.full((n, j, 3), np.nan),
            confidence=np.full((n, j), np.nan),
            below=np.full((n, j), np.nan),
            model_fit=np.full((n, len(MODEL_FIT_TERMS)), np.nan),
            source=np.full(n, -1, dtype=np.int64),
            reasons=dict(problems),
            total=sum(len(t.frames) for t in tasks),
            progress=progress,
            on_result=on_result,
        )

    def store(self, r: _TaskResult) -> None:
        """Store a finished task's rows."""
        fr = r.frames
        self.joints[fr], self.confidence[fr], self.below[fr] = r.joints, r.confidence, r.below
        self.source[fr] = r.sources
        self.model_fit[fr] = r.model_fit
        self.reasons.update(r.skipped)

    def add_remote(self, r: _TaskResult) -> None:
        """A task finished in another process: store it, report its frames and progress."""
        self.store(r)
        if self.on_result is not None:
            for k, f in enumerate(r.frames):
                if int(f) not in r.skipped:
                    self.on_result(int(f), r.joints[k], r.confidence[k])
        self.order.extend(int(f) for f in r.frames)
        self.done += len(r.frames)
        if self.progress is not None:
            self.progress(self.done, self.total)

    def emit(self, f: int, x, c) -> None:
        """One frame finished in this process (``x`` None if it was skipped)."""
        self.order.append(f)
        self.done += 1
        if x is not None and self.on_result is not None:
            self.on_result(f, x, c)
        if self.progress is not None and (
            self.done % _PROGRESS_EVERY == 0 or self.done == self.total
        ):
            self.progress(self.done, self.total)

    def result(self, seconds: float) -> PropagationResult:
        skipped = sorted(self.reasons)
        return PropagationResult(
            joints_mm=self.joints,
            confidence=self.confidence,
            skipped=skipped,
            reasons={f: self.reasons[f] for f in skipped},
            source=self.source,
            below_surface_mm=self.below,
            model_fit=self.model_fit,
            seconds=seconds,
            order=self.order,
        )


def _run_local(ctx: _Context, tasks: list[_Task], out: _Collector) -> None:
    """Run the tasks in this process, reporting every frame as it is done."""
    for task in tasks:
        out.store(_run_task(ctx, task, out.emit))
