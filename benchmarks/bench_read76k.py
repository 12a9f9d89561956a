"""Read a 76,000-frame MSRA-layout sequence: wall time and peak memory of the lazy reader.

Generates (into a temporary folder) an MSRA-2015-sized dataset: 9 subjects x 17 gestures
(``P0/1`` ... ``P8/Y``), 76,000 ``%06d_depth.bin`` frames with a 40x40 box of depth each and a
``joint.txt`` per gesture. Then, in a fresh Python process (so the generator's memory is not
counted), opens it with ``open_sequence``, iterates every frame (mean valid depth), reads the
ground truth, and reports the timings and the peak RSS (``resource.getrusage().ru_maxrss``).

    .venv/bin/python benchmarks/bench_read76k.py [--frames 76000] [--keep DIR]

Writes benchmarks/results/read76k.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handanno_core.datasets.msra import GESTURES  # noqa: E402

SUBJECTS = [f"P{k}" for k in range(9)]
BOX = 40


def generate(out: Path, frames: int, seed: int = 0) -> dict:
    """Write the dataset; frames are written with the header + box bytes of the MSRA format."""
    from handanno_core.datasets import write_msra_frame, write_msra_joints

    rng = np.random.default_rng(seed)
    folders = [(s, g) for s in SUBJECTS for g in GESTURES]
    counts = np.full(len(folders), frames // len(folders))
    counts[: frames % len(folders)] += 1
    base_box = rng.uniform(350.0, 550.0, (BOX, BOX)).astype("<f4")
    t0 = time.perf_counter()
    for (subject, gesture), n in zip(folders, counts, strict=True):
        folder = out / subject / gesture
        folder.mkdir(parents=True)
        lefts = rng.integers(0, 320 - BOX, n)
        tops = rng.integers(0, 240 - BOX, n)
        offsets = rng.uniform(-50.0, 50.0, n).astype("<f4")
        for i in range(n):
            header = np.array([320, 240, lefts[i], tops[i], lefts[i] + BOX, tops[i] + BOX], "<i4")
            with open(folder / f"{i:06d}_depth.bin", "wb") as fh:
                fh.write(header.tobytes())
                fh.write((base_box + offsets[i]).tobytes())
        joints = rng.normal(0.0, 40.0, (n, 21, 3))
        joints[..., 2] += 450.0
        write_msra_joints(folder / "joint.txt", joints)
    # one frame through the real writer, to check the fast path writes the same format
    d = np.zeros((240, 320), np.float32)
    d[10 : 10 + BOX, 20 : 20 + BOX] = base_box
    write_msra_frame(out / SUBJECTS[0] / GESTURES[0] / "000000_depth.bin", d)
    return {"generate_s": time.perf_counter() - t0, "gesture_folders": len(folders)}


def read(path: Path) -> dict:
    """Run in a fresh process: open, iterate every frame, read ground truth."""
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    from handanno_core.datasets import BadFrameReport, open_sequence

    rss_import = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    seq = open_sequence(path)
    t_open = time.perf_counter() - t0
    rss_open = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    report = BadFrameReport()
    means = np.zeros(len(seq))
    t0 = time.perf_counter()
    for i, depth in seq.iter_depth(report=report):
        valid = depth[depth > 0]
        means[i] = valid.mean() if valid.size else 0.0
    t_iter = time.perf_counter() - t0
    t0 = time.perf_counter()
    gt = seq.ground_truth
    t_gt = time.perf_counter() - t0
    rss_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {
        "frames": len(seq),
        "sequence_breaks": len(seq.sequence_breaks),
        "bad_frames": len(report.errors),
        "mean_depth_mm": float(means.mean()),
        "ground_truth_shape": list(gt.joints_mm.shape),
        "open_s": t_open,
        "iterate_s": t_iter,
        "iterate_frames_per_s": len(seq) / t_iter,
        "ground_truth_s": t_gt,
        "rss_after_numpy_mb": rss0,
        "rss_after_import_mb": rss_import,
        "rss_after_open_mb": rss_open,
        "peak_rss_mb": rss_peak,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=76_000)
    parser.add_argument("--keep", type=Path, help="generate into this folder and keep it")
    parser.add_argument("--read", type=Path, help=argparse.SUPPRESS)  # child-process mode
    args = parser.parse_args()
    if args.read is not None:
        print(json.dumps(read(args.read)))
        return

    tmp = None
    if args.keep is not None:
        out = args.keep
        if out.exists():
            shutil.rmtree(out)
        out.mkdir(parents=True)
    else:
        tmp = tempfile.mkdtemp(prefix="handanno_read76k_")
        out = Path(tmp)
    try:
        print(f"generating {args.frames} frames in {out} ...", flush=True)
        gen = generate(out, args.frames)
        print(f"  generated in {gen['generate_s']:.1f} s", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--read", str(out)],
            check=True,
            capture_output=True,
            text=True,
        )
        wall = time.perf_counter() - t0
        res = json.loads(proc.stdout.strip().splitlines()[-1])
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    result = {
        "benchmark": "read76k",
        "layout": f"MSRA, {gen['gesture_folders']} gesture folders, {BOX}x{BOX} box per 320x240 frame",
        **gen,
        **res,
        "child_wall_s": wall,
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "note": "2 shared cores, other jobs running; page cache warm after generation",
        },
    }
    for key in (
        "frames",
        "open_s",
        "iterate_s",
        "iterate_frames_per_s",
        "ground_truth_s",
        "child_wall_s",
        "rss_after_import_mb",
        "rss_after_open_mb",
        "peak_rss_mb",
    ):
        val = result[key]
        print(f"{key:>22}: {val:.3f}" if isinstance(val, float) else f"{key:>22}: {val}")
    results = ROOT / "benchmarks" / "results"
    results.mkdir(parents=True, exist_ok=True)
    (results / "read76k.json").write_text(json.dumps(result, indent=2) + "\n")
    assert res["frames"] == args.frames and res["bad_frames"] == 0
    assert res["peak_rss_mb"] < 1024, "peak RSS over 1 GB"


if __name__ == "__main__":
    main()
