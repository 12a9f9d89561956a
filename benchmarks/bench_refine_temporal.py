"""Refinement's temporal prior compared on the benchmark suite, on identical initializations.

Runs ``handanno_core.refine.refine`` with several weight sets on the sessions a suite bench left
in its work folder (``handanno bench SUITE --part P --work-dir WORK ...``: one folder per dataset,
``WORK/<dataset>/<strategy>-<fraction>``), so every variant starts from the same lift and
propagation. The constants are chosen on the suite's tune part and reported on its report part.

    handanno suite /tmp/suite --frames-scale 0.5
    handanno bench /tmp/suite --part tune --ref-fraction 0.05 --strategy uniform --work-dir /tmp/w
    .venv/bin/python benchmarks/bench_refine_temporal.py /tmp/w --json tune.json

Refinement runs as the pipeline runs it: with the hand model where the session has it on
(``settings.hand_model``, the default). The variants ``scale-*`` weigh the constant-velocity prior
by the hand's own acceleration (``RefineWeights.acceleration_scale_mm``, the default since stop
38), ``speed-7`` by the law before it, ``(7 mm / v)²`` on the initialization's median joint step;
``huber-15`` and ``huber-1`` change the prior's Huber scale (2 mm, the default, since stop 44;
every other variant uses the default's).
Prints one line per dataset (mean / max mm of the initialization and of every variant) and the
mean of means; writes the JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from handanno_core import pipeline
from handanno_core.bench import machine_description
from handanno_core.refine import RefineWeights, refine
from handanno_core.session import Session


def _speed_law(init_mm: np.ndarray, speed_mm: float = 7.0) -> RefineWeights:
    """Stops 28-37's weighting: ``(speed_mm / v)²`` within the factor range, ``v`` the median
    joint step of the initialization (sessions without breaks)."""
    w = RefineWeights(acceleration_scale_mm=None, acceleration_factor_range=(0.25, 16.0))
    step = np.linalg.norm(np.diff(init_mm, axis=0), axis=-1)
    v = max(float(np.nanmedian(step)), 1e-3)
    factor = float(np.clip((speed_mm / v) ** 2, *w.acceleration_factor_range))
    return replace(w, acceleration=w.acceleration * factor)


VARIANTS = {
    "none": RefineWeights(temporal=0.0, acceleration=0.0, acceleration_scale_mm=None),
    "velocity": RefineWeights(temporal=1.0, acceleration=0.0),  # the default until 2026-11
    "acceleration": RefineWeights(),
    "acceleration x3": RefineWeights(acceleration=3.0),
    "constant": RefineWeights(acceleration_scale_mm=None),
    "speed-7": _speed_law,  # weights made per session from its initialization
    # the acceleration law within stop 28's range 0.25-16, and (the default) within 0.25-64
    "scale-1.5": RefineWeights(acceleration_scale_mm=1.5, acceleration_factor_range=(0.25, 16.0)),
    "scale-2": RefineWeights(acceleration_scale_mm=2.0, acceleration_factor_range=(0.25, 16.0)),
    "scale-3": RefineWeights(acceleration_scale_mm=3.0, acceleration_factor_range=(0.25, 16.0)),
    "scale-2-top-64": RefineWeights(
        acceleration_scale_mm=2.0, acceleration_factor_range=(0.25, 64.0)
    ),
    # the prior's Huber scale: 2 mm (the default since stop 44), 15 mm before, and 1 mm
    "huber-15": RefineWeights(acceleration_huber_mm=15.0),
    "huber-1": RefineWeights(acceleration_huber_mm=1.0),
}


def _errors(pred: np.ndarray, gt: np.ndarray) -> list[float]:
    e = np.linalg.norm(pred - gt, axis=-1)
    return [round(float(np.nanmean(e)), 3), round(float(np.nanmax(e)), 2)]


def run_session(folder: Path, variants: dict[str, RefineWeights | Callable]) -> dict:
    """Initialization and final errors (mean, max mm) of every variant on one bench session."""
    session = Session.open(folder)
    try:
        gt = session.open_sequence().ground_truth.joints_mm
        init, problem = pipeline.refine_inputs(session, quiet=True)
        model = bool(session.model.settings.hand_model)
        row = {"frames": session.num_frames, "init": _errors(init, gt), "variants": {}}
        row["hand_model"] = model
        for name, weights in variants.items():
            if callable(weights):
                if session.model.sequence_breaks:
                    raise ValueError(f"{folder}: variant {name} ignores sequence breaks")
                weights = weights(init)
            t = time.perf_counter()
            out = refine(init, weights=weights, hand_model=model, **problem)
            row["variants"][name] = {
                "final": _errors(out.joints_mm, gt),
                "time_s": round(time.perf_counter() - t, 1),
            }
        return row
    finally:
        session.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path, help="work folder of a suite bench (--work-dir)")
    ap.add_argument("--run", default="uniform-0.05", help="session folder inside each dataset")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated names")
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args()
    variants = {name: VARIANTS[name] for name in args.variants.split(",")}
    doc = {"machine": machine_description(), "run": args.run, "datasets": {}}
    for folder in sorted(args.work.glob(f"*/{args.run}")):
        load = os.getloadavg()[0]
        row = run_session(folder, variants)
        row["load_avg_1m"] = round(load, 1)
        doc["datasets"][folder.parent.name] = row
        cells = "  ".join(
            f"{k} {v['final'][0]:6.2f}/{v['final'][1]:5.0f}" for k, v in row["variants"].items()
        )
        print(
            f"{folder.parent.name:32s} init {row['init'][0]:6.2f}/{row['init'][1]:5.0f}  {cells}",
            flush=True,
        )
        args.json.write_text(json.dumps(doc, indent=2))
    rows = list(doc["datasets"].values())
    doc["mean_of_means"] = {
        "init": round(float(np.mean([r["init"][0] for r in rows])), 3),
        **{
            k: round(float(np.mean([r["variants"][k]["final"][0] for r in rows])), 3)
            for k in variants
        },
    }
    doc["worse_than_init"] = {
        k: [n for n, r in doc["datasets"].items() if r["variants"][k]["final"][0] > r["init"][0]]
        for k in variants
    }
    args.json.write_text(json.dumps(doc, indent=2))
    print("mean of means:", doc["mean_of_means"])
    print("worse than the initialization:", doc["worse_than_init"])


if __name__ == "__main__":
    main()
