"""The guesses drawn for a frame's unplaced joints, refitted after every click.

A reference frame opens with a guess of every joint (the pre-fill,
:func:`handanno_core.prefill.prefill_reference`). After each click the app's live lift re-solves
the frame with the joints placed so far (:func:`handanno_core.lift.lift_frame`, bounded to
:data:`LIVE_MAX_ITER` iterations); the unplaced joints of that solution are the new guesses, which
the annotator moves or accepts ("accept guesses", G). :func:`refit_guesses` is that refit: THE one
function the app's live lift (``app.control.jobs.lift_for_session``) and the bench's interactive
simulated annotator (:func:`handanno_core.review_loop.interactive_fix`) both call.

The unplaced joints of a lift are only held by the bones, the angle ranges and a weak pull
(``lift.solve._W_FREE``) towards the solve's start pose: the previous refit of the frame, or the
pre-fill for the first one. The bone lengths matter most: the bench passes the bones estimated from
the references annotated before (what the app's "Lift all" stores in the session). The variants
tried and not adopted (other starts, a wrist-and-fingertips-first click order) and their figures
are in the README ("Third round: pre-filled references").

With a personalized hand model and the frame's points (the app's lift worker and the bench's
annotator pass them once two references are lifted), :func:`model_guesses` then fits the
unplaced joints to the frame's own depth, the clicks as a 2D prior: one click pulls the other
guesses onto the observed hand (tune part: 11.0 -> 9.0 joints moved per reference, README
"Fourth round").
No ground truth is read here.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .annotation import FrameAnnotation
from .camera import CameraIntrinsics
from .skeleton import Skeleton

__all__ = [
    "LIVE_MAX_ITER",
    "GuessFit",
    "GuessWeights",
    "live_lift_function",
    "model_guesses",
    "refit_guesses",
]

#: SLSQP iterations of the live re-lift while a joint is edited (measured on the demo: hard solves
#: converge in 13-28 iterations at ~0.9 ms each, elastic ones in 16-22 at ~2.5 ms each, since their
#: slacks add 21 variables and 46 rows). The preview stops at 30 where a solve would take longer
#: (a frame with only its first joints placed; `handanno lift` re-solves every reference to
#: convergence), which keeps the slowest elastic preview under 100 ms. A frame whose lift needed
#: slack (a 2D point off the finger reads the surface behind it) is re-lifted in elastic mode
#: directly, skipping a hard solve that would fail again, with slacks on the joints that needed
#: them only (~20 ms instead of ~50 ms).
LIVE_MAX_ITER = 30


def live_lift_function() -> Callable[..., object]:
    """``handanno_core.lift.lift_frame`` bounded to :data:`LIVE_MAX_ITER` iterations."""
    from .lift import lift_frame

    return functools.partial(lift_frame, max_iter=LIVE_MAX_ITER)


@dataclass(frozen=True)
class GuessWeights:
    """Weights of :func:`model_guesses` (the hand model's energy units, ``handmodel.FitWeights``):
    ``uv`` per px² to a placed joint's click (the lift refit's weight for exact clicks,
    ``lift.model_refit.RefitSettings``: 1.2 / 0.4²), ``pose`` per mm² to the lift's pose. Chosen
    on the suite's tune part (``benchmarks/bench_prefill.py``; README "Fourth round")."""

    uv: float = 7.5
    pose: float = 0.02


@dataclass
class GuessFit:
    """One refit: ``joints_mm`` (J, 3) mm (placed joints where the lift put them, unplaced ones
    the guesses), ``confidence`` (J,), ``slack_joints``: joints whose depth interval could not be
    met (the next refit of the frame starts elastic on them)."""

    joints_mm: np.ndarray
    confidence: np.ndarray
    slack_joints: tuple[int, ...] = ()


