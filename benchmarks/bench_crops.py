"""Benchmark hand localization + cropping (handanno_core.crops).

Figures (printed and written to benchmarks/results/crops.json):

- SR305 real frames: per-frame ``locate_hand`` time (640x480) and an annotated montage of all 19
  frames (centre cross + crop box) and of their 128x128 crops in benchmarks/results/sr305_crops/
  (frames: LadaOndris/hand-recognition, MIT licence, (c) 2021 Ladislav Ondris).
- synthetic sequence (handanno_core.synth if it works, else the SR305 frames repeated):
  ``locate_hands`` and ``compute_crops`` ms per frame, and the localization error against the
  synthetic ground truth (palm centre = mean of wrist and the four MCPs; scoring only).
- memory: peak RSS of ``locate_hands`` + ``compute_crops(out_path=...)`` on a cheap fake sequence
  (one blob moving around) at 2,000 vs 20,000 frames, each run in a fresh subprocess.

Run: ``.venv/bin/python benchmarks/bench_crops.py [--quick]``. Timings are wall clock on whatever
machine runs it (on the shared 2-core dev box they are under load from other jobs).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handanno_core.camera import MSRA_CAMERA, SR305_CAMERA  # noqa: E402
from handanno_core.crops import (  # noqa: E402
    compute_crops,
    crop_boxes,
    crop_depth,
    locate_hand,
    locate_hands,
)
from handanno_core.datasets.base import BadFrameReport, DepthSequence  # noqa: E402
from handanno_core.skeleton import MSRA21  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
SR305_DIR = Path("/work/shared/data/real-sr305")
if not SR305_DIR.exists():
    SR305_DIR = ROOT / "shared" / "data" / "real-sr305"


def colourize(depth: np.ndarray, near: float = 400.0, far: float = 1100.0) -> np.ndarray:
    img = np.where(depth > 0, 255 - np.clip((depth - near) / (far - near) * 255, 0, 255), 0)
    img = cv2.applyColorMap(img.astype(np.uint8), cv2.COLORMAP_JET)
    img[depth <= 0] = 0
    return img


def montage(images: list[np.ndarray], cols: int) -> np.ndarray:
    blank = np.zeros_like(images[0])
    images = images + [blank] * (-len(images) % cols)
    return np.vstack([np.hstack(images[i : i + cols]) for i in range(0, len(images), cols)])


# ---------------------------------------------------------------------------- SR305
def bench_sr305() -> dict:
    out_dir = RESULTS / "sr305_crops"
    out_dir.mkdir(parents=True, exist_ok=True)
    frames, crops, times, rows = [], [], [], []
    for path in sorted(SR305_DIR.glob("*/*.png")):
        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float32) * 0.125
        t0 = time.perf_counter()
        c = locate_hand(depth, SR305_CAMERA)
        times.append(time.perf_counter() - t0)
        name = f"{path.parent.name}/{path.name}"
        img = colourize(depth)
        u, v = SR305_CAMERA.project(c)
        b = crop_boxes(c, SR305_CAMERA)
        p0 = (int(round(b[0])), int(round(b[1])))
        p1 = (int(round(b[0] + 128 * b[2])), int(round(b[1] + 128 * b[3])))
        cv2.rectangle(img, p0, p1, (255, 255, 255), 2)
        cv2.drawMarker(
            img, (int(round(u)), int(round(v))), (255, 255, 255), cv2.MARKER_CROSS, 24, 3
        )
        cv2.putText(img, name, (5, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.9, (255, 255, 255), 2)
        frames.append(cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA))
        crop = crop_depth(depth, SR305_CAMERA, c)
        crops.append(((1.0 - crop) * 127.5).astype(np.uint8))  # near = white, background = black
        d_px = float(depth[int(round(v)), int(round(u))])
        rows.append(
            {
                "frame": name,
                "centre_mm": np.round(c, 1).tolist(),
                "uv_px": [round(u, 1), round(v, 1)],
                "depth_at_centre_px_mm": d_px,
            }
        )
    cv2.imwrite(str(out_dir / "montage.png"), montage(frames, 5))
    cv2.imwrite(str(out_dir / "crops.png"), montage(crops, 5))
    return {
        "frames": len(rows),
        "locate_hand_ms_mean": 1e3 * float(np.mean(times)),
        "locate_hand_ms_max": 1e3 * float(np.max(times)),
        "centres": rows,
        "images": [
            str((out_dir / "montage.png").relative_to(ROOT)),
            str((out_dir / "crops.png").relative_to(ROOT)),
        ],
    }


# ---------------------------------------------------------------------------- synthetic timing
class RepeatedFrames(DepthSequence):
    format = "bench"

    def __init__(self, depths: list[np.ndarray], n: int, camera):
        super().__init__("/nonexistent/repeated", camera, MSRA21)
        self.depths, self.n = depths, n

    def __len__(self):
        return self.n

    def depth(self, index):
        return self.depths[self._check_index(index) % len(self.depths)]


def bench_sequence(frames: int) -> dict:
    result: dict = {}
    seq = None
    gt = None
    with tempfile.TemporaryDirectory() as tmp:
        try:
            from handanno_core.datasets import open_sequence
            from handanno_core.synth import generate_sequence

            t0 = time.perf_counter()
            generate_sequence(Path(tmp) / "synth", frames=frames, seed=0, progress=False)
            result["synth_s"] = time.perf_counter() - t0
            seq = open_sequence(Path(tmp) / "synth")
            gt = seq.ground_truth
            result["source"] = (
                f"handanno_core.synth, {frames} frames, {seq.camera.width}x{seq.camera.height}"
            )
        except Exception as exc:  # synth missing or broken: fall back to real frames
            result["synth_error"] = f"{type(exc).__name__}: {exc}"[:300]
            depths = [
                cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float32) * 0.125
                for p in sorted(SR305_DIR.glob("*/*.png"))
            ]
            seq = RepeatedFrames(depths, frames, SR305_CAMERA)
            result["source"] = f"SR305 frames repeated, {frames} frames, 640x480"
        report = BadFrameReport()
        t0 = time.perf_counter()
        centres = locate_hands(seq, report=report)
        t_loc = time.perf_counter() - t0
        t0 = time.perf_counter()
        compute_crops(seq, centres, Path(tmp) / "crops.npy", report=report)
        t_crop = time.perf_counter() - t0
        # depth reading alone, to separate I/O from our work
        t0 = time.perf_counter()
        for i in range(len(seq)):
            seq.depth(i)
        t_read = time.perf_counter() - t0
        n = len(seq)
        result.update(
            frames=n,
            bad_frames=len(report.errors),
            read_ms_per_frame=1e3 * t_read / n,
            locate_hands_ms_per_frame=1e3 * t_loc / n,
            compute_crops_ms_per_frame=1e3 * t_crop / n,
        )
        if gt is not None:
            j = gt.joints_mm
            palm = j[:, [0, 1, 5, 9, 13]].mean(axis=1)  # wrist + 4 MCPs (scoring only)
            err = np.linalg.norm(centres - palm, axis=1)
            uv_err = np.linalg.norm(seq.camera.project(centres) - seq.camera.project(palm), axis=1)
            result["centre_vs_gt_palm_mm"] = {
                "mean": float(np.nanmean(err)),
                "median": float(np.nanmedian(err)),
                "p95": float(np.nanpercentile(err, 95)),
                "max": float(np.nanmax(err)),
                "nan_frames": int(np.sum(~np.isfinite(err))),
            }
            result["centre_vs_gt_palm_px"] = {
                "median": float(np.nanmedian(uv_err)),
                "max": float(np.nanmax(uv_err)),
            }
    return result


# ---------------------------------------------------------------------------- memory
class BlobSequence(DepthSequence):
    """Cheap fake sequence: a hand-sized disc + 'forearm' bar moving on a circle (MSRA camera)."""

    format = "bench"

    def __init__(self, n: int):
        super().__init__("/nonexistent/blob", MSRA_CAMERA, MSRA21)
        self.n = n
        h, w = MSRA_CAMERA.height, MSRA_CAMERA.width
        yy, xx = np.mgrid[0:120, 0:120]
        blob = np.where((xx - 60) ** 2 + (yy - 45) ** 2 < 30**2, 380 + 0.02 * ((xx - 60) ** 2), 0)
        blob[70:120, 50:70] = 420.0
        self.blob = blob.astype(np.float32)
        self.shape = (h, w)

    def __len__(self):
        return self.n

    def depth(self, index):
        i = self._check_index(index)
        d = np.zeros(self.shape, np.float32)
        oy = int(60 + 40 * np.sin(i / 50.0))
        ox = int(100 + 60 * np.cos(i / 70.0))
        d[oy : oy + 120, ox : ox + 120] = self.blob
        return d


def memory_child(n: int, out: str) -> None:
    seq = BlobSequence(n)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    centres = locate_hands(seq)
    t1 = time.perf_counter()
    crops = compute_crops(seq, centres, out)
    t2 = time.perf_counter()
    fg = float((np.asarray(crops[:: max(1, n // 50)]) < 1).mean())
    print(
        json.dumps(
            {
                "frames": n,
                "rss_before_mb": rss0,
                "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                "locate_hands_ms_per_frame": 1e3 * (t1 - t0) / n,
                "compute_crops_ms_per_frame": 1e3 * (t2 - t1) / n,
                "crops_file_mb": Path(out).stat().st_size / 2**20,
                "foreground_fraction": fg,
                "nan_centres": int(np.sum(~np.isfinite(centres[:, 0]))),
            }
        )
    )


def bench_memory(sizes: list[int]) -> list[dict]:
    rows = []
    for n in sizes:
        with tempfile.TemporaryDirectory() as tmp:
            proc = subprocess.run(
                [sys.executable, __file__, "--memory-child", str(n), str(Path(tmp) / "crops.npy")],
                capture_output=True,
                text=True,
                check=True,
            )
            rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes (smoke run)")
    ap.add_argument("--frames", type=int, default=None, help="synthetic sequence length")
    ap.add_argument("--memory-child", nargs=2, metavar=("N", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.memory_child:
        memory_child(int(args.memory_child[0]), args.memory_child[1])
        return
    frames = args.frames or (100 if args.quick else 600)
    sizes = [200, 2000] if args.quick else [2000, 20000]
    res = {
        "machine_note": "wall clock; shared 2-core dev box under load from other jobs unless stated"
    }
    if SR305_DIR.exists():
        res["sr305"] = bench_sr305()
        s = res["sr305"]
        print(
            f"SR305: {s['frames']} frames, locate_hand {s['locate_hand_ms_mean']:.1f} ms/frame "
            f"(max {s['locate_hand_ms_max']:.1f}); images: {', '.join(s['images'])}"
        )
    res["sequence"] = bench_sequence(frames)
    q = res["sequence"]
    print(
        f"sequence ({q['source']}): read {q['read_ms_per_frame']:.2f} ms, locate_hands "
        f"{q['locate_hands_ms_per_frame']:.2f} ms, compute_crops {q['compute_crops_ms_per_frame']:.2f} ms per frame"
    )
    if "centre_vs_gt_palm_mm" in q:
        e = q["centre_vs_gt_palm_mm"]
        print(
            f"  centre vs GT palm: mean {e['mean']:.1f} mm, median {e['median']:.1f}, p95 {e['p95']:.1f}, "
            f"max {e['max']:.1f}, NaN {e['nan_frames']}"
        )
    if "synth_error" in q:
        print(f"  (synth unavailable: {q['synth_error']})")
    res["memory"] = bench_memory(sizes)
    for m in res["memory"]:
        print(
            f"memory: {m['frames']} frames -> peak RSS {m['peak_rss_mb']:.0f} MB (before {m['rss_before_mb']:.0f} MB), "
            f"crops file {m['crops_file_mb']:.0f} MB, locate {m['locate_hands_ms_per_frame']:.2f} ms/f, "
            f"crops {m['compute_crops_ms_per_frame']:.2f} ms/f"
        )
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "crops.json").write_text(json.dumps(res, indent=1))
    print(f"wrote {RESULTS / 'crops.json'}")


if __name__ == "__main__":
    main()
