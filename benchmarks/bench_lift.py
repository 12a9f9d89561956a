"""Lift benchmark: speed per frame and accuracy on the reference frames of one or more sequences.

Usage::

    .venv/bin/python benchmarks/bench_lift.py [--seq /tmp/synth3040[,fpha:Subject_2:/tmp/fpha2]]
        [--step 20] [--noise 0,2] [--gt-bones] [--workers 1] [--lift-kw w_angle=1.0]
        [--json benchmarks/results/lift.json]
    .venv/bin/python benchmarks/bench_lift.py --suite /tmp/suite --part tune [--ref-fraction 0.05]
        [--noise 0,2] [--lift-kw incline_surface=false] --json OUT

``--suite``: every sequence of that part of a benchmark suite folder (``handanno suite``), with
the references of ``uniform`` selection at ``--ref-fraction`` over all frames (the pipeline's
``select`` also skips frames without a usable crop, so its reference set can differ by a few
frames); only select + simulated annotation + lift run, in seconds per sequence. Each run adds
diagnostics: error of visible / occluded joints, depth and image-plane parts of the error, the
signed depth error, per-joint means and the estimated bones' error.

A plain ``--seq`` folder is generated (``synth.generate_sequence(seq, frames=3040, seed=0)``) if
missing. ``fpha:<subject>:<folder>`` renders real recorded hand motion instead (FPHA, the
``real-motion`` README in shared/data): the first ``--fpha-sequences`` sequences of ``<subject>``
(sorted by action and number), every ``--fpha-every``-th frame, with the synthetic renderer
(:func:`render_fpha_sequence`: per-sequence bone lengths, palm frame from the wrist and MCPs, each
sequence centred 380 mm in front of the MSRA camera), written in the MSRA layout. The lift's angle
ranges are learned on FPHA ``Subject_1`` only (benchmarks/learn_angle_ranges.py), so
``Subject_2`` is motion the lift was not tuned on. Run the script with ``PYTHONPATH`` set to an
older checkout to measure that version on the same sequences ("before").
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
import warnings
from pathlib import Path

import numpy as np

from handanno_core.datasets import open_sequence
from handanno_core.evaluate import error_summary
from handanno_core.lift import lift_frame, lift_references
from handanno_core.select import select_references
from handanno_core.suite import read_suite
from handanno_core.synth import (
    HandModel,
    generate_sequence,
    render_frame,
    simulate_annotations,
)

REPO = Path(__file__).resolve().parents[1]
FPHA = next(
    (
        p
        for p in (
            REPO.parent / "shared/data/real-motion/fpha",
            Path("/work/shared/data/real-motion/fpha"),
        )
        if p.is_dir()
    ),
    REPO.parent / "shared/data/real-motion/fpha",
)
#: FPHA joint order -> MSRA-21 (as handanno_core.skeleton.FPHA_TO_MSRA21; repeated here so the
#: script also runs against older checkouts)
_FPHA_TO_MSRA21 = (0, 2, 9, 10, 11, 3, 12, 13, 14, 4, 15, 16, 17, 5, 18, 19, 20, 1, 6, 7, 8)


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def render_fpha_sequence(
    out: Path, subject: str, sequences: int, every: int, seed: int = 0
) -> Path:
    """Render FPHA joint trajectories (MSRA-21 order) as an MSRA-layout sequence in ``out``."""
    from handanno_core.camera import MSRA_CAMERA
    from handanno_core.datasets.msra import write_msra_frame, write_msra_joints
    from handanno_core.skeleton import MSRA21

    files = [f for f in sorted((FPHA / subject).glob("*/*/skeleton.txt")) if f.stat().st_size]
    step = max(1, len(files) // sequences)
    chosen = files[::step][:sequences]
    out.mkdir(parents=True, exist_ok=True)
    all_joints, k = [], 0
    for f in chosen:
        a = np.loadtxt(f, ndmin=2)[::every, 1:].reshape(-1, 21, 3)[:, _FPHA_TO_MSRA21]
        lengths = np.median(MSRA21.bone_lengths(a), axis=0)
        y = _unit(a[:, 5] - a[:, 0])
        x = _unit(a[:, 1] - a[:, 13])
        x = _unit(x - np.sum(x * y, axis=-1, keepdims=True) * y)
        z = np.cross(x, y)
        rot = np.stack([x, y, z], axis=-1)  # (N, 3, 3) local -> camera
        local = np.einsum("nji,nkj->nki", rot, a - a[:, :1])
        base = np.median(local, axis=0)
        centre = np.median(a[:, [0, 5]].mean(axis=1), axis=0)
        joints = a - centre + np.array([0.0, 0.0, 380.0])
        model = HandModel(
            bone_lengths_mm=lengths,
            local_base=base,
            palm_centre=np.array([0.0, 0.5 * base[[1, 5, 9, 13], 1].mean(), 0.0]),
            palm_normal=np.array([0.0, 0.0, 1.0]),
        )
        for i in range(len(joints)):
            depth = render_frame(model, joints[i], rot[i], MSRA_CAMERA, noise_seed=(seed, k))
            write_msra_frame(str(out / f"{k:06d}_depth.bin"), depth)
            k += 1
        all_joints.append(joints)
    MSRA_CAMERA.to_json(out / "camera.json")
    write_msra_joints(out / "joint.txt", np.concatenate(all_joints))
    (out / "fpha.json").write_text(
        json.dumps({"subject": subject, "every": every, "files": [str(f) for f in chosen]})
    )
    return out


def _diagnostics(pred, gt, anns, frames, skeleton) -> dict:
    """Where the error is: visible vs occluded joints, depth vs image plane, per joint (mm)."""
    err = np.linalg.norm(pred - gt, axis=-1)  # (F, J)
    vis = np.stack([anns[f].visible & anns[f].has_2d for f in frames])
    dz = pred[..., 2] - gt[..., 2]
    return {
        "visible_fraction": float(vis.mean()),
        "visible_mean_mm": float(err[vis].mean()) if vis.any() else None,
        "occluded_mean_mm": float(err[~vis].mean()) if (~vis).any() else None,
        "depth_abs_mean_mm": float(np.abs(dz).mean()),
        "depth_signed_mean_mm": float(dz.mean()),
        "image_plane_mean_mm": float(np.linalg.norm(pred[..., :2] - gt[..., :2], axis=-1).mean()),
        "per_joint_mean_mm": {
            n: float(e) for n, e in zip(skeleton.joint_names, err.mean(axis=0), strict=True)
        },
    }


def _run(seq, frames, noise, bones, workers, label, lift_kw):
    gt = seq.ground_truth.joints_mm
    anns = simulate_annotations(seq, frames, noise_px=noise, seed=0)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lifted = lift_references(
            anns,
            seq.depth,
            seq.camera,
            seq.skeleton,
            bone_lengths_mm=bones,
            pin_bone_lengths=bones is not None,
            workers=workers,
            **lift_kw,
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
        "stretched_fraction": float(np.mean([getattr(r, "stretched", False) for r in res])),
        "max_bone_violation_mm": float(max(r.bone_error_mm for r in res)),
        "wall_s": elapsed,
        "workers": workers,
        **_diagnostics(pred, gt[frames], anns, frames, seq.skeleton),
    }
    print(
        f"{label:9s} noise {noise:.1f} px: mean {summ['mean_mm']:.2f} median {summ['median_mm']:.2f} "
        f"max {summ['max_mm']:.2f} mm | bones |err| mean {bone_err.mean():.2f} max "
        f"{bone_err.max():.2f} mm, rounds {out['bone_rounds']} | converged "
        f"{out['converged_fraction']:.3f} | visible {out['visible_mean_mm']:.2f} occluded "
        f"{out['occluded_mean_mm'] or float('nan'):.2f} depth {out['depth_abs_mean_mm']:.2f} "
        f"(signed {out['depth_signed_mean_mm']:+.2f}) mm | {elapsed:.1f} s"
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


def _open(spec: str, frames: int, args) -> tuple[str, object]:
    """``spec`` -> (label, sequence): a synthetic folder or ``fpha:<subject>:<folder>``."""
    if spec.startswith("fpha:"):
        _, subject, folder = spec.split(":", 2)
        if not (Path(folder) / "joint.txt").exists():
            render_fpha_sequence(Path(folder), subject, args.fpha_sequences, args.fpha_every)
        return f"fpha-{subject}", open_sequence(folder)
    if not (Path(spec) / "joint.txt").exists():
        generate_sequence(spec, frames=frames, seed=0)
    return Path(spec).name, open_sequence(spec)


def _parse_kw(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, value = item.split("=", 1)
        out[key] = {"true": True, "false": False, "none": None}.get(value.lower(), value)
        if isinstance(out[key], str):
            parts = [float(v) for v in value.split(",")]
            out[key] = parts[0] if len(parts) == 1 else tuple(parts)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", default="/tmp/synth3040", help="comma-separated sequences")
    ap.add_argument("--suite", help="a benchmark suite folder (replaces --seq)")
    ap.add_argument("--part", default="tune", choices=["tune", "report", "all"])
    ap.add_argument("--ref-fraction", type=float, default=0.05, help="with --suite: uniform")
    ap.add_argument("--frames", type=int, default=3040)
    ap.add_argument("--step", type=int, default=20)
    ap.add_argument("--noise", default="0,2")
    ap.add_argument("--gt-bones", action="store_true", help="also run with ground-truth bones")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--speed-frames", type=int, default=60)
    ap.add_argument("--fpha-sequences", type=int, default=8)
    ap.add_argument("--fpha-every", type=int, default=3)
    ap.add_argument("--lift-kw", nargs="*", default=[], help="key=value lift_references options")
    ap.add_argument("--json", default=str(Path(__file__).parent / "results" / "lift.json"))
    args = ap.parse_args()
    lift_kw = _parse_kw(args.lift_kw)

    datasets = []
    specs = (
        [str(p) for _, _, p in read_suite(args.suite, args.part)]
        if args.suite
        else args.seq.split(",")
    )
    for spec in specs:
        label, seq = _open(spec, args.frames, args)
        if args.suite:
            n = len(seq)
            frames = select_references(
                np.zeros((n, 1)), "uniform", ref_fraction=args.ref_fraction
            ).reference_frames
        else:
            frames = np.arange(0, len(seq), args.step)
        gt = seq.ground_truth.joints_mm
        gt_bones = seq.skeleton.estimate_bone_lengths(gt)
        print(f"== {label}: {len(seq)} frames, {len(frames)} references")
        runs = []
        lifted0 = anns0 = None
        for noise in [float(x) for x in args.noise.split(",")]:
            out, lifted, anns = _run(seq, frames, noise, None, args.workers, "estimated", lift_kw)
            runs.append(out)
            if lifted0 is None:
                lifted0, anns0 = lifted, anns
            if args.gt_bones:
                runs.append(
                    _run(seq, frames, noise, gt_bones, args.workers, "gt_bones", lift_kw)[0]
                )
        entry = {"dataset": spec, "label": label, "frames": len(seq), "step": args.step}
        if args.suite:
            entry.update(step=None, ref_fraction=args.ref_fraction, references=len(frames))
        entry["runs"] = runs
        if args.speed_frames > 0:
            speed_frames = frames[:: max(1, len(frames) // args.speed_frames)][: args.speed_frames]
            speed = _speed(seq, speed_frames, anns0, lifted0.bone_lengths_mm)
            print(
                f"speed (1 process, load avg {speed['load_average_1min']:.1f} on "
                f"{speed['cpu_count']} cores): cold median {speed['cold_median_ms']:.1f} ms "
                f"(p90 {speed['cold_p90_ms']:.1f}), warm median {speed['warm_median_ms']:.1f} ms "
                f"(p90 {speed['warm_p90_ms']:.1f}), {speed['median_iterations']:.0f} SLSQP "
                "iterations"
            )
            entry["speed"] = speed
        datasets.append(entry)
    result = datasets[0] if len(datasets) == 1 else {"datasets": datasets}
    result["lift_kw"] = lift_kw
    result["load_average_1min"] = os.getloadavg()[0]
    if len(datasets) > 1:
        for noise in sorted({r["noise_px"] for d in datasets for r in d["runs"]}):
            means = [r["mean_mm"] for d in datasets for r in d["runs"]
                     if r["noise_px"] == noise and r["bones"] == "estimated"]  # fmt: skip
            print(f"mean of means, noise {noise:.1f} px: {np.mean(means):.2f} mm")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
