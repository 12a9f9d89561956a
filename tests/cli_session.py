"""A session made through the CLI the way a user would (synth, new, select, annotate-from-gt, lift,
propagate), for the tests that need a propagated session on disk."""

from __future__ import annotations

from pathlib import Path


def propagated_cli_session(root: Path, frames: int, seed: int) -> Path:
    """``root/sessions/s`` on a ``frames``-frame synthetic sequence: 10 % uniform references
    annotated from ground truth, lifted and propagated."""
    from app.cli import main

    data, sessions = root / "data", root / "sessions"
    assert (
        main(["synth", str(data), "--frames", str(frames), "--seed", str(seed), "--workers", "1"])
        == 0
    )
    base = ["--sessions-dir", str(sessions)]
    assert main([*base, "new", "s", str(data)]) == 0
    assert main([*base, "select", "s", "--strategy", "uniform", "--ref-fraction", "0.1"]) == 0
    assert main([*base, "annotate-from-gt", "s"]) == 0
    assert main([*base, "lift", "s"]) == 0
    assert main([*base, "propagate", "s"]) == 0
    return sessions / "s"
