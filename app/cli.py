"""``handanno`` command line. Each subcommand calls one pipeline function; see README for usage."""

from __future__ import annotations

import argparse
import os
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
        raise ValueError(f"--intrinsics {text!r}: expects FX,FY,CX,CY[,WIDTH,HEIGHT]")
    try:
        fx, fy, cx, cy = map(float, parts[:4])
        width, height = (
            (int(parts[4]), int(parts[5]))
            if len(parts) == 6
            else (int(round(2 * cx)), int(round(2 * cy)))
        )
        return CameraIntrinsics.checked(
            "--intrinsics", fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height
        )
    except (ValueError, OverflowError) as exc:  # non-numbers, inf/nan, absurd values
        msg = str(exc) if str(exc).startswith("--intrinsics") else f"--intrinsics {text!r}: {exc}"
        raise ValueError(msg) from None


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def _strings(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def _switches(text: str) -> list[bool]:
    """``off,on`` -> [False, True]."""
    values = {"off": False, "on": True}
    out = []
    for x in _strings(text):
        if x.lower() not in values:
            raise argparse.ArgumentTypeError(f"{x!r}: expected off or on")
        out.append(values[x.lower()])
    if not out:
        raise argparse.ArgumentTypeError("expected off, on or off,on")
    return out


WORKFLOW = """workflow (one session, in this order):
  handanno new SESSION DATASET        create a session for a depth sequence
  handanno select SESSION             choose the reference frames (5 % by default)
  handanno serve SESSION              annotate them in the browser; the app's Review tab lifts,
                                      propagates, refines, reviews and exports without the CLI
  handanno lift / propagate / refine SESSION     the same stages from the command line
  handanno export SESSION --format json -o OUT   write the result
try it: handanno demo (a synthetic sequence, served at http://localhost:8080)"""

#: default share of frames ``select`` makes references (the paper's operating point)
DEFAULT_REF_FRACTION = 0.05
ALIGNERS = ["sift", "dis", "ncc"]
FORMATS = ["msra", "blender", "nyu", "icvl", "folder"]


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Appends ``(default: X)`` to every option that has a default (not None or False)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    """Every option has a help text; ``(default: ...)`` is appended by the formatter."""
    fmt = _HelpFormatter
    parser = argparse.ArgumentParser(
        prog="handanno",
        description="Semi-automatic 3D hand-pose annotation of depth videos.",
        epilog=WORKFLOW,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--sessions-dir",
        default="sessions",
        help="where bare session names live (default ./sessions; also accepted after the command)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name: str, help_text: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=fmt)
        # after the command too; SUPPRESS keeps the value given before it
        p.add_argument("--sessions-dir", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
        return p

    def session_arg(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "session", metavar="SESSION", help="session folder, or a name under --sessions-dir"
        )

    def server_args(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--host",
            default=DEFAULT_HOST,
            help="interface to bind (0.0.0.0 only behind a proxy)",
        )
        p.add_argument(
            "--port",
            type=int,
            default=DEFAULT_PORT,
            help="port to serve on; a port in use is an error (never a silent move)",
        )

    p = add("demo", "synthetic sequence -> session -> app")
    server_args(p)
    p.add_argument(
        "--frames", type=int, default=300, help="frames in the demo sequence (first run only)"
    )

    p = add("serve", "serve an existing session in the browser app")
    session_arg(p)
    server_args(p)

    p = add("synth", "write a synthetic sequence with exact ground truth (MSRA layout)")
    p.add_argument("out_dir", metavar="OUT_DIR", help="folder to write the sequence to")
    p.add_argument("--frames", type=int, default=3040, help="number of frames")
    p.add_argument("--seed", type=int, default=0, help="random seed of the motion and hand shape")
    p.add_argument("--workers", type=int, default=2, help="processes rendering frames")

    p = add("suite", "write the benchmark suite (tune and report parts) with suite.json")
    p.add_argument("out_dir", metavar="OUT_DIR", help="folder to write the suite to")
    p.add_argument("--seed", type=int, default=0, help="random seed of every generated sequence")
    p.add_argument(
        "--part", choices=["tune", "report", "all"], default="all", help="which part to write"
    )
    p.add_argument(
        "--frames-scale", type=float, default=1.0, help="scale every sequence's length (0.5: half)"
    )
    p.add_argument("--workers", type=int, default=2, help="processes rendering frames")

    p = add("new", "create a session for a depth dataset")
    session_arg(p)
    p.add_argument("dataset", metavar="DATASET", help="dataset folder (or file list)")
    p.add_argument("--format", choices=FORMATS, help="dataset layout (default: detected)")
    p.add_argument(
        "--intrinsics",
        metavar="FX,FY,CX,CY[,W,H]",
        help="camera intrinsics in px (default: the dataset's own)",
    )
    p.add_argument("--depth-scale", type=float, help="mm per PNG unit for --format folder")
    p.add_argument(
        "--breaks",
        metavar="F1,F2|FILE",
        help="frames where a new recording starts (indices, or a file: one index or frame file "
        "name per line); replaces the reader's breaks; '' for none",
    )
    p.add_argument(
        "--one-hand",
        action="store_true",
        help="treat every sequence as the same person's hand (one set of bone lengths); by "
        "default each subject folder of an MSRA layout (P0/1, P0/2, P1/1 ...) is its own hand "
        "with its own bone lengths (other layouts, and --breaks, give one hand)",
    )
    p.add_argument(
        "--hands",
        metavar="L1,L2,...|FILE",
        help="whose hand each sequence (between breaks) shows: one label per sequence, "
        "comma-separated or one per line in a file; sequences with the same label share bone "
        "lengths (replaces the reader's labels)",
    )
    p.add_argument("--force", action="store_true", help="replace an existing session")

    p = add("info", "print a session's summary")
    session_arg(p)
    p.add_argument(
        "--frame",
        type=int,
        action="append",
        help="also say where this frame's result came from (repeatable)",
    )

    _add_stage_commands(add, session_arg)

    p = add("export", "export the result")
    session_arg(p)
    p.add_argument("--format", required=True, choices=["json", "npz", "msra"], help="file format")
    p.add_argument("-o", "--output", required=True, type=Path, help="file to write")

    p = add("import", "import a handanno JSON export into a session")
    session_arg(p)
    p.add_argument("json_file", type=Path, help="a JSON file written by `handanno export`")

    _add_bench_command(add)
    return parser


def _add_stage_commands(add, session_arg) -> None:
    """The pipeline stages' subcommands: select, annotate-from-gt, lift, propagate, refine."""
    p = add("select", "select reference frames")
    session_arg(p)
    p.add_argument(
        "--strategy",
        default="uniform",  # handanno_core.select.DEFAULT_STRATEGY (tests/test_cli.py checks)
        help="uniform, forest (cosine-distance parent forest), chain, chain-step, coverage",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--ref-fraction",
        type=float,
        default=None,
        help=f"exact budget as a share of frames (default: {DEFAULT_REF_FRACTION} unless --rho)",
    )
    g.add_argument("--rho", type=float, help="raw cosine-distance threshold instead of a budget")
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="local processes building the crop cache (when not built yet; same result)",
    )

    p = add("annotate-from-gt", "simulated annotator from ground truth (benchmarks only)")
    session_arg(p)
    p.add_argument("--noise-px", type=float, default=0.0, help="2D click noise (std, px)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the noise")

    p = add("lift", "lift annotated references to 3D and estimate the bone lengths")
    session_arg(p)
    p.add_argument("--workers", type=int, default=1, help="local processes")
    p.add_argument("--scheduler", help="tcp://HOST:PORT of a Dask distributed scheduler")
    p.add_argument(
        "--no-refit", action="store_true",
        help="skip the refit of the lifted references with the personalized hand model",
    )  # fmt: skip
    p.add_argument(
        "--click-noise-px", type=float,
        help="the annotators' click noise (px) the refit trusts the clicks by (default: estimated)",
    )  # fmt: skip

    p = add("propagate", "propagate references to every frame")
    session_arg(p)
    p.add_argument("--workers", type=int, default=1, help="local processes")
    p.add_argument("--scheduler", help="tcp://HOST:PORT of a Dask distributed scheduler")
    p.add_argument("--aligner", choices=ALIGNERS, help="flow method (default: the session's)")
    use_model = (
        "fit the personalized hand model to each frame's depth (articulated ICP, README 'Personalized "
        "hand model'); --no-model switches it off. Default: the session's setting"
    )
    p.add_argument("--model", action=argparse.BooleanOptionalAction, default=None, help=use_model)

    p = add("refine", "global refinement of all frames")
    session_arg(p)
    p.add_argument("--model", action=argparse.BooleanOptionalAction, default=None, help=use_model)
    p.add_argument(
        "--window",
        type=int,
        help="solve in pieces: each sequence between breaks, long ones in windows of this many "
        "frames (memory bounded by the window; resumable after a kill). Default: one whole "
        "system up to 5,000 frames, pieces (windows of 1024) beyond",
    )
    p.add_argument(
        "--whole",
        action="store_true",
        help="one whole system whatever the size (memory about 0.28 MB per frame)",
    )
    p.add_argument(
        "--overlap",
        type=int,
        help="frames shared by consecutive windows (default: 48, at most a quarter of the window)",
    )
    p.add_argument("--workers", type=int, default=1, help="local processes (pieces in parallel)")
    p.add_argument("--scheduler", help="tcp://HOST:PORT of a Dask distributed scheduler")
    p.add_argument(
        "--restart", action="store_true", help="ignore the checkpoints of a killed piecewise run"
    )


def _add_bench_command(add) -> None:
    """``handanno bench``'s options."""
    p = add("bench", "whole pipeline with the simulated annotator; JSON report")
    p.add_argument(
        "dataset", metavar="DATASET", nargs="+", help="datasets and/or suite folders (suite.json)"
    )
    p.add_argument(
        "--part",
        choices=["tune", "report", "all"],
        help="which part of a suite folder to run (required for a suite folder)",
    )
    p.add_argument("--format", choices=FORMATS, help="dataset layout (default: detected)")
    p.add_argument(
        "--ref-fraction",
        type=_floats,
        default=[0.02, 0.05, 0.10],
        help="comma-separated reference budgets",
    )
    p.add_argument(
        "--strategy",
        type=_strings,
        default=["forest", "chain", "coverage", "uniform"],
        help="comma-separated selection strategies",
    )
    p.add_argument("--noise-px", type=float, default=0.0, help="2D click noise (std, px)")
    p.add_argument(
        "--model",
        type=_switches,
        help="hand model in propagation and refinement, comma-separated off/on (e.g. off,on: both "
        "on the same lift, each run's JSON says which). Default: the session default, one run",
    )
    p.add_argument("--workers", type=int, default=2, help="local processes")
    p.add_argument("--aligner", choices=ALIGNERS, help="flow method (default: the session's)")
    p.add_argument(
        "--gt-bones", action="store_true", help="use ground-truth bone lengths (comparison only)"
    )
    p.add_argument("--json", required=True, type=Path, dest="json_out", help="report to write")
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
        help="references open pre-filled; the annotator moves the guess furthest off (> 4 px), "
        "the guesses refit as in the app, until none is off, then accepts them",
    )
    p.add_argument("--work-dir", type=Path, help="keep the bench sessions in this folder")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from handanno_core.datasets import DatasetError
    from handanno_core.session import SessionError

    try:
        return _run(args) or 0
    except (SessionError, DatasetError, OSError, ValueError) as exc:
        # Bad input (issue 16): one line naming the file and what is wrong, never a traceback;
        # HANDANNO_DEBUG=1 shows the traceback (for bugs, not for bad input).
        if os.environ.get("HANDANNO_DEBUG"):
            raise
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"handanno {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; every acknowledged edit is in the session journal", file=sys.stderr)
        return 130
    finally:
        _close_opened()


