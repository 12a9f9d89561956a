"""``handanno bench``: the whole pipeline per (strategy, reference fraction) with the simulated annotator.

Every configuration runs in the same invocation on the same data and machine, so the published
baselines (``chain`` = thesis, ``coverage`` = Oberweger et al., ``uniform``) and our strategy are
compared side by side. Crops are computed once and shared. Writes the JSON of DESIGN.md, prints a
table shaped like the thesis's Tables 2-4 and plots error against reference fraction (Figure 6).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import platform
import resource
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from . import pipeline
from .blas import blas_description
from .evaluate import error_summary
from .session import (
    CROPS_FILE,
    CROPS_META_FILE,
    Session,
    copy_session_folder,
    remove_session_folder,
)


def peak_rss_mb() -> float:
    """Peak resident memory of this process and its (finished) worker processes, in MB."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, children) / 1024.0


def _summary(pred: np.ndarray, gt: np.ndarray, frames: np.ndarray | None = None) -> dict:
    s = error_summary(pred, gt, frames=frames)
    return {k: round(float(s[k]), 3) for k in ("mean_mm", "median_mm", "max_mm")}


def run_session(base: Session, folder: Path) -> Session:
    """A fresh session in ``folder`` (replaced if it exists) on ``base``'s dataset, sharing its
    crop cache (symlinked, not recomputed): one bench run."""
    remove_session_folder(folder, f"handanno bench (replacing {folder.name})")
    session = Session.create(
        folder,
        base.model.dataset,
        base.num_frames,
        base.camera,
        base.model.skeleton,
        base.model.sequence_breaks,
    )
    with session.lock:
        # the base's crops were cut with its (possibly grown) cube: without its settings the
        # symlinked cache would not match and every run would cut all crops again
        session.model.settings = base.model.settings.model_copy()
        session.save()
    for name in (CROPS_FILE, CROPS_META_FILE):
        (folder / name).symlink_to((base.folder / name).resolve())
    return session


def annotated_session(
    base: Session, folder: Path, strategy: str, fraction: float, noise_px: float = 0.0
) -> Session:
    """A :func:`run_session` of ``base`` in ``folder`` with its references selected
    (``strategy``, ``fraction``) and annotated by the simulated annotator (``noise_px``): the start
    of the stage benchmarks in ``benchmarks/``."""
    session = run_session(base, folder)
    pipeline.select(session, strategy=strategy, ref_fraction=fraction, figures=False, quiet=True)
    pipeline.annotate_from_gt(session, noise_px=noise_px, quiet=True)
    return session


def noisy_stage_sessions(args, prefix: str) -> Iterator[tuple[str, float, Session, np.ndarray]]:
    """For every sequence of the suite part and every click noise of ``args.noise`` (px,
    comma-separated; :func:`stage_bench_parser` with ``noise``): ``(name, noise, session with its
    references selected and annotated at that noise, ground truth (N, J, 3) mm)``."""
    noises = [float(x) for x in args.noise.split(",")]
    for name, base, gt, tmp in suite_base_sessions(args.suite, args.part, prefix):
        for noise in noises:
            session = annotated_session(
                base, tmp / "run", args.strategy, args.ref_fraction, noise_px=noise
            )
            yield name, noise, session, gt


