"""A whole dataset through the whole pipeline: per-stage time and memory, local and on Dask.

Generates a synthetic MSRA-layout dataset (``P0/1`` ... ``P8/Y``: ``--folders`` gesture folders of
``--frames-per-folder`` frames, each rendered by ``synth.generate_sequence`` with its own seed, so
the dataset opens as one sequence with a break at every folder), then runs every stage as its own
``handanno`` CLI process (the measured process is the pipeline alone, not this script):

``new`` -> crops -> ``select --strategy forest --ref-fraction F`` -> ``annotate-from-gt`` (the
simulated annotator, exact 2D) -> ``lift --workers W`` -> ``propagate --workers W`` ->
``refine --window K --workers W`` (pieces, :mod:`handanno_core.pieces`).

For each stage: wall time, CPU seconds, the peak RSS of its largest process (``wait4``) and the
peak of the *sum* over its process tree (sampled every 0.2 s with psutil: workers included).
Then, on copies of the annotated session:

* ``--dask``: lift, propagate and refine again with ``--scheduler`` on a ``LocalCluster`` (2
  worker processes, 1 thread each; the cluster's processes are included in the sampled sum),
  and a check that ``lifted_mm``, ``init_mm`` and ``final_mm`` are bit-identical to the local run;
* ``--compare-whole``: the refinement as one whole solve (the old way) and in windows of
  ``--small-window`` frames, with time, memory and the difference to the pieces' result.

Accuracy (per-joint 3D error against the synthetic ground truth): over all frames, the spread of
the per-folder means, every folder's mean/max (``per_folder_final``), and per subject its mean and
the relative error of the bone lengths the session gave its frames (``hands_report``; the session
has one hand per subject folder unless ``--one-hand``). ``--per-sequence N``: the same pipeline on
N folders (gesture 1 of P0, P1, ... in turn) as separate sessions, beside the same folders inside
the big session (``per_sequence``).

    nice .venv/bin/python benchmarks/bench_scale.py [--folders 153] [--frames-per-folder 500]
        [--ref-fraction 0.05] [--workers 2] [--window 1024] [--dask] [--compare-whole]
        [--hands subject|folder] [--one-hand] [--per-sequence N] [--data DIR] [--work DIR]
        [--json benchmarks/results/scale.json]

The dataset is kept in ``--data`` (reused when complete). Writes the JSON given by ``--json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handanno_core.bench import machine_description  # noqa: E402
from handanno_core.datasets.msra import GESTURES  # noqa: E402


def generate(data: Path, folders: int, frames: int, workers: int, hands: str) -> float:
    """Render the dataset (folders already complete are kept); returns seconds spent.

    Folder ``k`` is subject ``P{k // 17}``, gesture ``k % 17``, motion seed ``1000 + k``. Its hand:
    ``hands="subject"`` one hand per subject (``make_hand_model(subject)``, as in MSRA where the
    17 gestures of a subject share a hand), ``"folder"`` the seed's own hand (every folder a
    different hand, as ``generate_sequence`` does)."""
    from handanno_core import synth

    t0 = time.perf_counter()
    for k in range(folders):
        subject, gesture = divmod(k, len(GESTURES))
        out = data / f"P{subject}" / GESTURES[gesture]
        if (out / "joint.txt").exists() and (out / f"{frames - 1:06d}_depth.bin").exists():
            continue
        seed = 1000 + k
        if hands == "folder":
            synth.generate_sequence(out, frames=frames, seed=seed, progress=False, workers=workers)
            continue
        motion = synth.synthesize_motion(frames, seed, model=synth.make_hand_model(subject))
        synth.write_sequence(
            out, motion.model, motion.joints_mm, motion.rotation, seed=seed,
            forearm=None,
            info=synth.describe_motion(motion, seed), progress=False, workers=workers,
        )  # fmt: skip
    return time.perf_counter() - t0


class _Sampler:
    """Peak of the summed RSS of a process tree (plus extra pids) and its CPU seconds, sampled
    every 0.2 s (a worker's last < 0.2 s of CPU before it exits can be missed; the extra pids'
    CPU before the start is not counted)."""

    def __init__(self, pid: int, extra: list[int]):
        import psutil

        self.psutil = psutil
        self.roots = [pid, *extra]
        self.peak = 0
        self.cpu: dict[int, float] = {}
        self.base = {}
        for root in extra:
            try:
                for q in [psutil.Process(root), *psutil.Process(root).children(recursive=True)]:
                    self.base[q.pid] = sum(q.cpu_times()[:2])
            except psutil.Error:
                continue
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        ps = self.psutil
        while not self._stop.is_set():
            total = 0
            for root in self.roots:
                try:
                    proc = ps.Process(root)
                    for p in [proc, *proc.children(recursive=True)]:
                        total += p.memory_info().rss
                        self.cpu[p.pid] = sum(p.cpu_times()[:2])
                except ps.Error:
                    continue
            self.peak = max(self.peak, total)
            self._stop.wait(0.2)

    def stop(self) -> tuple[float, float]:
        """(peak summed RSS in MB, CPU seconds of the tree)."""
        self._stop.set()
        self._thread.join()
        cpu = sum(c - self.base.get(pid, 0.0) for pid, c in self.cpu.items())
        return self.peak / 2**20, cpu


def stage(name: str, args: list[str], log: Path, extra_pids: list[int] | None = None) -> dict:
    """Run ``python -m app.cli ARGS`` (or a ``-c`` script) and measure it."""
    cmd = [sys.executable, "-u", *(args if args[0] == "-c" else ["-m", "app.cli", *args])]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with open(log, "a") as out:
        out.write(f"\n$ {' '.join(cmd)}\n")
        out.flush()
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT)
        sampler = _Sampler(proc.pid, extra_pids or [])
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        summed, cpu = sampler.stop()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"stage {name} failed (exit {proc.returncode}); see {log}")
    row = {
        "stage": name,
        "wall_s": round(wall, 1),
        "cpu_s_sampled": round(cpu, 1),
        "peak_rss_largest_mb": round(usage.ru_maxrss / 1024.0, 1),
        "peak_rss_sum_mb": round(summed, 1),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    print(json.dumps(row), flush=True)
    return row


def _folders_of(seq) -> tuple[list[str], list[int]]:
    """Each gesture folder's name relative to the dataset (``P0/1``; ``.`` for a single folder)
    and the frame cuts ``[0, breaks..., N]`` (the folders are the reader's sequences)."""
    names = seq.frame_names
    cuts = [0, *seq.sequence_breaks, len(seq)]
    return [os.path.dirname(names[a]) or "." for a in cuts[:-1]], cuts


def per_folder_errors(folder: Path, key: str = "final_mm") -> dict[str, dict]:
    """``{gesture folder: {"mean_mm", "max_mm"}}`` of a session's ``key`` joints."""
    from handanno_core.session import Session

    with Session.open(folder) as s:
        seq = s.open_sequence()
        gt = seq.ground_truth.joints_mm
        pred = s.load_results()[key]
    names, cuts = _folders_of(seq)
    err = np.linalg.norm(pred - gt, axis=-1)
    return {
        n: {
            "mean_mm": round(float(np.nanmean(err[a:b])), 3),
            "max_mm": round(float(np.nanmax(err[a:b])), 2),
        }
        for n, a, b in zip(names, cuts[:-1], cuts[1:], strict=True)
    }


def hand_report(folder: Path) -> dict:
    """Per subject (the MSRA reader's hand labels, whatever hands the session used): the final
    mean error and the relative error of the bone lengths the session gave its frames against
    the subject's true ones (mean over bones, %; ground truth: evaluation only)."""
    from handanno_core.session import Session

    with Session.open(folder) as s:
        seq = s.open_sequence()
        gt = seq.ground_truth.joints_mm
        pred = s.load_results()["final_mm"]
        bones = np.broadcast_to(s.frame_bone_lengths(), (len(gt), len(seq.skeleton.bones)))
        labels = seq.hand_labels or ["all"]
        cuts = [0, *seq.sequence_breaks, len(seq)]
        hands_used = s.hand_names
    subject = np.repeat(labels, np.diff(cuts))
    true_bones = seq.skeleton.bone_lengths(gt)
    err = np.linalg.norm(pred - gt, axis=-1).mean(axis=1)
    out = {}
    for name in dict.fromkeys(labels):
        at = subject == name
        truth = true_bones[at].mean(axis=0)
        out[name] = {
            "frames": int(at.sum()),
            "final_mean_mm": round(float(np.nanmean(err[at])), 3),
            "bone_rel_err_pct": round(
                float(np.mean(np.abs(bones[at].mean(axis=0) / truth - 1)) * 100), 2
            ),
        }
    return {"session_hands": hands_used, "per_subject": out}


def accuracy(folder: Path, key: str) -> dict:
    from handanno_core.evaluate import error_summary
    from handanno_core.session import Session

    with Session.open(folder) as s:
        seq = s.open_sequence()
        gt = seq.ground_truth.joints_mm
        pred = s.load_results()[key]
        refs = s.reference_frames
        cuts = [0, *s.model.sequence_breaks, s.num_frames]
    all_ = error_summary(pred, gt)
    non_ref = np.setdiff1d(np.arange(len(gt)), refs)
    err = np.linalg.norm(pred - gt, axis=-1).mean(axis=1)
    per_folder = [float(np.nanmean(err[a:b])) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    return {
        "mean_mm": round(float(all_["mean_mm"]), 3),
        "median_mm": round(float(all_["median_mm"]), 3),
        "max_mm": round(float(all_["max_mm"]), 2),
        "non_reference_mean_mm": round(
            float(error_summary(pred, gt, frames=non_ref)["mean_mm"]), 3
        ),
        "per_folder_mean_mm": {
            "min": round(min(per_folder), 3),
            "median": round(float(np.median(per_folder)), 3),
            "max": round(max(per_folder), 3),
        },
    }


def per_sequence(a, big: Path, sessions: Path, log: Path, inside: dict[str, dict]) -> dict:
    """The same pipeline (fraction, strategy, simulated annotation, lift, propagate, refine) on
    ``a.per_sequence`` gesture folders, each its own session: their final mean/max beside the
    same folders' errors inside the big session ``big``."""
    subjects = max(1, -(-a.folders // len(GESTURES)))
    rows = []
    w = str(a.workers)
    for i in range(a.per_sequence):
        subject, gesture = i % subjects, i // subjects
        if subject * len(GESTURES) + gesture >= a.folders:
            break
        name = f"P{subject}/{GESTURES[gesture]}"
        tag = f"seq-P{subject}-{GESTURES[gesture]}"
        base = ["--sessions-dir", str(sessions)]
        for step, args in (
            ("new", [*base, "new", tag, str(a.data / name)]),
            ("select", [*base, "select", tag, "--strategy", "forest"]
             + ["--ref-fraction", str(a.ref_fraction)]),
            ("annotate", [*base, "annotate-from-gt", tag]),
            ("lift", [*base, "lift", tag, "--workers", w]),
            ("propagate", [*base, "propagate", tag, "--workers", w]),
            ("refine", [*base, "refine", tag, "--workers", w, "--window", str(a.window)]),
        ):  # fmt: skip
            stage(f"{tag}-{step}", args, log)
        own = per_folder_errors(sessions / tag)["."]
        rows.append({"folder": name, "alone": own, "in_big_session": inside[name]})
    alone = [r["alone"]["mean_mm"] for r in rows]
    big_ = [r["in_big_session"]["mean_mm"] for r in rows]
    return {
        "folders": rows,
        "alone_mean_mm": round(float(np.mean(alone)), 3),
        "in_big_session_mean_mm": round(float(np.mean(big_)), 3),
        "alone_max_mm": max(r["alone"]["max_mm"] for r in rows),
        "in_big_session_max_mm": max(r["in_big_session"]["max_mm"] for r in rows),
    }


def reports(s: Path) -> dict:
    """The main run's accuracy: per stage, per subject (with bone errors), per folder."""
    return {
        "accuracy": {
            k: accuracy(s, key)
            for k, key in (("lift", "lifted_mm"), ("init", "init_mm"), ("final", "final_mm"))
        },
        "hands_report": hand_report(s),
        "per_folder_final": per_folder_errors(s),
    }


def results(folder: Path) -> dict[str, np.ndarray]:
    from handanno_core.session import Session

    with Session.open(folder) as s:
        return {k: np.asarray(v) for k, v in s.load_results().items()}


def _args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--folders", type=int, default=153)
    ap.add_argument("--frames-per-folder", type=int, default=500)
    ap.add_argument("--ref-fraction", type=float, default=0.05)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--window", type=int, default=1024)
    ap.add_argument("--small-window", type=int, default=200)
    ap.add_argument("--hands", choices=["subject", "folder"], default="subject")
    ap.add_argument(
        "--one-hand",
        action="store_true",
        help="the session treats every subject as one hand (handanno new --one-hand)",
    )
    ap.add_argument(
        "--per-sequence",
        type=int,
        default=0,
        metavar="N",
        help="after the main run, run the same pipeline on N gesture folders (one per subject "
        "in turn: gesture 1 of P0, P1, ...) as separate sessions and compare them with the same "
        "folders inside the big session",
    )
    ap.add_argument("--dask", action="store_true")
    ap.add_argument("--compare-whole", action="store_true")
    ap.add_argument("--data", type=Path, default=Path("/tmp/handanno-scale-data"))
    ap.add_argument("--work", type=Path, default=Path("/tmp/handanno-scale-work"))
    ap.add_argument("--json", type=Path, default=ROOT / "benchmarks/results/scale.json")
    return ap.parse_args()


def main() -> None:
    a = _args()

    frames = a.folders * a.frames_per_folder
    gen_s = generate(a.data, a.folders, a.frames_per_folder, a.workers, a.hands)
    if a.work.exists():
        shutil.rmtree(a.work)
    a.work.mkdir(parents=True)
    log = a.work / "log.txt"
    sessions = a.work / "sessions"
    base = ["--sessions-dir", str(sessions)]
    s = sessions / "local"
    doc: dict = {
        "dataset": f"{a.folders} synthetic MSRA-layout folders x {a.frames_per_folder} frames",
        "hands": a.hands,
        "frames": frames,
        "ref_fraction": a.ref_fraction,
        "workers": a.workers,
        "window": a.window,
        "machine": machine_description(),
        "generate_s": round(gen_s, 1),
        "local": [],
    }

    def save() -> None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(doc, indent=2))

    crops = (
        "import sys; from handanno_core import pipeline; from handanno_core.session import "
        "Session; s = Session.open(sys.argv[1]); "
        "pipeline.ensure_crops(s, quiet=True, workers=int(sys.argv[2])); s.close()"
    )
    w = str(a.workers)
    steps = [
        ("new", [*base, "new", "local", str(a.data), *(["--one-hand"] if a.one_hand else [])]),
        ("crops", ["-c", crops, str(s), w]),
        ("select", [*base, "select", "local", "--strategy", "forest"]
         + ["--ref-fraction", str(a.ref_fraction)]),
        ("annotate", [*base, "annotate-from-gt", "local"]),
        ("lift", [*base, "lift", "local", "--workers", w]),
        ("propagate", [*base, "propagate", "local", "--workers", w]),
        ("refine", [*base, "refine", "local", "--workers", w, "--window", str(a.window)]),
    ]  # fmt: skip
    for name, args in steps:
        if name == "lift":
            shutil.copytree(s, sessions / "annotated")  # the start of the Dask run
        if name == "refine":
            shutil.copytree(s, sessions / "propagated")  # the start of the whole-solve comparison
        doc["local"].append(stage(name, args, log))
        save()
    doc["local_total_wall_s"] = round(sum(r["wall_s"] for r in doc["local"]), 1)
    doc["local_peak_rss_sum_mb"] = max(r["peak_rss_sum_mb"] for r in doc["local"])
    doc.update(reports(s), one_hand=a.one_hand)
    save()
    local = results(s)
    if a.per_sequence:
        doc["per_sequence"] = per_sequence(a, s, sessions, log, doc["per_folder_final"])
        save()

    if a.dask:
        import psutil
        from dask.distributed import LocalCluster

        with LocalCluster(
            n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None
        ) as cluster:
            me = psutil.Process()
            cluster_pids = [p.pid for p in me.children(recursive=True)]
            addr = cluster.scheduler_address
            d = sessions / "annotated"
            rows = []
            for name, args in (
                ("lift", [*base, "lift", "annotated", "--scheduler", addr]),
                ("propagate", [*base, "propagate", "annotated", "--scheduler", addr]),
                ("refine", [*base, "refine", "annotated", "--scheduler", addr]
                 + ["--window", str(a.window)]),
            ):  # fmt: skip
                rows.append(stage(f"dask-{name}", args, log, cluster_pids))
            remote = results(d)
        doc["dask"] = rows
        doc["dask_identical"] = {
            k: bool(np.array_equal(local[k], remote[k], equal_nan=True))
            for k in ("lifted_mm", "init_mm", "final_mm")
        }
        save()

    if a.compare_whole:
        p = sessions / "propagated"
        small = sessions / "small-window"
        shutil.copytree(p, small)
        whole = stage("refine-whole", [*base, "refine", "propagated"], log)
        win = stage(
            "refine-small-window",
            [*base, "refine", "small-window", "--workers", w, "--window", str(a.small_window)],
            log,
        )
        ref = results(p)["final_mm"]
        out = {"whole": whole, "small_window": win, "accuracy_whole": accuracy(p, "final_mm")}
        for name, arr in (
            ("pieces", local["final_mm"]),
            ("small_window", results(small)["final_mm"]),
        ):
            d = np.linalg.norm(arr - ref, axis=-1)
            out[f"diff_{name}_vs_whole_mm"] = {
                "mean": round(float(d.mean()), 3),
                "p99": round(float(np.percentile(d, 99)), 3),
                "max": round(float(d.max()), 3),
            }
        out["accuracy_small_window"] = accuracy(small, "final_mm")
        doc["compare_whole"] = out
        save()
    print(json.dumps({k: v for k, v in doc.items() if k not in ("local", "dask")}, indent=2))


if __name__ == "__main__":
    main()
