"""The pipeline composes the stages on a session; the CLI and the app call these functions.

Each function reads what it needs from the session folder, runs one stage and stores its output
back in the session (``session.json`` for selection and bone lengths, ``results.npz`` for joints).
Stages never call each other behind the user's back except :func:`ensure_crops`, a cache.
"""

from __future__ import annotations

import time
import warnings
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .camera import CameraIntrinsics
from .datasets import BadFrameReport, FrameError
from .forest import roots as root_reference
from .results import NO_SOURCE
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
    breaks: str | None = None,
    one_hand: bool = False,
    hands: str | None = None,
) -> Session:
    """Create a session for a dataset (format auto-detected unless given).

    ``breaks`` (any format) replaces the reader's sequence breaks: comma-separated frame indices
    (``"120,300"``) or the path of a breaks file (one frame index or frame file name per line,
    see :func:`handanno_core.datasets.base.read_breaks_file`); ``""`` means none.
    The reader's hand labels (``sequence.hand_labels``: the subject folders of an MSRA layout)
    become the session's hands, each with its own bone lengths, unless ``one_hand`` or
    ``breaks`` (the labels belong to the reader's breaks) is given. ``hands`` (any format)
    gives the labels: comma-separated, one per sequence between breaks (``"anna,anna,ben"``),
    or the path of a file with one label per line.
    """
    from .datasets import open_sequence

    dataset_path = Path(dataset_path).resolve()
    sequence = open_sequence(
        dataset_path, format=format, intrinsics=intrinsics, depth_scale_mm=depth_scale_mm
    )
    if one_hand:
        labels = None
    elif hands is not None:
        labels = _hands_arg(hands)
    else:  # the reader's labels belong to the reader's breaks
        labels = sequence.hand_labels if breaks is None else None
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
        sequence_breaks=_breaks_arg(breaks, sequence)
        if breaks is not None
        else list(sequence.sequence_breaks),
        overwrite=overwrite,
        hands=labels,
    )


def _hands_arg(hands: str) -> list[str]:
    """Hand labels from ``--hands`` (see :func:`new_session`): a file's non-empty lines, else
    the comma-separated labels."""
    text = hands.strip()
    path = Path(text)
    if "," not in text and path.is_file():
        return [line.strip() for line in path.read_text().splitlines() if line.strip()]
    return [t.strip() for t in text.split(",")]


def _breaks_arg(breaks: str, sequence) -> list[int]:
    """Frame indices from ``--breaks`` (see :func:`new_session`); DatasetError if not frames."""
    from .datasets.base import DatasetError, read_breaks_file

    n = len(sequence)
    text = breaks.strip()
    if not text:
        return []
    if all(t.strip().isdigit() for t in text.split(",")):
        out = sorted({int(t) for t in text.split(",")})
        bad = [b for b in out if b >= n]
        if bad:
            raise DatasetError(f"--breaks {breaks}: frame {bad[0]} out of range (0..{n - 1})")
        return [b for b in out if b > 0]
    if not Path(text).is_file():
        raise DatasetError(
            f"--breaks {breaks}: neither comma-separated frame indices nor a breaks file"
        )
    return read_breaks_file(text, sequence.frame_names, n)


# ---------------------------------------------------------------------------------------------
# Crops (cache)

_FINGERPRINT_BLOCKS = 64
_FINGERPRINT_BLOCK_BYTES = 1 << 16