def stage_bench_parser(description: str, noise: str | None = None) -> argparse.ArgumentParser:
    """The arguments every stage benchmark over a suite part takes (``benchmarks/bench_lift_refit
    .py``, ``bench_refine_model.py``): the suite folder, ``--part``, ``--ref-fraction``,
    ``--strategy``, ``--json``, and ``--noise`` (default ``noise``) where given; the script adds
    its own."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("suite")
    ap.add_argument("--part", default="tune", choices=["tune", "report", "all"])
    ap.add_argument("--ref-fraction", type=float, default=0.05)
    ap.add_argument("--strategy", default="uniform")
    ap.add_argument("--json", required=True)
    if noise is not None:
        ap.add_argument("--noise", default=noise, help="click noises (px), comma-separated")
    return ap


def logged_lift(session: Session, **kwargs) -> tuple[float, str]:
    """:func:`pipeline.lift` of ``session`` (``kwargs`` passed on) with its log captured, for the
    stage benchmarks that read it: (seconds, log text)."""
    log = io.StringIO()
    t = time.perf_counter()
    with contextlib.redirect_stdout(log):
        pipeline.lift(session, **kwargs)
    return time.perf_counter() - t, log.getvalue()


def print_means_by_noise(rows: list[dict], keys: tuple[str, ...]) -> None:
    """The stage benchmarks' last lines: per variant ``key`` and click noise, the mean over the
    sequences of ``row[key]["mean_mm"]`` (rows carry ``noise_px``)."""
    noises = sorted({r["noise_px"] for r in rows})
    for key in keys:
        for noise in noises:
            sel = [r[key]["mean_mm"] for r in rows if r["noise_px"] == noise]
            print(f"{key:>8} noise {noise:3.1f}: mean of means {np.mean(sel):.3f} mm ({len(sel)})")


def suite_base_sessions(
    suite: str | Path, part: str, prefix: str
) -> Iterator[tuple[str, Session, np.ndarray, Path]]:
    """For every sequence of the suite's ``part`` (:func:`handanno_core.suite.read_suite`):
    ``(name, base session with its crops cached, ground truth (N, J, 3) mm, scratch folder)``, the
    base session in a new temporary folder named ``prefix...`` (closed when the caller moves on);
    runs are made from it with :func:`annotated_session` under the scratch folder."""
    from .suite import read_suite

    tmp = Path(tempfile.mkdtemp(prefix=prefix))
    for name, _part, path in read_suite(suite, part):
        base = pipeline.new_session(tmp / "base", path, overwrite=True)
        try:
            gt = base.open_sequence().ground_truth.joints_mm
            pipeline.ensure_crops(base, quiet=True)
            yield name, base, gt, tmp
        finally:
            base.close()


def copy_session(folder: Path, to: Path) -> None:
    """Copy a closed session folder to ``to`` (replaced if it exists); symlinks (the shared crop
    cache) stay symlinks."""
    copy_session_folder(folder, to, f"handanno bench (replacing {to.name})")


def stage_errors(results: dict, gt: np.ndarray, refs: np.ndarray) -> dict:
    """Error summaries of a run: ``lift`` (references), ``init``, ``final``, ``final_non_reference``."""
    non_ref = np.setdiff1d(np.arange(len(gt)), refs)
    return {
        "lift": _summary(results["lifted_mm"], gt, refs),
        "init": _summary(results["init_mm"], gt),
        "final": _summary(results["final_mm"], gt),
        "final_non_reference": _summary(results["final_mm"], gt, non_ref),
    }


def machine_description() -> str:
    import os

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    # the numeric libraries' versions and the BLAS kernels picked for this CPU: the same commit
    # under other versions or on another CPU rounds differently, and the recorded fast sequences
    # amplify that, so figures compare only within one such line
    import cv2
    import scipy

    libs = f"numpy {np.__version__}, scipy {scipy.__version__}, opencv {cv2.__version__}"
    blas = blas_description()
    libs += f", {blas}" if blas else ""
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, {libs}"


def run_bench(
    dataset: str | Path,
    *,
    format: str | None = None,
    fractions: list[float] = (0.02, 0.05, 0.10),  # type: ignore[assignment]
    strategies: list[str] = ("forest", "chain", "coverage", "uniform"),  # type: ignore[assignment]
    noise_px: float = 0.0,
    json_out: str | Path = "bench.json",
    workers: int = 2,
    aligner: str | None = None,
    gt_bones: bool = False,
    work_dir: str | Path | None = None,
    quiet: bool = False,
    review: dict | None = None,
    models: list[bool] | None = None,
) -> dict:
    """``review``: keyword arguments of :func:`handanno_core.review_loop.bench_run_review`
    (``rounds``, ``budget``, ``rankings``, ``prefill``, ...); None: no pre-fill, no review rounds.

    ``models``: hand model off/on (``[False, True]``: propagation and refinement run once per
    value on the same selection, annotation and lift, each from a copy of the session made after
    the lift; each run's JSON gains ``"model"`` and ``"kept_initialization"``, the frames
    refinement returned at their initialization). None: the session default, one run, today's
    JSON keys."""
    json_out = Path(json_out)
    json_out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(work_dir) if work_dir else Path(tempfile.mkdtemp(prefix="handanno-bench-"))
    tmp.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    base = pipeline.new_session(tmp / "base", dataset, format=format, overwrite=True)
    sequence = base.open_sequence()
    if sequence.ground_truth is None:
        raise ValueError(f"{dataset}: bench needs a dataset with ground truth")
    gt = sequence.ground_truth.joints_mm
    pipeline.ensure_crops(base, quiet=quiet, workers=workers)
    load_s = time.perf_counter() - t0
    gt_bone_lengths = sequence.skeleton.estimate_bone_lengths(gt) if gt_bones else None

    runs = []
    doc = {
        "dataset": str(dataset),
        "frames": len(sequence),
        "machine": machine_description(),
        "workers": workers,
        "aligner": aligner or base.model.settings.aligner,
        "runs": runs,
    }
    for strategy in strategies:
        for fraction in fractions:
            folder = tmp / f"{strategy}-{fraction:g}"
            session = run_session(base, folder)
            timings = {"load": round(load_s, 3)}

            t = time.perf_counter()
            pipeline.select(
                session, strategy=strategy, ref_fraction=fraction, figures=False, quiet=True
            )
            timings["select"] = round(time.perf_counter() - t, 3)
            refs = session.reference_frames
            prefilled = None
            if review and review.get("prefill"):
                from .review_loop import annotate_prefilled

                prefilled = annotate_prefilled(session, noise_px=noise_px, quiet=True)
            else:
                pipeline.annotate_from_gt(session, noise_px=noise_px, quiet=True)
            if gt_bone_lengths is not None:
                session.set_bone_lengths(gt_bone_lengths, pinned=True)

            t = time.perf_counter()
            pipeline.lift(session, workers=workers, quiet=True)
            timings["lift"] = round(time.perf_counter() - t, 3)
            session.close()
            for i, use_model in enumerate(models or [None]):
                run_folder = folder
                if i + 1 < len(
                    models or [None]
                ):  # all but the last value run in a copy of the lift
                    run_folder = folder.with_name(f"{folder.name}-model{i}")
                    copy_session(folder, run_folder)
                run = _propagate_and_refine(
                    run_folder,
                    use_model,
                    {
                        "strategy": strategy,
                        "ref_fraction_target": fraction,
                        "references": int(len(refs)),
                    },
                    dict(timings),
                    gt,
                    workers=workers,
                    aligner=aligner,
                    noise_px=noise_px,
                    gt_bones=gt_bones,
                    with_model_keys=bool(models),
                )
                runs.append(run)
                if review:
                    from .review_loop import bench_run_review

                    bench_run_review(
                        run, run_folder, review, prefilled, noise_px, workers, aligner, quiet
                    )
                json_out.write_text(json.dumps(doc, indent=2))
                if not quiet:
                    print(_row(run), flush=True)
    if not quiet:
        print()
        print(format_table(doc))
    plot_error_vs_fraction(doc, json_out.with_suffix(".png"))
    if review and review.get("rounds"):
        from .review_loop import plot_effort

        plot_effort(doc, json_out.with_name(json_out.stem + "_effort.png"))
    if not work_dir:
        shutil.rmtree(tmp, ignore_errors=True)
    return doc


def crop_coverage(session: Session, gt: np.ndarray) -> dict:
    """Evaluation: ``crops_held_pct``, the share of frames whose every ground-truth joint
    ``gt`` ``(N, J, 3)`` mm lies inside the session's crop (x, y, 8 mm from its edge: the crops
    propagation and refinement used, after :func:`handanno_core.pipeline.recrop_from_references`),
    and ``crops_missed_frames`` (the first 50 that do not); ``crops_depth_held_pct`` and
    ``crops_depth_missed_frames`` the same with the joints also within the cube's depth range
    (a frame whose hand lies in front of its cube is lost to the hand model)."""
    from .crops import joints_inside_crops
    from .session import CROPS_META_FILE

    with np.load(session.folder / CROPS_META_FILE, allow_pickle=False) as meta:
        centres = np.asarray(meta["centres_mm"])
        box = np.asarray(meta["box_cubes_mm"])
    camera, size = session.open_sequence().camera, session.model.settings.crop_size
    held = joints_inside_crops(gt, centres, camera, box, size)
    deep = joints_inside_crops(
        gt, centres, camera, box, size, cube_mm=session.model.settings.cube_mm
    )
    return {
        "crops_held_pct": round(100.0 * float(held.mean()), 2),
        "crops_missed_frames": np.flatnonzero(~held)[:50].tolist(),
        "crops_depth_held_pct": round(100.0 * float(deep.mean()), 2),
        "crops_depth_missed_frames": np.flatnonzero(~deep)[:50].tolist(),
    }


#: frame-error thresholds (mm) of :func:`hidden_bad_joints`
BAD_JOINT_MM = (20.0, 40.0)


def shown_by_depth(sequence, skeleton, poses_mm: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """``(len(frames), J)`` bool: the joints of ``poses_mm[f]`` ``(N, J, 3)`` mm that frame f's
    depth shows (:func:`handanno_core.sampling.visible_by_depth` with the skeleton's surface
    offsets), for each f of ``frames``; reads those frames' depth only."""
    from .sampling import visible_by_depth

    offsets = skeleton.surface_offsets_mm
    out = np.zeros((len(frames), skeleton.num_joints), dtype=bool)
    for i, f in enumerate(frames):
        out[i] = visible_by_depth(poses_mm[f], sequence.depth(int(f)), sequence.camera, offsets)
    return out


