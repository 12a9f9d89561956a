"""The benchmark suite (handanno_core/suite.py), the real-motion fit (real_motion.py) and the
multi-dataset bench (handanno_core/bench.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from handanno_core import bench, real_motion, suite, synth
from handanno_core.datasets import open_sequence
from handanno_core.skeleton import MSRA21

REAL_MOTION = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real-motion"
if not REAL_MOTION.is_dir():  # git worktrees sit one level deeper
    REAL_MOTION = real_motion.DEFAULT_REAL_MOTION
needs_data = pytest.mark.skipif(not REAL_MOTION.is_dir(), reason="shared/data/real-motion absent")


# ---------------------------------------------------------------------------- catalogue and split
def test_catalogue_split_is_disjoint_and_deterministic():
    rows = suite.catalogue(0, REAL_MOTION)
    assert rows == suite.catalogue(0, REAL_MOTION)
    assert len({r.name for r in rows}) == len(rows)
    tune = [r for r in rows if r.part == "tune"]
    report = [r for r in rows if r.part == "report"]
    assert tune and report and len(tune) + len(report) == len(rows)
    # no motion source and no hand (seed) in both parts
    assert not {r.seed for r in tune} & {r.seed for r in report}

    def sources(part):
        return {r.motion.split(":")[0] for r in part if r.hand == "recorded"}

    def subjects(part):
        return {r.motion.split(":")[1].split("/")[0] for r in part if "fpha" in r.motion}

    def icvl(part):
        return {r.motion for r in part if r.motion.startswith("icvl")}

    # recorded datasets in both parts are split by subject (FPHA) or test sequence (ICVL)
    assert not sources(tune) & sources(report) - {"fpha", "icvl"}
    if REAL_MOTION.is_dir():
        assert subjects(tune) == {"Subject_1"} and subjects(report) == {"Subject_2"}
        assert icvl(tune) == {"icvl:2"} and icvl(report) == {"icvl:1"}
    # the report part holds every kind of variation the issue asks for
    assert {r.motion for r in report} >= {"smooth", "fast"}
    assert {r.sensor for r in report} >= {"msra", "kinect", "sr300"}
    assert {suite.CAMERAS[r.camera].width for r in report} == {320, 640}
    assert {r.arm for r in report} >= {"top-down", "egocentric"}
    assert any(r.sleeve for r in report) and any(r.hand == "varied" for r in report)
    other = suite.catalogue(1, REAL_MOTION)
    assert {r.seed for r in other}.isdisjoint({r.seed for r in rows})


def test_varied_hands_span_sizes_and_proportions():
    template = np.asarray(MSRA21.template_bone_lengths_mm)
    models = [synth.make_varied_hand_model(s) for s in range(40)]
    size = np.array([m.bone_lengths_mm[4:8].sum() / template[4:8].sum() for m in models])
    assert size.min() < 0.88 and size.max() > 1.12 and np.all((size > 0.74) & (size < 1.27))
    # proportions differ beyond the overall size: ratio of index to little finger length varies
    ratio = [m.bone_lengths_mm[1:4].sum() / m.bone_lengths_mm[13:16].sum() for m in models]
    assert np.std(ratio) > 0.02
    radii = np.array([m.finger_radii[1, 0] / s for m, s in zip(models, size, strict=True)])
    assert np.std(radii / radii.mean()) > 0.03  # thickness varies independently of size
    again = synth.make_varied_hand_model(7)
    assert np.array_equal(again.bone_lengths_mm, models[7].bone_lengths_mm)
    # the articulated hand of a varied model still measures its own parameters
    params = np.clip(np.asarray(synth.GESTURES["claw"]), synth.PARAM_LO, synth.PARAM_HI)
    lengths = MSRA21.bone_lengths(synth.local_pose(models[3], params[None]))[0]
    assert np.allclose(lengths, models[3].bone_lengths_mm, atol=1e-6)


def test_fast_motion_is_fast():
    model = synth.make_varied_hand_model(5)
    motion = synth.synthesize_motion(
        300, 5, model=model, speed_mm=suite.FAST_SPEED_MM, hold_frames=suite.FAST_HOLD_FRAMES
    )
    step = suite.mean_joint_step_mm(motion.joints_mm)
    assert step >= 10.0
    smooth = suite.mean_joint_step_mm(synth.synthesize_motion(300, 5, model=model).joints_mm)
    assert smooth < 4.0


# ---------------------------------------------------------------------------- inverse kinematics
def _markers_of(joints: np.ndarray, rotation: np.ndarray, markers) -> np.ndarray:
    out = []
    for m in markers:
        if m.kind == "bone":
            out.append(joints[:, m.a] + m.t * (joints[:, m.b] - joints[:, m.a]))
        else:
            out.append(joints[:, 0] + rotation @ np.asarray(m.offset))
    return np.stack(out, axis=1)


def test_ik_recovers_a_known_hand_from_nyu_like_markers():
    model = synth.make_varied_hand_model(11, scale=1.1)
    motion = synth.synthesize_motion(60, 11, model=model)
    targets = _markers_of(motion.joints_mm, motion.rotation, real_motion.NYU14_MARKERS)
    fit = real_motion.fit_skeleton(targets, real_motion.NYU14_MARKERS, shape_frames=20)
    assert fit.residual_mm.mean() < 1.0
    # the joints the markers do not pin (MCPs, DIPs) are recovered too, within a few mm
    err = np.linalg.norm(fit.joints_mm - motion.joints_mm, axis=-1)
    assert np.median(err) < 6.0
    # bone lengths are one per sequence: constant over frames
    lengths = MSRA21.bone_lengths(fit.joints_mm)
    assert np.ptp(lengths, axis=0).max() < 1e-6
    assert abs(lengths[0, 4:8].sum() / model.bone_lengths_mm[4:8].sum() - 1) < 0.08


@needs_data
@pytest.mark.parametrize("layout", ["nyu", "icvl"])
def test_fitted_skeleton_reproduces_recorded_joints(layout):
    """The residual is printed (pytest -s) and recorded per sequence in suite.json."""
    if layout == "nyu":
        targets, markers = real_motion.load_nyu(REAL_MOTION)[1000:1040], real_motion.NYU14_MARKERS
    else:
        targets, markers = real_motion.load_icvl(REAL_MOTION, 2)[:40], real_motion.ICVL16_MARKERS
        targets = targets * np.array([-1.0, 1.0, 1.0])  # ICVL labels are a left hand
    fit = real_motion.fit_skeleton(targets, markers, shape_frames=15)
    summary = fit.summary()
    print(f"{layout} IK residual (40 frames): {summary}")
    assert summary["mean_mm"] < 3.0 and summary["p95_mm"] < 8.0
    # a plausible hand: middle finger 60-120 mm, bones constant over the sequence
    lengths = MSRA21.bone_lengths(fit.joints_mm)
    assert np.ptp(lengths, axis=0).max() < 1e-6
    assert 50.0 < lengths[0, 5:8].sum() < 130.0
    assert 140.0 < lengths[0, 4:8].sum() < 230.0  # wrist to middle tip: an adult hand


@needs_data
def test_fpha_reader_maps_onto_msra21():
    path = real_motion.fpha_sequences(REAL_MOTION, "Subject_1")[0]
    joints = real_motion.load_fpha(path)
    assert joints.shape[1:] == (21, 3)
    lengths = MSRA21.estimate_bone_lengths(joints)
    # wrist->MCP bones are the longest; the thumb's first bone (CMC side) is shorter than them
    assert lengths[[0, 4, 8, 12]].min() > lengths[[1, 5, 9, 13]].max()
    rot = real_motion.rotation_of_joints(joints)
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    normal = MSRA21.palm_normal(joints)
    assert np.median(np.sum(normal * rot[:, :, 2], axis=-1)) > 0.9  # z out of the palm


# ---------------------------------------------------------------------------- generation
@pytest.fixture(scope="module")
def small_suite(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("suite")
    # no real motion here (a folder that does not exist): the synthetic rows only, 30 frames each
    suite.generate_suite(
        out,
        seed=3,
        part="report",
        frames_scale=0.05,
        real_motion=out / "no-real-motion",
        workers=1,
        progress=False,
    )
    return out


def test_generate_suite_writes_sequences_and_manifest(small_suite):
    manifest = json.loads((small_suite / "suite.json").read_text())
    assert manifest["seed"] == 3 and manifest["frames_scale"] == 0.05
    assert "tune" in manifest["split"] and "report" in manifest["split"]
    names = [e["name"] for e in manifest["sequences"]]
    assert names and all(n.startswith("report-") for n in names)
    for e in manifest["sequences"]:
        seq = open_sequence(small_suite / e["path"])
        assert len(seq) == e["frames"] == 30
        cam = suite.CAMERAS[e["camera"]]
        assert seq.camera == cam and seq.depth(0).shape == (cam.height, cam.width)
        assert seq.depth(0).max() > 0
        assert e["stats"]["mean_joint_step_mm"] > 0
        info = json.loads((small_suite / e["path"] / "synth.json").read_text())
        assert info["suite"]["name"] == e["name"]
    fast = next(e for e in manifest["sequences"] if e["motion"] == "fast")
    assert fast["stats"]["mean_joint_step_mm"] >= 10.0
    kinect = next(e for e in manifest["sequences"] if e["sensor"] == "kinect")
    assert 550 < kinect["stats"]["median_depth_mm"] < 750


def test_generate_suite_is_deterministic_and_keeps_the_other_part(small_suite, tmp_path):
    again = tmp_path / "again"
    suite.generate_suite(
        again,
        seed=3,
        part="report",
        frames_scale=0.05,
        real_motion=again / "none",
        workers=2,
        progress=False,
    )
    name = "report-sr300-topdown"
    for f in ("000000_depth.bin", "000017_depth.bin", "joint.txt"):
        assert (again / name / f).read_bytes() == (small_suite / name / f).read_bytes()
    suite.generate_suite(
        again, seed=3, part="tune", frames_scale=0.05, real_motion=again / "none", progress=False
    )
    parts = {e["part"] for e in json.loads((again / "suite.json").read_text())["sequences"]}
    assert parts == {"tune", "report"}
    assert [r[0] for r in suite.read_suite(again, "tune")] == [
        r.name for r in suite.catalogue(3, again / "none") if r.part == "tune"
    ]


@needs_data
def test_recorded_motion_rows_render(tmp_path):
    rows = [r for r in suite.catalogue(0, REAL_MOTION) if r.motion.startswith(("fpha", "icvl"))]
    fpha = next(r for r in rows if r.motion.startswith("fpha"))
    entry = suite.render_suite_sequence(
        fpha, tmp_path, frames_scale=0.06, real_motion=REAL_MOTION, workers=1
    )
    seq = open_sequence(tmp_path / entry["path"])
    recorded = real_motion.load_fpha(REAL_MOTION / "fpha" / fpha.motion[5:] / "skeleton.txt")
    assert np.allclose(seq.ground_truth.joints_mm, recorded[: len(seq)], atol=1e-4)
    assert seq.camera == real_motion.FPHA_CAMERA
    # the rendered hand covers its joints' projections (most joints on or behind the surface)
    depth = seq.depth(0)
    uv = np.rint(seq.camera.project(recorded[0])).astype(int)
    assert (depth[uv[:, 1], uv[:, 0]] > 0).mean() > 0.6


# ---------------------------------------------------------------------------- bench over datasets
def test_expand_datasets(small_suite, tmp_path):
    with pytest.raises(ValueError, match="needs --part"):
        bench.expand_datasets([small_suite])
    with pytest.raises(ValueError, match="no tune sequences"):
        bench.expand_datasets([small_suite], "tune")
    got = bench.expand_datasets([small_suite, tmp_path / "x", tmp_path / "y" / "x"], "report")
    assert [d["part"] for d in got][-2:] == [None, None]
    assert len({d["name"] for d in got}) == len(got)  # the second "x" is renamed
    assert all(Path(d["path"]).is_dir() for d in got if d["part"])


def _run(strategy: str, fraction: float, mean: float, mx: float, init: float) -> dict:
    summ = lambda m, x: {"mean_mm": m, "median_mm": m, "max_mm": x}  # noqa: E731
    return {
        "strategy": strategy,
        "ref_fraction_target": fraction,
        "noise_px": 0.0,
        "bones": "estimated",
        "lift": summ(1.0, 3.0),
        "init": summ(init, 2 * mx),
        "final": summ(mean, mx),
        "final_non_reference": summ(mean, mx),
        "timings_s": {"load": 1.0, "refine": 2.0},
    }


def test_summary_is_mean_of_means_and_worst_max():
    docs = [
        {"name": "a", "dataset": "a", "runs": [_run("forest", 0.05, 2.0, 20.0, 3.0)]},
        {"name": "b", "dataset": "b", "runs": [_run("forest", 0.05, 6.0, 50.0, 5.0)]},
    ]
    (row,) = bench.summarize_datasets(docs)
    assert row["datasets"] == 2
    assert row["final"] == {"mean_of_means_mm": 4.0, "worst_mean_mm": 6.0, "worst_max_mm": 50.0}
    assert row["init"]["worst_max_mm"] == 100.0
    assert row["refine_worse"] == ["b"]
    assert row["timings_s"] == {"load": 2.0, "refine": 4.0}
    assert "forest" in bench.format_summary({"datasets": docs, "summary": [row], "frames": 9})


def test_bad_joints_are_split_by_what_their_frames_depth_shows():
    from types import SimpleNamespace

    from handanno_core.camera import CameraIntrinsics

    cam = CameraIntrinsics(fx=200.0, fy=200.0, cx=32.0, cy=24.0, width=64, height=48)
    wall = np.full((48, 64), 300.0)  # a wall 300 mm from the camera fills the view
    sequence = SimpleNamespace(camera=cam, depth=lambda f: wall)
    gt = np.zeros((2, MSRA21.num_joints, 3))
    gt[:, :, 2] = 300.0  # on the wall: the depth shows them
    gt[0, 1, 2] = 400.0  # 100 mm behind the wall: hidden
    gt[0, 2, 0] = 400.0  # projects at u = 299 px, past the 64 px wide image: hidden
    final = gt.copy()
    final[0, :3, 1] += 50.0  # joints 0-2 of frame 0 50 mm off: one shown, two hidden
    final[1, 3, 1] += 30.0  # one shown joint 30 mm off
    out = bench.hidden_bad_joints(sequence, MSRA21, gt, final)
    assert out == {
        "joints_over_20_mm": 4,
        "hidden_over_20_mm": 2,
        "joints_over_40_mm": 3,
        "hidden_over_40_mm": 2,
    }
    docs = [
        {"name": n, "dataset": n, "runs": [{**_run("uniform", 0.05, 2.0, 50.0, 3.0), **out}]}
        for n in ("a", "b")
    ]
    (row,) = bench.summarize_datasets(docs)
    assert (row["joints_over_40_mm"], row["hidden_over_40_mm"]) == (6, 4)
    assert "6 (4)" in bench.format_summary({"datasets": docs, "summary": [row], "frames": 4})


def test_machine_line_names_the_libraries_and_blas_kernels():
    # two installs (or CPUs) of one commit round differently: the line must tell them apart
    import scipy
    from threadpoolctl import threadpool_info

    line = bench.machine_description()
    assert f"numpy {np.__version__}" in line and f"scipy {scipy.__version__}" in line
    for info in threadpool_info():
        if info["user_api"] == "blas" and info.get("architecture"):
            assert f"{info['version']} {info['architecture']}" in line
    assert len(line.split(", ")) == len(set(line.split(", ")))


def test_single_dataset_keeps_todays_json(monkeypatch, tmp_path):
    calls = []

    def fake(dataset, **kwargs):
        calls.append((dataset, kwargs))
        return {"dataset": str(dataset), "runs": []}

    monkeypatch.setattr(bench, "run_bench", fake)
    out = bench.run_bench_datasets(
        [tmp_path / "seq"], json_out=tmp_path / "b.json", fractions=[0.05], quiet=True
    )
    assert out == {"dataset": str(tmp_path / "seq"), "runs": []}
    assert calls == [
        (
            str(tmp_path / "seq"),
            {"json_out": tmp_path / "b.json", "quiet": True, "fractions": [0.05]},
        )
    ]
    assert not (tmp_path / "b.datasets").exists()


def test_bench_keeps_one_work_dir_per_dataset(monkeypatch, tmp_path):
    seen = []

    def fake(dataset, **kwargs):
        seen.append(kwargs["work_dir"])
        return {"dataset": str(dataset), "frames": 1, "runs": []}

    monkeypatch.setattr(bench, "run_bench", fake)
    bench.run_bench_datasets(
        [tmp_path / "a", tmp_path / "b"],
        json_out=tmp_path / "s.json",
        work_dir=tmp_path / "w",
        quiet=True,
    )
    assert seen == [tmp_path / "w" / "a", tmp_path / "w" / "b"]  # not one folder overwritten


@pytest.mark.slow
def test_bench_over_two_datasets_end_to_end(tmp_path):
    paths = []
    for seed in (1, 2):
        paths.append(
            synth.generate_sequence(
                tmp_path / f"s{seed}", frames=40, seed=seed, progress=False, workers=1
            )
        )
    single = bench.run_bench(
        paths[0],
        fractions=[0.1],
        strategies=["uniform"],
        json_out=tmp_path / "one.json",
        quiet=True,
    )
    doc = bench.run_bench_datasets(
        paths,
        fractions=[0.1],
        strategies=["uniform"],
        json_out=tmp_path / "two.json",
        quiet=True,
    )
    assert json.loads((tmp_path / "two.json").read_text()) == doc
    assert [d["name"] for d in doc["datasets"]] == ["s1", "s2"]
    assert doc["frames"] == 80
    first = doc["datasets"][0]
    # each dataset's entry is that dataset's own bench JSON plus name, part and load
    assert set(first) == set(single) | {"name", "part", "load_avg_1m"}
    assert first["runs"][0]["final"] == single["runs"][0]["final"]
    (row,) = doc["summary"]
    means = [d["runs"][0]["final"]["mean_mm"] for d in doc["datasets"]]
    assert row["final"]["mean_of_means_mm"] == pytest.approx(np.mean(means), abs=1e-3)
    assert (tmp_path / "two.datasets" / "s2.json").is_file()


def test_cli_bench_refuses_a_suite_without_part(small_suite, tmp_path, capsys):
    from app.cli import main

    assert main(["bench", str(small_suite), "--json", str(tmp_path / "b.json")]) == 2
    err = capsys.readouterr().err
    assert "needs --part" in err and str(small_suite) in err and "\n" == err[-1]
    assert not (tmp_path / "b.json").exists()


def test_cli_suite_command(tmp_path, capsys, monkeypatch):
    from app.cli import main

    monkeypatch.setattr(
        suite,
        "catalogue",
        lambda seed, real_motion=None: [
            suite.SuiteSequence("tune-x", "tune", "smooth", 100, seed + 1),
            suite.SuiteSequence("report-x", "report", "fast", 100, seed + 2, hand="varied"),
        ],
    )
    out = tmp_path / "s"
    assert (
        main(["suite", str(out), "--part", "report", "--frames-scale", "0.3", "--workers", "1"])
        == 0
    )
    text = capsys.readouterr().out
    assert "report-x" in text and "tune-x" not in text and "report part only" in text
    manifest = json.loads((out / "suite.json").read_text())
    assert [e["name"] for e in manifest["sequences"]] == ["report-x"]
    assert len(open_sequence(out / "report-x")) == 30


def test_bench_runs_share_the_base_crop_cache_with_a_grown_cube(tmp_path):
    from handanno_core import pipeline

    data = synth.generate_sequence(tmp_path / "seq", frames=6, seed=1, progress=False, workers=1)
    base = pipeline.new_session(tmp_path / "base", data, format="msra", overwrite=True)
    with base.lock:
        base.model.settings.cube_mm = 260.0  # as if the hand had grown the cube
        base.save()
    pipeline.ensure_crops(base, quiet=True)
    stamp = (tmp_path / "base" / "crops.npy").stat().st_mtime_ns
    run = bench.run_session(base, tmp_path / "run")
    assert run.model.settings.cube_mm == 260.0
    assert isinstance(
        pipeline._cached_crops(run, run.folder / "crops.npy", run.folder / "crops_meta.npz"), tuple
    )
    pipeline.ensure_crops(run, quiet=True)
    assert (tmp_path / "base" / "crops.npy").stat().st_mtime_ns == stamp  # not cut again


def test_cli_bench_model_option(monkeypatch, tmp_path):
    from app.cli import main

    seen = []
    monkeypatch.setattr(bench, "run_bench_datasets", lambda paths, **kw: seen.append(kw["models"]))
    args = ["bench", str(tmp_path / "d"), "--json", str(tmp_path / "b.json")]
    assert main(args + ["--model", "off,on"]) == 0
    assert main(args) == 0
    assert seen == [[False, True], None]  # None: the session default, one run
    with pytest.raises(SystemExit):
        main(args + ["--model", "maybe"])


def test_bench_with_and_without_the_model_on_one_lift(tmp_path):
    data = synth.generate_sequence(tmp_path / "seq", frames=24, seed=4, progress=False, workers=1)
    kw = dict(fractions=[0.1], strategies=["uniform"], workers=1, quiet=True)
    doc = bench.run_bench(data, json_out=tmp_path / "m.json", models=[False, True], **kw)
    off, on = doc["runs"]
    assert (off["model"], on["model"]) == (False, True)
    assert off["lift"] == on["lift"] and off["timings_s"]["lift"] == on["timings_s"]["lift"]
    assert off["init"] != on["init"]  # the model changed propagation
    assert off["kept_initialization"] == 0
    # without the option: one run, today's keys
    (plain,) = bench.run_bench(data, json_out=tmp_path / "p.json", **kw)["runs"]
    assert "model" not in plain and "kept_initialization" not in plain
    assert plain["lift"] == off["lift"]
    rows = bench.summarize_datasets([doc])
    assert [r["model"] for r in rows] == [False, True]


@pytest.mark.parametrize("command", ["propagate", "refine"])
def test_cli_model_switch_defaults_to_the_session(command):
    from app.cli import build_parser

    parse = build_parser().parse_args
    assert parse([command, "sess"]).model is None  # the session's settings.hand_model
    assert parse([command, "sess", "--no-model"]).model is False
    assert parse([command, "sess", "--model"]).model is True


def test_a_session_written_before_the_model_setting_reads_it_as_on():
    from handanno_core.session.model import Settings

    old = {"cube_mm": 250.0, "crop_size": 128, "descriptor": "downsampled", "aligner": "dis"}
    assert Settings.model_validate(old).hand_model is True
