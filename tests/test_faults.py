"""Fault injection (issue 16): torn journal tails, a full disk, two writers, kills during refinement,
foreign and out-of-range journal entries.

Each test asserts on the bytes on disk: every acknowledged edit is in ``journal.jsonl`` exactly
once, in order, with a valid checksum and continuous sequence numbers; refused edits are not.
Processes that must die (SIGKILL) or hit a file-size limit run as subprocesses.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from handanno_core.camera import MSRA_CAMERA
from handanno_core.session import (
    JOURNAL_FILE,
    RESULTS_FILE,
    DatasetSpec,
    Session,
    SessionError,
    SessionLockedError,
    SetJoint2D,
    encode_entry,
    entry_checksum,
)

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def make_session(folder: Path, frames: int = 10) -> Session:
    s = Session.create(
        folder, DatasetSpec(path=str(folder / "data"), format="msra"), frames, MSRA_CAMERA
    )
    s.set_selection(
        {
            "strategy": "uniform",
            "reference_frames": [0, 5],
            "parent": [-1, 0, 1, 2, 3, -1, 5, 6, 7, 8][:frames],
        }
    )
    return s


def edit(k: int) -> SetJoint2D:
    """The k-th test edit: a distinct 2D position, so each one is recognisable on disk."""
    return SetJoint2D(frame=k % 10, joint=k % 21, uv_px=(1000.0 + k, 2000.0 + k))


def journal_on_disk(folder: Path) -> list[dict]:
    """Parse journal.jsonl strictly: every line complete, checksummed, sequence continuous."""
    model = json.loads((folder / "session.json").read_text())
    data = (folder / JOURNAL_FILE).read_bytes()
    assert data.endswith(b"\n"), "journal ends in a torn line"
    entries = []
    for number, raw in enumerate(data.split(b"\n")[:-1], start=1):
        doc = json.loads(raw)
        crc = doc.pop("crc")
        assert crc == entry_checksum(model["session_id"], doc), f"line {number}: bad checksum"
        entries.append(doc)
    assert [e["seq"] for e in entries] == list(range(1, len(entries) + 1))
    return entries


def uv_edits(entries: list[dict]) -> list[tuple[float, float]]:
    return [tuple(e["command"]["uv_px"]) for e in entries if e["command"]["kind"] == "set_2d"]


def run_py(code: str, *args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
        **kw,
    )


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ------------------------------------------------------------------------------------- torn tail
def test_torn_tail_is_cut_before_the_next_append_and_kept_beside(tmp_path):
    s = make_session(tmp_path / "s")
    for k in range(3):
        s.execute(edit(k))
    path = tmp_path / "s" / JOURNAL_FILE
    fragment = b'{"action":"do","client":"cli","command":{"frame":3,"joint":3,"ki'
    with open(path, "ab") as f:  # a write that never completed (never acknowledged)
        f.write(fragment)
    # the app (or the library) reopens after the crash and appends
    again = Session.open(tmp_path / "s", writer="test")
    for k in range(3, 6):
        again.execute(edit(k))
    entries = journal_on_disk(tmp_path / "s")
    assert uv_edits(entries) == [edit(k).uv_px for k in range(6)]
    torn = list((tmp_path / "s").glob(f"{JOURNAL_FILE}.torn-*"))
    assert len(torn) == 1 and torn[0].read_bytes() == fragment
    # a kill now (no close) and a restart replays all six, once each
    third = Session.open(tmp_path / "s")
    assert third.model.journal_seq == 6
    assert third.annotation(5).uv_px[5].tolist() == [1005.0, 2005.0]


def test_corrupt_complete_last_line_is_treated_as_torn(tmp_path):
    s = make_session(tmp_path / "s")
    s.execute(edit(0))
    line = encode_entry(
        s.execute(edit(1)).model_copy(update={"seq": 2}), s.model.session_id
    )  # the same bytes, damaged
    path = tmp_path / "s" / JOURNAL_FILE
    data = path.read_bytes()
    path.write_bytes(data[: -len(line)] + line.replace(b"1001.0", b"1001.5"))
    again = Session.open(tmp_path / "s")
    assert again.model.journal_seq == 1  # the damaged last entry is not applied
    again.execute(edit(7))
    assert uv_edits(journal_on_disk(tmp_path / "s")) == [edit(0).uv_px, edit(7).uv_px]


# ------------------------------------------------------------------------------------- disk full
DISK_FULL = r"""
import json, os, resource, signal, sys
from handanno_core.session import Session, SessionError, SetJoint2D
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)   # get EFBIG / a short write instead of dying
folder = sys.argv[1]
s = Session.open(folder, writer="disk-full test")
s.execute(SetJoint2D(frame=0, joint=0, uv_px=(1000.0, 2000.0)))   # opens the journal
size = os.path.getsize(os.path.join(folder, "journal.jsonl"))
# room for two more entries and half of a third: the third write is cut in the middle
resource.setrlimit(resource.RLIMIT_FSIZE, (size + int(size * 2.5), resource.RLIM_INFINITY))
for k in range(1, 6):
    try:
        s.execute(SetJoint2D(frame=k, joint=k, uv_px=(1000.0 + k, 2000.0 + k)))
        print(json.dumps({"ack": k}), flush=True)
    except SessionError as exc:
        print(json.dumps({"refused": k, "error": str(exc)}), flush=True)