def hidden_bad_joints(sequence, skeleton, gt: np.ndarray, final_mm: np.ndarray) -> dict:
    """Evaluation: per threshold T of :data:`BAD_JOINT_MM`, ``joints_over_T_mm``, the (frame,
    joint) estimates ``final_mm`` ``(N, J, 3)`` more than T mm from ``gt``, and ``hidden_over_T_mm``,
    those whose true position the frame's depth does not show (off the image, or behind a nearer
    surface: :func:`handanno_core.sampling.visible_by_depth`, the simulated annotator's rule). A
    hidden joint's position is decided by the priors and its neighbours in time, not by its frame's
    depth. ``sequence``: the :class:`~handanno_core.datasets.base.DepthSequence` (its depth
    frames and camera); ``skeleton``: its joints' surface offsets. Reads only the frames with a
    joint over the lowest threshold."""
    from .evaluate import joint_errors_mm

    err = joint_errors_mm(final_mm, gt)
    with np.errstate(invalid="ignore"):
        over = err > min(BAD_JOINT_MM)
    hidden = np.zeros_like(over)
    frames = np.flatnonzero(over.any(axis=1))
    hidden[frames] = ~shown_by_depth(sequence, skeleton, gt, frames)
    out = {}
    for t in BAD_JOINT_MM:
        with np.errstate(invalid="ignore"):
            bad = err > t
        out[f"joints_over_{t:g}_mm"] = int(bad.sum())
        out[f"hidden_over_{t:g}_mm"] = int((bad & hidden).sum())
    return out


