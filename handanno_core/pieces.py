"""Refinement in independent pieces: memory bounded by a window, pieces in parallel, resumable.

:func:`handanno_core.refine.refine` solves every frame in one system; its memory grows with the
dataset (about 0.24 MB per frame measured). Its temporal term only couples consecutive frames of
one sequence, so the problem falls apart into independent pieces:

* every **sequence between breaks** is its own problem (no term couples two sequences);
* a sequence longer than ``window`` frames is split into **overlapping windows** of at most
  ``window`` frames, consecutive windows sharing ``overlap`` frames. Each window is solved on its
  own, and in the shared frames the two solutions are **blended** with linear weights that fall
  to zero at each window's own edge (where a window lacks the context beyond its end), then put
  back onto the fixed bone lengths (``Kinematics.fit``). Blending rather than "solve the next
  window with its first frames fixed to the previous solution" because (a) fixed boundary
  frames chain the windows, so a sequence could not be solved in parallel or resumed in any
  order, and (b) the fixed frames would be the previous window's *least* reliable frames (its
  last ones, solved without their future); blending gives those frames the least weight.

The influence of a window's edge on the solution decays quickly along the time chain (the
temporal term is a spring between neighbours, the other terms tie every frame to its own data),
so with a few dozen frames of overlap the blended result is close to the whole solve; the
difference is measured by ``tests/test_pieces.py`` and ``benchmarks/bench_scale.py``.

A frame whose closest reference (its appearance template) lies outside its window gets that
reference appended to the piece as a **fixed** frame behind a sequence break (its crop and
annotation are needed for the template; being fixed and unlinked, it changes nothing else).

**Back-ends**: in this process, in ``workers`` local processes, or on a Dask distributed cluster
(``scheduler="tcp://HOST:PORT"``). Crops travel by path (a memory map opened in each worker: on a
cluster the session folder must be on a filesystem every worker sees under the same path); each
task carries only its window's small arrays.

**Resume**: with ``checkpoint_dir`` every finished piece is written there atomically
(``piece-NNNNN.npz``, :func:`handanno_core.fileio.atomic_save_npz`) with a key hashing all of the
piece's inputs; a rerun takes every piece whose checkpoint key matches and solves only the rest
(the log says which). Pieces are deterministic (one BLAS thread each), so a resumed run equals an
uninterrupted one bit for bit.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .annotation import FrameAnnotation
from .blas import single_blas_thread
from .camera import CameraIntrinsics
from .crops import DEFAULT_CROP
from .fileio import atomic_save_npz
from .handmodel import Kinematics
from .hands import BoneTable, bone_table
from .parallel import Runner
from .refine import sub_problem
from .skeleton import Skeleton

__all__ = ["Piece", "PiecesResult", "plan_pieces", "refine_pieces"]

#: default window (frames) and overlap; the window bounds a piece's memory (about 0.24 MB/frame
#: in the solver plus its crops), the overlap the seam error (see the README's scale section)
DEFAULT_WINDOW = 1024
DEFAULT_OVERLAP = 48


@dataclass(frozen=True)
class Piece:
    """Frames ``[start, stop)`` solved together; ``lead``/``trail`` frames shared with the
    previous/next piece of the same sequence (0 at a sequence's ends)."""

    index: int
    start: int
    stop: int
    lead: int
    trail: int


@dataclass
class PiecesResult:
    """``joints_mm`` (N, J, 3) mm; per piece its LM ``iterations``, ``converged`` and solve
    seconds; ``resumed``: indices of the pieces taken from checkpoints."""

    joints_mm: np.ndarray
    pieces: list[Piece]
    iterations: list[int]
    converged: list[bool]
    seconds: list[float]
    resumed: list[int]
    bone_violation_max_mm: float


def plan_pieces(
    n: int, breaks: Iterable[int], window: int = DEFAULT_WINDOW, overlap: int = DEFAULT_OVERLAP
) -> list[Piece]:
    """Split ``n`` frames at the sequence ``breaks`` and into windows of <= ``window`` frames.

    Windows of one sequence are evenly spaced and consecutive ones share exactly ``overlap``
    frames. Raises ValueError unless ``window > 2 * overlap >= 0``.
    """
    if overlap < 0 or window <= 2 * overlap:
        raise ValueError(f"window ({window}) must exceed twice the overlap ({overlap})")
    cuts = sorted({0, n, *(int(b) for b in breaks if 0 < int(b) < n)})
    pieces: list[Piece] = []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        length = b - a
        k = 1 if length <= window else -(-(length - overlap) // (window - overlap))
        edges = [a + round(i * (length - overlap) / k) for i in range(k + 1)]
        for i in range(k):
            start = edges[i]
            stop = b if i == k - 1 else edges[i + 1] + overlap
            pieces.append(
                Piece(
                    index=len(pieces),
                    start=start,
                    stop=stop,
                    lead=overlap if i > 0 else 0,
                    trail=overlap if i < k - 1 else 0,
                )
            )
    return pieces


@dataclass
class _Crops:
    """Crops by path (memory-mapped where used) or, in this process, the array itself."""

    path: str | None
    offset: int
    shape: tuple[int, ...]
    dtype: str
    array: np.ndarray | None = None

    def take(self, frames: np.ndarray) -> np.ndarray:
        arr = self.array
        if arr is None:
            arr = np.memmap(
                self.path, dtype=np.dtype(self.dtype), mode="r", offset=self.offset,
                shape=self.shape,
            )  # fmt: skip
        return np.ascontiguousarray(arr[frames])

    def __getstate__(self):
        return dict(self.__dict__, array=None)


@dataclass
class _Task:
    """One piece's sub-problem in local frame indices (frames = window, then fixed extra refs)."""

    piece: Piece
    frames: np.ndarray  # (n_local,) global frame indices
    crops: _Crops
    init: np.ndarray
    boxes: np.ndarray
    centres: np.ndarray
    refs: np.ndarray  # local
    annotations: dict[int, FrameAnnotation]  # local frame -> annotation
    closest: np.ndarray  # local
    breaks: list[int]
    fixed: np.ndarray  # local
    kwargs: dict  # camera, skeleton, bone lengths, weights, iterations, cube, tol, hand model


def _solve(task: _Task) -> tuple[int, np.ndarray, int, bool, float]:
    """Solve one piece (one BLAS thread: identical results in any process)."""
    from .refine import refine

    with single_blas_thread():
        res = refine(
            task.init,
            crops=task.crops.take(task.frames),
            boxes=task.boxes,
            centres_mm=task.centres,
            reference_frames=task.refs,
            reference_annotations=task.annotations,
            closest_reference=task.closest,
            sequence_breaks=task.breaks,
            fixed_frames=task.fixed,
            **task.kwargs,
        )
    w = task.piece.stop - task.piece.start
    return task.piece.index, res.joints_mm[:w], res.iterations, res.converged, res.time_s


def _digest(*parts) -> str:
    """Hash of arrays (exact bytes), dataclasses, containers and scalars (full-precision repr),
    the same in every process (no pickling: a set's pickle depends on the string hash seed)."""
    h = hashlib.blake2b(digest_size=16)

    def feed(obj) -> None:
        if isinstance(obj, np.ndarray):
            h.update(f"a{obj.dtype}{obj.shape}".encode())
            h.update(np.ascontiguousarray(obj).tobytes())
        elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            h.update(type(obj).__name__.encode())
            for f in dataclasses.fields(obj):
                h.update(f.name.encode())
                feed(getattr(obj, f.name))
        elif isinstance(obj, dict):
            h.update(b"{")
            for k in sorted(obj, key=repr):
                feed(k)
                feed(obj[k])
        elif isinstance(obj, list | tuple):
            h.update(b"(")
            for v in obj:
                feed(v)
        elif isinstance(obj, set | frozenset):
            h.update(repr(sorted(obj, key=repr)).encode())
        else:
            h.update(repr(obj).encode())

    for p in parts:
        feed(p)
    return h.hexdigest()


def _task_key(task: _Task, extra_key: str) -> str:
    anns = [
        (f, np.asarray(a.uv_px, dtype=np.float64), np.asarray(a.visible))
        for f, a in sorted(task.annotations.items())
    ]
    kw = task.kwargs
    return _digest(
        task.piece, task.frames, task.init, task.boxes, task.centres, task.refs, task.closest,
        task.fixed, anns, kw, extra_key,
    )  # fmt: skip


def refine_pieces(
    init_mm: np.ndarray,
    *,
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray,
    reference_frames: Iterable[int],
    reference_annotations: dict[int, FrameAnnotation],
    closest_reference: np.ndarray,
    sequence_breaks: Iterable[int] = (),
    window: int = DEFAULT_WINDOW,
    overlap: int = DEFAULT_OVERLAP,
    workers: int = 1,
    scheduler=None,
    checkpoint_dir: str | Path | None = None,
    checkpoint_key: str = "",
    log: Callable[[str], None] | None = None,
    progress: Callable[[int, int], None] | None = None,
    hand_model=False,
    fixed_frames: Iterable[int] | None = None,
    **refine_kwargs,
) -> PiecesResult:
    """Refine ``init_mm`` (N, J, 3) mm piece by piece (see the module docstring).

    Arguments as :func:`handanno_core.refine.refine` (``refine_kwargs``: ``weights``,
    ``iterations``, ``cube_mm``, ``tol``, ``fit_weights``), plus: ``window``/``overlap`` (frames,
    :func:`plan_pieces`); ``workers`` local processes or ``scheduler`` (``"tcp://HOST:PORT"`` or a
    ``dask.distributed.Client``); ``checkpoint_dir`` to resume from (``checkpoint_key``: anything
    else the result depends on, e.g. the crops' fingerprint); ``log(message)``;
    ``progress(pieces_done, pieces_total)``. ``hand_model=True`` personalizes one hand model from
    all references (as the whole solve would) and gives it to every piece. ``bone_lengths_mm``
    ``(N, B)`` (several hands, :mod:`handanno_core.hands`): every piece is solved with its
    frames' bones (one set per sequence) and gets a hand model personalized from that set's
    references. ``fixed_frames``: frames kept at their initialization in every piece that
    holds them (as :func:`handanno_core.refine.refine`'s).
    """
    init = np.asarray(init_mm, dtype=np.float64)
    n, j = init.shape[:2]
    boxes = np.asarray(boxes, dtype=np.float64)
    centres = np.asarray(centres_mm, dtype=np.float64)
    closest = np.asarray(closest_reference, dtype=np.int64)
    if crops.shape[0] != n or boxes.shape != (n, 4) or centres.shape != (n, 3):
        raise ValueError("crops, boxes and centres_mm must have one row per frame")
    if closest.shape != (n,):
        raise ValueError(f"closest_reference must be ({n},), got {closest.shape}")
    refs = np.asarray(sorted({int(r) for r in reference_frames}), dtype=np.int64)
    is_ref = np.zeros(n, dtype=bool)
    is_ref[refs] = True
    held = np.zeros(n, dtype=bool)
    if fixed_frames is not None:
        held[np.asarray(list(fixed_frames), dtype=np.int64)] = True
    table = bone_table(bone_lengths_mm, n, len(skeleton.bones))
    say = log or (lambda _m: None)
    pieces = plan_pieces(n, sequence_breaks, window, overlap)
    hand_of_piece = _hand_of_pieces(pieces, table)
    models = [hand_model] * len(table.lengths)
    if hand_model is True:
        cube = refine_kwargs.get("cube_mm", DEFAULT_CROP.cube_mm)
        models = [
            _one_hand_model(
                init, refs if table.single else np.intersect1d(refs, table.frames_of(h)),
                crops, boxes, centres, camera, skeleton, lengths, cube,
            )
            for h, lengths in enumerate(table.lengths)
        ]  # fmt: skip
    kwargs = [
        dict(
            refine_kwargs, camera=camera, skeleton=skeleton, bone_lengths_mm=lengths,
            hand_model=models[h],
        )
        for h, lengths in enumerate(table.lengths)
    ]  # fmt: skip

    remote = scheduler is not None or workers > 1
    shared, tmpdir = _shared_crops(crops, remote)

    def task_of(p: Piece) -> _Task:
        sub = sub_problem(np.arange(p.start, p.stop), closest, is_ref, reference_annotations)
        return _Task(
            piece=p,
            frames=sub.frames,
            crops=shared,
            init=init[sub.frames],
            boxes=boxes[sub.frames],
            centres=centres[sub.frames],
            refs=sub.refs,
            annotations=sub.annotations,
            closest=sub.closest,
            breaks=sub.breaks,
            fixed=np.union1d(sub.extra, np.flatnonzero(held[sub.frames[: sub.own]])),
            kwargs=kwargs[hand_of_piece[p.index]],
        )

    folder = Path(checkpoint_dir) if checkpoint_dir is not None else None
    tasks = [task_of(p) for p in pieces]
    solved, keys, todo = _load_checkpoints(tasks, folder, checkpoint_key, say)
    resumed = sorted(solved)
    _say_plan(pieces, todo, resumed, folder, window, overlap, say)

    def collect(out) -> None:
        index, joints, iterations, converged, seconds = out
        solved[index] = (joints, iterations, converged, seconds)
        if folder is not None:
            atomic_save_npz(
                folder / f"piece-{index:05d}.npz",
                {
                    "key": np.asarray(keys[index]),
                    "joints_mm": joints,
                    "iterations": np.asarray(iterations),
                    "converged": np.asarray(converged),
                    "seconds": np.asarray(seconds),
                },
            )
        p = pieces[index]
        say(
            f"piece {index} (frames {p.start}-{p.stop - 1}) done: {iterations} iterations, "
            f"{seconds:.1f} s"
        )
        if progress is not None:
            progress(len(solved), len(pieces))

    try:
        with Runner(
            min(workers, max(1, len(todo))) if remote else 1, scheduler, fresh_processes=True
        ) as runner:
            runner.each(_solve, todo, collect)
    finally:
        if tmpdir is not None:
            for f in Path(tmpdir).iterdir():
                f.unlink()
            os.rmdir(tmpdir)

    joints = _blend(pieces, {i: s[0] for i, s in solved.items()}, n, j)
    joints = _onto_bones(joints, pieces, skeleton, table, hand_of_piece)
    viol = (
        float(np.max(np.abs(skeleton.bone_lengths(joints) - table.per_frame(np.arange(n)))))
        if n
        else 0.0
    )
    return PiecesResult(
        joints_mm=joints,
        pieces=pieces,
        iterations=[solved[p.index][1] for p in pieces],
        converged=[solved[p.index][2] for p in pieces],
        seconds=[solved[p.index][3] for p in pieces],
        resumed=resumed,
        bone_violation_max_mm=viol,
    )


def _one_hand_model(init, refs, crops, boxes, centres, camera, skeleton, bones, cube_mm):
    """The hand model personalized from all lifted references (as the whole solve would), or
    False without one."""
    from . import handmodel as hmod

    ok = refs[np.all(np.isfinite(init[refs]), axis=(1, 2))]
    if not len(ok):
        return False
    return hmod.personalize_from_crops(
        skeleton, bones, init[ok], crops[ok], boxes[ok], centres[ok], camera, cube_mm=cube_mm
    )[0]


def _shared_crops(crops: np.ndarray, remote: bool) -> tuple[_Crops, str | None]:
    """How pieces reach the crops: the array itself in this process; for other processes or a
    cluster a path (the memmap's own file, or a temporary copy whose folder is returned)."""
    if not remote:
        return _Crops(None, 0, tuple(crops.shape), str(crops.dtype), array=crops), None
    if isinstance(crops, np.memmap) and crops.filename is not None:
        return _Crops(
            str(crops.filename), int(crops.offset), tuple(crops.shape), str(crops.dtype)
        ), None
    tmpdir = tempfile.mkdtemp(prefix="handanno-crops-")
    mm = np.lib.format.open_memmap(
        Path(tmpdir) / "crops.npy", mode="w+", dtype=crops.dtype, shape=crops.shape
    )
    mm[:] = crops
    shared = _Crops(str(mm.filename), int(mm.offset), tuple(crops.shape), str(crops.dtype))
    del mm
    return shared, tmpdir


def _load_checkpoints(tasks: list[_Task], folder: Path | None, checkpoint_key: str, say):
    """Pieces already solved (``{index: (joints, iterations, converged, seconds)}``, from
    checkpoints whose key matches), every piece's key, and the tasks left to solve."""
    solved: dict[int, tuple[np.ndarray, int, bool, float]] = {}
    keys: dict[int, str] = {}
    todo: list[_Task] = []
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
    for task in tasks:
        index = task.piece.index
        if folder is not None:
            keys[index] = _task_key(task, checkpoint_key)
            ck = folder / f"piece-{index:05d}.npz"
            if ck.exists():
                try:
                    with np.load(ck, allow_pickle=False) as z:
                        if str(z["key"]) == keys[index]:
                            solved[index] = (
                                np.asarray(z["joints_mm"]), int(z["iterations"]),
                                bool(z["converged"]), float(z["seconds"]),
                            )  # fmt: skip
                            continue
                except Exception as exc:  # a damaged checkpoint is solved again
                    say(f"{ck}: unreadable checkpoint ({type(exc).__name__}), solving again")
        todo.append(task)
    return solved, keys, todo


def _say_plan(pieces, todo, resumed, folder, window: int, overlap: int, say) -> None:
    n_seq = len({p.start for p in pieces if p.lead == 0})
    say(
        f"refine: {len(pieces)} piece(s) in {n_seq} sequence(s) (window {window}, overlap "
        f"{overlap} frames)"
    )
    if resumed:
        first = todo[0].piece if todo else None
        say(
            f"resuming: {len(resumed)} of {len(pieces)} pieces done (checkpoints in {folder}); "
            + (
                f"continuing from piece {first.index} (frames {first.start}-{first.stop - 1})"
                if first is not None
                else "nothing left to solve"
            )
        )


def _blend(pieces: list[Piece], joints: dict[int, np.ndarray], n: int, j: int) -> np.ndarray:
    """(N, J, 3): every piece's frames, shared frames weighted linearly (0 at a piece's edge)."""
    acc = np.zeros((n, j, 3))
    wsum = np.zeros(n)
    for p in pieces:
        length = p.stop - p.start
        w = np.ones(length)
        if p.lead:
            w[: p.lead] = (np.arange(p.lead) + 0.5) / p.lead
        if p.trail:
            w[length - p.trail :] = (p.trail - np.arange(p.trail) - 0.5) / p.trail
        acc[p.start : p.stop] += w[:, None, None] * joints[p.index]
        wsum[p.start : p.stop] += w
    return acc / wsum[:, None, None]


def _onto_bones(
    joints: np.ndarray, pieces: list[Piece], skeleton: Skeleton, table: BoneTable, hand_of_piece
) -> np.ndarray:
    """Put the blended (shared) frames back onto the fixed bone lengths (each its hand's)."""
    for h, lengths in enumerate(table.lengths):
        shared = np.concatenate(
            [
                np.arange(p.stop - p.trail, p.stop)
                for p in pieces
                if p.trail and hand_of_piece[p.index] == h
            ]
            or [np.zeros(0, int)]
        )
        if len(shared):
            kin = Kinematics(skeleton, lengths)
            joints[shared] = kin.joints(*kin.fit(joints[shared]))
    return joints


def _hand_of_pieces(pieces: list[Piece], table: BoneTable) -> list[int]:
    """Each piece's row of ``table.lengths``; ValueError if a piece's frames have several (bone
    lengths may change only at a sequence break)."""
    if table.single:
        return [0] * len(pieces)
    out = []
    for p in pieces:
        rows = np.unique(table.hand[p.start : p.stop])
        if len(rows) != 1:
            raise ValueError(
                f"frames {p.start}-{p.stop - 1}: bone lengths change inside a sequence "
                "(they may change only at a sequence break)"
            )
        out.append(int(rows[0]))
    return out