#: sessions a command opened for writing; closed (snapshot, lock released) when it ends
_OPENED: list = []


def _close_opened() -> None:
    while _OPENED:
        session = _OPENED.pop()
        try:
            session.close()
        except Exception as exc:  # the journal already holds every edit
            print(f"handanno: warning: {exc}", file=sys.stderr)


def _open(args, write: bool = False):
    """The session of ``args``; ``write=True`` takes its writer lock for the whole command, so a
    command that writes refuses to start while ``serve`` (or another command) writes the session."""
    from handanno_core.session import Session, default_writer_command, resolve_session

    folder = resolve_session(args.session, args.sessions_dir)
    session = Session.open(folder, writer=default_writer_command() if write else None)
    _OPENED.append(session)
    return session


def _info(session, frames: list[int]) -> str:
    """The session's summary and, once it has results, where its propagated results came from
    (``results.npz`` ``source``: the candidate chain propagation kept per frame)."""
    from handanno_core.export import best_joints
    from handanno_core.results import RESULTS_FILE, describe_frame, describe_sources

    lines = [session.summary()]
    bad = [f for f in frames if not 0 <= f < session.num_frames]
    if bad:
        raise ValueError(f"--frame {bad[0]}: the session has frames 0-{session.num_frames - 1}")
    if not (session.folder / RESULTS_FILE).exists():
        return "\n".join([*lines, "  no results yet"])
    results = session.load_results()
    _, stage = best_joints(results)
    source, parent = results["source"], session.parent
    lines.append(f"  {describe_sources(source, parent)}")
    lines += [f"  {describe_frame(f, source, parent, int(stage[f]))}" for f in frames]
    return "\n".join(lines)


