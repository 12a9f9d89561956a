"""Pre-filled references: the best current estimate of a frame's joints, before anyone clicks.

When a reference frame is opened for annotation (in the app, or by the bench's simulated
annotator), its joints start from :func:`prefill_reference` so that the annotator only moves what
is wrong. The estimate, best first:

1. the frame's own results: refined (``final_mm``), else propagated (``init_mm``), else lifted
   (``lifted_mm``);
2. propagation (:func:`handanno_core.propagate.propagate`: flow between hand crops, depth read
   from each frame's own depth map, bone lengths restored) in one jump from the nearest frame in
   time, within the same sequence segment, that has joints (a lifted reference or a frame with
   results). With ``descriptors`` (the session's crop descriptors) also one jump from the frame
   that looks most alike; of the two the propagation with the higher mean confidence wins
   (walking through the frames in between, and other sources and choices, were tried and not
   adopted: README, "pre-filled references");
   With ``hand_model`` the propagation ends with the hand model personalized from the lifted
   references fitted to the frame's own depth (:func:`reference_hand_model`,
   :func:`session_hand_model`; the app and the bench's annotator use it once two references are
   lifted: on the suite's tune part with the interactive annotator it lowered the joints moved
   per reference from 12.0 to 11.0, README "Fourth round");
3. without hand crops on disk (the app never computes them on the UI thread): that neighbour's
   joints moved by the difference of the two hand centres (no translation without crop metadata).

``None`` when no frame of the session has joints yet. No ground truth is read here.
"""

from __future__ import annotations

import numpy as np

from .datasets.base import segment_ids
from .session import CROPS_FILE, CROPS_META_FILE, Session

__all__ = [
    "cached_crops",
    "known_joints",
    "prefill_reference",
    "prefill_uv",
    "frame_observation",
    "guess_model",
    "reference_hand_model",
    "session_hand_model",
]

#: result arrays a frame's own estimate is read from, best first
STAGES = ("final_mm", "init_mm", "lifted_mm")
#: lifted references needed before pre-fills are fitted with the hand model personalized from them
MODEL_MIN_REFERENCES = 2
#: :func:`session_hand_model` personalizes from at most this many lifted references, the nearest
#: in time to the frame (bounds its cost in long sessions; the bench's sequences have <= 18)
MODEL_MAX_REFERENCES = 32


