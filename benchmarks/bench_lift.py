"""Lift benchmark: speed per frame and accuracy on the synthetic sequence's reference frames.

Usage::

    .venv/bin/python benchmarks/bench_lift.py [--seq /tmp/synth3040] [--step 20] [--noise 0,2]
        [--gt-bones] [--workers 1] [--json benchmarks/results/lift.json]

The sequence is generated (``synth.generate_sequence(seq, frames=3040, seed=0)``) if missing.
References are every ``step``-th frame (5 % at step 20), annotated by the simulated annotator
(exact or noisy 2D, visibility, depth order). Bone lengths are estimated jointly by
``lift_references``; ``--gt-bones`` additionally runs with the ground-truth bone lengths, for
comparison only. Speed is the time of ``lift_frame`` per reference (cold start from the
observed depth) and the warm start used while a joint is dragged (previous solution, one joint
moved by 3 px). BLAS threading is limited inside ``lift_frame`` (``blas.single_blas_thread``), so
no environment variable is needed. The machine load (1-minute load average) is recorded.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from handanno_core.datasets import open_sequence
from handanno_core.evaluate import error_summary
from handanno_core.lift import lift_frame, lift_references
from handanno_core.synth import generate_sequence, simulate_annotations


def _run(seq, frames, noise, bones, workers, label):
    gt = seq.ground_truth.joints_mm
    anns = simulate_annotations(seq, frames, noise_px=noise, seed=0)
    t0 = time.perf_counter()
    lifted = lift_references(
        anns,
        seq.depth,
        seq.camera,
        seq.skeleton,
        bone_lengths_mm=bones,
        pin_bone_lengths=bones is not None,
        workers=workers,
    )
    elapsed = time.perf_counter() - t0
    pred = np.stack([lifted.joints_mm[f] for f in frames])
    summ = error_summary(pred, gt[frames])
    true_bones = seq.skeleton.estimate_bone_lengths(gt)
    bone_err = np.abs(lifted.bone_lengths_mm - true_bones)
    res = [lifted.results[f] for f in frames]
    out = {
        "bones": label,
        "noise_px": noise,
        "references": len(frames),
        **{k: float(v) for k, v in summ.items()},
        "bone_abs_error_mm": {"mean": float(bone_err.mean()), "max": float(bone_err.max())},
        "bone_rounds": len(lifted.bone_history_mm) - 1,
        "converged_fraction": float(np.mean([r.converged for r in res])),
        "max_bone_violation_mm": float(max(r.bone_error_mm for r in res)),
        "wall_s": elapsed,
        "workers": workers,
    }
    print(
        f"{label:9s} noise {noise:.1f} px: mean {summ['mean_mm']:.2f} median {summ['median_mm']:.2f} "
        f"max {summ['max_mm']:.2f} mm | bones |err| mean {bone_err.mean():.2f} max "
        f"{bone_err.max():.2f} mm, rounds {out['bone_rounds']} | converged "
        f"{out['converged_fraction']:.3f} | {elapsed:.1f} s"
    )
    return out, lifted, anns


def _speed(seq, frames, anns, bones):
    cold, warm, its, wits = [], [], [], []
    for f in frames:
        depth = seq.depth(f)
        r = lift_frame(anns[f], depth, seq.camera, seq.skeleton, bones)
        cold.append(r.time_s)
        its.append(r.iterations)
        dragged = anns[f].copy()
        j = int(np.flatnonzero(dragged.has_2d)[len(dragged.uv_px) // 2 % dragged.has_2d.sum()])
        dragged.uv_px[j] += 3.0
        r2 = lift_frame(dragged, depth, seq.camera, seq.skeleton, bones, init_mm=r.joints_mm)
        warm.append(r2.time_s)
        wits.append(r2.iterations)
    return {
        "cold_median_ms": 1000 * float(np.median(cold)),
        "cold_p90_ms": 1000 * float(np.percentile(cold, 90)),
        "warm_median_ms": 1000 * float(np.median(warm)),
        "warm_p90_ms": 1000 * float(np.percentile(warm, 90)),
        "median_iterations": float(np.median(its)),
        "warm_median_iterations": float(np.median(wits)),
        "frames": len(frames),
        "load_average_1min": os.getloadavg()[0],
        "cpu_count": os.cpu_count(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", default="/tmp/synth3040")
    ap.add_argument("--frames", type=int, default=3040)
    ap.add_argument("--step", type=int, default=20)
    ap.add_argument("--noise", default="0,2")
    ap.add_argument("--gt-bones", action="store_true", help="also run with ground-truth bones")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--speed-frames", type=int, default=60)
    ap.add_argument("--json", default=str(Path(__file__).parent / "results" / "lift.json"))
    args = ap.parse_args()

    if not (Path(args.seq) / "joint.txt").exists():
        generate_sequence(args.seq, frames=args.frames, seed=0)
    seq = open_sequence(args.seq)
    frames = np.arange(0, len(seq), args.step)
    gt = seq.ground_truth.joints_mm
    gt_bones = seq.skeleton.estimate_bone_lengths(gt)
    runs = []
    lifted0 = anns0 = None
    for noise in [float(x) for x in args.noise.split(",")]:
        out, lifted, anns = _run(seq, frames, noise, None, args.workers, "estimated")
        runs.append(out)
        if lifted0 is None:
            lifted0, anns0 = lifted, anns
        if args.gt_bones:
            runs.append(_run(seq, frames, noise, gt_bones, args.workers, "gt_bones")[0])
    speed_frames = frames[:: max(1, len(frames) // args.speed_frames)][: args.speed_frames]
    speed = _speed(seq, speed_frames, anns0, lifted0.bone_lengths_mm)
    print(
        f"speed (1 process, load avg {speed['load_average_1min']:.1f} on {speed['cpu_count']} cores): "
        f"cold median {speed['cold_median_ms']:.1f} ms (p90 {speed['cold_p90_ms']:.1f}), "
        f"warm median {speed['warm_median_ms']:.1f} ms (p90 {speed['warm_p90_ms']:.1f}), "
        f"{speed['median_iterations']:.0f} SLSQP iterations"
    )
    result = {
        "dataset": str(args.seq),
        "frames": len(seq),
        "step": args.step,
        "runs": runs,
        "speed": speed,
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
