"""Benchmark the synthetic-sequence generator and save a montage of frames.

Run: ``.venv/bin/python benchmarks/bench_synth.py [--frames 3040] [--seed 0] [--workers 2] [--keep DIR]``

Times ``generate_sequence`` end to end (motion, rendering, noise, writing), reports seconds,
frames/s and peak RSS (this process + worker children), describes the sequence (gestures, yaw range,
depth range, fraction of joints visible to the simulated annotator) and writes
``benchmarks/results/synth.json`` and ``benchmarks/results/synth_montage.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from handanno_core.datasets import open_sequence  # noqa: E402
from handanno_core.synth import generate_sequence, simulate_annotations  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process and its finished children (the workers)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def peak_rss_mb() -> dict[str, float]:
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {"main_mb": self_kb / 1024.0, "largest_worker_mb": child_kb / 1024.0}


def montage(seq, frames: list[int], path: Path, gestures: dict[int, str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gt = seq.ground_truth.joints_mm
    cols = 4
    rows = int(np.ceil(len(frames) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.2 * rows))
    for ax, f in zip(axes.ravel(), frames, strict=False):
        d = seq.depth(f)
        uv = seq.camera.project(gt[f])
        # crop around the hand (joints +- 30 px), keep the aspect ratio
        u0, v0 = np.maximum(np.floor(uv.min(axis=0) - 30), 0).astype(int)
        u1, v1 = np.minimum(np.ceil(uv.max(axis=0) + 30), [d.shape[1], d.shape[0]]).astype(int)
        shown = np.where(d > 0, d, np.nan)[v0:v1, u0:u1]
        ax.imshow(shown, cmap="viridis_r", interpolation="nearest", extent=(u0, u1, v1, v0))
        for p, c in zip(seq.skeleton.bones[:, 0], seq.skeleton.bones[:, 1], strict=True):
            ax.plot(uv[[p, c], 0], uv[[p, c], 1], "r-", lw=0.5, alpha=0.6)
        normal_z = seq.skeleton.palm_normal(gt[f])[2]
        side = "palm" if normal_z < -0.3 else ("back" if normal_z > 0.3 else "side")
        ax.set_title(f"frame {f} ({side}) {gestures.get(f, '')}", fontsize=8)
        ax.axis("off")
    for ax in axes.ravel()[len(frames) :]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _gesture_at(meta: dict, frames: list[int]) -> dict[int, str]:
    """Name of the keyframe gesture being held or approached at each frame."""
    keys = meta["keyframes"]
    out = {}
    for f in frames:
        k = max((k for k in keys if k["frame"] <= f), key=lambda k: k["frame"])
        nxt = [n for n in keys if n["frame"] > f]
        held = f < k["frame"] + k["hold"] or not nxt
        out[int(f)] = k["gesture"] if held else f"{k['gesture']}->{nxt[0]['gesture']}"
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3040)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--keep", type=Path, default=None, help="write the sequence here and keep it")
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)

    with tempfile.TemporaryDirectory() as tmp:
        out = args.keep or Path(tmp) / "synth"
        load = os.getloadavg()
        cpu0 = _cpu_seconds()
        t0 = time.perf_counter()
        generate_sequence(out, frames=args.frames, seed=args.seed, workers=args.workers)
        seconds = time.perf_counter() - t0
        cpu = _cpu_seconds() - cpu0
        rss = peak_rss_mb()

        seq = open_sequence(out)
        gt = seq.ground_truth.joints_mm
        meta = json.loads((out / "synth.json").read_text())
        sample = np.linspace(0, len(seq) - 1, min(len(seq), 400)).astype(int)
        anns = simulate_annotations(seq, sample)
        visible = np.array([anns[f].visible for f in sample])
        hand_px = [int(np.count_nonzero(seq.depth(int(f)))) for f in sample]
        step = np.linalg.norm(np.diff(gt, axis=0), axis=-1).max(axis=1)
        normal_z = seq.skeleton.palm_normal(gt)[:, 2]
        nbytes = sum(p.stat().st_size for p in out.iterdir())
        shown = list(np.linspace(0, len(seq) - 1, 12).astype(int))
        montage(seq, shown, RESULTS / "synth_montage.png", _gesture_at(meta, shown))

    gestures = [k["gesture"] for k in meta["keyframes"]]
    result = {
        "frames": args.frames,
        "seed": args.seed,
        "workers": args.workers,
        "seconds": round(seconds, 2),
        "frames_per_s": round(args.frames / seconds, 1),
        "cpu_seconds": round(cpu, 2),
        "cpu_ms_per_frame": round(1000 * cpu / args.frames, 2),
        "peak_rss": {k: round(v, 1) for k, v in rss.items()},
        "load_average_before": [round(x, 2) for x in load],
        "cpu_count": os.cpu_count(),
        "bytes_written": nbytes,
        "sequence": {
            "keyframes": len(gestures),
            "distinct_gestures": sorted(set(gestures)),
            "revisits": sum(k["revisit_of"] >= 0 for k in meta["keyframes"]),
            "yaw_range_deg": [round(x, 1) for x in meta["yaw_range_deg"]],
            "palm_facing_fraction": round(float(np.mean(normal_z < 0)), 3),
            "joint_depth_range_mm": [round(x, 1) for x in meta["joint_depth_range_mm"]],
            "joint_step_mm_per_frame": {
                "median": round(float(np.median(step)), 2),
                "p99": round(float(np.percentile(step, 99)), 2),
                "max": round(float(step.max()), 2),
            },
            "visible_joint_fraction": round(float(visible.mean()), 3),
            "visible_fraction_per_joint": [round(float(x), 2) for x in visible.mean(axis=0)],
            "hand_pixels_median": int(np.median(hand_px)),
            "bone_lengths_mm": meta["bone_lengths_mm"],
        },
    }
    (RESULTS / "synth.json").write_text(json.dumps(result, indent=2))
    print(json.dumps({k: v for k, v in result.items() if k != "sequence"}, indent=2))
    s = result["sequence"]
    print(
        f"{args.frames} frames in {seconds:.1f} s ({result['frames_per_s']} frames/s, "
        f"{args.workers} workers, load before {load[0]:.2f}; {cpu:.1f} CPU s); {s['keyframes']} keyframes, "
        f"{s['revisits']} revisits, yaw {s['yaw_range_deg']}, depth {s['joint_depth_range_mm']} mm, "
        f"visible joints {s['visible_joint_fraction']:.1%}, steps {s['joint_step_mm_per_frame']}"
    )


if __name__ == "__main__":
    main()
