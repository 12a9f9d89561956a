"""The pipeline composes the stages on a session; the CLI and the app call these functions.

Each function reads what it needs from the session folder, runs one stage and stores its output
back in the session (``session.json`` for selection and bone lengths, ``results.npz`` for joints).
Stages never call each other behind the user's back except :func:`ensure_crops`, a cache.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .camera import CameraIntrinsics
from .datasets import BadFrameReport
from .session import (
    CROPS_FILE,
    CROPS_META_FILE,
    Batch,
    DatasetSpec,
    Session,
    SessionError,
    SetFrameAnnotation,
    atomic_save_npz,
)

Progress = Callable[[int, int], None] | None


def _log(message: str, quiet: bool = False) -> None:
    if not quiet:
        print(message, flush=True)


# ---------------------------------------------------------------------------------------------
# Sessions


def new_session(
    folder: str | Path,
    dataset_path: str | Path,
    *,
    format: str | None = None,
    intrinsics: CameraIntrinsics | None = None,
    depth_scale_mm: float | None = None,
    overwrite: bool = False,
) -> Session:
    """Create a session for a dataset (format auto-detected unless given)."""
    from .datasets import open_sequence

    dataset_path = Path(dataset_path).resolve()
    sequence = open_sequence(
        dataset_path, format=format, intrinsics=intrinsics, depth_scale_mm=depth_scale_mm
    )
    spec = DatasetSpec(
        path=str(dataset_path),
        format=sequence.format,
        intrinsics=intrinsics,
        depth_scale_mm=depth_scale_mm,
    )
    return Session.create(
        folder,
        spec,
        frames=len(sequence),
        camera=sequence.camera,
        skeleton=sequence.skeleton.name,
        sequence_breaks=list(sequence.sequence_breaks),
        overwrite=overwrite,
    )


def root_reference(parent: np.ndarray) -> np.ndarray:
    """For a parent forest ``(N,)`` (-1 at references) the reference at the root of each frame's tree."""
    parent = np.asarray(parent, dtype=np.int64)
    hop = np.where(parent < 0, np.arange(len(parent)), parent)
    # Pointer jumping: log2(depth) vectorized passes instead of walking every chain in Python.
    while True:
        nxt = hop[hop]
        if np.array_equal(nxt, hop):
            break
        hop = nxt
    if np.any(parent[hop] >= 0):
        raise ValueError("parent array is not a forest rooted at references (cycle found)")
    return hop


# ---------------------------------------------------------------------------------------------
# Crops (cache)


