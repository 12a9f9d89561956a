"""Refit lifted references with the personalized hand model, the clicks weighted by the session's
estimated click noise.

The lift (:func:`handanno_core.lift.lift_references`) follows every 2D click exactly and reads
depth only at the clicked pixels, so a click a pixel or two off a thin finger becomes millimetres
of error in 3D. Here each lifted reference is fitted again with the hand model personalized from
all of them (:func:`handanno_core.handmodel.personalize`: capsules with the lift's bone lengths and
radii from the references' own point clouds), by articulated ICP to the reference's whole point
cloud inside its crop (:func:`handanno_core.handmodel.fit_frames`), with the clicks as a 2D prior
and the lifted pose as a weak pose prior. Joints placed in 3D keep their position (a strong pose
prior).

How much the clicks are trusted follows the annotator's click noise ``σ`` (px), estimated per
session from the clicks themselves (:func:`estimate_click_noise`): a probing fit with a moderate
2D weight leaves residuals between the clicks and the fitted joints that grow with ``σ``; the
final fit's 2D weight is ``uv_gain / (σ² + model_px²)`` (per px², the model's own error
``model_px`` keeps it finite for exact clicks). ``noise_px`` given by the caller (the annotator's
known accuracy) replaces the estimate.

The model carries the session's pose prior (:func:`handanno_core.handmodel.personalize`); here it
weighs in as the clicks lose weight, ``FitWeights.prior · σ² / (σ² + model_px²)``: none for exact
clicks, where it made the tune part's references worse, most of it for noisy ones.

A reference keeps its lift where the fit breaks one of its annotated depth orders that the lift
met (the fit does not see depth orders), or where its lift is not finite.

The constants (:class:`RefitSettings`) were chosen on the benchmark suite's tune part
(``benchmarks/bench_lift_refit.py``; figures in the README).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .. import handmodel as hm
from ..annotation import FrameAnnotation
from ..camera import CameraIntrinsics
from ..skeleton import Skeleton


@dataclass(frozen=True)
class RefitSettings:
    """Weights of the refit (units: the hand model's energy, :class:`handmodel.FitWeights`).

    * ``uv_gain`` / ``model_px``: the 2D weight per px² of the final fit is
      ``uv_gain / (σ² + model_px²)`` for click noise ``σ`` px.
    * ``probe_uv``: the 2D weight of the probing fit whose residuals estimate ``σ``;
      ``probe_floor_px`` is the residual it leaves with exact clicks and ``probe_slope`` the share
      of the click noise it leaves in the residual (residual² ≈ floor² + (slope σ)²).
    * ``pose``: per mm² to the lifted pose (Huber, the model's ``pose_huber_mm``);
      ``placed_pose``: the same for joints placed in 3D (they stay where they were placed).
    * ``chunk``: references fitted per batch (memory: the observations of a batch).
    """

    uv_gain: float = 1.2
    model_px: float = 0.4
    probe_uv: float = 0.3
    probe_floor_px: float = 0.44
    probe_slope: float = 0.8
    pose: float = 0.02
    placed_pose: float = 100.0
    chunk: int = 128


@dataclass
class RefitResult:
    """``joints_mm`` (K, J, 3) mm refitted references (rows that kept their lift included);
    ``kept`` (K,) bool: the reference kept its lift; ``noise_px`` the click noise used (estimated
    unless given); ``uv_weight`` the final fit's 2D weight per px²; ``depth_energy`` (K,) the
    final fit's data + free-space terms (how well the model explains the reference's depth; NaN
    where the reference kept its lift)."""

    joints_mm: np.ndarray
    kept: np.ndarray
    noise_px: float
    uv_weight: float
    depth_energy: np.ndarray


def estimate_click_noise(residual_px: np.ndarray, settings: RefitSettings | None = None) -> float:
    """Click noise ``σ`` (px) from the probing fit's 2D residuals ``residual_px`` (n,) px (the
    distance between each click and its fitted joint's projection).

    The residual of a 2D Gaussian of scale ``s`` has ``median(r²) = 2 ln 2 · s²``; ``s² =
    floor² + (slope σ)²`` is solved for ``σ`` (0 where the residuals are at the floor). NaN-free
    input; no residual gives 0."""
    st = settings or RefitSettings()
    r = np.asarray(residual_px, dtype=np.float64)
    r = r[np.isfinite(r)]
    if len(r) == 0:
        return 0.0
    s2 = float(np.median(r**2)) / (2.0 * np.log(2.0))
    return float(np.sqrt(max(s2 - st.probe_floor_px**2, 0.0)) / st.probe_slope)


def denoised_clicks(
    annotations: dict[int, FrameAnnotation],
    joints_mm: dict[int, np.ndarray],
    camera: CameraIntrinsics,
    noise_px: float,
    settings: RefitSettings | None = None,
) -> dict[int, FrameAnnotation]:
    """The clicks of ``annotations`` moved towards the projections of the refitted ``joints_mm``
    (frame -> (J, 3) mm): the precision-weighted mean of a click (variance ``noise_px²``) and
    the model's projection (variance ``model_px²``, :class:`RefitSettings`), per joint with 2D.
    Exact clicks (``noise_px`` 0) are returned unchanged; a frame without finite joints keeps
    its clicks."""
    st = settings or RefitSettings()
    move = float(noise_px) ** 2 / (float(noise_px) ** 2 + st.model_px**2)
    out = {}
    for f, a in annotations.items():
        x = np.asarray(joints_mm.get(f, np.full((a.num_joints, 3), np.nan)), dtype=np.float64)
        if move <= 0.0 or not np.all(np.isfinite(x)):
            out[f] = a
            continue
        uv = np.where(a.has_2d[:, None], a.uv_px + move * (camera.project(x) - a.uv_px), np.nan)
        out[f] = replace(a, uv_px=uv)
    return out


def click_priors(
    pose_mm: np.ndarray, annotations: list[FrameAnnotation], placed_pose_w: float = 1.0
) -> hm.Priors:
    """The clicks of ``annotations`` (K of them) as the hand-model fit's priors
    (:class:`handanno_core.handmodel.Priors`): each joint's 2D click (weight 1, 0 where not
    clicked) and the pose ``pose_mm`` (K, J, 3) mm as a pose prior (weight 1), replaced by the
    annotation's 3D placement where a joint was placed in 3D (weight ``placed_pose_w``: it
    multiplies ``FitWeights.pose``). Used by the references' refit here and by the guesses' fit
    (:func:`handanno_core.guesses.model_guesses`)."""
    uv = np.stack([a.uv_px for a in annotations]).astype(np.float64)
    has_uv = np.all(np.isfinite(uv), axis=-1)
    placed = np.stack([a.has_3d for a in annotations])
    pose = np.where(placed[..., None], np.stack([a.xyz_mm for a in annotations]), pose_mm)
    pose_w = np.where(placed, placed_pose_w, 1.0)
    return hm.Priors(pose=pose, pose_w=pose_w, uv=np.nan_to_num(uv), uv_w=has_uv.astype(float))


def _orders_broken(x: np.ndarray, annotations, parents: np.ndarray) -> np.ndarray:
    """(K,) bool: some annotated depth order ``σ_k (z_k − z_parent) >= 0`` fails in ``x``."""
    order = np.stack([np.asarray(a.depth_order, dtype=np.float64) for a in annotations])
    has_parent = parents >= 0
    dz = x[:, :, 2] - x[:, np.where(has_parent, parents, 0), 2]
    return np.any((order != 0) & has_parent & (order * dz < 0), axis=1)


def refit_references(
    joints_mm: np.ndarray,
    annotations: list[FrameAnnotation],
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray,
    *,
    cube_mm: float,
    noise_px: float | None = None,
    settings: RefitSettings | None = None,
    fit_weights: hm.FitWeights | None = None,
) -> RefitResult:
    """Refit K lifted references of one hand (see the module docstring).

    Parameters
    ----------
    joints_mm : (K, J, 3) mm lifted references (rows with NaN keep their lift).
    annotations : K annotations of those frames (2D clicks, depth orders, joints placed in 3D).
    crops : (K, S, S) normalized depth crops of those frames; boxes (K, 4); centres_mm (K, 3).
    bone_lengths_mm : (B,) the hand's bone lengths (the lift's estimate).
    noise_px : the annotator's click noise (px); None estimates it from the clicks.
    """
    st = settings or RefitSettings()
    x0 = np.asarray(joints_mm, dtype=np.float64)
    k = len(x0)
    if len(annotations) != k:
        raise ValueError(f"{k} lifted references but {len(annotations)} annotations")
    out = x0.copy()
    kept = np.ones(k, dtype=bool)
    ok = np.flatnonzero(np.all(np.isfinite(x0), axis=(1, 2)))
    if len(ok) == 0:
        return RefitResult(out, kept, float(noise_px or 0.0), 0.0, np.full(k, np.nan))
    base = replace(fit_weights or hm.FitWeights(), pose=st.pose)
    model, obs = hm.personalize_from_crops(
        skeleton, bone_lengths_mm, x0[ok], crops[ok], np.asarray(boxes)[ok],
        np.asarray(centres_mm)[ok], camera, cube_mm=cube_mm,
    )  # fmt: skip
    anns = [annotations[i] for i in ok]
    # pose_w multiplies FitWeights.pose: a placed joint's weight is placed_pose per mm²
    priors = click_priors(x0[ok], anns, st.placed_pose / base.pose)

    def fit(uv_weight: float, prior: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        w = replace(base, uv=uv_weight, prior=prior)
        parts, depth = [], []
        for a in range(0, len(ok), st.chunk):
            rows = np.arange(a, min(a + st.chunk, len(ok)))
            res = hm.fit_frames(
                model, x0[ok][rows], obs.take(rows), camera, weights=w, priors=priors.take(rows)
            )
            parts.append(res.joints_mm)
            depth.append(res.terms["data"] + res.terms["free_space"])
        return np.concatenate(parts), np.concatenate(depth)

    if noise_px is None:
        probe, _ = fit(st.probe_uv)
        has = priors.uv_w > 0
        residual = np.linalg.norm(camera.project(probe) - priors.uv, axis=-1)[has]
        noise_px = estimate_click_noise(residual, st)
    uv_weight = st.uv_gain / (float(noise_px) ** 2 + st.model_px**2)
    # the session's pose prior weighs in as the clicks lose weight (none for exact clicks)
    share = float(noise_px) ** 2 / (float(noise_px) ** 2 + st.model_px**2)
    fitted, depth = fit(uv_weight, base.prior * share)
    parents = skeleton.parent_array
    broken = _orders_broken(fitted, anns, parents) & ~_orders_broken(x0[ok], anns, parents)
    out[ok[~broken]] = fitted[~broken]
    kept[ok[~broken]] = False
    depth_energy = np.full(k, np.nan)
    depth_energy[ok[~broken]] = depth[~broken]
    return RefitResult(out, kept, float(noise_px), float(uv_weight), depth_energy)