def _propagate_and_refine(
    folder: Path,
    use_model: bool | None,
    fields: dict,
    timings: dict,
    gt: np.ndarray,
    *,
    workers: int,
    aligner: str | None,
    noise_px: float,
    gt_bones: bool,
    with_model_keys: bool,
) -> dict:
    """Propagate and refine the lifted session in ``folder`` (hand model ``use_model``, stored as
    the session's setting; None: the session default) and return its run: ``fields`` + errors, ``timings`` + stage times, and
    with ``with_model_keys`` ``"model"``, ``"kept_initialization"`` and ``"recovered"`` (frames
    the hand model could not explain that refinement fitted again, :mod:`handanno_core.recover`)."""
    session = Session.open(folder)
    if use_model is not None:  # the session's setting, so that review rounds use it too
        with session.lock:
            session.model.settings.hand_model = use_model
            session.save()
    refs = session.reference_frames
    t = time.perf_counter()
    pipeline.propagate(session, workers=workers, aligner=aligner, quiet=True)
    timings["propagate"] = round(time.perf_counter() - t, 3)
    t = time.perf_counter()
    # one system, as a session of this size is refined by default; its per-frame terms on the
    # ``workers`` cores (threads: the same result as one thread)
    refined = pipeline.refine(session, quiet=True, threads=workers)
    timings["refine"] = round(time.perf_counter() - t, 3)
    results = session.load_results()
    run = {
        **fields,
        "corrections": len(session.model.corrections),
        "noise_px": noise_px,
        "bones": "ground-truth" if gt_bones else "estimated",
        **stage_errors(results, gt, refs),
        "timings_s": timings,
        "peak_rss_mb": round(peak_rss_mb(), 1),
    }
    run.update(crop_coverage(session, gt))
    run.update(
        hidden_bad_joints(session.open_sequence(), session.skeleton, gt, results["final_mm"])
    )
    if with_model_keys:
        run["model"] = bool(session.model.settings.hand_model)
        run["kept_initialization"] = len(refined.info.get("kept_initialization", []))
        run["recovered"] = len(refined.info.get("recovered", []))
    session.close()
    return run