os._exit(0)  # a crash: no close, no snapshot
"""


def test_disk_full_mid_append_rolls_back_and_refused_edit_never_resurfaces(tmp_path):
    make_session(tmp_path / "s").close()
    out = run_py(DISK_FULL, str(tmp_path / "s"))
    assert out.returncode == 0, out.stderr
    events = [json.loads(line) for line in out.stdout.splitlines()]
    acked = [0] + [e["ack"] for e in events if "ack" in e]
    refused = [e for e in events if "refused" in e]
    assert acked == [0, 1, 2] and [e["refused"] for e in refused] == [3, 4, 5]
    assert "NOT saved" in refused[0]["error"] and "journal.jsonl" in refused[0]["error"]
    # the file holds exactly the acknowledged entries (the half-written one was truncated away)
    assert uv_edits(journal_on_disk(tmp_path / "s")) == [(1000.0 + k, 2000.0 + k) for k in acked]
    # restart with room on the disk: replay, then a new edit takes the next sequence number
    s = Session.open(tmp_path / "s", writer="restart")
    assert s.model.journal_seq == 3 and s.annotation(3) is None
    s.execute(SetJoint2D(frame=9, joint=9, uv_px=(9.0, 9.0)))
    entries = journal_on_disk(tmp_path / "s")
    assert uv_edits(entries) == [(1000.0 + k, 2000.0 + k) for k in acked] + [(9.0, 9.0)]
    assert not list((tmp_path / "s").glob(f"{JOURNAL_FILE}.torn-*"))  # nothing was left to cut


# ------------------------------------------------------------------------------------- two writers
HOLDER = r"""
import sys, time
from handanno_core.session import Session, SetJoint2D
s = Session.open(sys.argv[1], writer="handanno serve s")
for k in range(3):
    s.execute(SetJoint2D(frame=k, joint=1, uv_px=(500.0 + k, 600.0)))
