"""Reference-selection benchmark: quality (GT coverage) and speed/memory at 3040 and 76k frames.

    .venv/bin/python benchmarks/bench_select.py [--synth DIR] [--large-frames 76000] [--skip-large]

1. Quality on a synthetic 3040-frame sequence (``handanno synth``; generated into ``--synth`` if
   missing): crops from ``locate_hands`` + ``compute_crops`` (no GT), then for each descriptor,
   strategy and budget (2/5/10 %) the pose-space statistics of :func:`forest_stats` (GT used only
   here): mean max-joint distance (centroid removed) of every frame to its root reference, of
   every parent->child step, and summed along the path; plus the coverage curve (0..80 mm).
2. Speed at 3040: descriptors + selection, per descriptor and strategy.
3. Scale: ``--large-frames`` (default 76,000) crops made by tiling the 3040 synthetic crops with a
   smooth per-frame random affine warp (rotation +-12 deg, scale +-8 %, shift +-6 px), a random
   time shift/direction per tile and 0.01 depth noise on the hand, stored as a float16 memmap
   ``.npy`` (as ``compute_crops`` writes); descriptors + selection run in a fresh subprocess that
   reports its wall time and peak RSS.

Writes ``benchmarks/results/select.json`` and PNGs next to it. Timings are on the machine as it
is (often shared): see ``load_avg`` in the JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handanno_core.descriptors import compute_descriptors  # noqa: E402
from handanno_core.select import (  # noqa: E402
    DEFAULT_STRATEGY,
    STRATEGIES,
    coverage_curve,
    forest_stats,
    knn,
    plot_coverage,
    plot_embedding,
    select_references,
)

RESULTS = ROOT / "benchmarks" / "results"
FRACTIONS = (0.02, 0.05, 0.10)
KINDS = ("downsampled", "hog")


def load_synthetic(synth_dir: Path, cache: Path):
    """(crops (N,128,128) memmap, gt (N,J,3), sequence_breaks) of a synthetic sequence."""
    from handanno_core.crops import compute_crops, locate_hands
    from handanno_core.datasets import open_sequence

    if not (synth_dir / "joint.txt").exists():
        from handanno_core.synth import generate_sequence

        print(f"generating synthetic sequence into {synth_dir} ...", flush=True)
        generate_sequence(synth_dir, frames=3040, seed=0, progress=False)
    seq = open_sequence(synth_dir)
    crops_path = cache / f"crops_{synth_dir.name}_{len(seq)}.npy"
    if not crops_path.exists():
        print("locating hands and cropping ...", flush=True)
        centres = locate_hands(seq)
        compute_crops(seq, centres, crops_path)
    crops = np.load(crops_path, mmap_mode="r")
    return crops, seq.ground_truth.joints_mm, list(seq.sequence_breaks)


def quality_and_speed(crops, gt, breaks) -> dict:
    out: dict = {"frames": len(crops), "descriptors": {}, "runs": []}
    curves = {}
    for kind in KINDS:
        t0 = time.perf_counter()
        x = compute_descriptors(crops, kind)
        t_desc = time.perf_counter() - t0
        out["descriptors"][kind] = {"dim": int(x.shape[1]), "time_s": round(t_desc, 3)}
        print(f"{kind}: {x.shape[1]}-D in {t_desc:.2f} s", flush=True)
        for fraction in FRACTIONS:
            for strategy in STRATEGIES:
                t0 = time.perf_counter()
                sel = select_references(x, strategy, ref_fraction=fraction, sequence_breaks=breaks)
                t_sel = time.perf_counter() - t0
                stats = forest_stats(gt, sel)
                t, frac = coverage_curve(gt, sel)
                run = {
                    "descriptor": kind,
                    "strategy": strategy,
                    "ref_fraction": fraction,
                    "threshold": sel.threshold,
                    "select_s": round(t_sel, 3),
                    "descriptors_plus_select_s": round(t_sel + t_desc, 3),
                    **{k: round(v, 3) if isinstance(v, float) else v for k, v in stats.items()},
                    "coverage_at_mm": {str(m): round(float(frac[m]), 4) for m in (5, 10, 20, 40)},
                }
                out["runs"].append(run)
                print(
                    f"  {fraction:.2f} {strategy:10s} K={stats['references']:4d} "
                    f"root {stats['root_mean_mm']:6.1f} mm (p95 {stats['root_p95_mm']:6.1f}) "
                    f"edge {stats['edge_mean_mm']:5.1f} (p95 {stats['edge_p95_mm']:5.1f}) "
                    f"path {stats['path_mean_mm']:6.1f} depth {stats['depth_mean']:5.1f}/"
                    f"{stats['depth_max']:4d}  {t_sel:.2f}+{t_desc:.2f} s",
                    flush=True,
                )
                if fraction == 0.05 and kind == KINDS[0]:
                    curves[strategy] = (t, frac)
                    if strategy in ("chain", DEFAULT_STRATEGY):
                        plot_embedding(x, sel, RESULTS / f"select_embedding_{strategy}.png")
    plot_coverage(curves, RESULTS / "select_coverage_5pct.png", title="5 % references, 3040 frames")
    return out


def make_large_crops(base: np.ndarray, frames: int, path: Path, seed: int = 0) -> None:
    """Tile ``base`` crops to ``frames`` frames with smooth random affine warps and noise."""
    import cv2

    rng = np.random.default_rng(seed)
    n0, s, _ = base.shape
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float16, shape=(frames, s, s))
    # smooth per-frame warp parameters: low-pass-filtered random walks
    steps = rng.standard_normal((frames, 4))
    kernel = np.hanning(301)
    kernel /= kernel.sum()
    walk = np.stack([np.convolve(steps[:, i], kernel, mode="same") for i in range(4)], axis=1)
    walk /= np.abs(walk).max(axis=0)
    rot, scale, dx, dy = walk[:, 0] * 12, 1 + walk[:, 1] * 0.08, walk[:, 2] * 6, walk[:, 3] * 6
    done = 0
    tile = 0
    while done < frames:
        m = min(n0, frames - done)
        shift = int(rng.integers(n0))
        idx = (np.arange(m) + shift) % n0
        if tile % 2:
            idx = idx[::-1]
        chunk = np.asarray(base[np.sort(idx)], np.float32)
        chunk = chunk[np.argsort(np.argsort(idx))]  # back to the tile's time order
        for j in range(m):
            f = done + j
            a = cv2.getRotationMatrix2D((s / 2 - 0.5, s / 2 - 0.5), rot[f], scale[f])
            a[:, 2] += (dx[f], dy[f])
            w = cv2.warpAffine(chunk[j], a, (s, s), flags=cv2.INTER_LINEAR, borderValue=1.0)
            hand = w < 0.999
            w[hand] += rng.normal(0, 0.01, int(hand.sum())).astype(np.float32)
            out[f] = np.clip(w, -1, 1)
        out.flush()
        done += m
        tile += 1
    del out


def _peak_mb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def large_worker(path: str, kind: str, strategy: str, fraction: float) -> None:
    """Run in a fresh process: descriptors + selection on a memmap, print JSON."""
    crops = np.load(path, mmap_mode="r")
    c0 = time.process_time()
    t0 = time.perf_counter()
    x = compute_descriptors(crops, kind)
    t_desc = time.perf_counter() - t0
    rss_desc = _peak_mb()
    t1 = time.perf_counter()
    g = knn(x, 32 if strategy.startswith("chain") else 200 if strategy == "coverage" else 5)
    t_knn = time.perf_counter() - t1
    rss_knn = _peak_mb()
    sel = select_references(x, strategy, ref_fraction=fraction, graph=g)
    t_sel = time.perf_counter() - t1
    sel.validate()
    print(
        json.dumps(
            {
                "frames": len(crops),
                "descriptor": kind,
                "dim": int(x.shape[1]),
                "strategy": strategy,
                "ref_fraction": fraction,
                "references": int(len(sel.reference_frames)),
                "descriptors_s": round(t_desc, 2),
                "knn_s": round(t_knn, 2),
                "select_total_s": round(t_sel, 2),
                "total_s": round(t_desc + t_sel, 2),
                "cpu_s": round(time.process_time() - c0, 2),
                "peak_rss_mb": _peak_mb(),
                "peak_rss_mb_after_descriptors": rss_desc,
                "peak_rss_mb_after_knn": rss_knn,
                "depth_max": int(sel.depths().max()),
            }
        )
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--synth", type=Path, default=Path("/tmp/synth3040"))
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()))
    ap.add_argument("--large-frames", type=int, default=76000)
    ap.add_argument("--skip-large", action="store_true")
    ap.add_argument("--skip-quality", action="store_true")
    ap.add_argument(
        "--large-runs",
        default=f"downsampled:{DEFAULT_STRATEGY}:0.05,downsampled:chain:0.05",
        help="comma list of descriptor:strategy:fraction for the large run",
    )
    ap.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        large_worker(args.worker[0], args.worker[1], args.worker[2], float(args.worker[3]))
        return
    RESULTS.mkdir(parents=True, exist_ok=True)
    result: dict = {"cpu_count": os.cpu_count(), "load_avg_start": os.getloadavg()}
    crops, gt, breaks = load_synthetic(args.synth, args.cache)
    if not args.skip_quality:
        result["synthetic_3040"] = quality_and_speed(crops, gt, breaks)
    if not args.skip_large:
        path = args.cache / f"sel_crops_large_{args.large_frames}.npy"
        if not path.exists():
            print(f"making {args.large_frames} crops in {path} ...", flush=True)
            t0 = time.perf_counter()
            make_large_crops(crops, args.large_frames, path)
            print(f"  {time.perf_counter() - t0:.1f} s", flush=True)
        result["large"] = {
            "crops": "3040 synthetic crops tiled with smooth random affine warps + noise",
            "runs": [],
        }
        for spec in args.large_runs.split(","):
            kind, strategy, fraction = spec.split(":")
            print(f"large: {kind} {strategy} {fraction} ...", flush=True)
            cmd = [sys.executable, __file__, "--worker", str(path), kind, strategy, fraction]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                print(proc.stderr, flush=True)
                result["large"]["runs"].append({"spec": spec, "error": proc.stderr[-2000:]})
                continue
            run = json.loads(proc.stdout.strip().splitlines()[-1])
            run["load_avg_after"] = os.getloadavg()
            print(f"  {run}", flush=True)
            result["large"]["runs"].append(run)
    result["load_avg_end"] = os.getloadavg()
    out = RESULTS / "select.json"
    if out.exists():  # keep the parts of an earlier run that were skipped this time
        old = json.loads(out.read_text())
        for key in ("synthetic_3040", "large"):
            if key not in result and key in old:
                result[key] = old[key]
        if "large" in result and "large" in old and not args.skip_large:
            done = {(r.get("descriptor"), r.get("strategy")) for r in result["large"]["runs"]}
            result["large"]["runs"] += [
                r
                for r in old["large"].get("runs", [])
                if (r.get("descriptor"), r.get("strategy")) not in done
            ]
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
