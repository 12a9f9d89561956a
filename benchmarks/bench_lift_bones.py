"""The lift with and without the second bone estimate for noisy clicks (``lift_denoise_min_px``).

Usage::

    .venv/bin/python benchmarks/bench_lift_bones.py /tmp/suite --part tune [--noise 0,1,2]
        [--ref-fraction 0.05] [--strategy uniform] --json OUT

For every sequence of the suite part and every click noise: one session (the pipeline's
``select``, the simulated annotator with that noise), lifted twice on the same annotations: one
bone estimate from the clicks as they are (``lift_denoise_min_px`` None), and the default (a
second estimate, shrunk and from the clicks moved towards the refit, tried where the click noise
reaches 1 px and kept where the hand model explains the references' depth better). Per run: lift
error on the references (mean / median / max mm), the mean relative bone-length error against
the ground truth's median lengths (scoring only), the click noise the refit estimated, whether
the second estimate was kept, the seconds of each lift. The machine load is recorded.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from handanno_core.bench import (
    logged_lift,
    noisy_stage_sessions,
    print_means_by_noise,
    stage_bench_parser,
)
from handanno_core.evaluate import error_summary


def main() -> None:
    args = stage_bench_parser(__doc__.splitlines()[0], noise="0,1,2").parse_args()
    rows = []
    for name, noise, session, gt in noisy_stage_sessions(args, "bench-lift-bones-"):
        refs = session.reference_frames
        sk = session.skeleton
        true_bones = np.median(sk.bone_lengths(gt), axis=0)
        row = {"dataset": name, "noise_px": noise, "references": int(len(refs))}
        default = session.model.settings.lift_denoise_min_px
        for key, least in (("once", None), ("default", default)):
            session.model.settings.lift_denoise_min_px = least
            session.save()
            seconds, text = logged_lift(session)
            row[f"lift_s_{key}"] = round(seconds, 2)
            lifted = session.load_results()["lifted_mm"][refs]
            row[key] = error_summary(lifted, gt[refs])
            bones = np.asarray(session.model.bone_lengths_mm)
            row[f"bone_rel_error_{key}"] = round(
                float(np.mean(np.abs(bones - true_bones) / true_bones)), 4
            )
            found = re.findall(r"click noise ([0-9.]+) px, estimated", text)
            row["click_noise_estimated_px"] = [float(x) for x in found][:1]
            if key == "default":
                row["second_estimate"] = (
                    "kept" if ": kept" in text else "not kept" if "not kept" in text else "-"
                )
        row["load_avg_1m"] = round(os.getloadavg()[0], 2)
        rows.append(row)
        print(
            f"{name:>28} noise {noise:3.1f}  once {row['once']['mean_mm']:6.3f} / "
            f"{row['once']['max_mm']:6.1f}  default {row['default']['mean_mm']:6.3f} / "
            f"{row['default']['max_mm']:6.1f} mm  bones {row['bone_rel_error_once']:.3f} -> "
            f"{row['bone_rel_error_default']:.3f}  est {row['click_noise_estimated_px']} "
            f"second {row['second_estimate']} ({row['lift_s_once']:.1f} / "
            f"{row['lift_s_default']:.1f} s, load {row['load_avg_1m']:.1f})",
            flush=True,
        )
        Path(args.json).write_text(json.dumps(rows, indent=1))
        session.close()
    print_means_by_noise(rows, ("once", "default"))


if __name__ == "__main__":
    main()