def _progress_bar(desc: str):
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit="frame")

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    return bar, update


def _serve(args) -> int | None:
    """``demo`` / ``serve``; a busy port is an error naming it (never a silent move)."""
    from app.ui.server import PortInUseError, demo, serve

    try:
        if args.command == "demo":
            demo(Path(args.sessions_dir), host=args.host, port=args.port, frames=args.frames)
        else:
            from handanno_core.session import Session, resolve_session

            folder = resolve_session(args.session, args.sessions_dir)
            Session.open(folder).close()  # fail fast, in the terminal, on a bad session
            serve(folder, host=args.host, port=args.port)  # takes the writer lock (issue 16)
    except PortInUseError as exc:
        print(f"handanno {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return None


def warn_incomplete_references(session) -> list[str]:
    """Print (stderr) and return one warning line per kind of incomplete reference: references
    with only some joints placed (not counting joints marked outside the image) are lifted from
    those (the rest is guessed), references with no joint placed are skipped."""

    def frames_text(frames: list[int]) -> str:
        shown = ", ".join(map(str, frames[:10]))
        return shown + (f", ... ({len(frames)} in all)" if len(frames) > 10 else "")

    anns = session.annotations(session.reference_frames)
    partial = [
        int(f) for f, a in sorted(anns.items()) if a.annotated.any() and not a.complete.all()
    ]
    empty = [
        int(f) for f in session.reference_frames if f not in anns or not anns[f].annotated.any()
    ]
    total = len(session.reference_frames)
    lines = []
    if partial:
        lines.append(
            f"{len(partial)} of {total} reference frames are only partly annotated (frames "
            f"{frames_text(partial)}): their missing joints are guessed by the lift"
        )
    if empty:
        lines.append(
            f"{len(empty)} of {total} reference frames have no joint placed (frames "
            f"{frames_text(empty)}): they are not lifted"
        )
    for line in lines:
        print(f"handanno: warning: {line}", file=sys.stderr)
    return lines


def _propagate(args) -> None:
    """``handanno propagate``."""
    from handanno_core import pipeline

    session = _open(args, write=True)
    bar, update = _progress_bar("propagate")
    result = pipeline.propagate(
        session,
        workers=args.workers,
        scheduler=args.scheduler,
        aligner=args.aligner,
        progress=update,
        use_model=args.model,
    )
    bar.close()
    done = int(result.joints_mm.shape[0] - len(result.skipped))
    print(f"propagated {done} of {session.num_frames} frames")


def _refine(args) -> None:
    """``handanno refine``."""
    from handanno_core import pipeline

    session = _open(args, write=True)

    def report(iteration: int, energy: float) -> None:
        print(f"  iteration {iteration}: energy {energy:.6g}", flush=True)

    result = pipeline.refine(
        session,
        progress=report,
        use_model=args.model,
        window=args.window,
        overlap=args.overlap,
        workers=args.workers,
        scheduler=args.scheduler,
        resume=not args.restart,
        whole=args.whole,
    )
    print(
        f"refined {session.num_frames} frames; max bone-length violation {result.bone_violation_max_mm:.3f} mm"
    )


def _run(args) -> int | None:  # noqa: C901 - one branch per subcommand
    from handanno_core import pipeline

    cmd = args.command
    if cmd in ("demo", "serve"):
        return _serve(args)
    if cmd == "synth":
        from handanno_core.datasets import open_sequence
        from handanno_core.synth import generate_sequence

        out = generate_sequence(
            args.out_dir, frames=args.frames, seed=args.seed, workers=args.workers
        )
        print(open_sequence(out).describe())
    elif cmd == "suite":
        from handanno_core.suite import generate_suite

        manifest = generate_suite(
            args.out_dir,
            seed=args.seed,
            part=args.part,
            frames_scale=args.frames_scale,
            workers=args.workers,
        )
        for e in manifest["sequences"]:
            print(f"{e['part']:>6} {e['name']:<28} {e['frames']:5d} frames  {e['motion']}")
        print(manifest["split"])
    elif cmd == "new":
        from handanno_core.session import resolve_session

        folder = resolve_session(args.session, args.sessions_dir)
        session = pipeline.new_session(
            folder,
            args.dataset,
            format=args.format,
            intrinsics=_intrinsics(args.intrinsics),
            depth_scale_mm=args.depth_scale,
            overwrite=args.force,
            breaks=args.breaks,
            one_hand=args.one_hand,
            hands=args.hands,
        )
        _OPENED.append(session)
        print(session.summary())
    elif cmd == "info":
        print(_info(_open(args), args.frame or []))
    elif cmd == "select":
        session = _open(args, write=True)
        fraction = args.ref_fraction
        if fraction is None and args.rho is None:
            fraction = DEFAULT_REF_FRACTION
        selection = pipeline.select(
            session,
            strategy=args.strategy,
            ref_fraction=fraction,
            rho=args.rho,
            workers=args.workers,
        )
        print(f"references: {len(selection.reference_frames)} of {session.num_frames}")
        print(f"figures: {session.folder / 'selection_embedding.png'}")
    elif cmd == "annotate-from-gt":
        pipeline.annotate_from_gt(_open(args, write=True), noise_px=args.noise_px, seed=args.seed)
    elif cmd == "lift":
        session = _open(args, write=True)
        warn_incomplete_references(session)
        pipeline.lift(
            session, workers=args.workers, scheduler=args.scheduler,
            refit=False if args.no_refit else None, click_noise_px=args.click_noise_px,
        )  # fmt: skip
    elif cmd == "propagate":
        _propagate(args)
    elif cmd == "refine":
        _refine(args)
    elif cmd == "export":
        from handanno_core.export import export_session

        path = export_session(_open(args), args.format, args.output)
        print(f"wrote {path}")
    elif cmd == "import":
        from handanno_core.export import import_json

        n = import_json(_open(args, write=True), args.json_file)
        print(f"imported joints for {n} frames")
    elif cmd == "bench":
        from handanno_core.bench import expand_datasets, run_bench_datasets

        try:
            expand_datasets(args.dataset, args.part)  # fail fast on a suite without --part
        except ValueError as exc:
            print(f"handanno bench: error: {exc}", file=sys.stderr)
            return 2
        run_bench_datasets(
            args.dataset,
            part=args.part,
            format=args.format,
            fractions=args.ref_fraction,
            strategies=args.strategy,
            models=args.model,
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
