"""The bench's simulated annotator at work: pre-filled references and review rounds (benchmarks only).

Annotation effort is what the bench reports error against: **frames touched** (references plus
review corrections) and **joints clicked**. The simulated annotator behaves as a person with the
app would, from ground truth (2D positions, visibility and depth order only):

* :func:`simulated_fix` - a review correction: the frame opens with the result drawn, seeded
  as the app seeds it (every joint an accepted guess where it is shown, in 3D); the annotator
  moves only the joints whose drawn 2D position is more than ``click_px`` (4 px) from the truth
  (to the truth plus the bench's Gaussian ``noise_px``, with the truth's visibility and depth
  order) and accepts the others. One click per moved joint.
* :func:`interactive_fix` - what a person does in the app with a frame opened with guesses:
  move the guess furthest off, let the guesses refit to the joints placed so far (the app's live
  lift, :func:`handanno_core.guesses.refit_guesses`), repeat until every guess is within
  ``click_px``, accept the guesses. One click per moved joint.
* :func:`annotate_prefilled` - the references, in time order, each opened pre-filled by
  :func:`handanno_core.prefill.prefill_reference` (with the crop descriptors) from the references
  annotated before it and fixed with :func:`interactive_fix`; after each, the references
  annotated so far are lifted with their bone lengths estimated (as the app's "Lift all"), so the
  next one is pre-filled from them and refitted with those bones (and, from the second lifted
  reference on, with the hand model personalized from them); a frame with nothing to pre-fill
  from opens with the template hand at its hand centre, as in the app.
* :func:`review_rounds` - after the first pass, ``rounds`` times: the ranking
  (:func:`handanno_core.review.rank_priority`, no ground truth) picks ``budget`` frames not reviewed
  before; each is fixed as above and becomes a reference (a correction), or, where no joint is
  off by more than ``click_px``, is accepted as shown (the app's review *Accept*: no reference,
  nothing recomputed; a reference that only repeats the propagated pose would be held as if
  annotated and re-root its neighbours on it). Every shown frame counts as touched. The
  corrected frames are lifted, only their descendants in the propagation's forests re-propagate
  (:func:`handanno_core.pipeline.frames_to_repropagate`, as the app's review runner does), then
  those frames are refined again, the others held at their refined result (``pipeline.refine(
  frames=)``). One report entry per round (round 0 = the first pass).
* :func:`bench_review` - :func:`review_rounds` once per ranking, each on its own copy of a finished
  bench session, so that every ranking starts from the same first pass.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .annotation import FrameAnnotation
from .camera import CameraIntrinsics
from .prefill import MODEL_MIN_REFERENCES
from .session import (
    Batch,
    Session,
    SetFrameAnnotation,
    SetReference,
    SetReview,
    copy_session_folder,
)

__all__ = [
    "BAD_MM",
    "CLICK_PX",
    "annotate_prefilled",
    "bench_review",
    "interactive_fix",
    "effort_to_target",
    "review_rounds",
    "simulated_fix",
]

#: a drawn joint farther than this (px) from the truth is moved by the simulated annotator
CLICK_PX = 4.0
#: a frame is "bad" when a joint is more than this (mm) off
BAD_MM = 20.0


def simulated_fix(
    shown_mm: np.ndarray,
    gt_mm: np.ndarray,
    depth: np.ndarray,
    camera: CameraIntrinsics,
    skeleton,
    *,
    noise_px: float = 0.0,
    rng: np.random.Generator | None = None,
    click_px: float = CLICK_PX,
) -> tuple[FrameAnnotation, int]:
    """What the simulated annotator leaves on a propagated frame drawn with ``shown_mm`` (J, 3)
    mm, and how many joints it moved (clicks), as in the app's review: the correction seeds the
    frame's annotation from the shown skeleton (:func:`handanno_core.review.seed_annotation`:
    every joint an accepted guess in 3D, visibility from the depth), and the annotator clicks
    each joint drawn more than ``click_px`` from the truth ``gt_mm`` (J, 3) mm: its 2D becomes
    the truth's plus ``noise_px`` Gaussian noise, its 3D position is cleared (a click replaces
    it, ``AnnotateState.place_2d``), and it gets the truth's visibility and depth order
    (:func:`handanno_core.synth.simulate_annotation`). A joint whose truth is off the image
    cannot be clicked: it stays as seeded where the shown skeleton draws it off the image too,
    else the annotator marks it outside the image (the app's "Outside the image", not counted
    as a click). ``depth`` (H, W) mm."""
    from .review import seed_annotation
    from .synth import simulate_annotation

    full = simulate_annotation(gt_mm, depth, camera, skeleton, noise_px, rng)
    shown = np.asarray(shown_mm, dtype=np.float64)
    ann = seed_annotation(shown, camera, depth, skeleton.surface_offsets_mm)
    truth = camera.project(np.asarray(gt_mm, dtype=np.float64))
    with np.errstate(invalid="ignore"):
        moved = ~(np.linalg.norm(camera.project(shown) - truth, axis=-1) <= click_px)
    moved &= full.has_2d  # nobody clicks off the image
    ann.xyz_mm[moved] = np.nan  # NaN (not drawn): moved too
    ann.uv_px[moved] = full.uv_px[moved]
    ann.accepted[moved] = False
    ann.visible[moved] = full.visible[moved]
    ann.depth_order[moved] = full.depth_order[moved]
    ann.mark_outside(full.outside & camera.on_image(camera.project(shown)))
    return ann, int(moved.sum())


def interactive_fix(
    guess_mm: np.ndarray,
    gt_mm: np.ndarray,
    depth: np.ndarray,
    camera: CameraIntrinsics,
    skeleton,
    bone_lengths_mm: np.ndarray,
    *,
    eps_mm: float,
    angle_limits: bool,
    noise_px: float = 0.0,
    rng: np.random.Generator | None = None,
    click_px: float = CLICK_PX,
    refit_s: list[float] | None = None,
    hand_model=None,
    observation=None,
    guess_weights=None,
) -> tuple[FrameAnnotation, int, list[int]]:
    """What a person does in the app with a frame opened with guesses ``guess_mm`` (J, 3) mm: move
    the guess that is furthest off (more than ``click_px`` from the truth ``gt_mm`` (J, 3) mm),
    let the guesses refit
    (:func:`handanno_core.guesses.refit_guesses`, as the app's live lift, warm-started from the
    previous refit, ``bone_lengths_mm`` (B,) mm, ``eps_mm``/``angle_limits`` the session's), and
    repeat until no guess is more than ``click_px`` off; then accept the guesses (their 2D). A
    joint whose truth is off the image is never clicked (nobody can): the annotator marks it
    outside the image before the first click (the app's "Outside the image", not counted as a
    click), and no guess of it is accepted; a guess drawn off the image is not accepted either
    (the app skips it).

    A moved joint gets the true 2D plus ``noise_px`` Gaussian noise and the truth's visibility and
    depth order (:func:`handanno_core.synth.simulate_annotation`), which every joint gets in the
    annotation returned, as :func:`simulated_fix` gives them. A guess not drawn (NaN, behind the
    camera, off the image) counts as off. Returns ``(annotation, clicks, joints in click
    order)``. ``refit_s``: each refit's duration (s) is appended to it. ``hand_model`` /
    ``observation``: the refit also fits the unplaced joints to the frame's own points
    (:func:`handanno_core.guesses.model_guesses`, weights ``guess_weights``)."""
    from .guesses import refit_guesses
    from .synth import simulate_annotation

    full = simulate_annotation(gt_mm, depth, camera, skeleton, noise_px, rng)
    truth = camera.project(np.asarray(gt_mm, dtype=np.float64))
    guess = np.asarray(guess_mm, dtype=np.float64)
    ann = FrameAnnotation.empty(skeleton.num_joints)
    ann.outside[:] = full.outside
    shown, previous, slack = guess, None, ()
    clicked: list[int] = []
    while True:
        placed = ann.annotated
        drawn = camera.project(shown)
        with np.errstate(invalid="ignore"):
            off = np.where(camera.on_image(drawn), np.linalg.norm(drawn - truth, axis=-1), np.inf)
        off = np.where(np.isnan(off), np.inf, off)
        todo = ~placed & (off > click_px) & full.has_2d  # nobody clicks off the image
        if not todo.any():
            break
        cand = np.flatnonzero(todo)
        k = int(cand[np.argmax(off[cand])])  # the furthest off (the first of equals)
        ann.uv_px[k] = full.uv_px[k]
        ann.visible[k] = full.visible[k]
        ann.depth_order[k] = full.depth_order[k]
        clicked.append(k)
        t0 = time.perf_counter()
        try:
            fit = refit_guesses(
                ann,
                depth,
                camera,
                skeleton,
                bone_lengths_mm,
                eps_mm=eps_mm,
                angle_limits=angle_limits,
                prefill_mm=guess,
                previous_mm=previous,
                start_elastic=bool(slack),
                elastic_joints=slack,
                hand_model=hand_model,
                observation=observation,
                guess_weights=guess_weights,
            )
        except ValueError:  # the app keeps drawing the last guesses when a refit fails
            continue
        finally:
            if refit_s is not None:
                refit_s.append(time.perf_counter() - t0)
        shown, previous, slack = fit.joints_mm, fit.joints_mm, fit.slack_joints
    uv = camera.project(shown)
    take = ~ann.complete & camera.on_image(uv)  # "accept guesses" skips marked and off-image
    ann.uv_px[take] = uv[take]
    ann.accepted[:] = take
    ann.visible[:] = full.visible
    ann.depth_order[:] = full.depth_order
    return ann, len(clicked), clicked


def _lift(session: Session, ann: FrameAnnotation, depth: np.ndarray, bones, init_mm=None):
    from .lift import lift_frame

    s = session.model.settings
    return lift_frame(
        ann,
        depth,
        session.camera,
        session.skeleton,
        np.asarray(bones, dtype=np.float64),
        eps_mm=s.eps_mm,
        angle_limits=s.angle_limits,
        init_mm=init_mm,
    )


def _offsets_px(camera: CameraIntrinsics, a_mm: np.ndarray, b_mm: np.ndarray) -> list[float]:
    """``(J,)`` px between the projections of two skeletons (J, 3) mm, rounded, as a list."""
    off = np.linalg.norm(camera.project(a_mm) - camera.project(b_mm), axis=-1)
    return [round(float(v), 2) for v in off]


def _crop_descriptors(session: Session, crop_data) -> np.ndarray | None:
    """The session's crop descriptors (N, D), None without cached crops."""
    if crop_data is None:
        return None
    from .descriptors import compute_descriptors

    return compute_descriptors(crop_data[0], kind=session.model.settings.descriptor)


def _model_refit_inputs(session: Session, frame: int, model) -> dict:
    """``{"hand_model", "observation"}`` of :func:`interactive_fix` for ``frame`` (empty without
    a model or the crop cache)."""
    from .prefill import frame_observation

    obs = frame_observation(session, frame) if model else None
    return {} if obs is None else {"hand_model": model, "observation": obs}


def _template_guess(session: Session, frame: int) -> np.ndarray | None:
    """The app's first guess of a frame when nothing has joints: the template hand at the hand
    centre of the frame's crop (None without the crop cache or a template)."""
    from .prefill import cached_crops
    from .synth import template_hand

    crop_data = cached_crops(session)
    centre = None if crop_data is None else np.asarray(crop_data[1][frame], dtype=np.float64)
    if centre is None or not np.all(np.isfinite(centre)):
        return None
    return template_hand(session.skeleton, centre)


def _lift_all(
    session: Session, sequence, annotations: dict, lifted_mm: np.ndarray, start_bones=None
) -> np.ndarray:
    """The app's "Lift all" on the references annotated so far: their lifts written into
    ``lifted_mm`` (N, J, 3) mm; returns the bone lengths (B,) mm estimated with them, starting
    from ``start_bones`` (B,) mm (the previous estimate: fewer re-estimation rounds; None: from
    the annotations)."""
    from .lift import lift_references

    s = session.model.settings
    done = lift_references(
        annotations,
        sequence.depth,
        sequence.camera,
        session.skeleton,
        bone_lengths_mm=start_bones,
        eps_mm=s.eps_mm,
        angle_limits=s.angle_limits,
    )
    for g, joints in done.joints_mm.items():
        lifted_mm[g] = joints
    return np.asarray(done.bone_lengths_mm, dtype=np.float64)


def annotate_prefilled(
    session: Session,
    *,
    noise_px: float = 0.0,
    seed: int = 0,
    click_px: float = CLICK_PX,
    hand_model: bool = True,
    model_refit: bool = True,
    guess_weights=None,
    refit_s: list[float] | None = None,
    quiet: bool = False,
) -> dict:
    """Annotate every reference with pre-fills (see the module docstring); one journal entry.

    The references are annotated in time order, each opened with its pre-fill and fixed by
    :func:`interactive_fix` (each refit's seconds appended to ``refit_s``); the first, with
    nothing to pre-fill from, opens with the template hand at its hand centre, as in the app
    (:func:`handanno_core.synth.template_hand`; all its joints clicked without the crop cache).
    After each reference, the references annotated so far are lifted with their bone lengths
    estimated (:func:`handanno_core.lift.lift_references`, what the app's "Lift all" does), and
    those bones and lifts feed the next pre-fill and refits (one bone set for the session).
    ``hand_model``: once :data:`MODEL_MIN_REFERENCES` references are lifted, the hand model
    personalized from them (:func:`handanno_core.prefill.reference_hand_model`) snaps each further
    pre-fill to its frame's own depth and silhouette, and with ``model_refit`` each refit also fits
    the unplaced joints to the frame's own points (:func:`handanno_core.guesses.model_guesses`,
    weights ``guess_weights``, a :class:`handanno_core.guesses.GuessWeights`; None: its
    defaults). Both on by default, as in the app (chosen on the suite's tune part, README).

    Returns ``{"clicks": {frame: joints moved}, "prefilled": frames that opened pre-filled,
    "clicks_per_reference": mean, "click_order": {frame: joints in click order},
    "guess_off_px": {frame: (J,) px of the pre-fill from the truth (evaluation)}, "guess_mm":
    {frame: (J, 3) mm the pre-fill}, "gap": {frame:
    frames in time to the nearest reference annotated before it}, "order": the frames in
    annotation order, "template": the frames opened with the template hand}``. Needs the
    session's crops on disk for propagated pre-fills.
    """
    from .prefill import cached_crops, prefill_reference, reference_hand_model

    sequence = session.open_sequence()
    descriptors = _crop_descriptors(session, cached_crops(session))
    gt = sequence.ground_truth
    if gt is None:
        raise ValueError(f"{sequence.path}: the simulated annotator needs ground truth")
    skeleton = session.skeleton
    bones = session.model.bone_lengths_mm
    if bones is None:
        bones = skeleton.template_bone_lengths_mm
    results = session.load_results()
    scratch = {k: np.full_like(results[k], np.nan) for k in ("lifted_mm", "init_mm", "final_mm")}
    clicks: dict[int, int] = {}
    order_of: dict[int, list[int]] = {}
    prefilled: list[int] = []
    templates: list[int] = []
    annotations: dict[int, FrameAnnotation] = {}
    guess_off, gaps = {}, {}  # {frame: (J,) px}, {frame: frames to the nearest annotated}
    guess_of: dict[int, np.ndarray] = {}  # {frame: (J, 3) mm pre-fill}
    refs = sorted(int(f) for f in session.reference_frames)
    estimated = None  # the bones of the last "lift all"
    for f in refs:
        rng = np.random.default_rng([seed, f, 404])  # as pipeline.annotate_from_gt
        depth = sequence.depth(f)
        model = False
        lifted = np.flatnonzero(np.all(np.isfinite(scratch["lifted_mm"]), axis=(1, 2)))
        if hand_model and bones is not None and lifted.size >= MODEL_MIN_REFERENCES:
            model = reference_hand_model(session, scratch["lifted_mm"], lifted, bones) or False
        guess = prefill_reference(session, f, scratch, descriptors=descriptors, hand_model=model)
        if annotations:
            gaps[f] = int(min(abs(f - g) for g in annotations))
        elif guess is None:
            guess = _template_guess(session, f)  # as the app: a template hand at the centre
            templates += [] if guess is None else [f]
        if guess is None:
            from .synth import simulate_annotation

            ann = simulate_annotation(
                gt.joints_mm[f], depth, sequence.camera, skeleton, noise_px, rng
            )
            clicks[f] = int(ann.has_2d.sum())
        else:
            guess_off[f] = _offsets_px(sequence.camera, guess, gt.joints_mm[f])  # evaluation
            guess_of[f] = np.asarray(guess, dtype=np.float64)
            settings = session.model.settings
            ann, clicks[f], order_of[f] = interactive_fix(
                guess,
                gt.joints_mm[f],
                depth,
                sequence.camera,
                skeleton,
                np.asarray(bones),
                eps_mm=settings.eps_mm,
                angle_limits=settings.angle_limits,
                noise_px=noise_px,
                rng=rng,
                click_px=click_px,
                refit_s=refit_s,
                guess_weights=guess_weights,
                **_model_refit_inputs(session, f, model if model_refit else False),
            )
            prefilled += [] if f in templates else [f]
        annotations[f] = ann
        if len(annotations) >= 2:  # "lift all" on the references so far
            bones = _lift_all(session, sequence, annotations, scratch["lifted_mm"], estimated)
            estimated = bones
        elif bones is not None:  # lifted now so that the next reference can be pre-filled from it
            own = session.bone_lengths_of(f) or bones  # the frame's hand's, if lifted
            scratch["lifted_mm"][f] = _lift(session, ann, depth, own, guess).joints_mm
    session.execute(
        Batch(
            commands=[
                SetFrameAnnotation(frame=f, annotation=a.to_json()).model_dump()
                for f, a in annotations.items()
            ]
        ),
        client="simulated-annotator",
    )
    per_ref = float(np.mean(list(clicks.values()))) if clicks else float("nan")
    if not quiet:
        print(
            f"annotated {len(clicks)} references pre-filled: {per_ref:.1f} joints moved per "
            f"reference ({len(prefilled)} opened pre-filled)",
            flush=True,
        )
    return {
        "clicks": clicks,
        "prefilled": prefilled,
        "clicks_per_reference": per_ref,
        "click_order": order_of,
        "guess_off_px": guess_off,
        "guess_mm": guess_of,
        "gap": gaps,
        "order": refs,
        "template": templates,
    }


def _frame_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``(N,)`` worst joint error per frame, mm (inf where not predicted)."""
    e = np.linalg.norm(np.asarray(pred, dtype=np.float64) - gt, axis=-1).max(axis=1)
    return np.where(np.isfinite(e), e, np.inf)


def _accepted_frames(session: Session) -> np.ndarray:
    """Frames a review accepted as shown (``SetReview`` status "accepted"), sorted."""
    review = session.model.review
    return np.array(sorted(int(f) for f, s in review.items() if s == "accepted"), dtype=np.int64)


def _entry(session: Session, gt: np.ndarray, round_: int, clicked: int, bad_mm: float) -> dict:
    from .evaluate import error_summary

    final = session.load_results()["final_mm"]
    s = error_summary(final, gt)
    e = _frame_errors(final, gt)
    accepted = len(_accepted_frames(session))
    return {
        "round": round_,
        "references": len(session.reference_frames) - len(session.model.corrections),
        "corrections": len(session.model.corrections),
        "accepted": accepted,
        # references (incl. corrections) plus frames a review accepted as shown
        "frames_touched": len(session.reference_frames) + accepted,
        "joints_clicked": clicked,
        "mean_mm": round(float(s["mean_mm"]), 3),
        "median_mm": round(float(s["median_mm"]), 3),
        "max_mm": round(float(s["max_mm"]), 3),
        "bad_share": round(float(np.mean(e > bad_mm)), 5),
    }


def _show(ranking: str, session: Session, results, k: int, reviewed, bad) -> tuple:
    """The ``k`` frames a review round shows (``(k,)`` int, not the ``reviewed`` ones) by
    ``ranking``, and the recall of the ``bad`` (N,) frames in the ranking's first 10 %."""
    from .prefill import cached_crops
    from .review import pick_frames, rank_priority, recall_at, uniform_pick

    n = session.num_frames
    if ranking == "uniform":
        shown = uniform_pick(n, k, exclude=reviewed)
        top = uniform_pick(n, int(round(0.1 * n)), exclude=reviewed)
        return shown, float(bad[top].sum() / bad.sum()) if bad.any() else float("nan")
    breaks = session.model.sequence_breaks
    priority = rank_priority(ranking, session, results, cached_crops(session))
    shown = pick_frames(priority, k, exclude=reviewed, sequence_breaks=breaks)
    return shown, recall_at(priority, bad, 0.10, exclude=reviewed, sequence_breaks=breaks)


def _clicks_on_references(session: Session) -> int:
    """Joints clicked on the references that are not corrections, annotated without pre-fill:
    every joint with a 2D position (one whose truth is off the image has none)."""
    corrections = {int(f) for f in session.model.corrections}
    frames = [int(f) for f in session.reference_frames if int(f) not in corrections]
    return int(sum(a.has_2d.sum() for a in session.annotations(frames).values()))


def _review_frame(session: Session, sequence, frame: int, shown_mm, gt_mm, bones, **fix):
    """The simulated annotator on one shown frame (:func:`simulated_fix`, keyword arguments
    ``fix``): a correction journaled and lifted, or, with nothing to move, the frame accepted as
    shown. Returns ``(lift or None when accepted, joints clicked)``."""
    depth = sequence.depth(frame)
    ann, clicks = simulated_fix(shown_mm, gt_mm, depth, sequence.camera, session.skeleton, **fix)
    if clicks == 0:  # nothing to move: the annotator presses Accept (no new reference)
        session.execute(SetReview(frame=frame, status="accepted"), client="simulated-annotator")
        return None, 0
    commands = [
        SetReference(frame=frame, is_reference=True, correction=True).model_dump(),
        SetFrameAnnotation(frame=frame, annotation=ann.to_json()).model_dump(),
    ]
    session.execute(Batch(commands=commands), client="simulated-annotator")
    own = session.bone_lengths_of(frame)
    return _lift(session, ann, depth, bones if own is None else own, shown_mm), clicks


def review_rounds(
    session: Session,
    *,
    rounds: int,
    budget: float,
    ranking: str = "evidence",
    noise_px: float = 0.0,
    seed: int = 0,
    click_px: float = CLICK_PX,
    bad_mm: float = BAD_MM,
    reference_clicks: int | None = None,
    workers: int = 1,
    aligner: str | None = None,
    quiet: bool = False,
) -> list[dict]:
    """Simulated review rounds on a session whose first pass (lift, propagate, refine) is done.

    ``budget``: frames shown per round (``>= 1``), or a share of the sequence's frames (``< 1``).
    ``reference_clicks``: joints clicked on the references (default: every joint with a 2D
    position on each reference that is not a correction, :func:`_clicks_on_references`).
    Returns one entry per round (round 0 = before any correction): ``frames_touched`` (references,
    corrections and frames accepted as shown), ``corrections``, ``accepted``, ``joints_clicked``,
    the error of all frames (``mean_mm``, ``median_mm``, ``max_mm``), ``bad_share`` (frames with
    a joint more than ``bad_mm`` off) and, for the frames the round showed: ``shown``,
    ``shown_bad`` (of them bad before the round), ``recall`` (share of the bad frames shown),
    ``recall_at_10`` (share of them in the ranking's first 10 %), ``clicks`` and ``timings_s``.
    Ground truth feeds only the annotator and these statistics.
    """
    from . import pipeline
    from .export import best_joints

    sequence = session.open_sequence()
    gt = np.asarray(sequence.ground_truth.joints_mm, dtype=np.float64)
    n = session.num_frames
    k = int(round(budget * n)) if budget < 1 else int(budget)
    if k < 1:
        raise ValueError(f"review budget {budget} shows no frame of {n}")
    clicked = int(
        reference_clicks if reference_clicks is not None else _clicks_on_references(session)
    )
    entries = [_entry(session, gt, 0, clicked, bad_mm)]
    if not quiet:
        print(f"  {ranking} round 0: {entries[0]}", flush=True)
    for r in range(1, rounds + 1):
        timings: dict[str, float] = {}
        t = time.perf_counter()
        results = session.load_results()
        reviewed = np.union1d(session.reference_frames, _accepted_frames(session))
        shown_mm, _ = best_joints(results)
        err = _frame_errors(shown_mm, gt)
        bad = err > bad_mm
        bad[reviewed] = False
        shown, rec10 = _show(ranking, session, results, k, reviewed, bad)
        timings["rank"] = round(time.perf_counter() - t, 3)
        if shown.size == 0:
            break
        t = time.perf_counter()
        bones = np.asarray(session.model.bone_lengths_mm, dtype=np.float64)
        lifted, conf = results["lifted_mm"], results["confidence"]
        round_clicks = 0
        corrected: list[int] = []
        for f in (int(x) for x in shown):
            fix = dict(
                noise_px=noise_px, rng=np.random.default_rng([seed, f, 505]), click_px=click_px
            )
            lift, c = _review_frame(session, sequence, f, shown_mm[f], gt[f], bones, **fix)
            round_clicks += c
            if lift is not None:
                lifted[f], conf[f] = lift.joints_mm, lift.confidence
                corrected.append(f)
        timings["annotate_lift"] = round(time.perf_counter() - t, 3)
        frames = np.zeros(0, dtype=np.int64)
        if corrected:  # frames accepted as shown change nothing
            session.save_results(lifted_mm=lifted, confidence=conf)
            t = time.perf_counter()
            frames = pipeline.frames_to_repropagate(session, corrected)
            pipeline.propagate(session, workers=workers, aligner=aligner, frames=frames, quiet=True)
            timings["propagate"] = round(time.perf_counter() - t, 3)
            t = time.perf_counter()
            pipeline.refine(session, quiet=True, frames=frames)  # the corrected frames too
            timings["refine"] = round(time.perf_counter() - t, 3)
        clicked += round_clicks
        entry = _entry(session, gt, r, clicked, bad_mm)
        entry.update(
            shown=int(shown.size),
            shown_bad=int(bad[shown].sum()),
            bad_before=int(bad.sum()),
            recall=round(float(bad[shown].sum() / bad.sum()), 4) if bad.any() else None,
            recall_at_10=None if np.isnan(rec10) else round(rec10, 4),
            clicks=round_clicks,
            repropagated=int(frames.size),
            timings_s=timings,
        )
        entries.append(entry)
        if not quiet:
            print(f"  {ranking} round {r}: {entry}", flush=True)
    return entries


def bench_review(
    folder: str | Path,
    *,
    rankings: list[str],
    rounds: int,
    budget: float,
    **kw,
) -> dict[str, list[dict]]:
    """:func:`review_rounds` per ranking, each on a copy ``<folder>-review-<ranking>`` of the
    finished (closed) bench session in ``folder``; ``{ranking: entries}``. A copy another process
    is still reviewing is not replaced (:class:`~handanno_core.session.SessionLockedError` naming
    it): two runs on the same sessions would otherwise delete each other's copies mid-round."""
    folder = Path(folder)
    out: dict[str, list[dict]] = {}
    for ranking in rankings:
        copy = folder.with_name(f"{folder.name}-review-{ranking}")
        writer = f"bench review rounds ({ranking}) of {folder}"
        copy_session_folder(folder, copy, writer)
        session = Session.open(copy, writer=writer)
        try:
            out[ranking] = review_rounds(
                session, rounds=rounds, budget=budget, ranking=ranking, **kw
            )
        finally:
            session.close()
    return out


def effort_to_target(
    entries: list[dict], mean_mm: float = 3.0, bad_share: float = 0.01
) -> int | None:
    """Frames touched at the first round with ``mean_mm`` at most 3 mm and at most 1 % of frames
    with a joint more than :data:`BAD_MM` off; None if no round reached it."""
    for e in entries:
        if e["mean_mm"] <= mean_mm and e["bad_share"] <= bad_share:
            return int(e["frames_touched"])
    return None


def bench_run_review(
    run: dict,
    folder: Path,
    review: dict,
    prefilled: dict | None,
    noise_px: float,
    workers: int,
    aligner: str | None,
    quiet: bool,
) -> None:
    """The bench's per-run review part: adds to ``run`` (one JSON run of :mod:`handanno_core.bench`)
    ``reference_clicks`` and ``clicks_per_reference`` (joints moved on pre-filled references, or
    every joint on the image without pre-fill), ``review`` (:func:`bench_review`'s entries per
    ranking) and ``effort_to_target`` (frames touched to reach mean <= 3 mm with at most 1 % bad frames, per
    ranking). ``review``: ``rounds``, ``budget``, ``rankings`` (default evidence and uniform),
    ``prefill``, ``click_px``."""
    if prefilled is not None:
        clicks = int(sum(prefilled["clicks"].values()))
        run["clicks_per_reference"] = round(prefilled["clicks_per_reference"], 3)
        run["prefilled_references"] = len(prefilled["prefilled"])
    else:
        session = Session.open(folder)
        clicks = _clicks_on_references(session)
        session.close()
        run["clicks_per_reference"] = round(clicks / max(run["references"], 1), 3)
    run["reference_clicks"] = clicks
    rounds = int(review.get("rounds") or 0)
    if rounds <= 0:
        return
    out = bench_review(
        folder,
        rankings=list(review.get("rankings") or ("evidence", "uniform")),
        rounds=rounds,
        budget=float(review.get("budget", 0.02)),
        noise_px=noise_px,
        click_px=float(review.get("click_px", CLICK_PX)),
        reference_clicks=clicks,
        workers=workers,
        aligner=aligner,
        quiet=quiet,
    )
    run["review"] = out
    run["effort_to_target"] = {k: effort_to_target(v) for k, v in out.items()}


def plot_effort(doc: dict, path: Path) -> None:
    """The effort curve: mean error and share of bad frames against frames touched, one colour per
    (strategy, reference fraction), one line style per ranking (uniform dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4), dpi=120)
    styles = {"evidence": "-", "score": "-.", "uniform": "--"}
    for i, run in enumerate(doc["runs"]):
        for ranking, entries in (run.get("review") or {}).items():
            x = [100.0 * e["frames_touched"] / doc["frames"] for e in entries]
            label = f"{run['strategy']} {run['ref_fraction_target']:g} {ranking}"
            kw = {"color": f"C{i % 10}", "ls": styles.get(ranking, ":"), "marker": "o", "ms": 3}
            ax1.plot(x, [e["mean_mm"] for e in entries], label=label, **kw)
            ax2.plot(x, [100.0 * e["bad_share"] for e in entries], label=label, **kw)
    ax1.axhline(3.0, color="grey", lw=0.8, ls=":")
    ax2.axhline(1.0, color="grey", lw=0.8, ls=":")
    ax1.set_ylabel("mean 3D joint error (mm)")
    ax2.set_ylabel(f"frames with a joint > {BAD_MM:g} mm (%)")
    for ax in (ax1, ax2):
        ax.set_xlabel("frames touched: references + reviewed (% of sequence)")
        ax.grid(alpha=0.3)
    ax1.legend(fontsize=7)
    fig.suptitle(f"{Path(doc['dataset']).name}: error against annotation effort")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
