"""The CLI contract of DESIGN.md, end to end on a small synthetic sequence."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from handanno_core.datasets import open_sequence
from handanno_core.evaluate import error_summary
from handanno_core.session import Session


@pytest.fixture(scope="module")
def pipeline_session(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    data, sessions = root / "data", root / "sessions"
    assert main(["synth", str(data), "--frames", "120", "--seed", "3"]) == 0
    assert main(["--sessions-dir", str(sessions), "new", "s", str(data)]) == 0
    assert (
        main(
            [
                "--sessions-dir",
                str(sessions),
                "select",
                "s",
                "--strategy",
                "forest",
                "--ref-fraction",
                "0.1",
            ]
        )
        == 0
    )
    assert main(["--sessions-dir", str(sessions), "annotate-from-gt", "s"]) == 0
    assert main(["--sessions-dir", str(sessions), "lift", "s"]) == 0
    assert main(["--sessions-dir", str(sessions), "propagate", "s"]) == 0
    assert main(["--sessions-dir", str(sessions), "refine", "s"]) == 0
    return root, sessions / "s", data


def test_select_stores_the_documented_keys(pipeline_session, capsys):
    _, folder, data = pipeline_session
    doc = json.loads((folder / "session.json").read_text())
    assert doc["dataset"]["format"] == "msra" and doc["frames"] == 120
    assert doc["dataset"]["path"] == str(data.resolve())
    sel = doc["selection"]
    assert sel["strategy"] == "forest" and len(sel["parent"]) == 120
    assert abs(len(sel["reference_frames"]) - 12) <= 1
    assert all(sel["parent"][f] == -1 for f in sel["reference_frames"])
    assert (folder / "selection_embedding.png").exists() and (
        folder / "selection_coverage.png"
    ).exists()


def test_pipeline_result_is_accurate_on_synthetic_data(pipeline_session):
    _, folder, data = pipeline_session
    gt = open_sequence(data).ground_truth.joints_mm
    results = Session.open(folder).load_results()
    refs = Session.open(folder).reference_frames
    lifted = error_summary(results["lifted_mm"], gt, frames=refs)
    final = error_summary(results["final_mm"], gt)
    assert lifted["mean_mm"] < 4.0
    assert final["mean_mm"] < 10.0 and final["missing"] == 0


def test_export_formats_and_json_round_trip(pipeline_session):
    root, folder, _ = pipeline_session
    for fmt in ("json", "npz", "msra"):
        assert main(["export", str(folder), "--format", fmt, "-o", str(root / f"out.{fmt}")]) == 0
    doc = json.loads((root / "out.json").read_text())
    assert len(doc["frames"]) == 120 and doc["references"] == sum(
        f["is_reference"] for f in doc["frames"]
    )
    frame = doc["frames"][5]
    assert np.asarray(frame["joints_mm"]).shape == (21, 3) and np.asarray(frame["uv_px"]).shape == (
        21,
        2,
    )
    npz = np.load(root / "out.npz")
    np.testing.assert_allclose(
        npz["joints_mm"], np.asarray([f["joints_mm"] for f in doc["frames"]]), atol=1e-3
    )
    lines = (root / "out.msra").read_text().splitlines()
    assert int(lines[0]) == 120 and len(lines[1].split()) == 63
    # MSRA convention: y up, z negative
    assert float(lines[1].split()[2]) == pytest.approx(-npz["joints_mm"][0, 0, 2], abs=1e-3)

    # import into a fresh session of the same data, export again: same joints and references
    assert (
        main(["--sessions-dir", str(root / "sessions"), "new", "copy", doc["dataset"]["path"]]) == 0
    )
    assert (
        main(["--sessions-dir", str(root / "sessions"), "import", "copy", str(root / "out.json")])
        == 0
    )
    assert (
        main(
            [
                "--sessions-dir",
                str(root / "sessions"),
                "export",
                "copy",
                "--format",
                "json",
                "-o",
                str(root / "again.json"),
            ]
        )
        == 0
    )
    again = json.loads((root / "again.json").read_text())
    assert [f["is_reference"] for f in again["frames"]] == [
        f["is_reference"] for f in doc["frames"]
    ]
    np.testing.assert_allclose(
        np.asarray([f["joints_mm"] for f in again["frames"]]),
        np.asarray([f["joints_mm"] for f in doc["frames"]]),
        atol=1e-3,
    )


def test_bad_input_gives_clear_errors(tmp_path, capsys):
    assert main(["--sessions-dir", str(tmp_path), "lift", "missing"]) == 2
    assert "no such session folder" in capsys.readouterr().err
    assert main(["new", str(tmp_path / "s"), str(tmp_path / "no-dataset")]) == 2
    assert "no-dataset" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a budget or a threshold, not both (5 % without either)
        main(["select", "s", "--ref-fraction", "0.1", "--rho", "0.3"])


def test_demo_creates_the_session_once_and_serves_it(tmp_path, monkeypatch):
    import app.ui.server

    served = []
    monkeypatch.setattr(app.ui.server, "serve", lambda folder, **kw: served.append((folder, kw)))
    argv = ["--sessions-dir", str(tmp_path), "demo", "--frames", "40", "--port", "8123"]
    assert main(argv) == 0
    folder, kw = served[0]
    assert folder == tmp_path / "demo" and kw["host"] == "127.0.0.1" and kw["port"] == 8123
    session = Session.open(folder)
    assert session.num_frames == 40 and len(session.reference_frames) == 2
    data_mtime = (tmp_path / "demo-data" / "joint.txt").stat().st_mtime_ns
    assert main(argv) == 0  # second start reuses the data and the session's selection
    assert (tmp_path / "demo-data" / "joint.txt").stat().st_mtime_ns == data_mtime and len(
        served
    ) == 2
    assert Session.open(folder).model.selection == session.model.selection


def test_select_defaults_to_the_engine_default_strategy():
    from app.cli import build_parser
    from handanno_core.select import DEFAULT_STRATEGY

    args = build_parser().parse_args(["select", "s"])
    assert args.strategy == DEFAULT_STRATEGY