print("ready", flush=True)
time.sleep(3600)  # held until the test kills it, however slow the machine
"""


def test_second_writer_is_refused_with_the_owner_pid_and_a_dead_owner_is_taken_over(tmp_path):
    folder = tmp_path / "sessions" / "s"
    make_session(folder).close()
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(folder)], env=ENV, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "ready"
        # the library: an edit from this process is refused, naming the owner
        other = Session.open(folder)
        with pytest.raises(SessionLockedError, match=rf"PID {holder.pid} \(handanno serve s"):
            other.execute(edit(9))
        # the CLI: a writing command refuses to start (one line, exit 2); reading still works
        cli = [sys.executable, "-m", "app.cli", "--sessions-dir", str(folder.parent)]
        out = subprocess.run(
            [*cli, "import", "s", str(tmp_path / "x.json")], env=ENV, capture_output=True, text=True
        )
        assert out.returncode == 2 and f"PID {holder.pid}" in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr
        info = subprocess.run([*cli, "info", "s"], env=ENV, capture_output=True, text=True)
        assert info.returncode == 0, info.stderr
        # the server refuses to start, before binding a port
        from app.ui.server import serve

        with pytest.raises(SessionLockedError, match=f"PID {holder.pid}"):
            serve(folder, port=0, block=False)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    # the owner died: its lock died with it; the next writer takes over and continues the sequence
    again = Session.open(folder, writer="after the kill")
    again.execute(edit(9))
    entries = journal_on_disk(folder)
    assert uv_edits(entries) == [(500.0, 600.0), (501.0, 600.0), (502.0, 600.0), edit(9).uv_px]


def test_a_review_copy_another_run_is_writing_is_not_replaced(tmp_path, monkeypatch):
    """Must trigger: two bench review runs on the same first-pass session (``bench_review``
    copies it to ``<folder>-review-<ranking>``); the second deleted the first's copy mid-round
    and the first then wrote into the second's (found at stop 54). Now the second stops with
    the first's PID and the copy keeps every edit. Must not: a copy left by a finished run is
    replaced by a fresh one, held while it is reviewed."""
    from handanno_core import review_loop

    folder = tmp_path / "bench" / "uniform-0.05"
    make_session(folder).close()
    copy = folder.with_name("uniform-0.05-review-evidence")
    make_session(copy).close()
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(copy)], env=ENV, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "ready"
        with pytest.raises(SessionLockedError, match=f"PID {holder.pid}"):
            review_loop.bench_review(folder, rankings=["evidence"], rounds=1, budget=1)
        assert Session.open(copy).annotation(2).uv_px[1, 0] == 502.0  # its edits are all there
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    seen = []

    def rounds(session, **kw):
        seen.append((session.is_writer, session.annotation(2)))
        return []

    monkeypatch.setattr(review_loop, "review_rounds", rounds)
    assert review_loop.bench_review(folder, rankings=["evidence"], rounds=1, budget=1) == {
        "evidence": []
    }
    assert seen == [(True, None)]  # a fresh copy of the first pass, held while reviewed


# ------------------------------------------------------------------------------------- replay checks


def _append_line(folder: Path, session_id: str, seq: int, command: dict, inverse=None) -> int:
    body = {
        "seq": seq,
        "time": 1.0,
        "client": "cli",
        "action": "do",
        "target": None,
        "command": command,
        "inverse": inverse or {"kind": "set_2d", "frame": 0, "joint": 0, "uv_px": None},
    }
    line = json.dumps({**body, "crc": entry_checksum(session_id, body)}, sort_keys=True)
    with open(folder / JOURNAL_FILE, "ab") as f:
        f.write(line.encode() + b"\n")
    return len((folder / JOURNAL_FILE).read_bytes().splitlines())


@pytest.mark.parametrize(
    "command, reason",
    [
        ({"kind": "set_2d", "frame": 5000, "joint": 1, "uv_px": [1, 2]}, "frame 5000 out of range"),
        ({"kind": "set_2d", "frame": 1, "joint": 99, "uv_px": [1, 2]}, "joint 99 out of range"),
        ({"kind": "set_reference", "frame": 5000, "is_reference": True}, "frame 5000 out of range"),
        ({"kind": "set_reference", "frame": 2, "is_reference": False, "parent": 77}, "parent 77"),
        ({"kind": "teleport", "frame": 1}, "does not match any of the expected tags"),
        ({"kind": "set_2d", "frame": -1, "joint": 1, "uv_px": [1, 2]}, "frame -1 out of range"),
    ],
)
def test_out_of_range_entry_is_refused_on_replay_with_file_and_line(tmp_path, command, reason):
    s = make_session(tmp_path / "s")
    s.execute(edit(0))
    s.execute(edit(1))
    # a crafted but well-checksummed entry *followed* by more entries (not a torn tail)
    line = _append_line(tmp_path / "s", s.model.session_id, 3, command)
    _append_line(tmp_path / "s", s.model.session_id, 4, edit(4).model_dump())
    with pytest.raises(SessionError) as info:
        Session.open(tmp_path / "s")
    message = str(info.value)
    assert f"journal.jsonl:{line}:" in message and reason in message and "\n" not in message


def test_entry_copied_from_another_session_is_refused(tmp_path):
    a, b = make_session(tmp_path / "a"), make_session(tmp_path / "b")
    a.execute(edit(0))
    b.execute(edit(1))
    b.execute(edit(2))
    foreign = (tmp_path / "b" / JOURNAL_FILE).read_bytes().splitlines()[1]  # seq 2: fits a's
    with open(tmp_path / "a" / JOURNAL_FILE, "ab") as f:
        f.write(foreign + b"\n")
    _append_line(tmp_path / "a", a.model.session_id, 3, edit(3).model_dump())
    with pytest.raises(SessionError, match=r"journal.jsonl:2: corrupt entry: checksum mismatch"):
        Session.open(tmp_path / "a")


def test_repeated_sequence_number_is_refused_and_old_journals_without_checksum_load(tmp_path):
    s = make_session(tmp_path / "s")
    s.execute(edit(0))
    s.execute(edit(1))
    path = tmp_path / "s" / JOURNAL_FILE
    lines = path.read_bytes().splitlines()
    # an old (pre-checksum) journal: same entries without "crc" still load
    path.write_bytes(
        b"".join(
            json.dumps({k: v for k, v in json.loads(x).items() if k != "crc"}).encode() + b"\n"
            for x in lines
        )
    )
    assert Session.open(tmp_path / "s").model.journal_seq == 2
    path.write_bytes(lines[0] + b"\n" + lines[0] + b"\n" + lines[1] + b"\n")  # seq 1, 1, 2
    with pytest.raises(SessionError, match=r"journal.jsonl:2: sequence 1 follows 1"):
        Session.open(tmp_path / "s")


def test_undo_is_scoped_per_client_per_joint_and_per_field(tmp_path):
    from handanno_core.session import SetDepthOrder

    s = make_session(tmp_path / "s")
    s.execute(SetJoint2D(frame=0, joint=3, uv_px=(10.0, 20.0)), client="a")
    s.execute(SetDepthOrder(frame=0, joint=3, order=1), client="b")
    s.undo("a")  # a's 2D edit goes; b's depth order on the same joint stays
    ann = Session.open(tmp_path / "s").annotation(0)
    assert np.isnan(ann.uv_px[3]).all() and ann.depth_order[3] == 1


# ------------------------------------------------------------------------------------- kill -9
@pytest.fixture(scope="module")
def propagated(tmp_path_factory):
    """A 40-frame synthetic session, selected, annotated from ground truth, lifted, propagated."""
    from cli_session import propagated_cli_session

    return propagated_cli_session(tmp_path_factory.mktemp("faults"), frames=40, seed=5)


def _kill_when(proc: subprocess.Popen, marker: str, timeout_s: float = 90.0) -> str:
    seen = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        seen.append(line)
        if marker in line:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            return "".join(seen)
    proc.kill()
    raise AssertionError(f"never saw {marker!r}: {''.join(seen)}")


def test_kill_during_cli_refine_leaves_results_and_journal_as_they_were(propagated, tmp_path):
    folder = propagated
    results, journal = digest(folder / RESULTS_FILE), digest(folder / JOURNAL_FILE)
    proc = subprocess.Popen(
        [sys.executable, "-u", "-m", "app.cli", "refine", str(folder)],
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    _kill_when(proc, "iteration 1:")
    assert digest(folder / RESULTS_FILE) == results and digest(folder / JOURNAL_FILE) == journal
    Session.open(folder).load_results()  # readable, complete


APP_REFINE = r"""
import sys, time
import numpy as np
from app.control.jobs import ReviewRunner
from handanno_core.session import Session
session = Session.open(sys.argv[1], writer="handanno serve s")
def refine_then_hang(session, progress=None):
    print("refining", flush=True)   # propagation's init_mm is computed (in memory) by now
    time.sleep(60)
