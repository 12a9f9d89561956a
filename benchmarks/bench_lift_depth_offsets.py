"""How the lift's depth error follows the surface offsets: the references lifted with every
non-tip joint's offset moved by each of ``--shifts`` mm.

Usage::

    .venv/bin/python benchmarks/bench_lift_depth_offsets.py /tmp/suite --part tune
        [--shifts -1,0,1,2] [--noise 0] [--ref-fraction 0.05] [--strategy uniform] --json OUT

For every sequence of the suite part and click noise (px, comma-separated; default exact): one
session (the pipeline's ``select``, the simulated annotator's clicks at that noise), its
references lifted by :func:`handanno_core.lift.lift_references` (bones estimated, no hand-model
refit) once per shift, the skeleton's surface offsets (the depth of a joint centre
below the observed surface, :attr:`Skeleton.surface_offsets_mm`) moved by the shift for every
joint but the fingertips (the anchor of :func:`handanno_core.lift.references.surface_correction`).
Per run: lift error on the references (mean / max mm), the mean signed depth error (lifted minus
true z; all joints and the visible ones), the mean lift objective and what the per-session
calibration changed. Shift 0 is the shipped lift. Ground truth is used for evaluation only; the
shifts are a sensitivity, not a setting: the last lines say which shift would have been best per
sequence, which no session can know.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np

from handanno_core.bench import noisy_stage_sessions, stage_bench_parser
from handanno_core.lift import lift_references


def main() -> None:
    ap = stage_bench_parser(__doc__.splitlines()[0], noise="0")
    ap.add_argument("--shifts", default="-1,0,1,2", help="offset shifts (mm), comma-separated")
    args = ap.parse_args()
    shifts = [float(x) for x in args.shifts.split(",")]
    rows = []
    for name, noise, session, gt in noisy_stage_sessions(args, "bench-lift-depth-"):
        refs = session.reference_frames
        sequence = session.open_sequence()
        sk = sequence.skeleton
        annotations = session.annotations(refs)
        visible = np.stack([annotations[f].visible for f in refs])
        truth = gt[refs]
        moved = np.where(sk.surface_groups() >= 0, 1.0, 0.0)  # every joint but the tips
        row = {"dataset": name, "noise_px": noise, "references": int(len(refs)), "runs": []}
        for shift in shifts:
            offsets = np.asarray(sk.surface_offsets_mm, dtype=np.float64) + shift * moved
            shifted = dataclasses.replace(sk, surface_offsets_mm=tuple(float(o) for o in offsets))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "stretched" references: counted elsewhere
                lifted = lift_references(annotations, sequence.depth, sequence.camera, shifted)
            joints = np.stack([lifted.joints_mm[f] for f in refs])
            err = np.linalg.norm(joints - truth, axis=-1)
            dz = (joints - truth)[..., 2]
            run = {
                "shift_mm": shift,
                "lift_mean_mm": round(float(err.mean()), 3),
                "lift_max_mm": round(float(err.max()), 2),
                "dz_mean_mm": round(float(dz.mean()), 3),
                "dz_visible_mean_mm": round(float(dz[visible].mean()), 3),
                "objective_mean": round(
                    float(np.mean([lifted.results[f].objective for f in refs])), 4
                ),
                "calibration_mm": round(
                    float(np.max(np.abs(lifted.surface_offsets_mm - offsets))), 3
                ),
            }
            row["runs"].append(run)
            print(
                f"{name:>24} noise {noise:3.1f} shift {shift:+4.1f}  lift {run['lift_mean_mm']:6.3f} / "
                f"{run['lift_max_mm']:5.1f} mm  dz {run['dz_mean_mm']:+6.2f} (visible "
                f"{run['dz_visible_mean_mm']:+6.2f})  objective {run['objective_mean']:.3f}  "
                f"calibrated by {run['calibration_mm']:.2f} mm",
                flush=True,
            )
        row["visible_share"] = round(float(visible.mean()), 3)
        rows.append(row)
        Path(args.json).write_text(json.dumps(rows, indent=1))
        session.close()
    for noise in sorted({row["noise_px"] for row in rows}):
        part = [row for row in rows if row["noise_px"] == noise]
        for shift in shifts:
            sel = [r["lift_mean_mm"] for row in part for r in row["runs"] if r["shift_mm"] == shift]
            print(
                f"noise {noise:3.1f} shift {shift:+4.1f}: mean of means {np.mean(sel):.3f} mm ({len(sel)})"
            )
        best = [min(row["runs"], key=lambda r: r["lift_mean_mm"]) for row in part]
        print(f"noise {noise:3.1f} best shift per sequence (ground truth; no session can know it): " + ", ".join(
            f"{row['dataset']} {b['shift_mm']:+g} ({b['lift_mean_mm']:.3f})"
            for row, b in zip(part, best, strict=True)
        ))  # fmt: skip
        print(
            f"noise {noise:3.1f} mean of the per-sequence best: {np.mean([b['lift_mean_mm'] for b in best]):.3f} mm"
        )


if __name__ == "__main__":
    main()
