"""Bad-input corpus (issue 16): every case gets one line on stderr naming the file and what is
wrong, exit status 2, no traceback, and leaves the session as it was (session.json, journal.jsonl,
results.npz byte for byte). Cases that are *handled* rather than refused (unusable frames skipped
by selection, a 1-frame dataset, a stale crop cache) assert that they succeed and say so.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from cli_session import propagated_cli_session

from app.cli import main
from handanno_core.datasets import open_sequence
from handanno_core.session import CROPS_FILE, JOURNAL_FILE, RESULTS_FILE, SESSION_FILE, Session

STATE_FILES = (SESSION_FILE, JOURNAL_FILE, RESULTS_FILE)


def state(folder: Path) -> dict[str, str | None]:
    return {
        name: hashlib.sha256((folder / name).read_bytes()).hexdigest()
        if (folder / name).exists()
        else None
        for name in STATE_FILES
    }


def refused(capsys, argv: list[str], *needles: str) -> str:
    """Run the CLI; assert a one-line error containing every needle, exit 2, no traceback."""
    capsys.readouterr()
    assert main(argv) == 2
    full = capsys.readouterr().err
    assert "Traceback" not in full
    errors = [line for line in full.splitlines() if ": error: " in line]
    assert len(errors) == 1 and full.rstrip().endswith(errors[0]), full  # (progress bars aside)
    err = errors[0]
    for needle in needles:
        assert needle in err, (needle, err)
    return err


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A 20-frame synthetic MSRA dataset and a session on it, propagated and exported as JSON."""
    root = tmp_path_factory.mktemp("bad")
    data, sessions = root / "data", root / "sessions"
    propagated_cli_session(root, frames=20, seed=2)
    base = ["--sessions-dir", str(sessions)]
    assert (
        main(["export", str(sessions / "s"), "--format", "json", "-o", str(root / "e.json")]) == 0
    )
    return {
        "root": root,
        "data": data,
        "sessions": sessions,
        "folder": sessions / "s",
        "base": base,
    }


def folder_dataset(world, name: str, frames: list[np.ndarray | bytes | None]) -> Path:
    """A ``folder``-format dataset of ``.npy`` frames (bytes = raw file content) with the synth camera."""
    out = world["root"] / name
    out.mkdir()
    camera = json.loads((world["data"] / "camera.json").read_text())
    (out / "intrinsics.json").write_text(json.dumps(camera))
    for i, frame in enumerate(frames):
        path = out / f"{i:03d}.npy"
        if isinstance(frame, bytes):
            path.write_bytes(frame)
        else:
            np.save(path, frame)
    return out


def good_frames(world, n: int) -> list[np.ndarray]:
    seq = open_sequence(world["data"])
    return [seq.depth(i) for i in range(n)]


# ------------------------------------------------------------------------------ intrinsics
@pytest.mark.parametrize(
    "text, needle",
    [
        ("nan,241,160,120", "fx"),
        ("241,inf,160,120", "fy"),
        ("1e308,241,160,120", "fx"),
        ("-5,241,160,120", "fx"),
        ("241,241,160,120,50000,50000", "width"),
        ("241,241,1e9,120,320,240", "principal point"),
        ("a,b,c,d", "--intrinsics"),
        ("241,241,160", "FX,FY,CX,CY"),
        ("241,241,inf,120", "--intrinsics"),
    ],
)
def test_bad_intrinsics_are_refused(world, capsys, text, needle):
    argv = [*world["base"], "new", "x", str(world["data"]), f"--intrinsics={text}"]
    refused(capsys, argv, "--intrinsics", needle)
    assert not (world["sessions"] / "x").exists()


