"""Propagation benchmark: accuracy of the propagated initialization, speed and memory per aligner.

Pipeline without ground truth except for scoring and the simulated annotator: hand centres from
``locate_hands``, crops from ``compute_crops``, references by ``select_references`` (default
strategy, 5 % budget), references lifted with ``lift_references`` from simulated exact 2D
annotations (``--lift gt`` uses ground-truth joints instead, and says so in the JSON), then
``propagate`` with each aligner, scored against ground truth.

    .venv/bin/python benchmarks/bench_propagate.py [--seq /tmp/synth3040] [--ref-fraction 0.05]
        [--aligners dis,sift,ncc] [--workers 1] [--lift lift|gt] [--json benchmarks/results/propagate.json]

Also measures: per-frame time of each aligner's step in one process (ms/frame/core), the wall time
of a full run with ``--workers`` processes, peak RSS, and the memory growth with N (propagating
the first N frames' forests for growing N) to show it scales with N x J and not N x J x crop.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handanno_core.crops import compute_crops, crop_boxes, locate_hands  # noqa: E402
from handanno_core.datasets import open_sequence  # noqa: E402
from handanno_core.datasets.base import BadFrameReport  # noqa: E402
from handanno_core.propagate import propagate  # noqa: E402


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def summary(pred: np.ndarray, gt: np.ndarray, frames: np.ndarray | None = None) -> dict:
    try:
        from handanno_core.evaluate import error_summary

        return {
            k: (float(v) if isinstance(v, int | float | np.floating) else v)
            for k, v in error_summary(pred, gt, frames=frames).items()
        }
    except ImportError:
        e = np.linalg.norm(pred - gt, axis=-1)
        if frames is not None:
            e = e[frames]
        return {
            "mean_mm": float(np.nanmean(e)),
            "median_mm": float(np.nanmedian(e)),
            "max_mm": float(np.nanmax(e)),
            "missing": int(np.isnan(e).sum()),
        }


def prepare(
    seq_path: str, ref_fraction: float, lift_mode: str, cache_dir: Path, strategy: str | None
):
    """Sequence, crops, boxes, centres, selection parent, reference joints, bone lengths."""
    seq = open_sequence(seq_path)
    n = len(seq)
    cache_dir.mkdir(parents=True, exist_ok=True)
    tag = f"{Path(seq_path).name}_{n}"
    cpath = cache_dir / f"centres_{tag}.npy"
    crops_path = cache_dir / f"crops_{tag}.npy"
    t = time.perf_counter()
    if cpath.exists() and crops_path.exists():
        centres = np.load(cpath)
        crops = np.load(crops_path, mmap_mode="r")
    else:
        report = BadFrameReport()
        centres = locate_hands(seq, report=report)
        crops = compute_crops(seq, centres, crops_path, report=report)
        np.save(cpath, centres)
    boxes = crop_boxes(centres, seq.camera)
    t_crops = time.perf_counter() - t

    from handanno_core.descriptors import compute_descriptors
    from handanno_core.select import DEFAULT_STRATEGY, select_references

    strategy = strategy or DEFAULT_STRATEGY
    t = time.perf_counter()
    desc = compute_descriptors(crops)
    sel = select_references(
        desc, strategy, ref_fraction=ref_fraction, sequence_breaks=seq.sequence_breaks
    )
    t_select = time.perf_counter() - t
    refs = [int(f) for f in sel.reference_frames]

    gt = seq.ground_truth.joints_mm
    t = time.perf_counter()
    lift_cache = cache_dir / f"lift_{tag}_{strategy}_{ref_fraction}_{lift_mode}.npz"
    if lift_cache.exists():
        z = np.load(lift_cache)
        if list(z["refs"]) == refs:
            ref_joints = {f: z["joints"][i] for i, f in enumerate(refs)}
            bones = z["bones"]
            bones_src = str(z["bones_src"])
            lift_mode = "cached"
    if lift_mode == "cached":
        pass
    elif lift_mode == "gt":
        ref_joints = {f: gt[f].copy() for f in refs}
        bones = seq.skeleton.estimate_bone_lengths(gt[refs])
        bones_src = "ground truth (references)"
    else:
        from handanno_core.lift import lift_references
        from handanno_core.synth import simulate_annotations

        anns = simulate_annotations(seq, refs, noise_px=0.0, seed=0)
        lifted = lift_references(anns, seq.depth, seq.camera, seq.skeleton, workers=1)
        ref_joints = {int(f): np.asarray(v) for f, v in lifted.joints_mm.items()}
        bones = np.asarray(lifted.bone_lengths_mm)
        bones_src = "estimated by lift_references"
    if lift_mode != "cached":
        np.savez(
            lift_cache,
            refs=np.asarray(refs),
            joints=np.stack([ref_joints[f] for f in refs]),
            bones=bones,
            bones_src=bones_src,
        )
    t_lift = time.perf_counter() - t
    return dict(
        seq=seq,
        crops=crops,
        boxes=boxes,
        centres=centres,
        parent=sel.parent,
        strategy=strategy,
        refs=refs,
        ref_joints=ref_joints,
        bones=bones,
        bones_src=bones_src,
        gt=gt,
        timings={"crops_s": t_crops, "select_s": t_select, "lift_s": t_lift},
    )


def bfs_sample(p: dict, frames: int) -> np.ndarray:
    """The first ``frames`` frames of the forests, breadth-first (every parent included)."""
    from handanno_core.propagate import propagation_order

    levels = propagation_order(p["parent"], p["refs"])
    # interleave the references' subtrees so the sample spans the whole sequence
    order = []
    depth = 0
    while len(order) < frames and any(depth < len(x) for x in levels):
        for x in levels:
            if depth < len(x):
                order.append(int(x[depth]))
        depth += 1
    order = np.asarray(order[:frames])
    # keep it closed under parents
    keep = set(order.tolist()) | set(p["refs"])
    order = np.asarray([f for f in order if p["parent"][f] in keep])
    return np.sort(order)


def run_once(p: dict, aligner: str, frames=None, workers: int = 1):
    return propagate(
        p["parent"], p["ref_joints"], p["crops"], p["boxes"], p["centres"], p["seq"].depth,
        p["seq"].camera, p["seq"].skeleton, p["bones"], aligner=aligner, frames=frames,
        workers=workers,
    )  # fmt: skip


def timed(p: dict, aligner: str, frames) -> tuple[float, float]:
    """(wall ms, CPU ms) per frame of a single-process run over ``frames``."""
    t, c = time.perf_counter(), time.process_time()
    run_once(p, aligner, frames)
    return (
        1000.0 * (time.perf_counter() - t) / len(frames),
        1000.0 * (time.process_time() - c) / len(frames),
    )


def memory_scaling(p: dict, aligner: str, sizes: list[int]) -> list[dict]:
    """Peak traced Python/numpy memory of propagating N frames (crops are memory-mapped)."""
    import tracemalloc

    out = []
    for n in sizes:
        frames = bfs_sample(p, n)
        tracemalloc.start()
        run_once(p, aligner, frames)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        out.append({"frames": int(len(frames)), "peak_traced_mb": peak / 2**20})
        print(f"memory: {len(frames)} frames -> peak {peak / 2**20:.1f} MB")
    return out


def score_vs_error(res, pred, gt, frames) -> float | None:
    """Spearman correlation between the frame score and the frame's mean error (want < 0)."""
    err = np.linalg.norm(pred[frames] - gt[frames], axis=-1).mean(axis=1)
    score = res.frame_score[frames]
    ok = np.isfinite(err) & np.isfinite(score)
    if ok.sum() <= 3:
        return None
    ra = np.argsort(np.argsort(err[ok]))
    rb = np.argsort(np.argsort(score[ok]))
    return float(np.corrcoef(ra, rb)[0, 1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", default="/tmp/synth3040")
    ap.add_argument("--ref-fraction", type=float, default=0.05)
    ap.add_argument("--strategy", default=None)
    ap.add_argument("--aligners", default="dis,sift,ncc")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--lift", choices=("lift", "gt"), default="lift")
    ap.add_argument("--full-aligners", default="dis,ncc", help="aligners run on the full sequence")
    ap.add_argument(
        "--sample-frames", type=int, default=300, help="BFS sample scored for every aligner"
    )
    ap.add_argument("--timing-frames", type=int, default=100, help="frames timed in one process")
    ap.add_argument(
        "--no-memory", dest="memory", action="store_false", help="skip the memory scaling"
    )
    ap.add_argument("--cache", default="/tmp/handanno_bench_propagate")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/propagate.json"))
    args = ap.parse_args()

    if not Path(args.seq).exists():
        from handanno_core.synth import generate_sequence

        generate_sequence(args.seq, frames=3040, seed=0)
    p = prepare(args.seq, args.ref_fraction, args.lift, Path(args.cache), args.strategy)
    n = len(p["parent"])
    gt = p["gt"]
    nonref = np.flatnonzero(p["parent"] >= 0)
    ref_pred = np.full_like(gt, np.nan)
    for f, v in p["ref_joints"].items():
        ref_pred[f] = v
    doc = {
        "dataset": args.seq,
        "frames": n,
        "strategy": p["strategy"],
        "ref_fraction": args.ref_fraction,
        "references": len(p["refs"]),
        "reference_joints": "lifted from simulated exact 2D"
        if args.lift == "lift"
        else "ground truth",
        "bones": p["bones_src"],
        "lift": summary(ref_pred, gt, np.asarray(p["refs"])),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores "
        "(shared with other jobs: timings are under load)",
        "setup_timings_s": p["timings"],
        "aligners": {},
    }
    print(f"{n} frames, {len(p['refs'])} references ({p['strategy']}), lift: {doc['lift']}")
    full = set(args.full_aligners.split(","))
    sample = bfs_sample(p, args.sample_frames)
    timing_sample = sample[: args.timing_frames]
    doc["sample_frames"] = int(len(sample))
    for name in args.aligners.split(","):
        row: dict = {}
        wall_ms, cpu_ms = timed(p, name, timing_sample)
        row["ms_per_frame_wall_1proc"] = wall_ms
        row["ms_per_frame_cpu_1proc"] = cpu_ms
        res = run_once(p, name, sample)
        pred = res.joints_mm.copy()
        row["sample_non_reference"] = summary(pred, gt, sample)
        row["sample_spearman_score_vs_error"] = score_vs_error(res, pred, gt, sample)
        if name in full:
            t = time.perf_counter()
            res = run_once(p, name, None, workers=args.workers)
            row["full_wall_s"] = time.perf_counter() - t
            row["full_workers"] = args.workers
            pred = res.joints_mm.copy()
            for f, v in p["ref_joints"].items():
                pred[f] = v
            row["skipped"] = len(res.skipped)
            row["init_non_reference"] = summary(pred, gt, nonref)
            row["init_all"] = summary(pred, gt)
            row["spearman_score_vs_error"] = score_vs_error(res, pred, gt, nonref)
        doc["aligners"][name] = row
        print(name, json.dumps(row, indent=None))
    if args.memory:
        sizes = [250, 1000, len(nonref)]
        doc["memory_scaling_dis"] = memory_scaling(p, "dis", sizes)
    doc["peak_rss_mb"] = peak_rss_mb()
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(doc, indent=1))
    print("wrote", args.json)


if __name__ == "__main__":
    main()