def _finite_rows(x: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: rows of ``(N, J, 3)`` with every coordinate finite."""
    return np.all(np.isfinite(x), axis=(1, 2))


def known_joints(results: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(N, J, 3)`` mm best estimate per frame from ``results`` (:data:`STAGES` order) and
    ``(N,)`` bool: the frame has one."""
    joints = None
    for key in reversed(STAGES):  # worst first, so better stages overwrite
        arr = results.get(key)
        if arr is None:
            continue
        arr = np.asarray(arr, dtype=np.float64)
        if joints is None:
            joints = np.full_like(arr, np.nan)
        ok = _finite_rows(arr)
        joints[ok] = arr[ok]
    if joints is None:
        raise ValueError(f"results need one of {STAGES}")
    return joints, _finite_rows(joints)


def _nearest_known(frame: int, has: np.ndarray, segment: np.ndarray) -> int | None:
    """The frame nearest in time to ``frame`` with joints, same segment first (earlier on ties)."""
    cand = np.flatnonzero(has)
    cand = cand[cand != frame]
    if cand.size == 0:
        return None
    same = cand[segment[cand] == segment[frame]]
    if same.size:
        cand = same
    d = np.abs(cand - frame)
    return int(cand[np.lexsort((cand, d))[0]])


def _most_similar_known(frame: int, has: np.ndarray, descriptors: np.ndarray) -> int | None:
    """The frame with joints whose hand crop looks most like ``frame``'s (cosine distance of the
    L2-normalized ``descriptors`` (N, D) of :mod:`handanno_core.descriptors`)."""
    cand = np.flatnonzero(has)
    cand = cand[cand != frame]
    if cand.size == 0:
        return None
    d = 1.0 - np.asarray(descriptors[cand], dtype=np.float64) @ np.asarray(descriptors[frame])
    return int(cand[np.lexsort((np.abs(cand - frame), d))[0]])


def cached_crops(session: Session):
    """``(crops (N, S, S) memmap, centres (N, 3) mm, boxes (N, 4))`` from the session's crop cache
    (as :func:`handanno_core.pipeline.ensure_crops` wrote it), or None: never computed here."""
    folder = session.folder
    if not (folder / CROPS_FILE).exists() or not (folder / CROPS_META_FILE).exists():
        return None
    with np.load(folder / CROPS_META_FILE) as meta:
        if int(meta["frames"]) != session.num_frames:
            return None
        centres, boxes = np.asarray(meta["centres_mm"]), np.asarray(meta["boxes"])
    return np.load(folder / CROPS_FILE, mmap_mode="r"), centres, boxes


def _propagate_jump(
    session: Session, source: int, frame: int, joints: np.ndarray, crop_data, hand_model=False
):
    """Propagate ``source -> frame`` in one jump; ``((J, 3) mm, mean confidence)`` or None if it
    was skipped. ``hand_model``: a :class:`handanno_core.handmodel.HandModel` fitted to
    ``frame``'s own depth after the flow (see :func:`handanno_core.propagate.propagate`), or
    False."""
    from .propagate import propagate

    crops, centres, boxes = crop_data
    skeleton = session.skeleton
    bones = session.frame_bone_lengths()  # (B,), or (N, B): each frame its hand's
    bones = skeleton.bone_lengths(joints) if bones is None else bones
    parent = np.full(session.num_frames, -1, dtype=np.int64)
    parent[frame] = source
    sequence = session.open_sequence()
    result = propagate(
        parent,
        {source: joints},
        crops,
        boxes,
        centres,
        sequence.depth,
        session.camera,
        skeleton,
        bones,
        aligner=session.model.settings.aligner,
        frames=np.array([frame]),
        hand_model=hand_model,
    )
    out = result.joints_mm[frame]
    if not np.all(np.isfinite(out)):
        return None
    return out, float(np.nanmean(result.confidence[frame]))


def prefill_reference(
    session: Session,
    frame: int,
    results: dict[str, np.ndarray] | None,
    *,
    descriptors: np.ndarray | None = None,
    hand_model=False,
) -> np.ndarray | None:
    """``(J, 3)`` mm best current estimate of ``frame``'s joints (see the module docstring), or
    None when nothing in the session has joints. ``results`` are the session's result arrays
    (:meth:`Session.load_results`; read from the session when None); they are not modified.
    ``hand_model``: a personalized :class:`handanno_core.handmodel.HandModel`
    (:func:`reference_hand_model`) fitted to the frame's own depth after the flow: the guess
    snapped to the frame's surface and silhouette (False: flow only). ``descriptors`` (N, D):
    the session's crop descriptors (None: the nearest frame in time only).
    """
    frame = int(frame)
    n = session.num_frames
    if not 0 <= frame < n:
        raise ValueError(f"{session.folder}: frame {frame} is outside 0..{n - 1}")
    if results is None:
        results = session.load_results()
    joints, has = known_joints(results)
    if has[frame]:
        return joints[frame].copy()
    segment = segment_ids(n, session.model.sequence_breaks)
    source = _nearest_known(frame, has, segment)
    if source is None:
        return None
    crop_data = cached_crops(session)
    if crop_data is not None:
        tries = [source]
        if descriptors is not None:
            similar = _most_similar_known(frame, has, descriptors)
            if similar is not None and similar != source:
                tries.append(similar)
        found = [
            _propagate_jump(session, s, frame, joints[s], crop_data, hand_model) for s in tries
        ]
        found = [f for f in found if f is not None]
        if found:  # no ground truth: the most confident propagation
            return max(found, key=lambda f: f[1])[0].copy()
        centres = crop_data[1]
        shift = np.asarray(centres[frame] - centres[source], dtype=np.float64)
        if np.all(np.isfinite(shift)):
            return joints[source] + shift
    return joints[source].copy()


def reference_hand_model(session: Session, joints_mm: np.ndarray, frames, bone_lengths_mm):
    """The personalized hand model (:func:`handanno_core.handmodel.personalize`) of the lifted
    references ``frames`` with joints ``joints_mm`` (N, J, 3) mm (rows of those frames used) and
    ``bone_lengths_mm`` (B,), from the session's cached crops; None without crops or frames, or for
    a layout the model does not describe (``Skeleton.has_finger_segments``)."""
    from . import handmodel as hm

    crop_data = cached_crops(session)
    frames = np.asarray(list(frames), dtype=np.int64)
    if crop_data is None or frames.size == 0 or not session.skeleton.has_finger_segments:
        return None
    crops, centres, boxes = crop_data
    return hm.personalize_from_crops(
        session.skeleton,
        bone_lengths_mm,
        np.asarray(joints_mm)[frames],
        crops[frames],
        np.asarray(boxes)[frames],
        np.asarray(centres)[frames],
        session.camera,
        cube_mm=session.model.settings.cube_mm,
    )[0]


def session_hand_model(session: Session, frame: int, results: dict[str, np.ndarray]):
    """The hand model the app's pre-fill of ``frame`` is fitted with: personalized
    (:func:`reference_hand_model`) from the session's lifted references with the bones of
    ``frame``'s hand, as the bench's simulated annotator does with the references annotated so
    far (at most :data:`MODEL_MAX_REFERENCES`, the nearest in time). False (flow only) before
    "Lift all" (no bone lengths), with fewer than :data:`MODEL_MIN_REFERENCES` lifted
    references, or without the crop cache."""
    bones = session.bone_lengths_of(int(frame))
    lifted = np.asarray(results["lifted_mm"], dtype=np.float64)
    refs = [int(f) for f in session.reference_frames if np.all(np.isfinite(lifted[f]))]
    if bones is None or len(refs) < MODEL_MIN_REFERENCES:
        return False
    if len(refs) > MODEL_MAX_REFERENCES:
        near = np.argsort(np.abs(np.asarray(refs) - int(frame)), kind="stable")
        refs = sorted(refs[int(k)] for k in near[:MODEL_MAX_REFERENCES])
    return reference_hand_model(session, lifted, refs, np.asarray(bones, dtype=np.float64)) or False


def frame_observation(session: Session, frame: int):
    """``frame``'s :class:`handanno_core.handmodel.FrameObservations` (its hand points) from the
    session's crop cache; None without it."""
    from . import handmodel as hm

    crop_data = cached_crops(session)
    if crop_data is None:
        return None
    crops, centres, boxes = crop_data
    f = slice(int(frame), int(frame) + 1)
    return hm.observe(
        np.asarray(crops[f], dtype=np.float32),
        np.asarray(boxes[f], dtype=np.float64),
        np.asarray(centres[f], dtype=np.float64),
        session.camera,
        cube_mm=session.model.settings.cube_mm,
    )


def guess_model(session: Session, frame: int, results: dict[str, np.ndarray] | None = None):
    """``{"hand_model", "observation"}`` for :func:`handanno_core.guesses.refit_guesses` of
    ``frame`` (the refit then fits the unplaced joints to the frame's points): the model of
    :func:`session_hand_model` and :func:`frame_observation`; ``{}`` where either is missing."""
    if results is None:
        results = session.load_results()
    model = session_hand_model(session, frame, results)
    obs = frame_observation(session, frame) if model else None
    return {} if obs is None else {"hand_model": model, "observation": obs}


def prefill_uv(session: Session, joints_mm: np.ndarray) -> np.ndarray:
    """``(J, 2)`` px: the image positions of pre-filled joints ``(J, 3)`` mm (NaN behind the
    camera), where the annotate view draws them as guesses."""
    return session.camera.project(np.asarray(joints_mm, dtype=np.float64))
