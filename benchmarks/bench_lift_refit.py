"""The lift with and without the hand-model refit of the references (``lift.model_refit``).

Usage::

    .venv/bin/python benchmarks/bench_lift_refit.py /tmp/suite --part tune [--noise 0,1,2,3]
        [--ref-fraction 0.05] [--strategy uniform] --json OUT

For every sequence of the suite part and every click noise: one session (the pipeline's
``select``, the simulated annotator with that noise), lifted twice on the same annotations, refit
off and on (``pipeline.lift(refit=)``). Per run: lift error on the references (mean / median / max
mm), the click noise the refit estimated, the seconds of each lift. The machine load is recorded.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

from handanno_core.bench import (
    logged_lift,
    noisy_stage_sessions,
    print_means_by_noise,
    stage_bench_parser,
)
from handanno_core.evaluate import error_summary


def main() -> None:
    args = stage_bench_parser(__doc__.splitlines()[0], noise="0,2").parse_args()
    rows = []
    for name, noise, session, gt in noisy_stage_sessions(args, "bench-lift-refit-"):
        refs = session.reference_frames
        row = {"dataset": name, "noise_px": noise, "references": int(len(refs))}
        for refit in (False, True):
            seconds, log = logged_lift(session, refit=refit)
            row[f"lift_s_{'on' if refit else 'off'}"] = round(seconds, 2)
            lifted = session.load_results()["lifted_mm"][refs]
            row["refit" if refit else "lift"] = error_summary(lifted, gt[refs])
            found = re.findall(r"click noise ([0-9.]+) px, (?:estimated|given)", log)
            if refit and found:
                row["click_noise_estimated_px"] = [float(x) for x in found]
        row["load_avg_1m"] = round(os.getloadavg()[0], 2)
        rows.append(row)
        print(
            f"{name:>28} noise {noise:3.1f}  lift {row['lift']['mean_mm']:6.3f} / "
            f"{row['lift']['max_mm']:6.1f}  refit {row['refit']['mean_mm']:6.3f} / "
            f"{row['refit']['max_mm']:6.1f} mm  est {row.get('click_noise_estimated_px')} "
            f"({row['lift_s_off']:.1f} / "
            f"{row['lift_s_on']:.1f} s, load {row['load_avg_1m']:.1f})",
            flush=True,
        )
        Path(args.json).write_text(json.dumps(rows, indent=1))
        session.close()
    print_means_by_noise(rows, ("lift", "refit"))


if __name__ == "__main__":
    main()
