"""Normalized 3D-cube crops of the hand (DESIGN.md step 2).

Where the hand is (centre, size) comes from :mod:`handanno_core.localize` (no ground truth);
``locate_hand``, ``locate_hands`` and ``smooth_centres`` are re-exported here.

Crops are a cube of ``cube_mm`` around the centre, projected to an image box and resampled to
``size x size`` pixels (nearest neighbour, so depth edges never blend), with depth normalized to
``(d - z_c) / (cube_mm / 2)`` in ``[-1, 1]``:

- no depth, and everything behind the cube (``d > z_c + cube/2``): ``+1`` (background);
- inside the cube: the normalized depth;
- just in front of the cube (``z_c - cube <= d < z_c - cube/2``): clamped to ``-1``: usually a
  finger pointing at the camera that sticks out of the cube, which should stay foreground;
- far in front (``d < z_c - cube``): ``+1``, treated as background: flying pixels or an unrelated
  occluder, not hand.

Everything a crop's geometry depends on is one frozen :class:`CropSpec` (cube edge, pixel size;
the background value and test); :func:`locate_crops` finds a session's centres and grows its spec
until the hand fits.

Crop geometry (``boxes (N, 4)`` = ``[u_left, v_top, sx, sy]``): crop pixel ``(x, y)`` covers image
pixel ``u = u_left + (x + 0.5) * sx - 0.5``, ``v = v_top + (y + 0.5) * sy - 0.5`` with
``sx = fx * cube_mm / z_c / size`` image px per crop px; the centre's projection maps to crop
``((size - 1) / 2, (size - 1) / 2)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from .camera import CameraIntrinsics
from .cropspec import DEFAULT_CROP, CropSpec
from .datasets.base import BadFrameReport, DepthSequence, FrameError
from .localize import locate_hand, locate_hands, smooth_centres

__all__ = [
    "CropSpec",
    "DEFAULT_CROP",
    "locate_crops",
    "place_crops",
    "joints_inside_crops",
    "crops_from_references",
    "update_crops",
    "locate_hand",
    "locate_hands",
    "smooth_centres",
    "crop_boxes",
    "image_to_crop",
    "crop_to_image",
    "crop_depth",
    "compute_crops",
]


def crop_boxes(
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    cube_mm: float = DEFAULT_CROP.cube_mm,
    size: int = DEFAULT_CROP.size,
) -> np.ndarray:
    """Image boxes ``(..., 4)`` float64 ``[u_left, v_top, sx, sy]`` for centres ``(..., 3)`` mm
    at a cube of ``cube_mm`` (a float, or one per centre ``(...,)``: frames' own cubes in x, y).

    ``sx = fx * cube_mm / z_c / size`` (image px per crop px), box centred on the projection of
    the centre. NaN centres give NaN boxes.
    """
    c = np.asarray(centres_mm, dtype=np.float64)
    uv = camera.project(c)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(c[..., 2] > 0, c[..., 2], np.nan)
        sx = camera.fx * cube_mm / z / size
        sy = camera.fy * cube_mm / z / size
    u_left = uv[..., 0] + 0.5 - 0.5 * size * sx
    v_top = uv[..., 1] + 0.5 - 0.5 * size * sy
    return np.stack([u_left, v_top, sx, sy], axis=-1)


def crop_to_image(xy: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Crop pixels ``(..., 2)`` -> image pixels ``(..., 2)`` for boxes ``(..., 4)`` (broadcast)."""
    xy = np.asarray(xy, dtype=np.float64)
    b = np.asarray(boxes, dtype=np.float64)
    u = b[..., 0] + (xy[..., 0] + 0.5) * b[..., 2] - 0.5
    v = b[..., 1] + (xy[..., 1] + 0.5) * b[..., 3] - 0.5
    return np.stack([u, v], axis=-1)


def image_to_crop(uv: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Image pixels ``(..., 2)`` -> crop pixels ``(..., 2)``; exact inverse of :func:`crop_to_image`."""
    uv = np.asarray(uv, dtype=np.float64)
    b = np.asarray(boxes, dtype=np.float64)
    x = (uv[..., 0] - b[..., 0] + 0.5) / b[..., 2] - 0.5
    y = (uv[..., 1] - b[..., 1] + 0.5) / b[..., 3] - 0.5
    return np.stack([x, y], axis=-1)


def crop_depth(
    depth: np.ndarray,
    camera: CameraIntrinsics,
    centre_mm: np.ndarray,
    cube_mm: float = DEFAULT_CROP.cube_mm,
    size: int = DEFAULT_CROP.size,
    box_cube_mm: float | None = None,
) -> np.ndarray:
    """Normalized ``(size, size)`` float32 crop of ``depth (H, W)`` mm around ``centre_mm (3,)``.

    Nearest-neighbour resampling of the box from :func:`crop_boxes` at ``box_cube_mm`` (the
    frame's own cube in x and y, default ``cube_mm``; outside the image = no depth), then
    ``(d - z_c) / (cube_mm / 2)`` with the background rules in the module docstring (no depth /
    behind / far in front = +1, just in front = -1): depth is always at the session's
    ``cube_mm``. A NaN centre gives all +1.
    """
    c = np.asarray(centre_mm, dtype=np.float64)
    if not np.all(np.isfinite(c)) or c[2] <= 0:
        return np.full((size, size), CropSpec.BACKGROUND, np.float32)
    box_cube = cube_mm if box_cube_mm is None else float(box_cube_mm)
    u_left, v_top, sx, sy = crop_boxes(c, camera, box_cube, size)
    # dst (x, y) -> src (u, v) = (sx * x + u0, sy * y + v0)
    m = np.array(
        [[sx, 0.0, u_left + 0.5 * sx - 0.5], [0.0, sy, v_top + 0.5 * sy - 0.5]], dtype=np.float64
    )
    d = cv2.warpAffine(
        np.asarray(depth, dtype=np.float32),
        m,
        (size, size),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    half = 0.5 * cube_mm
    zc = float(c[2])
    out = np.clip((d - zc) / half, -1.0, 1.0).astype(np.float32)
    background = (d <= 0) | (d > zc + half) | (d < zc - 2.0 * half)
    out[background] = CropSpec.BACKGROUND
    return out


def compute_crops(
    sequence: DepthSequence,
    centres_mm: np.ndarray,
    out_path: str | Path | None = None,
    cube_mm: float = DEFAULT_CROP.cube_mm,
    size: int = DEFAULT_CROP.size,
    report: BadFrameReport | None = None,
    progress: bool = False,
    chunk_frames: int = 256,
    workers: int = 1,
    box_cubes_mm: np.ndarray | None = None,
) -> np.ndarray:
    """Normalized crops ``(N, size, size)`` float16 for every frame (see :func:`crop_depth`).

    With ``out_path`` the crops are written to a ``.npy`` file chunk by chunk (a fresh writable
    mapping of ``chunk_frames`` frames at a time, flushed and dropped, so resident memory stays
    flat however long the sequence) and returned as ``np.load(out_path, mmap_mode="r")``. Without
    it an in-memory array is returned. Bad frames (``FrameError``, recorded in ``report``; raised
    if ``report`` is None) and NaN centres stay all +1. ``workers`` > 1 (with ``out_path``):
    ranges of frames are cut by that many processes, each writing its own part of the file; the
    same bytes as one process. ``box_cubes_mm`` ``(N,)`` (optional): each frame's own cube in x
    and y (:func:`locate_crops`; default ``cube_mm``); depth is at ``cube_mm`` in every frame.
    """
    n = len(sequence)
    centres = np.asarray(centres_mm, dtype=np.float64)
    if centres.shape != (n, 3):
        raise ValueError(f"centres must be ({n}, 3), got {centres.shape}")
    box = np.full(n, float(cube_mm)) if box_cubes_mm is None else np.asarray(box_cubes_mm, float)
    if box.shape != (n,):
        raise ValueError(f"box_cubes_mm must be ({n},), got {box.shape}")
    cubes = (float(cube_mm), box)
    frame_shape = (size, size)
    if out_path is None:
        out = np.full((n, *frame_shape), CropSpec.BACKGROUND, np.float16)
        for a in range(0, n, chunk_frames):
            b = min(n, a + chunk_frames)
            out[a:b] = _crop_chunk(sequence, centres, a, b, cubes, size, report)
        return out
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(out_path.name + ".tmp.npy")
    header = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16, shape=(n, *frame_shape))
    offset = int(header.offset)
    del header
    file = (str(tmp), offset, frame_shape)
    if workers > 1 and n > 1:
        _crop_parallel(
            sequence, centres, file, cubes, size, report, progress, chunk_frames, workers
        )
    else:
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n, desc="cropping", unit="frame")
        for a in range(0, n, chunk_frames):
            b = min(n, a + chunk_frames)
            _write_chunk(file, a, _crop_chunk(sequence, centres, a, b, cubes, size, report))
            if bar is not None:
                bar.update(b - a)
        if bar is not None:
            bar.close()
    tmp.replace(out_path)
    return np.load(out_path, mmap_mode="r")


def update_crops(
    sequence: DepthSequence,
    path: str | Path,
    frames: np.ndarray,
    centres_mm: np.ndarray,
    cube_mm: float,
    size: int,
    box_cubes_mm: np.ndarray,
) -> None:
    """Cut ``frames`` again into the crop file ``path`` (:func:`compute_crops`'s ``.npy``) at
    ``centres_mm`` ``(N, 3)`` and ``box_cubes_mm`` ``(N,)``; the other frames' crops are kept.
    Written through a copy that replaces the file, so a crash leaves the old file whole. Bad
    frames stay at background."""
    import shutil

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npy")
    try:
        shutil.copyfile(path, tmp)
        header = np.load(tmp, mmap_mode="r")
        offset, frame_shape = int(header.offset), header.shape[1:]
        del header
        cubes = (float(cube_mm), np.asarray(box_cubes_mm, dtype=np.float64))
        centres = np.asarray(centres_mm, dtype=np.float64)
        for i in np.asarray(frames, dtype=int):
            buf = _crop_chunk(sequence, centres, int(i), int(i) + 1, cubes, size, BadFrameReport())
            _write_chunk((str(tmp), offset, frame_shape), int(i), buf)
        tmp.replace(path)
    finally:  # a failed copy (a full disk) leaves no half-written file behind
        tmp.unlink(missing_ok=True)


def _crop_chunk(sequence, centres, a, b, cubes, size, report) -> np.ndarray:
    """Crops ``(b - a, size, size)`` float16 of frames ``a..b-1`` (bad frames to ``report``);
    ``cubes``: ``(cube_mm, box cubes (N,))``."""
    cube_mm, box = cubes
    buf = np.full((b - a, size, size), CropSpec.BACKGROUND, np.float16)
    for i in range(a, b):
        if not np.all(np.isfinite(centres[i])):
            continue
        try:
            depth = sequence.depth(i)
        except FrameError as err:
            if report is None:
                raise
            report.errors.append(err)
            continue
        buf[i - a] = crop_depth(depth, sequence.camera, centres[i], cube_mm, size, box[i])
    return buf


def _write_chunk(file: tuple[str, int, tuple[int, int]], a: int, buf: np.ndarray) -> None:
    """Write ``buf`` (frames ``a..``) into the ``.npy`` file ``(path, data offset, frame shape)``
    through a mapping of just those frames (flushed and dropped)."""
    path, offset, shape = file
    target = np.memmap(
        path, dtype=np.float16, mode="r+", offset=offset + a * buf[0].nbytes, shape=buf.shape
    )
    target[:] = buf
    target.flush()
    del target


def _crop_job(sequence, centres, file, cubes, size, chunk_frames, job):
    """One process's share ``job = (a, b)``, cut and written chunk by chunk; bad frames come back
    as ``(path, frame, problem)`` (a FrameError does not pickle)."""
    a, b = job
    report = BadFrameReport()
    for c in range(a, b, chunk_frames):
        d = min(b, c + chunk_frames)
        _write_chunk(file, c, _crop_chunk(sequence, centres, c, d, cubes, size, report))
    return [(e.path, e.frame, e.problem) for e in report.errors]


def _crop_parallel(sequence, centres, file, cubes, size, report, progress, chunk_frames, workers):
    from functools import partial

    from .parallel import Runner, frame_ranges

    jobs = frame_ranges(len(sequence), workers)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc=f"cropping ({workers} processes)", unit="part")
    with Runner(workers, fresh_processes=True) as runner:
        done = runner.map(
            partial(_crop_job, sequence, centres, file, cubes, size, chunk_frames),
            jobs,
            progress=None if bar is None else lambda *_: bar.update(1),
        )
    if bar is not None:
        bar.close()
    for bad in done:
        errors = [FrameError(*e) for e in bad]
        if errors and report is None:
            raise errors[0]
        if report is not None:
            report.errors.extend(errors)


# ---------------------------------------------------------------------------------------------
# a session's crops: centres and the cube the hand needs
# ---------------------------------------------------------------------------------------------
def locate_crops(
    sequence: DepthSequence,
    spec: CropSpec = DEFAULT_CROP,
    report: BadFrameReport | None = None,
    progress: bool = False,
    workers: int = 1,
) -> tuple[np.ndarray, CropSpec, np.ndarray]:
    """Crop centres ``(N, 3)`` mm of every frame, the session's spec and each frame's own cube in
    x and y ``(N,)`` mm (``workers`` processes, see
    :func:`handanno_core.localize.locate_hand_geometry`).

    The hand's geometry is found once per frame, whatever the cube
    (:func:`handanno_core.localize.locate_hand_geometry`); the centres at a cube follow from it
    (:func:`handanno_core.localize.centres_at`). The session's cube grows until every frame's
    hand but a one-frame spike fits (:func:`handanno_core.localize.session_cube_mm`; it sets
    every crop's depth range), not counting frames whose hand is two candidates held together
    (the geometry's own-box column); then a frame whose own hand still does not fit gets a
    larger image box (:func:`handanno_core.localize.frame_cubes_mm`), the other frames' crops
    unchanged.
    Centres depend on the cube, so both are placed again from the same geometry until neither
    grows: one pass over the frames, and a rebuilt cache gives the same crops.
    """
    from .localize import locate_hand_geometry

    geometry = locate_hand_geometry(sequence, report=report, progress=progress, workers=workers)
    return place_crops(geometry, spec, sequence.sequence_breaks)


def place_crops(
    geometry: np.ndarray,
    spec: CropSpec = DEFAULT_CROP,
    breaks: Sequence[int] | None = None,
    grow: bool = True,
) -> tuple[np.ndarray, CropSpec, np.ndarray]:
    """:func:`locate_crops` from the frames' hand geometry ``(N, GEOMETRY_LEN)``
    (:func:`handanno_core.localize.locate_hand_geometry`): crop centres ``(N, 3)`` mm, the
    session's spec (its cube grown unless ``grow`` is False) and each frame's own cube in x and
    y ``(N,)`` mm."""
    from .localize import centres_at, frame_cubes_mm, session_cube_mm

    own = geometry[:, 14] == 1.0  # frames with their own box do not size the session's cube

    def session_cube(half):
        half = np.where(own[:, None], np.nan, half)
        return session_cube_mm(half, spec.cube_mm, sequence_breaks=breaks)

    centres, half = centres_at(geometry, spec.cube_mm, breaks)
    while grow and (cube := session_cube(half)) != spec.cube_mm:
        spec = spec.with_cube(cube)
        centres, half = centres_at(geometry, spec.cube_mm, breaks)
    boxes = frame_cubes_mm(half, spec.cube_mm)
    while True:
        centres, half = centres_at(geometry, spec.cube_mm, breaks, box_cubes_mm=boxes)
        grown = np.maximum(boxes, frame_cubes_mm(half, spec.cube_mm))
        if np.array_equal(grown, boxes):
            return centres, spec, boxes
        boxes = grown


def joints_inside_crops(
    joints_mm: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    box_cubes_mm: np.ndarray | float,
    size: int = DEFAULT_CROP.size,
    margin_mm: float = 8.0,
    cube_mm: float | None = None,
) -> np.ndarray:
    """``(N,)`` bool: every joint of ``joints_mm`` ``(N, J, 3)`` projects inside its frame's crop
    (crop centre ``centres_mm`` ``(N, 3)``, image box of ``box_cubes_mm`` ``(N,)`` or scalar, in
    x and y), ``margin_mm`` (at the box's scale) from its edge; with ``cube_mm`` (the session's
    cube, the crops' depth range) also within ``cube_mm / 2`` of the centre in depth (a hand in
    front of the cube is clamped to -1: silhouette without depth for the hand model). Joints with
    a NaN coordinate are not counted; a frame without a finite crop centre holds none."""
    j = np.asarray(joints_mm, dtype=np.float64)
    n = len(j)
    box = np.broadcast_to(np.asarray(box_cubes_mm, dtype=np.float64), (n,))
    boxes = crop_boxes(np.asarray(centres_mm, dtype=np.float64), camera, box, size)
    known = np.all(np.isfinite(j), axis=2) & (np.nan_to_num(j[..., 2]) > 0)
    uv = camera.project(np.where(known[..., None], j, 1.0))
    xy = image_to_crop(uv, boxes[:, None, :])
    mm = (xy - (size - 1) / 2) * box[:, None, None] / size
    inside = np.all(np.abs(mm) <= box[:, None, None] / 2 - margin_mm, axis=2)
    if cube_mm is not None:
        dz = j[..., 2] - np.asarray(centres_mm, dtype=np.float64)[:, None, 2]
        inside &= np.abs(np.nan_to_num(dz, nan=np.inf)) <= 0.5 * float(cube_mm)
    inside |= ~known
    return np.all(inside, axis=1) & np.all(np.isfinite(boxes), axis=1)


def crops_from_references(
    sequence: DepthSequence,
    geometry: np.ndarray | None,
    spec: CropSpec,
    centres_mm: np.ndarray,
    box_cubes_mm: np.ndarray,
    joints_mm: dict[int, np.ndarray],
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """The crops placed again where references' joints ``joints_mm`` (frame -> ``(J, 3)`` mm) fall
    outside their own crop (centres ``(N, 3)`` mm, image boxes of ``box_cubes_mm`` ``(N,)``):
    those references anchor :func:`handanno_core.localize.anchored_geometry`, the others stop its
    runs, and the crops are placed at ``spec``'s cube (not grown; a frame whose hand does not
    fit gets its own box). ``geometry`` ``(N, GEOMETRY_LEN)``: the sequence's hand geometry
    (None: located here, only if a reference is missed).

    Returns ``(missed (A,) frames, geometry, centres (N, 3), box cubes (N,))``: with no
    reference missed, the inputs unchanged."""
    from .localize import anchored_geometry, locate_hand_geometry

    frames = np.array(sorted(f for f, j in joints_mm.items() if np.isfinite(j).any()), int)
    missed = frames
    if frames.size:
        joints = np.stack([np.asarray(joints_mm[f], dtype=np.float64) for f in frames])
        held = joints_inside_crops(
            joints, centres_mm[frames], sequence.camera, box_cubes_mm[frames], spec.size
        )
        missed = frames[~held]
    if missed.size == 0:
        return missed, geometry, centres_mm, box_cubes_mm
    if geometry is None:
        geometry = locate_hand_geometry(sequence, report=BadFrameReport())
    anchored = anchored_geometry(
        sequence, geometry, {int(f): joints_mm[int(f)] for f in missed}, frames.tolist(),
        report=BadFrameReport(),
    )  # fmt: skip
    centres, _, box = place_crops(anchored, spec, sequence.sequence_breaks, grow=False)
    return missed, anchored, centres, box
