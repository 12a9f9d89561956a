"""``handanno`` command line. Each subcommand calls one pipeline function; see README for usage."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080


def _intrinsics(text: str | None):
    if not text:
        return None
    from handanno_core.camera import CameraIntrinsics

    parts = text.split(",")
    if len(parts) not in (4, 6):
        raise argparse.ArgumentTypeError("--intrinsics expects FX,FY,CX,CY[,WIDTH,HEIGHT]")
    fx, fy, cx, cy = map(float, parts[:4])
    width, height = (
        (int(parts[4]), int(parts[5]))
        if len(parts) == 6
        else (int(round(2 * cx)), int(round(2 * cy)))
    )
    return CameraIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def _strings(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="handanno",
        description="Semi-automatic 3D hand-pose annotation of depth videos.",
    )
    parser.add_argument(
        "--sessions-dir",
        default="sessions",
        help="where bare session names live (default ./sessions)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def session_arg(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "session", metavar="SESSION", help="session folder, or a name under --sessions-dir"
        )

    def server_args(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--host",
            default=DEFAULT_HOST,
            help="interface to bind (default 127.0.0.1; 0.0.0.0 only behind a proxy)",
        )
        p.add_argument("--port", type=int, default=DEFAULT_PORT)
        p.add_argument("--sessions-dir", default=argparse.SUPPRESS, help=argparse.SUPPRESS)

    p = sub.add_parser("demo", help="synthetic sequence -> session -> app")
    server_args(p)
    p.add_argument(
        "--frames", type=int, default=300, help="frames in the demo sequence (first run only)"
    )

    p = sub.add_parser("serve", help="serve an existing session in the browser app")
    session_arg(p)
    server_args(p)

    p = sub.add_parser(
        "synth", help="write a synthetic sequence with exact ground truth (MSRA layout)"
    )
    p.add_argument("out_dir", metavar="OUT_DIR")
    p.add_argument("--frames", type=int, default=3040)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2)

    p = sub.add_parser("new", help="create a session for a depth dataset")
    session_arg(p)
    p.add_argument("dataset", metavar="DATASET")
    p.add_argument("--format", choices=["msra", "blender", "nyu", "icvl", "folder"])
    p.add_argument("--intrinsics", type=_intrinsics, metavar="FX,FY,CX,CY[,W,H]")
    p.add_argument("--depth-scale", type=float, help="mm per PNG unit for --format folder")
    p.add_argument("--force", action="store_true", help="replace an existing session")

    p = sub.add_parser("info", help="print a session's summary")
    session_arg(p)

    p = sub.add_parser("select", help="select reference frames")
    session_arg(p)
    p.add_argument(
        "--strategy",
        default="forest",
        help="forest (ours, default), chain, chain-step, coverage, uniform",
    )
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--ref-fraction", type=float, help="exact budget, e.g. 0.05 for 5 %% of frames")
    g.add_argument("--rho", type=float, help="raw cosine-distance threshold")

    p = sub.add_parser(
        "annotate-from-gt", help="simulated annotator from ground truth (benchmarks only)"
    )
    session_arg(p)
    p.add_argument("--noise-px", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=0)

    p = sub.add_parser("lift", help="lift annotated references to 3D")
    session_arg(p)
    p.add_argument("--workers", type=int, default=1)

    p = sub.add_parser("propagate", help="propagate references to every frame")
    session_arg(p)
    p.add_argument("--workers", type=int, default=1, help="local processes (default 1)")
    p.add_argument("--scheduler", help="tcp://HOST:PORT of a Dask distributed scheduler")
    p.add_argument("--aligner", choices=["sift", "dis", "ncc"])

    p = sub.add_parser("refine", help="global refinement of all frames")
    session_arg(p)

    p = sub.add_parser("export", help="export the result")
    session_arg(p)
    p.add_argument("--format", required=True, choices=["json", "npz", "msra"])
    p.add_argument("-o", "--output", required=True, type=Path)

    p = sub.add_parser("import", help="import a handanno JSON export into a session")
    session_arg(p)
    p.add_argument("json_file", type=Path)

    p = sub.add_parser("bench", help="whole pipeline with the simulated annotator; JSON report")
    p.add_argument("dataset", metavar="DATASET")
    p.add_argument("--format", choices=["msra", "blender", "nyu", "icvl", "folder"])
    p.add_argument("--ref-fraction", type=_floats, default=[0.02, 0.05, 0.10])
    p.add_argument("--strategy", type=_strings, default=["forest", "chain", "coverage", "uniform"])
    p.add_argument("--noise-px", type=float, default=0.0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--aligner", choices=["sift", "dis", "ncc"])
    p.add_argument(
        "--gt-bones", action="store_true", help="use ground-truth bone lengths (comparison only)"
    )
    p.add_argument("--json", required=True, type=Path, dest="json_out")
    p.add_argument("--review-rounds", type=int, default=0, help="simulated review rounds")
    p.add_argument(
        "--review-budget",
        type=float,
        default=0.02,
        help="frames shown per review round (>= 1), or a share of the frames (< 1)",
    )
    p.add_argument(
        "--review-ranking",
        type=_strings,
        default=["evidence", "uniform"],
        help="rankings compared in review (evidence, score = the old one, uniform)",
    )
    p.add_argument(
        "--prefill",
        action="store_true",
        help="references open pre-filled; the annotator moves only joints > 4 px off",
    )
    p.add_argument("--work-dir", type=Path, help="keep the bench sessions in this folder")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from handanno_core.datasets import DatasetError
    from handanno_core.session import SessionError

    try:
        return _run(args) or 0
    except (SessionError, DatasetError, FileNotFoundError) as exc:
        print(f"handanno {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; every acknowledged edit is in the session journal", file=sys.stderr)
        return 130


def _open(args):
    from handanno_core.session import Session, resolve_session

    return Session.open(resolve_session(args.session, args.sessions_dir))


def _progress_bar(desc: str):
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit="frame")

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    return bar, update


def _run(args) -> int | None:  # noqa: C901 - one branch per subcommand
    from handanno_core import pipeline

    cmd = args.command
    if cmd == "demo":
        from app.server import demo

        demo(Path(args.sessions_dir), host=args.host, port=args.port, frames=args.frames)
    elif cmd == "serve":
        from app.server import serve
        from handanno_core.session import Session, resolve_session

        folder = resolve_session(args.session, args.sessions_dir)
        Session.open(folder).close()  # fail fast, in the terminal, on a missing or corrupt session
        serve(folder, host=args.host, port=args.port)
    elif cmd == "synth":
        from handanno_core.datasets import open_sequence
        from handanno_core.synth import generate_sequence

        out = generate_sequence(
            args.out_dir, frames=args.frames, seed=args.seed, workers=args.workers
        )
        print(open_sequence(out).describe())
    elif cmd == "new":
        from handanno_core.session import resolve_session

        folder = resolve_session(args.session, args.sessions_dir)
        session = pipeline.new_session(
            folder,
            args.dataset,
            format=args.format,
            intrinsics=args.intrinsics,
            depth_scale_mm=args.depth_scale,
            overwrite=args.force,
        )
        print(session.summary())
    elif cmd == "info":
        print(_open(args).summary())
    elif cmd == "select":
        session = _open(args)
        selection = pipeline.select(
            session, strategy=args.strategy, ref_fraction=args.ref_fraction, rho=args.rho
        )
        print(f"references: {len(selection.reference_frames)} of {session.num_frames}")
        print(f"figures: {session.folder / 'selection_embedding.png'}")
    elif cmd == "annotate-from-gt":
        pipeline.annotate_from_gt(_open(args), noise_px=args.noise_px, seed=args.seed)
    elif cmd == "lift":
        pipeline.lift(_open(args), workers=args.workers)
    elif cmd == "propagate":
        session = _open(args)
        bar, update = _progress_bar("propagate")
        result = pipeline.propagate(
            session,
            workers=args.workers,
            scheduler=args.scheduler,
            aligner=args.aligner,
            progress=update,
        )
        bar.close()
        done = int(result.joints_mm.shape[0] - len(result.skipped))
        print(f"propagated {done} of {session.num_frames} frames")
    elif cmd == "refine":
        session = _open(args)

        def report(iteration: int, energy: float) -> None:
            print(f"  iteration {iteration}: energy {energy:.6g}", flush=True)

        result = pipeline.refine(session, progress=report)
        print(
            f"refined {session.num_frames} frames; max bone-length violation {result.bone_violation_max_mm:.3f} mm"
        )
    elif cmd == "export":
        from handanno_core.export import export_session

        path = export_session(_open(args), args.format, args.output)
        print(f"wrote {path}")
    elif cmd == "import":
        from handanno_core.export import import_json

        n = import_json(_open(args), args.json_file)
        print(f"imported joints for {n} frames")
    elif cmd == "bench":
        from handanno_core.bench import run_bench

        run_bench(
            args.dataset,
            format=args.format,
            fractions=args.ref_fraction,
            strategies=args.strategy,
            noise_px=args.noise_px,
            json_out=args.json_out,
            workers=args.workers,
            aligner=args.aligner,
            gt_bones=args.gt_bones,
            work_dir=args.work_dir,
            review={
                "rounds": args.review_rounds,
                "budget": args.review_budget,
                "rankings": args.review_ranking,
                "prefill": args.prefill,
            }
            if args.review_rounds or args.prefill
            else None,
        )
    return None


if __name__ == "__main__":
    sys.exit(main())
