"""Refinement with the hand model's energy inside the LM, at several weights, on one propagation.

Usage::

    .venv/bin/python benchmarks/bench_refine_model.py /tmp/suite --part tune
        [--weights 0,0.3,1,3] [--ref-fraction 0.05] [--strategy uniform] --json OUT

For every sequence of the suite part: the pipeline's select, the simulated annotator (exact 2D),
lift and propagation with the hand model, then :func:`handanno_core.refine.refine` with the model
on and ``RefineWeights(model=w)`` for every weight (the same initialization each time). Per
weight: final mean / max joint error (mm), frames that kept their initialization, seconds. The
machine load is recorded.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from handanno_core import pipeline
from handanno_core.bench import annotated_session, stage_bench_parser, suite_base_sessions
from handanno_core.evaluate import error_summary
from handanno_core.refine import RefineWeights, refine


def main() -> None:
    ap = stage_bench_parser(__doc__.splitlines()[0])
    ap.add_argument("--weights", default="0,0.3,1,3")
    args = ap.parse_args()
    weights = [float(x) for x in args.weights.split(",")]
    rows = []
    for name, base, gt, tmp in suite_base_sessions(args.suite, args.part, "bench-refine-model-"):
        session = annotated_session(base, tmp / "run", args.strategy, args.ref_fraction)
        pipeline.lift(session, quiet=True)
        pipeline.propagate(session, quiet=True, use_model=True)
        init, problem = pipeline.refine_inputs(session, True)
        row = {"dataset": name, "init": error_summary(init, gt)}
        for w in weights:
            t = time.perf_counter()
            res = refine(init, weights=RefineWeights(model=w), hand_model=True, **problem)
            row[f"model_{w:g}"] = {
                **error_summary(res.joints_mm, gt),
                "kept_initialization": len(res.info.get("kept_initialization", [])),
                "seconds": round(time.perf_counter() - t, 1),
            }
        row["load_avg_1m"] = round(os.getloadavg()[0], 2)
        rows.append(row)
        print(
            f"{name:>28} init {row['init']['mean_mm']:6.2f}  "
            + "  ".join(
                f"w={w:g}: {row[f'model_{w:g}']['mean_mm']:6.2f} / "
                f"{row[f'model_{w:g}']['max_mm']:6.1f}"
                for w in weights
            ),
            flush=True,
        )
        Path(args.json).write_text(json.dumps(rows, indent=1))
        session.close()
    for w in weights:
        means = [r[f"model_{w:g}"]["mean_mm"] for r in rows]
        print(f"w={w:g}: mean of means {np.mean(means):.3f} mm over {len(means)} sequences")


if __name__ == "__main__":
    main()
