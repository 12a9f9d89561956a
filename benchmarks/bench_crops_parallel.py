"""The crop cache built by one process and by ``--workers`` processes: wall time and identity.

Builds the cache (``pipeline.ensure_crops``: locate the hand in every frame, grow the cube if
needed, cut the crops into the memory-mapped file) twice on fresh sessions over the same dataset,
once with one process and once with ``--workers``, and checks that ``crops.npy`` and the centres
and boxes are bit-identical. Location runs in parallel over whole sequences (the hint chain
restarts at every break), so the dataset should have breaks: by default a tiled MSRA-layout
dataset of ``--copies`` gesture folders linking the frames of one ``--base-frames``-frame
synthetic sequence (``tests/large_session.py``; every frame is located and cut for real).

    nice .venv/bin/python benchmarks/bench_crops_parallel.py [--dataset DIR] [--copies 20]
        [--base-frames 100] [--workers 2] [--json benchmarks/results/crops_parallel.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from handanno_core.bench import machine_description  # noqa: E402


def build(dataset: Path, folder: Path, workers: int) -> dict:
    from handanno_core.pipeline import ensure_crops, new_session

    session = new_session(folder, dataset, format="msra", overwrite=True)
    t0 = time.perf_counter()
    _, centres, boxes = ensure_crops(session, quiet=True, workers=workers)
    row = {
        "workers": workers,
        "wall_s": round(time.perf_counter() - t0, 1),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    session.close()
    print(json.dumps(row), flush=True)
    return {"row": row, "centres": centres, "boxes": boxes}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, help="an MSRA-layout dataset (default: tiled)")
    ap.add_argument("--copies", type=int, default=20)
    ap.add_argument("--base-frames", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks/results/crops_parallel.json")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="bench-crops-parallel-"))
    try:
        if args.dataset is None:
            from large_session import tiled_dataset

            from handanno_core.synth import generate_sequence

            base = tmp / "base"
            generate_sequence(base, frames=args.base_frames, seed=0, progress=False, workers=1)
            dataset = tiled_dataset(base, tmp / "data", args.copies)
            source = (
                f"tiled: {args.copies} folders x {args.base_frames} frames (one synthetic motion)"
            )
        else:
            dataset, source = args.dataset, str(args.dataset)
        one = build(dataset, tmp / "one", 1)
        many = build(dataset, tmp / "many", args.workers)
        same = (tmp / "one" / "crops.npy").read_bytes() == (tmp / "many" / "crops.npy").read_bytes()
        from handanno_core.session import Session

        with Session.open(tmp / "one") as s:
            frames, breaks = s.num_frames, len(s.model.sequence_breaks)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    report = {
        "dataset": source,
        "frames": frames,
        "sequence_breaks": breaks,
        "runs": [one["row"], many["row"]],
        "speedup": round(one["row"]["wall_s"] / max(many["row"]["wall_s"], 1e-9), 2),
        "identical": bool(
            same
            and np.array_equal(one["centres"], many["centres"], equal_nan=True)
            and np.array_equal(one["boxes"], many["boxes"], equal_nan=True)
        ),
        "machine": machine_description(),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
