"""Benchmark hand localization + cropping (handanno_core.localize, handanno_core.crops).

Figures (printed and written to benchmarks/results/crops.json):

- real frames (../shared/data: 19 SR305, the HANDS 2017 SR300 and the MSRA 2015 frame): per-frame
  ``locate_hand_region`` time, the method used, and a montage a person can check,
  benchmarks/results/crops_real_frames.png (depth, by-eye hand box in cyan, crop box in magenta
  at the frame's cube, centre cross) plus the 128x128 crops, crops_real_frames_crops.png
  (SR305 frames: LadaOndris/hand-recognition, MIT licence, (c) 2021 Ladislav Ondris).
- forearm fixture (tests/forearm_scenes.py: synthetic hand + long arm at any angle, sleeve or
  not): per sequence, the share of frames with every ground-truth joint inside the crop (x, y
  within the half cube less 8 mm, projected, at the session cube; and also in depth: not behind
  the cube, not more than a cube in front), median/p90 distance crop centre to the joints'
  centroid, localization ms/frame, for the TUNE and REPORT cases; with ``--baseline DIR`` (a
  checkout of another commit, e.g. main) also its ``crops.locate_hands`` at a 220 mm cube.
- benchmark suite (``--suite DIR --part tune|report``, a folder written by ``handanno suite``):
  per sequence the same scores, with the centres and session cube the pipeline makes
  (:func:`handanno_core.crops.locate_crops`), before (``--baseline``) and after.
- synthetic sequence and memory (``--sequence``): as before, ``locate_hands`` + ``compute_crops``
  ms/frame and peak RSS at 2,000 vs 20,000 frames.

Run: ``.venv/bin/python benchmarks/bench_crops.py [--suite DIR] [--part tune|report|all]
[--baseline DIR] [--no-forearm] [--no-real] [--out FILE] [--sequence] [--quick]``.
Timings are wall clock on whatever machine runs it (on the shared 2-core dev box they are under
load from other jobs: the load average is recorded).
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

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handanno_core.camera import MSRA_CAMERA, SR305_CAMERA  # noqa: E402
from handanno_core.crops import (  # noqa: E402
    compute_crops,
    crop_boxes,
    crop_depth,
    image_to_crop,
    locate_crops,
    locate_hands,
)
from handanno_core.datasets.base import BadFrameReport, DepthSequence  # noqa: E402
from handanno_core.localize import (  # noqa: E402
    locate_hand_region,
    session_cube_mm,
)
from handanno_core.skeleton import MSRA21  # noqa: E402
from tests.forearm_scenes import REPORT_CASES, TUNE_CASES, case_sequence  # noqa: E402
from tests.real_frames import DATA, HAND_BOXES, frame_names, load_frame  # noqa: E402

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


# ---------------------------------------------------------------------------- real frames
def bench_real() -> dict:
    frames, crops, rows = [], [], []
    for name in frame_names():
        depth, cam = load_frame(name)
        t0 = time.perf_counter()
        loc = locate_hand_region(depth, cam)
        dt = time.perf_counter() - t0
        cube = session_cube_mm(loc.half_extent_mm[None], 220.0)
        valid = depth[depth > 0]
        near, far = np.percentile(valid, [1, 99])
        img = colourize(depth, near, far)
        u0, v0, u1, v1 = HAND_BOXES[name]
        cv2.rectangle(img, (u0, v0), (u1, v1), (255, 255, 0), 1)
        b = crop_boxes(loc.centre_mm, cam, cube_mm=cube)
        p0 = (int(round(b[0])), int(round(b[1])))
        p1 = (int(round(b[0] + 128 * b[2])), int(round(b[1] + 128 * b[3])))
        cv2.rectangle(img, p0, p1, (255, 0, 255), 2)
        u, v = cam.project(loc.centre_mm)
        cv2.drawMarker(img, (int(round(u)), int(round(v))), (255, 0, 255), cv2.MARKER_CROSS, 24, 3)
        img = cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA)
        label = name.split("/", 1)[1][-26:]
        cv2.putText(img, label, (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1)
        cv2.putText(
            img,
            f"{loc.method} cube {cube:.0f}",
            (3, 232),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.42,
            (255, 255, 255),
            1,
        )
        frames.append(img)
        crop = crop_depth(depth, cam, loc.centre_mm, cube_mm=cube)
        crops.append(((1.0 - crop) * 127.5).astype(np.uint8))
        rows.append(
            {
                "frame": name,
                "method": loc.method,
                "cube_mm": cube,
                "centre_mm": np.round(loc.centre_mm, 1).tolist(),
                "half_extent_mm": np.round(loc.half_extent_mm, 1).tolist(),
                "ms": round(1e3 * dt, 1),
            }
        )
    RESULTS.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(RESULTS / "crops_real_frames.png"), montage(frames, 6))
    cv2.imwrite(str(RESULTS / "crops_real_frames_crops.png"), montage(crops, 7))
    ms = [r["ms"] for r in rows]
    return {
        "frames": len(rows),
        "locate_ms_mean": float(np.mean(ms)),
        "locate_ms_max": float(np.max(ms)),
        "rows": rows,
        "images": [
            "benchmarks/results/crops_real_frames.png",
            "benchmarks/results/crops_real_frames_crops.png",
        ],
    }


# ---------------------------------------------------------------------------- forearm fixture
def _load_baseline(path: Path):
    """``crops`` module of another checkout's handanno_core, loaded as package ``baseline_core``
    (its ``locate_crops`` if it has one, else its localize's cube loop or ``locate_hands`` at 220 mm
    is what :func:`baseline_locate` runs)."""
    import importlib.util

    init = path / "handanno_core" / "__init__.py"
    spec = importlib.util.spec_from_file_location(
        "baseline_core", init, submodule_search_locations=[str(init.parent)]
    )
    pkg = importlib.util.module_from_spec(spec)
    sys.modules["baseline_core"] = pkg
    spec.loader.exec_module(pkg)
    import importlib

    return importlib.import_module("baseline_core.crops")


def baseline_locate(baseline, seq) -> tuple[np.ndarray, float, np.ndarray | None]:
    """Centres ``(N, 3)``, cube (mm) and frames' own cubes in x, y (``(N,)`` mm, None where that
    checkout has none) of another checkout, as its pipeline would crop ``seq``."""
    if hasattr(baseline, "locate_crops"):
        out = baseline.locate_crops(seq)
        return out[0], out[1].cube_mm, (out[2] if len(out) > 2 else None)
    import importlib

    loc = importlib.import_module("baseline_core.localize")
    if not hasattr(loc, "session_cube_mm"):
        return baseline.locate_hands(seq), 220.0, None
    cube = 220.0
    centres, half = loc.locate_hands_with_extent(seq, cube_mm=cube)
    while (grown := loc.session_cube_mm(half, cube)) != cube:
        cube = grown
        centres, half = loc.locate_hands_with_extent(seq, cube_mm=cube)
    return centres, cube, None


def crop_scores(
    seq, centres: np.ndarray, cube: float, size: int = 128, box_cubes: np.ndarray | None = None
) -> dict:
    """Per-sequence scores of crop centres ``(N, 3)`` against the sequence's ground truth.

    A joint is inside in x, y when its projection is within the half cube less 8 mm of the crop
    centre (crop pixels converted at the cube's scale; ``box_cubes`` ``(N,)``: each frame's own
    cube in x, y, default ``cube``); in depth (``xyz``) when it is also not behind the cube and at
    most a cube in front of the centre (the crop keeps surface up to half a cube in front of the
    cube as foreground, clamped to -1); ``cube`` (strict) when within the cube itself
    (``|dz| <= cube / 2``). Depth is always at the session's ``cube``.
    """
    gt = seq.ground_truth.joints_mm
    box = np.full(len(gt), float(cube)) if box_cubes is None else np.asarray(box_cubes, float)
    boxes = crop_boxes(centres, seq.camera, box, size)
    xy = image_to_crop(seq.camera.project(gt), boxes[:, None, :])
    mm = (xy - (size - 1) / 2) * box[:, None, None] / size
    ok_xy = np.all(np.abs(mm) <= box[:, None, None] / 2 - 8.0, axis=(1, 2))
    dz = gt[..., 2] - centres[:, None, 2]
    ok_z = np.all((dz <= cube / 2) & (dz >= -cube), axis=1)
    ok_cube = np.all(np.abs(dz) <= cube / 2, axis=1)
    d = np.linalg.norm(centres - gt.mean(axis=1), axis=1)
    return {
        "frames": len(gt),
        "inside_xy_pct": 100.0 * float(ok_xy.mean()),
        "inside_xyz_pct": 100.0 * float((ok_xy & ok_z).mean()),
        "inside_cube_pct": 100.0 * float((ok_xy & ok_cube).mean()),
        "frames_out": np.flatnonzero(~(ok_xy & ok_z)).tolist()[:50],
        "centre_to_centroid_median_mm": float(np.median(d)),
        "centre_to_centroid_p90_mm": float(np.percentile(d, 90)),
        "frames_box_grown": int(np.sum(box > cube)),
        "box_cube_max_mm": float(box.max()),
    }


def uniform_references(n: int, fraction: float) -> np.ndarray:
    """``max(2, round(fraction * n))`` frames evenly spread over ``0..n-1`` (the bench's
    ``uniform`` selection within one segment)."""
    k = max(2, int(round(fraction * n)))
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(int))


def anchored_scores(seq, fraction: float) -> dict:
    """Coverage of the crops placed again from references (``pipeline.recrop_from_references``'s
    rule, :func:`handanno_core.crops.crops_from_references`, without a session): uniform
    references at ``fraction``, each with its ground-truth joints standing in for its lift (a lift
    is 1-3 mm off, far less than the crop's margin); the references outside their crop are the
    anchors."""
    from handanno_core.crops import crops_from_references, place_crops
    from handanno_core.cropspec import DEFAULT_CROP
    from handanno_core.localize import locate_hand_geometry

    gt = seq.ground_truth.joints_mm
    geometry = locate_hand_geometry(seq)
    centres, spec, box = place_crops(geometry, DEFAULT_CROP, seq.sequence_breaks)
    t0 = time.perf_counter()
    refs = uniform_references(len(seq), fraction)
    missed, _, centres, box = crops_from_references(
        seq, geometry, spec, centres, box, {int(f): gt[f] for f in refs}
    )
    return {
        **crop_scores(seq, centres, spec.cube_mm, box_cubes=box),
        "cube_mm": spec.cube_mm,
        "references": int(len(refs)),
        "anchors": missed.tolist(),
        "ms_per_frame": 1e3 * (time.perf_counter() - t0) / len(seq),
    }


def bench_suite(folder: Path, part: str, baseline=None, references: float | None = None) -> dict:
    """Crop coverage on every sequence of a benchmark suite folder (``handanno suite``), ``part``
    tune or report: centres and cube as the pipeline makes them (:func:`locate_crops`); with
    ``references`` also after the crops are placed again from references at that fraction
    (:func:`anchored_scores`, key ``anchored``)."""
    from handanno_core.datasets import open_sequence
    from handanno_core.suite import read_suite

    rows = []
    for name, _, path in read_suite(folder, part):
        seq = open_sequence(path)
        t0 = time.perf_counter()
        centres, spec, box = locate_crops(seq)
        ms = 1e3 * (time.perf_counter() - t0) / len(seq)
        row = {
            "sequence": name,
            "after": {**crop_scores(seq, centres, spec.cube_mm, box_cubes=box)},
        }
        row["after"].update(cube_mm=spec.cube_mm, ms_per_frame=ms)
        if references:
            row["anchored"] = anchored_scores(seq, references)
            a = row["anchored"]
            print(
                f"  {name:28s} from {a['references']} references (anchors {a['anchors']}): "
                f"inside {a['inside_xy_pct']:5.1f}% (depth too {a['inside_xyz_pct']:5.1f}%) "
                f"out {a['frames_out'][:10]}"
            )
        if baseline is not None:
            t0 = time.perf_counter()
            old, cube, old_box = baseline_locate(baseline, seq)
            ms = 1e3 * (time.perf_counter() - t0) / len(seq)
            row["before"] = {
                **crop_scores(seq, old, cube, box_cubes=old_box),
                "cube_mm": cube,
                "ms_per_frame": ms,
            }
        rows.append(row)
        _print_row(name, row)
    return {
        "rows": rows,
        "after": _total(rows, "after"),
        "before": _total(rows, "before"),
        "anchored": _total(rows, "anchored"),
    }


def _print_row(name: str, row: dict) -> None:
    a, b = row["after"], row.get("before")
    print(
        f"  {name:28s} inside {a['inside_xy_pct']:5.1f}% (depth too {a['inside_xyz_pct']:5.1f}%, "
        f"in cube {a['inside_cube_pct']:5.1f}%) centre-centroid "
        f"{a['centre_to_centroid_median_mm']:5.1f}/{a['centre_to_centroid_p90_mm']:5.1f} mm "
        f"cube {a['cube_mm']:.0f} (box grown on {a.get('frames_box_grown', 0)} frames, to "
        f"{a.get('box_cube_max_mm', a['cube_mm']):.0f}) {a['ms_per_frame']:5.1f} ms/f"
        + (
            f" | before {b['inside_xy_pct']:5.1f}% ({b['inside_xyz_pct']:5.1f}%) cube "
            f"{b['cube_mm']:.0f}"
            if b
            else ""
        ),
        flush=True,
    )


def _total(rows: list[dict], key: str) -> dict | None:
    sel = [r[key] for r in rows if key in r]
    if not sel:
        return None
    keys = ("inside_xy_pct", "inside_xyz_pct", "inside_cube_pct")
    return {
        k: float(np.mean([x[k] for x in sel]))
        for k in (*keys, "centre_to_centroid_median_mm", "ms_per_frame")
    } | {
        "sequences_at_100pct": sum(x["inside_xyz_pct"] == 100.0 for x in sel),
        "sequences_at_100pct_xy": sum(x["inside_xy_pct"] == 100.0 for x in sel),
        "frames": sum(x["frames"] for x in sel),
        "frames_inside_xyz_pct": float(
            sum(x["inside_xyz_pct"] * x["frames"] for x in sel) / sum(x["frames"] for x in sel)
        ),
    }


def bench_forearm(cases, baseline=None, references: float | None = None) -> dict:
    """Crop coverage on the forearm fixture's ``cases``; with ``references`` also after the crops
    are placed again from references at that fraction (:func:`anchored_scores`)."""
    rows = []
    for case in cases:
        seq = case_sequence(case)
        t0 = time.perf_counter()
        centres, spec, box = locate_crops(seq)
        ms = 1e3 * (time.perf_counter() - t0) / len(seq)
        row = {"case": case.name, "theta_deg": case.theta_deg, "sleeve": case.sleeve}
        row["after"] = {
            **crop_scores(seq, centres, spec.cube_mm, box_cubes=box),
            "cube_mm": spec.cube_mm,
            "ms_per_frame": ms,
        }
        if baseline is not None:
            t0 = time.perf_counter()
            old, cube, old_box = baseline_locate(baseline, seq)
            ms = 1e3 * (time.perf_counter() - t0) / len(seq)
            row["before"] = {
                **crop_scores(seq, old, cube, box_cubes=old_box),
                "cube_mm": cube,
                "ms_per_frame": ms,
            }
        if references:
            row["anchored"] = anchored_scores(seq, references)
        rows.append(row)
        _print_row(case.name, row)
    return {
        "rows": rows,
        "after": _total(rows, "after"),
        "before": _total(rows, "before"),
        "anchored": _total(rows, "anchored"),
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


def _summary(name: str, res: dict) -> None:
    for key in ("after", "before", "anchored"):
        t = res.get(key)
        if t:
            print(
                f"  {name} {key}: frames inside {t['frames_inside_xyz_pct']:.1f}% (x, y and depth; "
                f"mean of sequences {t['inside_xyz_pct']:.1f}%, x, y only {t['inside_xy_pct']:.1f}%, "
                f"in the cube {t['inside_cube_pct']:.1f}%), {t['sequences_at_100pct']} of "
                f"{len(res['rows'])} sequences at 100% ({t['sequences_at_100pct_xy']} in x, y), "
                f"centre-centroid median {t['centre_to_centroid_median_mm']:.1f} mm, "
                f"{t['ms_per_frame']:.1f} ms/frame",
                flush=True,
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes (smoke run)")
    ap.add_argument("--frames", type=int, default=None, help="synthetic sequence length")
    ap.add_argument("--baseline", type=Path, help="checkout whose crops to compare (before)")
    ap.add_argument("--sequence", action="store_true", help="also the sequence and memory runs")
    ap.add_argument(
        "--suite", type=Path, help="suite folder (handanno suite): coverage per sequence"
    )
    ap.add_argument(
        "--part",
        default="all",
        choices=("tune", "report", "all"),
        help="suite and forearm-fixture part",
    )
    ap.add_argument(
        "--references",
        type=float,
        help="suite: also the coverage after crops are placed again from uniform references at "
        "this fraction (ground truth standing in for their lifts)",
    )
    ap.add_argument("--no-forearm", action="store_true", help="skip the forearm fixture")
    ap.add_argument("--no-real", action="store_true", help="skip the real frames")
    ap.add_argument("--out", type=Path, default=RESULTS / "crops.json", help="JSON to write")
    ap.add_argument("--memory-child", nargs=2, metavar=("N", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.memory_child:
        memory_child(int(args.memory_child[0]), args.memory_child[1])
        return
    frames = args.frames or (100 if args.quick else 600)
    sizes = [200, 2000] if args.quick else [2000, 20000]
    res = {
        "machine_note": "wall clock; shared 2-core dev box under load from other jobs unless stated",
        "load_average_start": list(os.getloadavg()),
    }
    if DATA is not None and not args.no_real:
        res["real_frames"] = bench_real()
        s = res["real_frames"]
        print(
            f"real frames: {s['frames']}, locate_hand_region {s['locate_ms_mean']:.1f} ms/frame "
            f"(max {s['locate_ms_max']:.1f}); images: {', '.join(s['images'])}"
        )
    baseline = _load_baseline(args.baseline) if args.baseline else None
    if args.suite:
        for part in ("tune", "report") if args.part == "all" else (args.part,):
            print(f"suite {part}:", flush=True)
            res[f"suite_{part}"] = bench_suite(args.suite, part, baseline, args.references)
            _summary(f"suite {part}", res[f"suite_{part}"])
    if not args.no_forearm:
        for part, cases in (("forearm_tune", TUNE_CASES), ("forearm_report", REPORT_CASES)):
            if args.part != "all" and not part.endswith(args.part):
                continue
            print(f"{part}:")
            res[part] = bench_forearm(cases[:4] if args.quick else cases, baseline, args.references)
            _summary(part, res[part])
    if args.sequence:
        res["sequence"] = bench_sequence(frames)
        q = res["sequence"]
        print(
            f"sequence ({q['source']}): read {q['read_ms_per_frame']:.2f} ms, locate_hands "
            f"{q['locate_hands_ms_per_frame']:.2f} ms, compute_crops "
            f"{q['compute_crops_ms_per_frame']:.2f} ms per frame"
        )
        res["memory"] = bench_memory(sizes)
        for m in res["memory"]:
            print(
                f"memory: {m['frames']} frames -> peak RSS {m['peak_rss_mb']:.0f} MB, "
                f"locate {m['locate_hands_ms_per_frame']:.2f} ms/f"
            )
    res["load_average_end"] = list(os.getloadavg())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