def _label(run: dict) -> str:
    """The strategy, with ``+model`` / ``-model`` when the run says whether the model was on,
    right-aligned in its table column (10 characters, 13 with the model)."""
    if "model" not in run:
        return f"{run['strategy']:>10}"
    return f"{run['strategy'] + ('+' if run['model'] else '-') + 'model':>13}"


def _width(runs: list[dict]) -> int:
    """Width of the strategy column: 13 with model labels, else 10."""
    return 13 if any("model" in r for r in runs) else 10


def _row(run: dict) -> str:
    t = run["timings_s"]
    return (
        f"{_label(run)} {run['ref_fraction_target'] * 100:5.1f}% {run['references']:5d} "
        f"| {run['init']['mean_mm']:6.2f} {run['init']['median_mm']:6.2f} {run['init']['max_mm']:7.1f} "
        f"| {run['final']['mean_mm']:6.2f} {run['final']['median_mm']:6.2f} {run['final']['max_mm']:7.1f} "
        f"| {run['final_non_reference']['mean_mm']:6.2f} | {run['lift']['mean_mm']:5.2f} "
        f"| {t['select']:5.1f} {t['lift']:5.1f} {t['propagate']:6.1f} {t['refine']:6.1f} "
        f"| {_hidden_cell(run, 40.0):>15}"
    )


def format_table(doc: dict) -> str:
    head = (
        f"{'strategy':>{_width(doc['runs'])}} {'refs':>6} {'K':>5} | {'init: mean':>10} "
        f"{'median':>6} {'max':>7} "
        f"| {'final: mean':>11} {'median':>5} {'max':>7} | {'nonref':>6} | {'lift':>5} "
        f"| {'t_sel':>5} {'t_lift':>5} {'t_prop':>6} {'t_ref':>6} | {'>40 mm (hidden)':>15}"
    )
    return "\n".join(
        [
            f"{doc['dataset']} ({doc['frames']} frames), errors in mm, times in s; joints over "
            "40 mm off (of them hidden in their frame's depth)",
            head,
        ]
        + [_row(r) for r in doc["runs"]]
    )