def crops_fingerprint(path: Path) -> int:
    """CRC-32 of a crop cache's size and 64 evenly spaced 64 KiB blocks (~4 MiB read, whatever
    the file size): catches a truncated, foreign or half-rewritten ``crops.npy`` cheaply."""
    size = path.stat().st_size
    crc = zlib.crc32(str(size).encode())
    with open(path, "rb") as f:
        for k in range(_FINGERPRINT_BLOCKS):
            f.seek(k * size // _FINGERPRINT_BLOCKS)
            crc = zlib.crc32(f.read(_FINGERPRINT_BLOCK_BYTES), crc)
    return crc


def _cached_crops(
    session: Session, crops_path: Path, meta_path: Path
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """The cached ``(crops, centres, boxes)``, or why the cache cannot be used (a one-line reason)."""
    s = session.model.settings
    n = session.num_frames
    if not crops_path.exists() or not meta_path.exists():
        missing = crops_path if not crops_path.exists() else meta_path
        return f"{missing}: missing"
    try:
        with np.load(meta_path, allow_pickle=False) as meta:
            if (
                int(meta["frames"]) != n
                or float(meta["cube_mm"]) != s.cube_mm
                or int(meta["size"]) != s.crop_size
            ):
                return f"{meta_path}: made for other settings (frames, cube or crop size)"
            centres, boxes = np.asarray(meta["centres_mm"]), np.asarray(meta["boxes"])
            stored = int(meta["crops_fingerprint"]) if "crops_fingerprint" in meta.files else None
        if centres.shape != (n, 3) or boxes.shape != (n, 4):
            return f"{meta_path}: centres/boxes of shapes {centres.shape}/{boxes.shape}, expected ({n}, 3)/({n}, 4)"
        if stored is not None and stored != crops_fingerprint(crops_path):
            return f"{crops_path}: checksum does not match {meta_path.name} (stale or damaged)"
        crops = np.load(crops_path, mmap_mode="r", allow_pickle=False)
    except Exception as exc:  # BadZipFile, EOFError, KeyError, ValueError (short file), OSError
        return f"{meta_path.parent}: unreadable crop cache ({type(exc).__name__}: {exc})"
    expected = (n, s.crop_size, s.crop_size)
    if crops.shape != expected:
        return f"{crops_path}: shape {crops.shape}, expected {expected}"
    return crops, centres, boxes


def _save_crops_meta(session: Session, camera, spec, centres, box_cubes, geometry) -> None:
    """The crop cache's metadata (``CROPS_META_FILE``, written atomically): centres ``(N, 3)`` mm,
    image boxes of ``box_cubes`` ``(N,)`` mm, the hand geometry ``(N, GEOMETRY_LEN)`` and the
    checksum of the crop file as it is now."""
    from .crops import crop_boxes

    atomic_save_npz(
        session.folder / CROPS_META_FILE,
        {
            "frames": np.asarray(session.num_frames),
            "cube_mm": np.asarray(spec.cube_mm),
            "size": np.asarray(spec.size),
            "centres_mm": centres,
            "boxes": crop_boxes(centres, camera, cube_mm=box_cubes, size=spec.size),
            "box_cubes_mm": box_cubes,
            "geometry": geometry,
            "crops_fingerprint": np.asarray(crops_fingerprint(session.folder / CROPS_FILE)),
        },
    )


def ensure_crops(
    session: Session, *, quiet: bool = False, workers: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hand crops ``(N,S,S)`` (memory-mapped), centres ``(N,3)`` mm and boxes ``(N,4)``; cached in the session.

    Built with ``workers`` processes: locating the hand in runs of whole sequences (the hint
    chain restarts at every break, so a single sequence is located in one process), cutting the
    crops in ranges of frames, each process writing its part of the file; the cache is the same,
    bit for bit, as one process builds."""
    from .crops import CropSpec, compute_crops, crop_boxes, place_crops
    from .localize import locate_hand_geometry

    s = session.model.settings
    crops_path = session.folder / CROPS_FILE
    meta_path = session.folder / CROPS_META_FILE
    if crops_path.exists() or meta_path.exists():
        cached = _cached_crops(session, crops_path, meta_path)
        if isinstance(cached, tuple):
            return cached
        _log(f"{cached}; rebuilding the crop cache", quiet)
    sequence = session.open_sequence()
    report = BadFrameReport()
    t0 = time.perf_counter()
    # The hand may not fit the session's cube: place_crops grows it (all stages use it). The
    # geometry is kept: a lift whose references fall outside their crops places them again.
    spec = CropSpec.of(s)
    geometry = locate_hand_geometry(sequence, report=report, progress=not quiet, workers=workers)
    centres, grown, box_cubes = place_crops(geometry, spec, sequence.sequence_breaks)
    if grown != spec:
        with session.lock:
            s.cube_mm = grown.cube_mm
            session.save()
        _log(f"crops: hand larger than the cube, cube grown to {s.cube_mm:g} mm", quiet)
    # a frame whose hand does not fit the session's cube has a larger image box (box_cubes):
    # the boxes carry it to every stage, depth stays at the session's cube
    boxes = crop_boxes(centres, sequence.camera, cube_mm=box_cubes, size=grown.size)
    own = box_cubes > grown.cube_mm
    if own.any():
        _log(
            f"crops: {int(own.sum())} frames with their own larger box "
            f"(up to {box_cubes.max():g} mm; depth at the session's {grown.cube_mm:g} mm)",
            quiet,
        )
    # Bad frames were already reported by locate_hands; compute_crops leaves them at background.
    compute_crops(
        sequence,
        centres,
        out_path=crops_path,
        cube_mm=grown.cube_mm,
        size=grown.size,
        report=BadFrameReport(),
        progress=not quiet,
        workers=workers,
        box_cubes_mm=box_cubes,
    )
    _save_crops_meta(session, sequence.camera, grown, centres, box_cubes, geometry)
    _log(f"crops: {session.num_frames} frames in {time.perf_counter() - t0:.1f} s", quiet)
    if report.errors:
        _log(report.summary(), quiet)
    return np.load(crops_path, mmap_mode="r"), centres, boxes


# ---------------------------------------------------------------------------------------------
# Stages


def select(
    session: Session,
    *,
    strategy: str | None = None,
    ref_fraction: float | None = None,
    rho: float | None = None,
    figures: bool = True,
    quiet: bool = False,
    workers: int = 1,
):
    """Select reference frames and the parent forest; store them in ``session.json``
    (``strategy`` None: :data:`handanno_core.select.DEFAULT_STRATEGY`; ``workers``: processes
    building the crop cache when it is not built yet)."""
    from .descriptors import compute_descriptors
    from .select import DEFAULT_STRATEGY, select_references

    crops, _, _ = ensure_crops(session, quiet=quiet, workers=workers)
    usable, reasons = usable_frames(session, crops)
    if not usable.any():
        raise SessionError(
            f"{session.model.dataset.path}: none of the {session.num_frames} frames is usable as "
            f"a reference (first: {reasons[min(reasons)]})"
        )
    if reasons:
        listed = "; ".join(f"frame {f}: {r}" for f, r in list(reasons.items())[:10])
        more = f"; and {len(reasons) - 10} more" if len(reasons) > 10 else ""
        _log(f"selection skips {len(reasons)} unusable frame(s): {listed}{more}", quiet)
    index = np.flatnonzero(usable)
    descriptors = compute_descriptors(crops, kind=session.model.settings.descriptor)
    breaks = np.searchsorted(index, np.asarray(session.model.sequence_breaks, dtype=np.int64))
    sub = select_references(
        descriptors[index],
        strategy or DEFAULT_STRATEGY,
        ref_fraction=None
        if ref_fraction is None
        else min(1.0, ref_fraction * len(usable) / len(index)),
        rho=rho,
        sequence_breaks=sorted({int(b) for b in breaks if 0 < b < len(index)}),
    )
    selection = _expand_selection(sub, index, session.num_frames, session.model.sequence_breaks)
    data = selection.to_dict()
    data["ref_fraction"] = ref_fraction
    data["skipped_frames"] = sorted(reasons)
    session.set_selection(data)
    if figures and len(index) >= 3:  # (the embedding plot needs a few frames)
        from .select import coverage_curve, plot_coverage, plot_embedding

        plot_embedding(descriptors, selection, session.folder / "selection_embedding.png")
        gt = session.open_sequence().ground_truth
        if gt is not None:
            thresholds, fraction = coverage_curve(gt.joints_mm, selection)
            plot_coverage(thresholds, fraction, session.folder / "selection_coverage.png")
    return selection


def usable_frames(session: Session, crops: np.ndarray) -> tuple[np.ndarray, dict[int, str]]:
    """Frames that may become references: ``(N,)`` bool and a reason for each one that may not.

    A frame is unusable when its crop holds no hand pixel: its depth was unreadable, non-finite or
    all zero (the crop stage leaves such frames at background) or nothing was in the hand's cube.
    Reads the crops in chunks (``crops`` may be a memory map of any length).
    """
    from .crops import CropSpec

    n = len(crops)
    usable = np.zeros(n, dtype=bool)
    for a in range(0, n, 4096):
        usable[a : a + 4096] = np.any(~CropSpec.is_background(crops[a : a + 4096]), axis=(1, 2))
    reasons: dict[int, str] = {}
    bad = np.flatnonzero(~usable)
    sequence = session.open_sequence() if len(bad) else None
    names = sequence.frame_names if sequence is not None else None
    for f in bad[:50]:  # name the first ones precisely; the rest share the generic reason
        where = f"{sequence.path / names[f] if names else sequence.path} (frame {f})"
        try:
            depth = sequence.depth(int(f))
            reasons[int(f)] = f"{where}: " + (
                "no depth at all" if not np.any(depth > 0) else "no hand pixels"
            )
        except (FrameError, ValueError, OSError) as exc:
            reasons[int(f)] = str(exc)
    for f in bad[50:]:
        reasons[int(f)] = "no hand pixels or unreadable"
    return usable, reasons


def _expand_selection(sub, index: np.ndarray, n: int, sequence_breaks: list[int]):
    """Map a selection made on the usable frames ``index`` back to all ``n`` frames.

    An unusable frame is never a reference; its parent is the nearest usable frame of its
    segment (else the nearest usable frame at all), so it is still propagated.
    """
    from .select import Selection

    refs = index[np.asarray(sub.reference_frames, dtype=np.int64)]
    parent = np.full(n, -1, dtype=np.int64)
    sub_parent = np.asarray(sub.parent, dtype=np.int64)
    parent[index] = np.where(sub_parent >= 0, index[np.maximum(sub_parent, 0)], -1)
    others = np.setdiff1d(np.arange(n), index)
    if len(others):
        segment = np.searchsorted(
            np.asarray(sorted(sequence_breaks), dtype=np.int64), np.arange(n), side="right"
        )
        for f in others:
            same = index[segment[index] == segment[f]]
            pool = same if len(same) else index
            parent[f] = pool[np.argmin(np.abs(pool - f))]
    return Selection(
        strategy=sub.strategy,
        reference_frames=refs,
        parent=parent,
        threshold=sub.threshold,
    )


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


def lift(
    session: Session,
    *,
    workers: int = 1,
    scheduler: str | None = None,
    quiet: bool = False,
    progress: Progress = None,
    refit: bool | None = None,
    click_noise_px: float | None = None,
) -> dict[int, np.ndarray]:
    """Lift every annotated reference to 3D; store ``lifted_mm`` and the (estimated) bone lengths.

    ``refit`` (default: the session's ``lift_refit``) refits the lifted references with the
    personalized hand model (:mod:`handanno_core.lift.model_refit`), trusting the clicks by
    ``click_noise_px`` (default: the session's ``click_noise_px``, else estimated). Where that noise
    is at least the session's ``lift_denoise_min_px``, the bone lengths are estimated again from
    the clicks moved towards the refit, and the references lifted and refitted with them.

    With several hands (``session.model.hands``) the references of each hand are lifted together
    and give that hand's bone lengths; a hand without an annotated reference gets the mean of
    the others' (logged), and ``bone_lengths_mm`` is that mean. Pinned bones pin every hand.

    ``workers`` local processes or ``scheduler`` (``"tcp://HOST:PORT"``, a Dask cluster) lift the
    references in parallel. ``progress(done, total)`` is called after every frame of every
    bone-estimation round."""

    sequence = session.open_sequence()
    annotations = {  # a reference whose every joint was undone or cleared has nothing to lift
        f: a for f, a in session.annotations(session.reference_frames).items() if a.annotated.any()
    }
    if not annotations:
        raise SessionError(f"{session.folder}: no annotated reference frames to lift")
    pinned = _bones_pinned(session)
    hand = session.hand_of_frame()
    names = session.hand_names
    groups = {h: {f: a for f, a in annotations.items() if hand[f] == h} for h in range(len(names))}
    joints_mm: dict[int, np.ndarray] = {}
    confidence_of: dict[int, np.ndarray] = {}
    bones: dict[str, np.ndarray] = {}
    done = 0
    for h, group in groups.items():
        if not group:
            continue
        report = None
        if progress is not None:
            left = sum(len(g) for k, g in groups.items() if k > h)
            size = len(group)

            def report(d, t, _off=done, _n=size, _left=left):
                progress(_off + d, _off + t + round(_left * t / max(_n, 1)))

        result = _lift_group(
            session, sequence, group, workers, scheduler,
            bone_lengths_mm=np.asarray(session.model.bone_lengths_mm) if pinned else None,
            pin_bone_lengths=pinned, progress=report,
        )  # fmt: skip
        done += len(group)
        joints_mm.update(result.joints_mm)
        confidence_of.update(result.confidence)
        bones[names[h]] = np.asarray(result.bone_lengths_mm, dtype=np.float64)
    refit = session.model.settings.lift_refit if refit is None else refit
    noises: list[float] = []  # the click noise each refit used (none without a refit)
    if refit and not session.skeleton.has_finger_segments:
        _log(f"lift: no hand-model refit for the {session.skeleton.name} layout", quiet)
    elif refit:
        # one refit per distinct set of bones, as propagation personalizes one model per set
        sets: dict[bytes, list[int]] = {}
        for f in sorted(joints_mm):
            sets.setdefault(bones[names[hand[f]]].tobytes(), []).append(f)
        crop_data = ensure_crops(session, quiet=quiet, workers=workers)
        for frames in sets.values():
            first = _refit_with_model(
                session, crop_data, frames, annotations, joints_mm, bones[names[hand[frames[0]]]],
                quiet, click_noise_px,
            )  # fmt: skip
            noises.append(first.noise_px)
            _bones_from_denoised_clicks(
                session, sequence, crop_data, frames, annotations, joints_mm, bones, first,
                click_noise_px, workers, scheduler, quiet,
            )  # fmt: skip
    given = click_noise_px is not None or session.model.settings.click_noise_px is not None
    session.set_click_noise(max(noises) if noises else None, given=given)
    results = session.load_results()
    lifted = np.full_like(results["lifted_mm"], np.nan)
    confidence = results["confidence"]
    for f, joints in joints_mm.items():
        lifted[f] = joints
        confidence[f] = confidence_of[f]
    session.save_results(lifted_mm=lifted, confidence=confidence)
    if len(names) == 1:
        session.set_bone_lengths(bones[names[0]])
        summary = bones[names[0]]
    else:
        summary = np.mean(np.stack(list(bones.values())), axis=0)
        for name in names:
            if name not in bones:  # no annotated reference of this hand yet
                _log(f"hand {name}: no annotated reference; it uses the other hands' mean", quiet)
                bones[name] = summary
        session.set_bone_lengths(summary, hands={name: bones[name] for name in names})
    for h, name in enumerate(names):
        _log(
            f"lifted {sum(1 for f in joints_mm if hand[f] == h)} reference "
            f"frames{f' of hand {name}' if name else ''}; bone lengths (mm): "
            + " ".join(f"{b:.1f}" for b in bones[name]),
            quiet,
        )
    return joints_mm


def recrop_from_references(
    session: Session, joints_mm: dict[int, np.ndarray], *, quiet: bool = False, workers: int = 1
) -> np.ndarray:
    """Place the crops again where lifted references ``joints_mm`` (frame -> ``(J, 3)`` mm) fall
    outside their own crop: the localization took the wrong end of an elongated arm region for
    the hand, and its hint chain carried the mistake (README, crops "Eighth round").

    Each such reference becomes an anchor of :func:`handanno_core.localize.anchored_geometry`
    (:func:`handanno_core.crops.crops_from_references`): the hint chain restarts at its joints and
    runs to the neighbouring references, the annotated hand outvoting the shape cues. Only the
    frames whose crop changed are cut again; the cache stays consistent (rewritten through a
    copy, then its metadata).
    Returns the frames whose crop changed (sorted; empty when every reference holds its joints).
    """
    from .crops import CropSpec, crops_from_references, update_crops
    from .localize import locate_hand_geometry

    _, centres, _ = ensure_crops(session, quiet=quiet, workers=workers)
    meta_path = session.folder / CROPS_META_FILE
    n = session.num_frames
    with np.load(meta_path, allow_pickle=False) as meta:
        box_cubes = np.asarray(meta["box_cubes_mm"]) if "box_cubes_mm" in meta.files else None
        geometry = np.asarray(meta["geometry"]) if "geometry" in meta.files else None
    spec = CropSpec.of(session.model.settings)
    if box_cubes is None:
        box_cubes = np.full(n, float(spec.cube_mm))
    sequence = session.open_sequence()
    if geometry is not None and geometry.shape[0] != n:
        geometry = None
    if geometry is None and workers > 1:  # a cache of an older version: located in parallel
        geometry = locate_hand_geometry(sequence, report=BadFrameReport(), workers=workers)
    missed, anchored, new_centres, new_box = crops_from_references(
        sequence, geometry, spec, centres, box_cubes, joints_mm
    )
    if missed.size == 0:
        return missed
    same = np.all(np.isclose(new_centres, centres, atol=1e-6) | ~np.isfinite(new_centres), axis=1)
    changed = np.flatnonzero(~same | (new_box != box_cubes))
    if changed.size == 0:
        return changed
    update_crops(
        sequence, session.folder / CROPS_FILE, changed, new_centres, spec.cube_mm, spec.size,
        new_box,
    )  # fmt: skip
    _save_crops_meta(session, sequence.camera, spec, new_centres, new_box, anchored)
    _log(
        f"crops: {missed.size} lifted reference(s) outside their crop ({missed[:10].tolist()}); "
        f"{changed.size} frames' crops placed again from the references",
        quiet,
    )
    return changed


def _bones_pinned(session: Session) -> bool:
    """The session's bone lengths are pinned (given, never re-estimated by a lift)."""
    return session.model.bones_pinned and session.model.bone_lengths_mm is not None


def _lift_group(
    session: Session, sequence, annotations: dict, workers: int, scheduler: str | None, **kw
):
    """:func:`handanno_core.lift.lift_references` of ``annotations`` (frame ->
    :class:`FrameAnnotation`) on ``sequence`` with the session's lift settings; ``kw`` adds the
    call's own (pinned bones, progress, shrinkage)."""
    from .lift import lift_references

    s = session.model.settings
    return lift_references(
        annotations, sequence.depth, sequence.camera, sequence.skeleton,
        eps_mm=s.eps_mm, angle_limits=s.angle_limits, workers=workers, scheduler=scheduler, **kw,
    )  # fmt: skip


def _bones_from_denoised_clicks(
    session: Session, sequence, crop_data: tuple, frames: list[int], annotations: dict,
    joints_mm: dict[int, np.ndarray], bones: dict[str, np.ndarray], first,
    click_noise_px: float | None, workers: int, scheduler: str | None, quiet: bool,
) -> None:  # fmt: skip
    """A second estimate of each hand's bone lengths for noisy clicks, kept where the hand model
    explains the references' depth better with it.

    ``first`` is the refit (:class:`handanno_core.lift.model_refit.RefitResult`) of the
    references ``frames`` lifted with one estimate from the clicks as they are. Where its click
    noise reaches the session's ``lift_denoise_min_px`` (and the bones are not pinned), each
    hand's references are lifted again with the bone medians shrunk towards the template by their
    uncertainty (:func:`handanno_core.lift.references.shrink_to_template`) and refitted; the bones
    are then estimated once more from the clicks moved towards that refit
    (:func:`handanno_core.lift.model_refit.denoised_clicks`: noisy clicks spread and lengthen the
    bones measured from them; the refit explains a reference's whole depth, a click only its
    pixel), and the references lifted and refitted with them. The candidate replaces the first
    estimate in ``bones`` and ``joints_mm`` only if its refit's mean depth energy (data + free
    space) over the references is lower: the hand model's own misfit also shows as click noise
    (on a hand unlike the model's, exact clicks are estimated at 0.7-1.5 px)."""
    from .lift.model_refit import denoised_clicks

    least = session.model.settings.lift_denoise_min_px
    noise = first.noise_px
    if _bones_pinned(session) or least is None or noise <= 0.0 or noise < least:
        return
    row = {f: i for i, f in enumerate(frames)}
    hand = session.hand_of_frame()
    names = session.hand_names
    for h in sorted({hand[f] for f in frames}):
        own = [f for f in frames if hand[f] == h]
        with warnings.catch_warnings():
            # the first pass already warned about stretched references; the candidate's
            # confidences are not used
            warnings.simplefilter("ignore", UserWarning)
            shrunk = _lift_group(
                session, sequence, {f: annotations[f] for f in own}, workers, scheduler,
                shrink_bones=True,
            )  # fmt: skip
            joints = dict(shrunk.joints_mm)
            probe = _refit_with_model(
                session, crop_data, own, annotations, joints, shrunk.bone_lengths_mm, True,
                click_noise_px,
            )  # fmt: skip
            denoised = denoised_clicks(
                {f: annotations[f] for f in own}, joints, session.camera, probe.noise_px
            )
            again = _lift_group(session, sequence, denoised, workers, scheduler, shrink_bones=True)
        joints.update(again.joints_mm)
        final = _refit_with_model(
            session, crop_data, own, annotations, joints, again.bone_lengths_mm, True,
            probe.noise_px,
        )  # fmt: skip
        before = first.depth_energy[[row[f] for f in own]]
        after = final.depth_energy
        both = np.isfinite(before) & np.isfinite(after)
        e0, e1 = (float(np.mean(e[both])) if both.any() else np.nan for e in (before, after))
        better = bool(e1 < e0)
        _log(
            f"lift: click noise {noise:.2f} px >= {least:g} px: bones estimated again from "
            f"denoised clicks; the model's depth energy {e0:.3g} -> {e1:.3g}: "
            + ("kept" if better else "not kept"),
            quiet,
        )
        if better:
            bones[names[h]] = np.asarray(again.bone_lengths_mm, dtype=np.float64)
            joints_mm.update(joints)


def _refit_with_model(
    session: Session, crop_data: tuple, frames: list[int], annotations: dict,
    joints_mm: dict[int, np.ndarray], bone_lengths_mm: np.ndarray, quiet: bool,
    click_noise_px: float | None,
):  # fmt: skip
    """Replace ``joints_mm[f]`` of the lifted references ``frames`` (one set of bones) by their
    refit with the personalized hand model (:mod:`handanno_core.lift.model_refit`);
    ``crop_data`` = :func:`ensure_crops`' ``(crops, centres, boxes)``. Returns the
    :class:`handanno_core.lift.model_refit.RefitResult`."""
    from .lift.model_refit import refit_references

    index = np.asarray(frames, dtype=np.int64)
    crops, centres, boxes = crop_data
    s = session.model.settings
    noise = s.click_noise_px if click_noise_px is None else click_noise_px
    refit = refit_references(
        np.stack([joints_mm[f] for f in frames]),
        [annotations[f] for f in frames],
        crops[index],
        boxes[index],
        centres[index],
        session.camera,
        session.skeleton,
        bone_lengths_mm,
        cube_mm=s.cube_mm,
        noise_px=noise,
    )
    for i, f in enumerate(frames):
        joints_mm[f] = refit.joints_mm[i]
    source = "given" if noise is not None else "estimated"
    _log(
        f"lift: {int(np.sum(~refit.kept))} of {len(frames)} references refitted with the hand "
        f"model (click noise {refit.noise_px:.2f} px, {source})",
        quiet,
    )
    return refit


def _hand_model_on(session: Session, use_model: bool | None, stage: str, quiet: bool) -> bool:
    """Whether ``stage`` fits the hand model: ``use_model``, else the session's setting; never on
    a layout whose fingers are not three bones long (``Skeleton.has_finger_segments``: on the NYU
    fixture the model made the final error 2.0 -> 18.4 mm)."""
    on = session.model.settings.hand_model if use_model is None else use_model
    if on and not session.skeleton.has_finger_segments:
        _log(f"{stage}: no hand model for the {session.skeleton.name} layout", quiet)
        return False
    return bool(on)


def _reference_joints(session: Session, results: dict[str, np.ndarray]) -> dict[int, np.ndarray]:
    lifted = results["lifted_mm"]
    refs = [int(f) for f in session.reference_frames if np.all(np.isfinite(lifted[f]))]
    if not refs:
        raise SessionError(
            f"{session.folder}: no lifted reference frames; run `handanno lift` first"
        )
    return {f: lifted[f] for f in refs}


def propagation_forests(session: Session, use_model: bool | None = None) -> np.ndarray:
    """The parent forests ``(P, N)`` a session's frames are propagated along: its selection's
    (first) and, with the hand model on and ``PropagationSettings.both_ways``, the two temporal
    chains between its references (:func:`handanno_core.select.temporal_chains`); propagation
    keeps per frame the candidate whose fit explains the frame's depth best."""
    from .propagate import PropagationSettings
    from .select import temporal_chains

    parent = session.parent
    model_on = _hand_model_on(session, use_model, "propagate", quiet=True)
    if not (model_on and PropagationSettings.from_session(session.model.settings).both_ways):
        return parent[None]
    refs = np.flatnonzero(parent == -1)
    chains = temporal_chains(len(parent), refs, session.model.sequence_breaks)
    return np.concatenate([parent[None], chains])


def frames_to_repropagate(session: Session, changed, use_model: bool | None = None) -> np.ndarray:
    """Sorted frames whose propagation depends on ``changed`` frames (a corrected or re-lifted
    reference): their descendants in every forest of :func:`propagation_forests`."""
    from .forest import descendants

    forests = propagation_forests(session, use_model)
    return np.unique(np.concatenate([descendants(p, changed) for p in forests]))


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
    use_model: bool | None = None,
):
    """Propagate lifted references to every frame along the selection's parent forest
    (``use_model``: fit the personalized hand model to every frame, see ``handmodel``; None: the
    session's ``settings.hand_model``). Crops that miss a lifted reference's joints are placed
    again first (:func:`recrop_from_references`)."""
    from .propagate import PropagationSettings
    from .propagate import propagate as run_propagation

    sequence = session.open_sequence()
    results = session.load_results()
    reference_joints = _reference_joints(session, results)
    recrop_from_references(session, reference_joints, quiet=quiet, workers=workers)
    crops, centres, boxes = ensure_crops(session, quiet=quiet, workers=workers)
    if session.model.bone_lengths_mm is None:
        raise SessionError(f"{session.folder}: no bone lengths; run `handanno lift` first")
    settings = PropagationSettings.from_session(session.model.settings)
    model_on = _hand_model_on(session, use_model, "propagate", quiet)
    result = run_propagation(
        propagation_forests(session, model_on),
        reference_joints,
        crops,
        boxes,
        centres,
        sequence.depth,
        sequence.camera,
        sequence.skeleton,
        session.frame_bone_lengths(),
        aligner=aligner or session.model.settings.aligner,
        workers=workers,
        scheduler=scheduler,
        frames=frames,
        initial_mm=results["init_mm"] if frames is not None else None,
        initial_confidence=results["confidence"] if frames is not None else None,
        progress=progress,
        on_result=on_result,
        settings=settings,
        hand_model=model_on,
    )
    computed = np.all(np.isfinite(result.joints_mm), axis=(1, 2))
    with session.lock:
        # Merge into fresh arrays: an edit may have re-lifted a reference while this ran.
        current = session.load_results()
        if frames is not None:
            computed &= ~_previous_fits_better(result.model_fit, current)
        init = np.where(computed[:, None, None], result.joints_mm, current["init_mm"])
        confidence = np.where(computed[:, None], result.confidence, current["confidence"])
        model_fit = np.where(computed[:, None], result.model_fit, current["model_fit"])
        # the frame each result kept came from; frames not recomputed keep theirs (with their
        # joints), references have none
        source = np.where(computed, result.source, current["source"])
        if frames is None:
            init[~computed] = np.nan
            model_fit[~computed] = np.nan
            source[~computed] = NO_SOURCE
        source[session.parent < 0] = NO_SOURCE
        # A reference's initialization is its lifted pose, so every frame has one for refinement.
        for f, joints in reference_joints.items():
            init[f] = joints
        session.save_results(
            init_mm=init, confidence=confidence, model_fit=model_fit, source=source
        )
    if result.skipped:
        _log(f"propagation skipped {len(result.skipped)} frame(s): {result.skipped[:10]}", quiet)
    return result


def _previous_fits_better(model_fit: np.ndarray, current: dict) -> np.ndarray:
    """``(N,)`` bool: frames whose previous propagated pose (``current`` results) explains the
    frame's own depth better than the new one: a lower hand-model fit level (``model_fit``
    ``(N, T)``, column 0), the evidence that chooses among candidate forests. A re-propagation
    keeps those: a review correction re-roots its neighbours on itself, and a correction's few
    clicks are a weaker start than the references they were carried from (HISTORY.md, stop 39).
    False everywhere without the hand model (no levels)."""
    old, new = current["model_fit"][:, 0], model_fit[:, 0]
    had = np.all(np.isfinite(current["init_mm"]), axis=(1, 2))
    with np.errstate(invalid="ignore"):
        return had & np.isfinite(old) & np.isfinite(new) & (old < new)


#: checkpoints of a refinement in pieces (deleted once its result is saved)
REFINE_PIECES_DIR = "refine-pieces"


#: sessions up to this many frames are refined as one system by default (its peak memory is about
#: 0.28 MB per frame, 1.4 GB at 5,000 frames, measured; README "A whole dataset"), longer ones in
#: pieces of ``pieces.DEFAULT_WINDOW`` frames (memory bounded by the window). Results of sessions
#: up to this size are what they were before pieces existed.
WHOLE_SOLVE_MAX_FRAMES = 5000


def refine(
    session: Session,
    *,
    progress: Callable | None = None,
    save: bool = True,
    quiet: bool = False,
    use_model: bool | None = None,
    window: int | None = None,
    overlap: int | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    resume: bool = True,
    whole: bool = False,
    threads: int = 1,
    frames: np.ndarray | None = None,
):
    """Global refinement of all frames (thesis Eq. 4); stores ``final_mm`` unless ``save=False``.

    ``frames`` (K,) int: refine only these; every other frame that has a refined result keeps
    it, held fixed in the system (its neighbours' temporal terms still see it). A review round
    passes the frames its corrections propagated again: the frames it did not touch do not move.

    References start from their current lifted pose (a reference made by a review correction has a
    fresh lift but an old propagated ``init_mm``), every other frame from its propagated pose.
    Sessions of up to :data:`WHOLE_SOLVE_MAX_FRAMES` frames are solved as one system (``whole``:
    whatever the size); longer ones, and any run with ``window`` (frames), ``workers > 1`` or
    ``scheduler``, in pieces (:mod:`handanno_core.pieces`: each sequence between breaks, long
    ones in overlapping windows of ``window`` (default ``pieces.DEFAULT_WINDOW``) frames, pieces
    in parallel; returns a ``PiecesResult``), checkpointed per piece in the session's
    ``refine-pieces/`` folder so that a killed run resumes (``resume=False`` ignores them).
    ``use_model``: the hand-model checks of :func:`handanno_core.refine.refine` (None: the
    session's ``settings.hand_model``). ``threads``: threads of a whole solve (same result).
    """
    use_model = _hand_model_on(session, use_model, "refine", quiet)
    if whole and (window is not None or workers > 1 or scheduler is not None):
        raise ValueError(
            "a whole solve is one system in one process: no window, workers or scheduler"
        )
    pieces = window is not None or workers > 1 or scheduler is not None
    if not pieces and not whole and session.num_frames > WHOLE_SOLVE_MAX_FRAMES:
        _log(
            f"refine: {session.num_frames} frames (more than {WHOLE_SOLVE_MAX_FRAMES}): in pieces "
            "(--whole for one system)",
            quiet,
        )
        pieces = True
    if pieces:
        return _refine_pieces(
            session, quiet=quiet, save=save, use_model=use_model, window=window,
            overlap=overlap, workers=workers, scheduler=scheduler, resume=resume, frames=frames,
        )  # fmt: skip
    from .refine import refine as run_refine

    init, problem = refine_inputs(session, quiet)
    result = run_refine(
        init, progress=progress, hand_model=use_model, threads=threads,
        fixed_frames=_keep_refined(session, init, frames), **problem,
    )  # fmt: skip
    _log_recovered(result.info.get("recovered", []), quiet)
    if save:
        session.save_results(final_mm=result.joints_mm)
    return result


def _log_recovered(frames, quiet: bool) -> None:
    """Say which frames refinement fitted again because the hand model could not explain them."""
    if len(frames):
        shown = ", ".join(str(int(f)) for f in list(frames)[:10])
        more = f" and {len(frames) - 10} more" if len(frames) > 10 else ""
        _log(
            f"refine: {len(frames)} frames the hand model could not explain were fitted again "
            f"and replaced (frames {shown}{more})",
            quiet,
        )


def _keep_refined(session: Session, init: np.ndarray, frames) -> np.ndarray | None:
    """The frames outside ``frames`` (None: none) with a refined result, which keep it: their
    ``init`` (N, J, 3) mm rows become ``final_mm`` (in place), to be held fixed. References are
    never among them: refinement holds them at their (possibly new) lift."""
    if frames is None:
        return None
    final = session.load_results()["final_mm"]
    keep = np.all(np.isfinite(final), axis=(1, 2))
    keep[np.asarray(frames, dtype=np.int64)] = False
    keep[session.reference_frames] = False
    init[keep] = final[keep]
    return np.flatnonzero(keep)


def refine_inputs(session: Session, quiet: bool) -> tuple[np.ndarray, dict]:
    """The initialization (lifted references over propagation) and the session's refinement
    problem: the keyword arguments :func:`handanno_core.refine.refine` and
    :func:`handanno_core.pieces.refine_pieces` share (crops, boxes, centres, camera, skeleton,
    bones (``(B,)``, or ``(N, B)`` with several hands), references and their annotations,
    closest references, breaks, cube)."""
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
    return init, {
        "crops": crops,
        "boxes": boxes,
        "centres_mm": centres,
        "camera": session.camera,
        "skeleton": session.skeleton,
        "bone_lengths_mm": session.frame_bone_lengths(),
        "reference_frames": refs,
        "reference_annotations": session.annotations(refs),
        "closest_reference": root_reference(session.parent),
        "sequence_breaks": session.model.sequence_breaks,
        "cube_mm": session.model.settings.cube_mm,
    }


def _refine_pieces(session: Session, *, quiet, save, use_model, window, overlap, workers,
                   scheduler, resume, frames):  # fmt: skip
    """:func:`refine` in pieces (see there)."""
    import shutil

    from .pieces import DEFAULT_OVERLAP, DEFAULT_WINDOW, refine_pieces

    init, problem = refine_inputs(session, quiet)
    held = _keep_refined(session, init, frames)
    folder = session.folder / REFINE_PIECES_DIR
    if not resume and folder.exists():
        shutil.rmtree(folder)
    result = refine_pieces(
        init,
        hand_model=use_model,
        window=window or DEFAULT_WINDOW,
        overlap=min(DEFAULT_OVERLAP, (window or DEFAULT_WINDOW) // 4)
        if overlap is None
        else overlap,
        workers=workers,
        scheduler=scheduler,
        checkpoint_dir=folder,
        checkpoint_key=str(crops_fingerprint(session.folder / CROPS_FILE)),
        log=lambda m: _log(m, quiet),
        fixed_frames=held,
        **problem,
    )
    if save:
        session.save_results(final_mm=result.joints_mm)
        shutil.rmtree(folder, ignore_errors=True)
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
    select(session, ref_fraction=0.05, figures=False, quiet=quiet)
    session.close()
    return folder
