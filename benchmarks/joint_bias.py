"""Where a finished bench session's error is systematic: per joint, its mean signed error in the
hand's own palm frame, at each stage, split into visible and hidden.

For every session folder (``handanno bench --work-dir W`` leaves ``W/<sequence>/<strategy>-<f>``)
and every joint: the mean error (mm) and the mean signed error vector expressed in the true
pose's palm frame (:meth:`handanno_core.skeleton.Skeleton.palm_rotation`: ``x`` towards the
index side, ``y`` wrist to the knuckles' midpoint, ``z`` out of the palm) of the lifted references, of the
propagated initialization and of the final result on the non-reference frames; visible / hidden
as the simulated annotator marks them (exact clicks). A signed error that is a large part of
the mean error is a bias of the engine (a model's geometry, an offset), not noise: stop 42's
thumb-CMC anchor was found this way. Ground truth is used for evaluation only.

    .venv/bin/python benchmarks/joint_bias.py W/tune-fpha-2/uniform-0.05 [...] [--top 6] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from handanno_core.session import Session
from handanno_core.synth import simulate_annotations

STAGES = (("lift", "lifted_mm", True), ("init", "init_mm", False), ("final", "final_mm", False))


def joint_bias(folder: str | Path) -> dict:
    """``{stage: {joint: {...}}}`` for one session folder (see the module docstring); stages
    without frames are left out."""
    with Session.open(folder) as session:
        seq = session.open_sequence()
        results = session.load_results()
    sk = seq.skeleton
    if sk.palm_joints is None:
        raise ValueError(f"{folder}: layout {sk.name} has no palm joints")
    gt = np.asarray(seq.ground_truth.joints_mm, dtype=np.float64)
    refs = np.all(np.isfinite(results["lifted_mm"]), axis=(1, 2))
    anns = simulate_annotations(seq, np.arange(len(gt)), noise_px=0.0, seed=0)
    visible = np.stack([anns[f].visible for f in range(len(gt))])
    rot = sk.palm_rotation(gt)  # (N, 3, 3)
    out = {}
    for stage, key, on_refs in STAGES:
        x = np.asarray(results[key], dtype=np.float64)
        frames = (refs if on_refs else ~refs) & np.all(np.isfinite(x), axis=(1, 2))
        if not frames.any():
            continue
        d = x[frames] - gt[frames]
        local = np.einsum("njk,nkc->njc", d, rot[frames])  # signed error in the palm's frame
        err = np.linalg.norm(d, axis=-1)
        vis = visible[frames]
        out[stage] = {
            name: {
                "frames": int(frames.sum()),
                "mean_mm": float(err[:, j].mean()),
                "signed_palm_mm": [float(v) for v in local[:, j].mean(axis=0)],
                "visible_share": float(vis[:, j].mean()),
                "visible_mean_mm": float(err[vis[:, j], j].mean()) if vis[:, j].any() else None,
                "hidden_mean_mm": float(err[~vis[:, j], j].mean()) if (~vis[:, j]).any() else None,
            }
            for j, name in enumerate(sk.joint_names)
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--top", type=int, default=6, help="joints printed per stage (largest bias)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    report = {}
    for folder in args.sessions:
        report[str(folder)] = rows = joint_bias(folder)
        print(f"== {folder}")
        for stage, joints in rows.items():
            size = {n: float(np.linalg.norm(r["signed_palm_mm"])) for n, r in joints.items()}
            top = sorted(size, key=size.get, reverse=True)[: args.top]
            cells = [
                f"{n} {size[n]:.1f}/{joints[n]['mean_mm']:.1f} "
                f"({', '.join(f'{v:+.1f}' for v in joints[n]['signed_palm_mm'])})"
                for n in top
            ]
            print(f"  {stage:5s} bias/mean mm (x, y, z): " + "  ".join(cells))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