def refit_guesses(
    annotation: FrameAnnotation,
    depth: np.ndarray,
    camera: CameraIntrinsics,
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray,
    *,
    eps_mm: float,
    angle_limits: bool,
    prefill_mm: np.ndarray | None = None,
    previous_mm: np.ndarray | None = None,
    start_elastic: bool = False,
    elastic_joints: tuple[int, ...] = (),
    lift_fn: Callable[..., object] | None = None,
    hand_model=None,
    observation=None,
    guess_weights: GuessWeights | None = None,
) -> GuessFit:
    """Refit a frame's guesses to its placed joints (see the module docstring).

    ``annotation``: the frame's joints placed so far (at least one); ``depth`` (H, W) mm;
    ``bone_lengths_mm`` (B,) mm; ``eps_mm``, ``angle_limits``: the session's lift settings.
    ``prefill_mm`` (J, 3) mm: the frame's pre-fill (None: none); ``previous_mm`` (J, 3) mm: the
    previous refit of the frame (None: first); ``start_elastic`` / ``elastic_joints``: the previous
    refit needed slack on these joints. ``lift_fn``: the lift (default :func:`live_lift_function`,
    tests pass a fake). The solve starts from ``previous_mm``, else ``prefill_mm``, else the
    annotation's 3D placements when every joint has one (else the lift's own start).
    ``hand_model`` / ``observation`` (a personalized :class:`handanno_core.handmodel.HandModel`
    and the frame's :func:`handanno_core.handmodel.observe`): the unplaced joints are then
    fitted to the frame's own points (:func:`model_guesses`, weights ``guess_weights``).
    """
    if lift_fn is None:
        lift_fn = live_lift_function()
    init = previous_mm if previous_mm is not None else prefill_mm
    if init is None and np.all(np.isfinite(annotation.xyz_mm)):
        init = np.asarray(annotation.xyz_mm, dtype=np.float64)
    result = lift_fn(
        annotation,
        depth,
        camera,
        skeleton,
        np.asarray(bone_lengths_mm, dtype=np.float64),
        eps_mm=eps_mm,
        angle_limits=angle_limits,
        init_mm=None if init is None else np.asarray(init, dtype=np.float64),
        start_elastic=start_elastic,
        elastic_joints=np.asarray(elastic_joints, dtype=np.int64),
    )
    joints = np.asarray(result.joints_mm, dtype=np.float64)  # type: ignore[attr-defined]
    conf = np.asarray(getattr(result, "confidence", np.ones(len(joints))), dtype=np.float64)
    slack = tuple(int(k) for k in getattr(result, "slack_joints", ()))
    if hand_model is not None and observation is not None and np.all(np.isfinite(joints)):
        joints = model_guesses(
            joints, annotation, hand_model, observation, camera, weights=guess_weights
        )
    return GuessFit(joints, conf, slack)


def model_guesses(
    joints_mm: np.ndarray,
    annotation: FrameAnnotation,
    hand_model,
    observation,
    camera: CameraIntrinsics,
    weights: GuessWeights | None = None,
) -> np.ndarray:
    """``(J, 3)`` mm: ``joints_mm`` (a lift of the placed joints) with its unplaced joints moved to
    the hand model's fit of the frame's own points (articulated ICP,
    :func:`handanno_core.handmodel.fit_frames`, from ``joints_mm``): the placed joints' clicks
    as a 2D prior, the lift's pose as a weak prior (:func:`handanno_core.lift.model_refit.
    click_priors`, ``weights`` default :class:`GuessWeights`). The placed joints keep the lift's
    position. ``observation``: the frame's :class:`handanno_core.handmodel.FrameObservations`
    (one frame)."""
    from dataclasses import replace

    from . import handmodel as hm
    from .lift.model_refit import click_priors

    gw = weights or GuessWeights()
    x = np.asarray(joints_mm, dtype=np.float64)
    placed = np.asarray(annotation.has_2d, dtype=bool)
    priors = click_priors(x[None], [annotation])
    w = replace(hm.FitWeights(), uv=gw.uv, pose=gw.pose)
    fit = hm.fit_frames(hand_model, x[None], observation, camera, weights=w, priors=priors)
    out = x.copy()
    fitted = fit.joints_mm[0]
    if np.all(np.isfinite(fitted)):
        out[~placed] = fitted[~placed]
    return out