@pytest.mark.parametrize(
    "camera, needle",
    [
        ({"fx": 241, "fy": 241, "cx": 160, "cy": 120, "width": 50000, "height": 50000}, "width"),
        ({"fx": float("nan"), "fy": 241, "cx": 160, "cy": 120, "width": 320, "height": 240}, "fx"),
        ({"fx": 241, "fy": 241, "cx": 160, "cy": 120, "width": 320}, "height"),
        ([1, 2, 3], "JSON object"),
    ],
)
def test_bad_camera_json_is_refused(world, capsys, tmp_path, camera, needle):
    data = tmp_path / "d"
    data.mkdir()
    for src in world["data"].glob("*"):
        os.symlink(src, data / src.name)
    (data / "camera.json").unlink()
    (data / "camera.json").write_text(json.dumps(camera))
    refused(capsys, [*world["base"], "new", "y", str(data)], "camera.json", needle)


# ------------------------------------------------------------------------------ frames
def test_huge_png_is_refused_from_its_header_before_decoding(world, capsys, tmp_path):
    import struct
    import zlib

    data = tmp_path / "png"
    data.mkdir()
    (data / "intrinsics.json").write_text(
        json.dumps({"fx": 241.42, "fy": 241.42, "cx": 160, "cy": 120, "width": 320, "height": 240})
    )
    ihdr = struct.pack(">IIBBBBB", 16000, 16000, 16, 0, 0, 0, 0)
    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    (data / "0.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk)  # 33 bytes claiming 256 Mpx
    base = ["--sessions-dir", str(tmp_path / "sessions")]
    assert main([*base, "new", "p", str(data)]) == 0
    refused(
        capsys,
        [*base, "select", "p", "--ref-fraction", "0.1"],
        "0.png",
        "(16000, 16000)",
        "before decoding",
    )


def test_unusable_frames_are_skipped_by_selection_and_reported(world, capsys):
    frames = good_frames(world, 12)
    nan = frames[3].copy()
    nan[10:20, 10:20] = np.nan
    bad = {3: nan, 5: np.zeros_like(frames[5]), 7: b"junk", 9: b"\x93NUMPY\x01\x00"}
    data = folder_dataset(world, "mixed", [bad.get(i, f) for i, f in enumerate(frames)])
    base = ["--sessions-dir", str(world["root"] / "s-mixed")]
    assert main([*base, "new", "m", str(data)]) == 0
    capsys.readouterr()
    assert main([*base, "select", "m", "--strategy", "uniform", "--ref-fraction", "0.5"]) == 0
    out = capsys.readouterr().out
    assert "skips 4 unusable frame(s)" in out and "003.npy" in out and "NaN" in out
    session = Session.open(world["root"] / "s-mixed" / "m")
    refs = set(session.model.selection.reference_frames)
    assert refs and not refs & set(bad) and session.model.selection.skipped_frames == sorted(bad)
    assert all(session.parent[f] >= 0 for f in bad)  # still propagated from a neighbour


@pytest.mark.parametrize("kind", ["all-zero", "unreadable"])
def test_dataset_with_no_usable_frame_is_refused(world, capsys, kind):
    frames = good_frames(world, 4)
    content = [np.zeros_like(f) if kind == "all-zero" else b"junk" for f in frames]
    data = folder_dataset(world, f"none-{kind}", content)
    base = ["--sessions-dir", str(world["root"] / f"s-{kind}")]
    assert main([*base, "new", "n", str(data)]) == 0
    before = state(world["root"] / f"s-{kind}" / "n")
    refused(capsys, [*base, "select", "n", "--ref-fraction", "0.5"], "none of the 4 frames")
    assert state(world["root"] / f"s-{kind}" / "n") == before


def test_one_frame_dataset_is_handled_end_to_end(world):
    data = folder_dataset(world, "one", good_frames(world, 1))
    base = ["--sessions-dir", str(world["root"] / "s-one")]
    for argv in (["new", "o", str(data)], ["select", "o", "--ref-fraction", "0.5"]):
        assert main([*base, *argv]) == 0
    assert Session.open(world["root"] / "s-one" / "o").model.selection.reference_frames == [0]


# ------------------------------------------------------------------------------ results and caches
@pytest.mark.parametrize("damage", ["truncated", "empty", "wrong-shape", "not-a-zip"])
@pytest.mark.parametrize("command", ["export", "refine"])
def test_corrupt_results_are_named(world, capsys, tmp_path, damage, command):
    folder = tmp_path / "s"
    folder.mkdir()
    for name in (SESSION_FILE, JOURNAL_FILE, "crops.npy", "crops_meta.npz"):
        (folder / name).write_bytes((world["folder"] / name).read_bytes())
    good = (world["folder"] / RESULTS_FILE).read_bytes()
    if damage == "truncated":
        content = good[: len(good) // 2]
    elif damage == "empty":
        content = b""
    elif damage == "not-a-zip":
        content = b"hello"
    else:
        import io

        buf = io.BytesIO()
        np.savez(buf, final_mm=np.zeros((3, 21, 3)))
        content = buf.getvalue()
    (folder / RESULTS_FILE).write_bytes(content)
    before = state(folder)
    argv = [command, str(folder)]
    if command == "export":
        argv += ["--format", "json", "-o", str(tmp_path / "out.json")]
    refused(capsys, argv, "results.npz")
    assert state(folder) == before


@pytest.mark.parametrize("damage", ["truncated", "foreign", "meta-garbage"])
def test_corrupt_crop_cache_is_rebuilt(world, capsys, tmp_path, damage):
    folder = tmp_path / "s"
    folder.mkdir()
    for name in (SESSION_FILE, JOURNAL_FILE, RESULTS_FILE, "crops.npy", "crops_meta.npz"):
        (folder / name).write_bytes((world["folder"] / name).read_bytes())
    crops = folder / CROPS_FILE
    if damage == "truncated":
        crops.write_bytes(crops.read_bytes()[:5000])
    elif damage == "foreign":  # same shape, other content: only the checksum can tell
        arr = np.load(crops)
        np.save(crops, np.flip(arr, axis=0))
    else:
        (folder / "crops_meta.npz").write_bytes(b"PK\x03\x04garbage")
    capsys.readouterr()
    assert main(["select", str(folder), "--strategy", "uniform", "--ref-fraction", "0.1"]) == 0
    assert "rebuilding the crop cache" in capsys.readouterr().out
    np.testing.assert_array_equal(np.load(crops), np.load(world["folder"] / CROPS_FILE))


# ------------------------------------------------------------------------------ import
def _mutate(doc: dict, case: str) -> dict | list | str:
    frames = doc["frames"]
    if case == "frame -1":
        frames[0]["frame"] = -1
    elif case == "frame N":
        frames[0]["frame"] = len(frames)
    elif case == "duplicate frame":
        frames[1]["frame"] = 0
    elif case == "NaN joint":
        frames[2]["joints_mm"][0][0] = float("nan")
    elif case == "inf joint":
        frames[2]["joints_mm"][0][0] = float("inf")
    elif case == "1e308 joint":
        frames[2]["joints_mm"][0][0] = 1e308
    elif case == "behind camera":
        frames[2]["joints_mm"][4][2] = -30.0
    elif case == "too far":
        frames[2]["joints_mm"][4][2] = 9000.0
    elif case == "all null":
        for f in frames:
            f["joints_mm"] = None
            f.pop("annotation", None)
    elif case == "wrong joint count":
        frames[2]["joints_mm"] = frames[2]["joints_mm"][:5]
    elif case == "string joints":
        frames[2]["joints_mm"] = "abc"
    elif case == "confidence 2":
        frames[2]["confidence"][0] = 2.0
    elif case == "missing frames":
        del frames[5:]
    elif case == "wrong skeleton":
        doc["skeleton"] = "nyu14"
    elif case == "bad annotation":
        ref = next(f for f in frames if "annotation" in f)
        ref["annotation"]["uv_px"] = ref["annotation"]["uv_px"][:3]
    elif case == "annotation behind camera":
        ref = next(f for f in frames if "annotation" in f)
        ref["annotation"]["xyz_mm"] = [[0.0, 0.0, -5.0]] * 21
    elif case == "frames not a list":
        doc["frames"] = {"0": 1}
    elif case == "frame not an object":
        frames[0] = 7
    elif case == "not an export":
        return [1, 2, 3]
    elif case == "not json":
        return "{this is not json"
    elif case == "wrong format":
        doc["format"] = "something-else"
    return doc


IMPORT_CASES = [
    ("frame -1", "frame -1 out of range"),
    ("frame N", "frame 20 out of range"),
    ("duplicate frame", "frame 0 appears more than once"),
    ("NaN joint", "frames.2.joints_mm"),
    ("inf joint", "frames.2.joints_mm"),
    ("1e308 joint", "not a plausible hand position"),
    ("behind camera", "joint 4"),
    ("too far", "joint 4"),
    ("all null", "nothing to import"),
    ("wrong joint count", "5 joints, the skeleton has 21"),
    ("string joints", "frames.2.joints_mm"),
    ("confidence 2", "[0, 1]"),
    ("missing frames", "export has 5 frames"),
    ("wrong skeleton", "skeleton nyu14"),
    ("bad annotation", "annotation"),
    ("annotation behind camera", "behind the camera"),
    ("frames not a list", "frames"),
    ("frame not an object", "frames.0"),
    ("not an export", "not a handanno export"),
    ("not json", "not a readable JSON export"),
    ("wrong format", "not a handanno export"),
]


@pytest.mark.parametrize("case, needle", IMPORT_CASES, ids=[c for c, _ in IMPORT_CASES])
def test_bad_import_is_refused_whole_and_leaves_the_session_unchanged(world, capsys, case, needle):
    doc = _mutate(json.loads((world["root"] / "e.json").read_text()), case)
    path = world["root"] / f"import-{case.replace(' ', '_')}.json"
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    before = state(world["folder"])
    refused(capsys, [*world["base"], "import", "s", str(path)], str(path), needle)
    assert state(world["folder"]) == before


# ------------------------------------------------------------------------------ export and names
@pytest.mark.parametrize("kind", ["symlink", "fifo", "folder"])
def test_export_never_replaces_a_non_regular_file(world, capsys, tmp_path, kind):
    target = tmp_path / "out.json"
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    if kind == "symlink":
        target.symlink_to(victim)
    elif kind == "fifo":
        os.mkfifo(target)
    else:
        target.mkdir()
    refused(
        capsys, ["export", str(world["folder"]), "--format", "json", "-o", str(target)], "out.json"
    )
    assert victim.read_text() == "keep me"
    assert target.is_symlink() if kind == "symlink" else not target.is_file()


@pytest.mark.parametrize("name", ["..", "."])
def test_dot_session_names_are_refused(world, capsys, name):
    refused(capsys, [*world["base"], "info", name], repr(name))


def test_corrupt_session_file_and_journal_are_named(world, capsys, tmp_path):
    folder = tmp_path / "s"
    folder.mkdir()
    (folder / SESSION_FILE).write_text("{not json")
    refused(capsys, ["info", str(folder)], "session.json", "corrupt session file")
    (folder / SESSION_FILE).write_bytes((world["folder"] / SESSION_FILE).read_bytes())
    lines = (world["folder"] / JOURNAL_FILE).read_bytes().splitlines()
    (folder / JOURNAL_FILE).write_bytes(b"{]\n" + b"\n".join(lines) + b"\n")
    refused(capsys, ["info", str(folder)], "journal.jsonl:1: corrupt entry")


def test_session_files_share_one_mode(world):
    from handanno_core.session import FILE_MODE

    modes = {
        p.name: p.stat().st_mode & 0o777
        for p in world["folder"].iterdir()
        if p.is_file() and not p.name.endswith(".png")
    }
    assert set(modes.values()) == {FILE_MODE}, modes