runner = ReviewRunner(session, refine_fn=refine_then_hang)
runner.start_full()
time.sleep(120)
"""


def test_kill_during_app_refinement_leaves_results_exactly_as_they_were(propagated):
    folder = propagated
    before = digest(folder / RESULTS_FILE)
    old = Session.open(folder).load_results()
    proc = subprocess.Popen(
        [sys.executable, "-u", "-c", APP_REFINE, str(folder)],
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    _kill_when(proc, "refining")
    assert digest(folder / RESULTS_FILE) == before
    now = Session.open(folder).load_results()
    for key in old:
        np.testing.assert_array_equal(now[key], old[key])


def test_entries_written_before_the_accepted_flag_replay_as_clicks(tmp_path):
    """A ``set_2d`` line checksummed without the ``accepted`` field (journals written before it)
    still verifies and replays as a click; undoing it leaves another joint's flag alone."""
    s = make_session(tmp_path / "s")
    s.execute(SetJoint2D(frame=0, joint=2, uv_px=(40.0, 50.0), accepted=True))
    session_id = s.model.session_id
    s.close()
    old = {"kind": "set_2d", "frame": 0, "joint": 1, "uv_px": [10.0, 20.0]}
    old_inverse = {"kind": "set_joint", "frame": 0, "joint": 1, "uv_px": None}
    _append_line(tmp_path / "s", session_id, 2, old, old_inverse)
    again = Session.open(tmp_path / "s")
    ann = again.annotation(0)
    assert ann.uv_px[1].tolist() == [10.0, 20.0]
    assert ann.accepted.tolist()[:3] == [False, False, True]
    again.undo()
    ann = again.annotation(0)
    assert np.isnan(ann.uv_px[1]).all() and ann.accepted[2]
    again.close()