def ensure_crops(
    session: Session, *, quiet: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hand crops ``(N,S,S)`` (memory-mapped), centres ``(N,3)`` mm and boxes ``(N,4)``; cached in the session."""
    from .crops import compute_crops, crop_boxes, locate_hands

    s = session.model.settings
    crops_path = session.folder / CROPS_FILE
    meta_path = session.folder / CROPS_META_FILE
    if crops_path.exists() and meta_path.exists():
        with np.load(meta_path) as meta:
            ok = (
                int(meta["frames"]) == session.num_frames
                and float(meta["cube_mm"]) == s.cube_mm
                and int(meta["size"]) == s.crop_size
            )
            centres, boxes = meta["centres_mm"], meta["boxes"]
        if ok:
            return np.load(crops_path, mmap_mode="r"), centres, boxes
    sequence = session.open_sequence()
    report = BadFrameReport()
    t0 = time.perf_counter()
    centres = locate_hands(sequence, report=report, cube_mm=s.cube_mm, progress=not quiet)
    boxes = crop_boxes(centres, sequence.camera, cube_mm=s.cube_mm, size=s.crop_size)
    # Bad frames were already reported by locate_hands; compute_crops leaves them at background.
    compute_crops(
        sequence,
        centres,
        out_path=crops_path,
        cube_mm=s.cube_mm,
        size=s.crop_size,
        report=BadFrameReport(),
        progress=not quiet,
    )
    atomic_save_npz(
        meta_path,
        {
            "frames": np.asarray(session.num_frames),
            "cube_mm": np.asarray(s.cube_mm),
            "size": np.asarray(s.crop_size),
            "centres_mm": centres,
            "boxes": boxes,
        },
    )
    _log(f"crops: {session.num_frames} frames in {time.perf_counter() - t0:.1f} s", quiet)
    if report.errors:
        _log(report.summary(), quiet)
    return np.load(crops_path, mmap_mode="r"), centres, boxes


# ---------------------------------------------------------------------------------------------
# Stages


def select(
    session: Session,
    *,
    strategy: str = "forest",
    ref_fraction: float | None = None,
    rho: float | None = None,
    figures: bool = True,
    quiet: bool = False,
):
    """Select reference frames and the parent forest; store them in ``session.json``."""
    from .descriptors import compute_descriptors
    from .select import select_references

    crops, _, _ = ensure_crops(session, quiet=quiet)
    descriptors = compute_descriptors(crops, kind=session.model.settings.descriptor)
    selection = select_references(
        descriptors,
        strategy,
        ref_fraction=ref_fraction,
        rho=rho,
        sequence_breaks=session.model.sequence_breaks,
    )
    data = selection.to_dict()
    data["ref_fraction"] = ref_fraction
    session.set_selection(data)
    if figures:
        from .select import coverage_curve, plot_coverage, plot_embedding

        plot_embedding(descriptors, selection, session.folder / "selection_embedding.png")
        gt = session.open_sequence().ground_truth
        if gt is not None:
            thresholds, fraction = coverage_curve(gt.joints_mm, selection)
            plot_coverage(thresholds, fraction, session.folder / "selection_coverage.png")
    return selection


def annotate_from_gt(
    session: Session, *, noise_px: float = 0.0, seed: int = 0, quiet: bool = False
) -> int:
    """Simulated annotator (benchmarks only): fill every reference frame from ground truth.

    Uses ground truth for the 2D joints, visibility and depth order only, as a real annotator would
    give them. Returns the number of frames annotated. One journal entry (one undo step).
    """
    from .synth import simulate_annotations

    sequence = session.open_sequence()
    if sequence.ground_truth is None:
        raise SessionError(
            f"{session.model.dataset.path}: dataset has no ground truth to simulate an annotator"
        )
    refs = session.reference_frames
    if len(refs) == 0:
        raise SessionError(f"{session.folder}: no reference frames; run `handanno select` first")
    annotations = simulate_annotations(sequence, refs, noise_px=noise_px, seed=seed)
    batch = Batch(
        commands=[
            SetFrameAnnotation(frame=f, annotation=a.to_json()).model_dump()
            for f, a in annotations.items()
        ]
    )
    session.execute(batch, client="simulated-annotator")
    _log(
        f"annotated {len(annotations)} reference frames from ground truth (noise {noise_px:g} px)",
        quiet,
    )
    return len(annotations)


def lift(session: Session, *, workers: int = 1, quiet: bool = False) -> dict[int, np.ndarray]:
    """Lift every annotated reference to 3D; store ``lifted_mm`` and the (estimated) bone lengths."""
    from .lift import lift_references

    sequence = session.open_sequence()
    annotations = session.annotations(session.reference_frames)
    if not annotations:
        raise SessionError(f"{session.folder}: no annotated reference frames to lift")
    pinned = session.model.bones_pinned and session.model.bone_lengths_mm is not None
    result = lift_references(
        annotations,
        sequence.depth,
        sequence.camera,
        sequence.skeleton,
        bone_lengths_mm=np.asarray(session.model.bone_lengths_mm) if pinned else None,
        pin_bone_lengths=pinned,
        eps_mm=session.model.settings.eps_mm,
        angle_limits=session.model.settings.angle_limits,
        workers=workers,
    )
    results = session.load_results()
    lifted = np.full_like(results["lifted_mm"], np.nan)
    confidence = results["confidence"]
    for f, joints in result.joints_mm.items():
        lifted[f] = joints
        confidence[f] = result.confidence[f]
    session.save_results(lifted_mm=lifted, confidence=confidence)
    session.set_bone_lengths(result.bone_lengths_mm)
    _log(
        f"lifted {len(result.joints_mm)} reference frames; bone lengths (mm): "
        + " ".join(f"{b:.1f}" for b in result.bone_lengths_mm),
        quiet,
    )
    return result.joints_mm


def _reference_joints(session: Session, results: dict[str, np.ndarray]) -> dict[int, np.ndarray]:
    lifted = results["lifted_mm"]
    refs = [int(f) for f in session.reference_frames if np.all(np.isfinite(lifted[f]))]
    if not refs:
        raise SessionError(
            f"{session.folder}: no lifted reference frames; run `handanno lift` first"
        )
    return {f: lifted[f] for f in refs}


def propagate(
    session: Session,
    *,
    workers: int = 1,
    scheduler: str | None = None,
    aligner: str | None = None,
    frames: np.ndarray | None = None,
    progress: Progress = None,
    on_result: Callable | None = None,
    quiet: bool = False,
    use_model: bool = True,
):
    """Propagate lifted references to every frame along the selection's parent forest
    (``use_model``: fit the personalized hand model to every frame, see ``handmodel``)."""
    from .propagate import propagate as run_propagation

    sequence = session.open_sequence()
    crops, centres, boxes = ensure_crops(session, quiet=quiet)
    results = session.load_results()
    reference_joints = _reference_joints(session, results)
    if session.model.bone_lengths_mm is None:
        raise SessionError(f"{session.folder}: no bone lengths; run `handanno lift` first")
    result = run_propagation(
        session.parent,
        reference_joints,
        crops,
        boxes,
        centres,
        sequence.depth,
        sequence.camera,
        sequence.skeleton,
        np.asarray(session.model.bone_lengths_mm),
        aligner=aligner or session.model.settings.aligner,
        workers=workers,
        scheduler=scheduler,
        frames=frames,
        initial_mm=results["init_mm"] if frames is not None else None,
        initial_confidence=results["confidence"] if frames is not None else None,
        progress=progress,
        on_result=on_result,
        hand_model=use_model,
    )
    computed = np.all(np.isfinite(result.joints_mm), axis=(1, 2))
    with session.lock:
        # Merge into fresh arrays: an edit may have re-lifted a reference while this ran.
        current = session.load_results()
        init = np.where(computed[:, None, None], result.joints_mm, current["init_mm"])
        confidence = np.where(computed[:, None], result.confidence, current["confidence"])
        if frames is None:
            init[~computed] = np.nan
        # A reference's initialization is its lifted pose, so every frame has one for refinement.
        for f, joints in reference_joints.items():
            init[f] = joints
        session.save_results(init_mm=init, confidence=confidence)
    if result.skipped:
        _log(f"propagation skipped {len(result.skipped)} frame(s): {result.skipped[:10]}", quiet)
    return result


def refine(
    session: Session,
    *,
    progress: Callable | None = None,
    save: bool = True,
    quiet: bool = False,
    use_model: bool = True,
):
    """Global refinement of all frames (thesis Eq. 4); stores ``final_mm`` unless ``save=False``.

    References start from their current lifted pose (a reference made by a review correction has a
    fresh lift but an old propagated ``init_mm``), every other frame from its propagated pose.
    """
    from .refine import refine as run_refine

    crops, centres, boxes = ensure_crops(session, quiet=quiet)
    results = session.load_results()
    init = np.array(results["init_mm"], dtype=np.float64)
    refs = session.reference_frames
    lifted_refs = refs[np.all(np.isfinite(results["lifted_mm"][refs]), axis=(1, 2))]
    init[lifted_refs] = results["lifted_mm"][lifted_refs]
    if not np.isfinite(init).any():
        raise SessionError(
            f"{session.folder}: nothing propagated yet; run `handanno propagate` first"
        )
    result = run_refine(
        init,
        crops=crops,
        boxes=boxes,
        centres_mm=centres,
        depth_of=None,  # the observed depth is read from the crops
        camera=session.camera,
        skeleton=session.skeleton,
        bone_lengths_mm=np.asarray(session.model.bone_lengths_mm),
        reference_frames=refs,
        reference_annotations=session.annotations(refs),
        closest_reference=root_reference(session.parent),
        sequence_breaks=session.model.sequence_breaks,
        cube_mm=session.model.settings.cube_mm,
        progress=progress,
        hand_model=use_model,
    )
    if save:
        session.save_results(final_mm=result.joints_mm)
    return result


# ---------------------------------------------------------------------------------------------
# Demo


def ensure_demo_session(
    sessions_dir: str | Path, *, frames: int = 300, seed: int = 0, quiet: bool = False
) -> Path:
    """Create ``sessions_dir/demo`` from a synthetic sequence once (with a 5 % selection); return its folder."""
    from .synth import generate_sequence

    folder = Path(sessions_dir) / "demo"
    if (folder / "session.json").exists():
        try:
            Session.open(folder).close()
            return folder
        except SessionError as exc:
            raise SessionError(f"{exc}\n(delete {folder} to recreate the demo session)") from exc
    data = Path(sessions_dir) / "demo-data"
    if not (data / "joint.txt").exists():
        _log(f"generating a {frames}-frame synthetic sequence in {data} ...", quiet)
        generate_sequence(data, frames=frames, seed=seed, progress=not quiet)
    session = new_session(folder, data, format="msra", overwrite=True)
    select(session, strategy="forest", ref_fraction=0.05, figures=False, quiet=quiet)
    session.close()
    return folder
