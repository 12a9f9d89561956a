"""Sequence breaks: read off folder file names, from a breaks file, or given to ``handanno new``;
hand localization never smooths across them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from handanno_core.datasets import DatasetError, open_sequence
from handanno_core.datasets.base import breaks_from_names
from handanno_core.session import Session


def _folder(path, names):
    path.mkdir(parents=True, exist_ok=True)
    for n in names:
        np.save(path / n, np.full((8, 10), 500.0, np.float32))
    cam = {"fx": 10.0, "fy": 10.0, "cx": 5.0, "cy": 4.0, "width": 10, "height": 8}
    (path / "intrinsics.json").write_text(json.dumps(cam))
    return path


def test_breaks_from_names_prefix_order_and_gaps():
    assert breaks_from_names([f"{i}.png" for i in range(0, 100, 20)]) == []  # sparse but even
    assert breaks_from_names(["a_1.png", "a_2.png", "b_0.png", "b_1.png"]) == [2]  # new take
    assert breaks_from_names(["f5.png", "f6.png", "f2.png"]) == [2]  # numbering restarts
    # millisecond timestamps at ~30 fps with a 9 s pause
    ts = [1000, 1033, 1066, 1100, 10100, 10133]
    assert breaks_from_names([f"{t}.png" for t in ts]) == [4]
    assert breaks_from_names(["a.png", "b.png"]) == []  # no numbers: nothing to read
    # a single skipped frame (2x the usual step) is not a break
    assert breaks_from_names(["0.npy", "1.npy", "3.npy", "4.npy"]) == []


def test_folder_reader_takes_breaks_from_names_and_breaks_file(tmp_path):
    names = ["rec1_000.npy", "rec1_001.npy", "rec1_002.npy", "rec2_000.npy", "rec2_001.npy"]
    folder = _folder(tmp_path / "f", names)
    assert open_sequence(folder).sequence_breaks == [3]
    # a breaks file replaces what the names say: an index and a file name, with comments
    (folder / "breaks.txt").write_text("# my cuts\n1\nrec2_001.npy  # second take\n")
    assert open_sequence(folder).sequence_breaks == [1, 4]
    (folder / "breaks.txt").write_text("7\n")
    with pytest.raises(DatasetError, match=r"breaks.txt line 1: frame 7 out of range"):
        open_sequence(folder)
    (folder / "breaks.txt").write_text("nope.png\n")
    with pytest.raises(DatasetError, match=r"breaks.txt line 1: 'nope.png'"):
        open_sequence(folder)


def test_cli_new_breaks_override_any_reader(tmp_path, capsys):
    folder = _folder(tmp_path / "f", [f"{i}.npy" for i in range(6)])
    sessions = tmp_path / "sessions"
    main(["new", str(sessions / "a"), str(folder), "--breaks", "2,4"])
    assert Session.open(sessions / "a").model.sequence_breaks == [2, 4]
    cuts = tmp_path / "cuts.txt"
    cuts.write_text("3.npy\n")
    main(["new", str(sessions / "b"), str(folder), "--breaks", str(cuts)])
    assert Session.open(sessions / "b").model.sequence_breaks == [3]
    main(["new", str(sessions / "c"), str(folder)])
    assert Session.open(sessions / "c").model.sequence_breaks == []
    rc = main(["new", str(sessions / "d"), str(folder), "--breaks", "9"])
    assert rc not in (None, 0)
    assert "--breaks 9: frame 9 out of range" in capsys.readouterr().err
