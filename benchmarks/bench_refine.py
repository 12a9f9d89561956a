"""Benchmark of handanno_core.refine on a synthetic sequence.

Initializations: ``perturbed`` (ground truth plus propagation-like errors: smooth offsets correlated
in time within segments, larger at fingertips, outlier frames with 20-40 mm errors, bone-length
violations; references get small lift-like errors) or ``propagated`` (the real pipeline: lift +
propagate, when those modules are available). References every ``--ref-step``-th frame with exact
simulated 2D annotations. Crop centres come from ``crops.locate_hands`` (no ground truth).

    .venv/bin/python benchmarks/bench_refine.py [--seq /tmp/synth3040] [--init perturbed|propagated]

Prints error before/after, time, peak RSS; writes benchmarks/results/refine.json.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

from handanno_core.crops import compute_crops, crop_boxes, locate_hands
from handanno_core.datasets import open_sequence
from handanno_core.evaluate import error_summary
from handanno_core.refine import RefineWeights, refine
from handanno_core.synth import generate_sequence, simulate_annotations


def perturb(
    gt: np.ndarray, refs: np.ndarray, breaks: list[int], skeleton, seed: int = 0
) -> np.ndarray:
    """Propagation-like errors on ground truth (N,J,3) mm (see the module docstring)."""
    rng = np.random.default_rng(seed)
    n, j, _ = gt.shape
    starts = [0, *sorted(b for b in breaks if 0 < b < n), n]
    noise = rng.normal(size=(n, j, 3))
    out = np.empty_like(noise)
    for a, b in zip(starts[:-1], starts[1:], strict=False):
        out[a:b] = gaussian_filter1d(noise[a:b], sigma=8.0, axis=0, mode="nearest")
    out /= out.std()
    scale = np.full(j, 5.0)
    scale[list(skeleton.fingertips)] = 9.0
    # distal joints a bit more than proximal ones
    depth = np.zeros(j)
    for k in range(j):
        q = k
        while skeleton.parent_array[q] >= 0:
            depth[k] += 1
            q = skeleton.parent_array[q]
    scale *= 0.7 + 0.15 * depth
    err = out * scale[None, :, None]
    # error grows with the distance from the nearest reference (propagation drift)
    dist = np.min(np.abs(np.arange(n)[:, None] - refs[None, :]), axis=1)
    err *= np.clip(dist / 5.0, 0.3, 1.0)[:, None, None]
    # outlier frames: a few joints (or the whole hand) off by 20-40 mm
    out_frames = rng.choice(np.setdiff1d(np.arange(n), refs), size=max(1, n // 50), replace=False)
    for f in out_frames:
        joints = rng.choice(j, size=rng.integers(1, j + 1), replace=False)
        d = rng.normal(size=3)
        err[f, joints] += d / np.linalg.norm(d) * rng.uniform(20, 40)
    # small lift errors at references
    err[refs] = rng.normal(0, 1.5, size=(len(refs), j, 3))
    return gt + err


def closest_in_time(n: int, refs: np.ndarray, breaks: list[int]) -> np.ndarray:
    seg = np.searchsorted(np.asarray(sorted(breaks)), np.arange(n), side="right")
    ref_seg = seg[refs]
    out = np.empty(n, dtype=np.int64)
    for i in range(n):
        cand = refs[ref_seg == seg[i]]
        if len(cand) == 0:
            cand = refs
        out[i] = cand[np.argmin(np.abs(cand - i))]
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seq", default="/tmp/synth3040")
    ap.add_argument("--frames", type=int, default=3040)
    ap.add_argument("--ref-step", type=int, default=20)
    ap.add_argument("--init", default="perturbed", choices=["perturbed", "file"])
    ap.add_argument("--init-file", default=None, help="npz: init_mm (N,J,3), refs, closest, bones")
    ap.add_argument("--iterations", type=int, default=25)
    ap.add_argument("--json", default="benchmarks/results/refine.json")
    ap.add_argument("--weights", default="{}", help="JSON overrides of RefineWeights")
    args = ap.parse_args()

    seq_path = Path(args.seq)
    if not (seq_path / "joint.txt").exists():
        generate_sequence(seq_path, frames=args.frames, seed=0)
    seq = open_sequence(seq_path)
    n = len(seq)
    cache = seq_path.parent / (seq_path.name + ".refine_cache")
    cache.mkdir(exist_ok=True)
    if (cache / "centres.npy").exists():
        centres = np.load(cache / "centres.npy")
    else:
        centres = locate_hands(seq)
        np.save(cache / "centres.npy", centres)
    crops_path = cache / "crops.npy"
    crops = (
        np.load(crops_path, mmap_mode="r")
        if crops_path.exists()
        else compute_crops(seq, centres, crops_path)
    )
    boxes = crop_boxes(centres, seq.camera)
    gt = seq.ground_truth.joints_mm
    skel = seq.skeleton
    breaks = list(seq.sequence_breaks)
    refs = np.arange(0, n, args.ref_step)
    if args.init == "perturbed":
        init = perturb(gt, refs, breaks, skel)
        bones = skel.estimate_bone_lengths(init[refs])
        closest = closest_in_time(n, refs, breaks)
    else:
        # npz from the real pipeline: init_mm, refs, closest (root reference of the forest), bones
        data = np.load(args.init_file)
        init = data["init_mm"]
        refs = np.asarray(data["refs"])
        bones = np.asarray(data["bones"])
        closest = np.asarray(data["closest"])
        for f in refs:  # the references' own entries are their lifted poses
            if not np.all(np.isfinite(init[f])) and "lifted_mm" in data.files:
                init[f] = data["lifted_mm"][f]
    anns = simulate_annotations(seq, refs)
    weights = RefineWeights(**json.loads(args.weights))

    hist = []
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    cpu0 = r0.ru_utime + r0.ru_stime
    t0 = time.perf_counter()
    res = refine(
        init,
        crops=crops,
        boxes=boxes,
        centres_mm=centres,
        camera=seq.camera,
        skeleton=skel,
        bone_lengths_mm=bones,
        reference_frames=refs,
        reference_annotations=anns,
        closest_reference=closest,
        sequence_breaks=breaks,
        weights=weights,
        iterations=args.iterations,
        progress=lambda it, e: hist.append((it, e, time.perf_counter() - t0)),
    )
    elapsed = time.perf_counter() - t0
    cpu = resource.getrusage(resource.RUSAGE_SELF)
    cpu_s = cpu.ru_utime + cpu.ru_stime - cpu0
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    before = error_summary(init, gt)
    after = error_summary(res.joints_mm, gt)
    nonref = np.setdiff1d(np.arange(n), refs)
    out = {
        "sequence": str(seq_path),
        "frames": n,
        "references": len(refs),
        "init": args.init,
        "weights": weights.__dict__,
        "before": before,
        "after": after,
        "after_non_reference": error_summary(res.joints_mm, gt, frames=nonref),
        "time_s": elapsed,
        "cpu_s": cpu_s,
        "iterations": res.iterations,
        "peak_rss_mb": rss_mb,
        "bone_violation_max_mm": res.bone_violation_max_mm,
        "energy_first_last": [res.energy_history[0], res.energy_history[-1]],
        "terms": res.terms,
        "load_avg": list(np.round(np.loadtxt("/proc/loadavg", usecols=(0, 1, 2)), 2)),
    }
    for it, e, t in hist:
        print(f"  iter {it:3d}  E={e:14.1f}  t={t:6.1f}s")
    print(json.dumps(out, indent=1, default=float))
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()
