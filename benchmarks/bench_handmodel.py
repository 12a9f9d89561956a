"""Benchmark of the per-frame hand-model fit (handanno_core.handmodel) on synthetic frames.

A synthetic sequence (``synth.generate_sequence``: sensor noise, forearm, ellipsoid palm, i.e. a
hand that is *not* the capsule model) is cropped with ``crops.locate_hands`` (no ground truth).
The model is personalized from every ``--ref-step``-th frame with the ground-truth joints standing
in for lifted references (this benchmark measures speed and basin, not the lift). Every frame is
then fitted alone (as propagation does) from its ground truth perturbed by ``--perturb-mm``
(smooth per-joint offsets, larger at the tips), with a weak pose prior to that start; reported:
wall and CPU (process) ms per frame on one core (single-threaded BLAS), LM iterations, error
before/after. A batched fit of all frames at once (as refinement evaluates the term) is timed too,
and the per-finger hypotheses (``handmodel.refit_fingers``) tried on every batched fit.
``--dataset PATH`` fits a dataset's own frames (e.g. a suite sequence) instead of a synth sequence.

    nice .venv/bin/python benchmarks/bench_handmodel.py [--frames 200] [--seed 3] [--dataset P]

Writes benchmarks/results/handmodel.json.

``--compare DATASET ...`` instead runs ``handanno bench --model off,on`` (``--strategy``
selection, simulated exact 2D annotator, bones estimated by the lift; propagation + refinement
twice on the same lift, without and with the hand model) and prints its tables (``--json`` to
save them; ``--part`` for a suite folder).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from handanno_core import handmodel as hm
from handanno_core.blas import single_blas_thread
from handanno_core.crops import DEFAULT_CROP, compute_crops, crop_boxes, locate_hands
from handanno_core.datasets import open_sequence
from handanno_core.synth import generate_sequence


def compare(
    datasets: list[str],
    fractions: list[float],
    json_out: str | None,
    strategy: str = "uniform",
    workers: int = 1,
    part: str | None = None,
) -> dict:
    """With / without the hand model on the same selection and lift: ``handanno bench --model
    off,on`` (:func:`handanno_core.bench.run_bench_datasets`), one strategy."""
    from handanno_core.bench import run_bench_datasets

    out = json_out or str(Path(tempfile.mkdtemp(prefix="bench-handmodel-cmp-")) / "compare.json")
    return run_bench_datasets(
        datasets,
        part=part,
        json_out=out,
        fractions=fractions,
        strategies=[strategy],
        models=[False, True],
        workers=workers,
    )


def _frames(args):
    """The benchmark's sequence and its crops, boxes, centres and cube (``--dataset`` or synth)."""
    tmp = Path(tempfile.mkdtemp(prefix="bench-handmodel-"))
    cube_mm = DEFAULT_CROP.cube_mm
    if args.dataset:
        from handanno_core import pipeline

        base = pipeline.new_session(tmp / "base", args.dataset, overwrite=True)
        seq = base.open_sequence()
        crops, centres, boxes = pipeline.ensure_crops(base, quiet=True)
        crops = np.asarray(crops, dtype=np.float32)
        cube_mm = base.model.settings.cube_mm
    else:
        generate_sequence(tmp / "seq", frames=args.frames, seed=args.seed, progress=False)
        seq = open_sequence(tmp / "seq")
        centres = locate_hands(seq)
        boxes = crop_boxes(centres, seq.camera)
        crops = compute_crops(seq, centres)
    return seq, crops, centres, boxes, cube_mm


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--dataset", help="fit on this dataset's frames instead of a synth sequence")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--ref-step", type=int, default=20)
    ap.add_argument("--perturb-mm", type=float, default=6.0)
    ap.add_argument("--out", default="benchmarks/results/handmodel.json")
    ap.add_argument("--compare", nargs="+", metavar="DATASET")
    ap.add_argument("--fractions", default="0.05,0.10")
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--strategy", default="uniform", help="selection strategy of --compare")
    ap.add_argument("--workers", type=int, default=1, help="processes of --compare")
    ap.add_argument("--part", choices=["tune", "report", "all"], help="suite part of --compare")
    args = ap.parse_args()
    if args.compare:
        fractions = [float(f) for f in args.fractions.split(",")]
        compare(args.compare, fractions, args.json_out, args.strategy, args.workers, args.part)
        return

    seq, crops, centres, boxes, cube_mm = _frames(args)
    gt = seq.ground_truth.joints_mm
    cam, sk = seq.camera, seq.skeleton
    bones = sk.estimate_bone_lengths(gt)

    t = time.perf_counter()
    obs = hm.observe(crops, boxes, centres, cam, cube_mm=cube_mm)
    observe_ms = (time.perf_counter() - t) * 1000 / len(gt)
    refs = np.arange(0, len(gt), args.ref_step)
    t = time.perf_counter()
    model = hm.personalize(sk, bones, gt[refs], obs.take(refs))
    personalize_s = time.perf_counter() - t

    rng = np.random.default_rng(args.seed)
    offs = rng.normal(size=gt.shape)
    offs *= args.perturb_mm / np.sqrt(np.mean(np.sum(offs**2, axis=-1)))
    offs[:, list(sk.fingertips)] *= 1.5
    start = gt + offs
    kin = hm.Kinematics(sk, model.bone_lengths_mm)
    fitted = np.empty_like(gt)
    iters = []
    with single_blas_thread():
        t, c = time.perf_counter(), time.process_time()
        for f in range(len(gt)):
            pri = hm.Priors(pose=start[f][None], pose_w=np.ones((1, sk.num_joints)))
            r = hm.fit_frames(model, start[f][None], obs.take([f]), cam, priors=pri, kin=kin)
            fitted[f] = r.joints_mm[0]
            iters.append(r.iterations)
        single_ms = (time.perf_counter() - t) * 1000 / len(gt)
        single_cpu = (time.process_time() - c) * 1000 / len(gt)
        t, c = time.perf_counter(), time.process_time()
        pri = hm.Priors(pose=start, pose_w=np.ones(gt.shape[:2]))
        batched = hm.fit_frames(model, start, obs, cam, priors=pri, kin=kin)
        batched_ms = (time.perf_counter() - t) * 1000 / len(gt)
        batched_cpu = (time.process_time() - c) * 1000 / len(gt)
        # per-finger hypotheses on every frame (propagation tries only frames whose fit is above
        # PropagationSettings.finger_level): grid only, no per-frame starts
        t, c = time.perf_counter(), time.process_time()
        fingers = hm.refit_fingers(model, batched, obs, cam, priors=pri, kin=kin)
        fingers_ms = (time.perf_counter() - t) * 1000 / len(gt)
        fingers_cpu = (time.process_time() - c) * 1000 / len(gt)

    def err(x):
        e = np.linalg.norm(x - gt, axis=-1)
        return {"mean_mm": round(float(e.mean()), 2), "max_mm": round(float(e.max()), 1)}

    doc = {
        "dataset": str(args.dataset) if args.dataset else f"synth --frames {args.frames}",
        "frames": len(gt),
        "seed": args.seed,
        "perturb_mm": args.perturb_mm,
        "radii_mm": [round(float(r), 2) for r in model.radii],
        "personalize_s": round(personalize_s, 2),
        "observe_ms_per_frame": round(observe_ms, 2),
        "fit_ms_per_frame_single": round(single_ms, 1),
        "fit_ms_per_frame_batched": round(batched_ms, 1),
        "fit_cpu_ms_per_frame_single": round(single_cpu, 1),
        "fit_cpu_ms_per_frame_batched": round(batched_cpu, 1),
        "fingers_ms_per_frame_tried": round(fingers_ms, 1),
        "fingers_cpu_ms_per_frame_tried": round(fingers_cpu, 1),
        "fingers_changed_frames": int(np.sum(fingers.energy < batched.energy)),
        "iterations_mean": round(float(np.mean(iters)), 1),
        "start": err(start),
        "fitted_single": err(fitted),
        "fitted_batched": err(batched.joints_mm),
        "fitted_batched_fingers": err(fingers.joints_mm),
        "load_average": [round(x, 2) for x in os.getloadavg()],
    }
    print(json.dumps(doc, indent=1))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