def plot_error_vs_fraction(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for strategy in dict.fromkeys(_label(r).strip() for r in doc["runs"]):
        rows = sorted(
            (r for r in doc["runs"] if _label(r).strip() == strategy),
            key=lambda r: r["ref_fraction_target"],
        )
        x = [100 * r["references"] / doc["frames"] for r in rows]
        ax.plot(x, [r["final"]["mean_mm"] for r in rows], "o-", label=f"{strategy} final")
        ax.plot(x, [r["init"]["mean_mm"] for r in rows], "x--", alpha=0.6, label=f"{strategy} init")
    ax.set_xlabel("reference frames (% of sequence)")
    ax.set_ylabel("mean 3D joint error (mm)")
    ax.set_title(f"{Path(doc['dataset']).name}: error vs. reference fraction")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ---------------------------------------------------------------------------- several datasets
def expand_datasets(paths: list[str | Path], part: str | None = None) -> list[dict]:
    """The datasets a bench call names: each path is a dataset, or a suite folder (``suite.json``,
    see :mod:`handanno_core.suite`) that stands for its ``part`` (tune, report or all; required for
    a suite folder, so nobody reports on the tune part or tunes on the report part by default).

    Returns ``[{"name", "part", "path"}]`` (``part`` None for a plain dataset), names unique.
    """
    from .suite import is_suite, read_suite

    out: list[dict] = []
    for path in paths:
        if is_suite(path):
            if part is None:
                raise ValueError(f"{path}: a suite folder needs --part tune, report or all")
            out += [{"name": n, "part": p, "path": str(f)} for n, p, f in read_suite(path, part)]
        else:
            out.append({"name": Path(path).name, "part": None, "path": str(path)})
    seen: dict[str, int] = {}
    for d in out:
        seen[d["name"]] = seen.get(d["name"], 0) + 1
        if seen[d["name"]] > 1:
            d["name"] = f"{d['name']}-{seen[d['name']]}"
    return out


def summarize_datasets(docs: list[dict]) -> list[dict]:
    """Per (strategy, fraction, noise, bones): the mean over datasets of each dataset's mean error
    and the worst max (mm), for lift, init, final and final_non_reference; ``datasets`` counts
    the datasets that ran that configuration; ``refine_worse`` lists those where final > init;
    ``joints_over_T_mm`` / ``hidden_over_T_mm`` summed (:func:`hidden_bad_joints`). Runs with and
    without the hand model (``"model"``) are separate rows."""
    groups: dict[tuple, list[tuple[str, dict]]] = {}
    for doc in docs:
        for run in doc["runs"]:
            key = (
                run["strategy"],
                run["ref_fraction_target"],
                run["noise_px"],
                run["bones"],
                run.get("model"),
            )
            groups.setdefault(key, []).append((doc.get("name", doc["dataset"]), run))
    rows = []
    for (strategy, fraction, noise, bones, model), runs in groups.items():
        row = {
            "strategy": strategy,
            "ref_fraction_target": fraction,
            "noise_px": noise,
            "bones": bones,
            "datasets": len(runs),
        }
        if model is not None:
            row["model"] = model
        for stage in ("lift", "init", "final", "final_non_reference"):
            row[stage] = {
                "mean_of_means_mm": round(
                    float(np.mean([r[stage]["mean_mm"] for _, r in runs])), 3
                ),
                "worst_mean_mm": round(float(max(r[stage]["mean_mm"] for _, r in runs)), 3),
                "worst_max_mm": round(float(max(r[stage]["max_mm"] for _, r in runs)), 3),
            }
        row["refine_worse"] = [
            name for name, r in runs if r["final"]["mean_mm"] > r["init"]["mean_mm"]
        ]
        for t in BAD_JOINT_MM:  # runs from before these keys count nothing
            for key in (f"joints_over_{t:g}_mm", f"hidden_over_{t:g}_mm"):
                row[key] = int(sum(r.get(key, 0) for _, r in runs))
        row["timings_s"] = {
            k: round(float(sum(r["timings_s"].get(k, 0.0) for _, r in runs)), 3)
            for k in runs[0][1]["timings_s"]
        }
        rows.append(row)
    return rows


def _hidden_cell(row: dict, t: float) -> str:
    """``"n (m)"``: joints over ``t`` mm, of them hidden in the depth (:func:`hidden_bad_joints`)."""
    n = row.get(f"joints_over_{t:g}_mm")
    return "-" if n is None else f"{n} ({row[f'hidden_over_{t:g}_mm']})"


def format_summary(doc: dict) -> str:
    """The suite summary table of :func:`run_bench_datasets`' JSON."""
    head = (
        f"{'strategy':>{_width(doc['summary'])}} {'refs':>6} {'n':>3} | {'lift':>5} | {'init':>6} "
        f"| {'final: mean':>11} "
        f"{'worst':>6} {'max':>7} | {'nonref':>6} | {'>40 mm (hidden)':>15} | refine worse on"
    )
    lines = [
        f"suite summary over {len(doc['datasets'])} datasets ({doc['frames']} frames): "
        "mean of per-dataset means, worst per-dataset mean, worst max (mm); joints over 40 mm off "
        "(of them hidden in their frame's depth)",
        head,
    ]
    for r in doc["summary"]:
        lines.append(
            f"{_label(r)} {r['ref_fraction_target'] * 100:5.1f}% {r['datasets']:3d} "
            f"| {r['lift']['mean_of_means_mm']:5.2f} | {r['init']['mean_of_means_mm']:6.2f} "
            f"| {r['final']['mean_of_means_mm']:11.2f} {r['final']['worst_mean_mm']:6.2f} "
            f"{r['final']['worst_max_mm']:7.1f} | {r['final_non_reference']['mean_of_means_mm']:6.2f} "
            f"| {_hidden_cell(r, 40.0):>15} | {', '.join(r['refine_worse']) or '-'}"
        )
    return "\n".join(lines)


def run_bench_datasets(
    paths: list[str | Path],
    *,
    part: str | None = None,
    json_out: str | Path = "bench.json",
    quiet: bool = False,
    **kwargs,
) -> dict:
    """``handanno bench`` over several datasets or suite folders (:func:`expand_datasets`).

    One dataset: exactly :func:`run_bench` (today's JSON). Several: :func:`run_bench` per dataset
    (its JSON and plot under ``<json_out stem>.datasets/<name>.json``, its table printed), then a
    suite summary (:func:`summarize_datasets`); ``json_out`` gets ``{"datasets": [each dataset's
    JSON plus name, part, 1-minute load average before and after], "summary": [...], "frames",
    "machine", "part"}``, rewritten after every dataset. ``kwargs`` go to :func:`run_bench`.
    """
    import os

    datasets = expand_datasets(paths, part)
    if len(datasets) == 1 and datasets[0]["part"] is None:
        return run_bench(datasets[0]["path"], json_out=json_out, quiet=quiet, **kwargs)
    json_out = Path(json_out)
    json_out.parent.mkdir(parents=True, exist_ok=True)
    folder = json_out.with_name(json_out.stem + ".datasets")
    folder.mkdir(parents=True, exist_ok=True)
    suite = {
        "part": part,
        "machine": machine_description(),
        "frames": 0,
        "datasets": [],
        "summary": [],
    }
    for d in datasets:
        load_before = os.getloadavg()[0]
        kw = dict(kwargs)
        if kw.get("work_dir"):  # one session folder per dataset, or each would overwrite the last
            kw["work_dir"] = Path(kw["work_dir"]) / d["name"]
        doc = run_bench(d["path"], json_out=folder / f"{d['name']}.json", quiet=quiet, **kw)
        entry = {"name": d["name"], "part": d["part"], **doc}
        entry["load_avg_1m"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
        suite["datasets"].append(entry)
        suite["frames"] += doc["frames"]
        suite["summary"] = summarize_datasets(suite["datasets"])
        json_out.write_text(json.dumps(suite, indent=2))
    if not quiet:
        print()
        print(format_summary(suite))
    return suite
