"""Depth-sequence readers: round trips, format conversions, laziness and bad input."""

from __future__ import annotations

import builtins
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io

from handanno_core.camera import MSRA_CAMERA, NYU_CAMERA, SR305_CAMERA, CameraIntrinsics
from handanno_core.datasets import (
    FORMATS,
    BadFrameReport,
    BlenderSequence,
    DatasetError,
    FolderSequence,
    FrameError,
    ICVLSequence,
    MSRASequence,
    NYUSequence,
    detect_format,
    open_sequence,
    write_msra_frame,
    write_msra_joints,
)
from handanno_core.datasets import msra as msra_module
from handanno_core.datasets.blender import BLENDER_CAMERA
from handanno_core.datasets.icvl import ICVL_CAMERA
from handanno_core.datasets.nyu import NYU_JOINTS, encode_nyu_png

SMALL = CameraIntrinsics(fx=100.0, fy=110.0, cx=20.0, cy=15.0, width=40, height=30)


def _hand_depth(rng, shape=(240, 320), box=(50, 80, 100, 140)) -> np.ndarray:
    """A depth map that is 0 except a random box of 300-600 mm (top, bottom, left, right)."""
    depth = np.zeros(shape, np.float32)
    top, bottom, left, right = box
    depth[top:bottom, left:right] = rng.uniform(300, 600, (bottom - top, right - left)).astype(
        np.float32
    )
    return depth


def _joints(rng, n, j=21) -> np.ndarray:
    xyz = rng.normal(0.0, 40.0, (n, j, 3))
    xyz[..., 2] += 450.0
    return xyz


def _write_gesture(folder: Path, rng, n=3, shape=(240, 320)):
    folder.mkdir(parents=True, exist_ok=True)
    depths = []
    for i in range(n):
        d = _hand_depth(rng, shape, box=(10 + i, 40 + i, 20, 60 + 2 * i))
        write_msra_frame(folder / f"{i:06d}_depth.bin", d)
        depths.append(d)
    joints = _joints(rng, n)
    write_msra_joints(folder / "joint.txt", joints)
    return np.stack(depths), joints


# ---------------------------------------------------------------------------- MSRA
def test_msra_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    depths, joints = _write_gesture(tmp_path, rng, n=4)
    seq = open_sequence(tmp_path)
    assert isinstance(seq, MSRASequence) and seq.format == "msra"
    assert len(seq) == 4 and seq.sequence_breaks == []
    assert seq.camera == MSRA_CAMERA and seq.skeleton.name == "msra21"
    for i in range(4):
        d = seq.depth(i)
        assert d.dtype == np.float32 and d.shape == (240, 320)
        np.testing.assert_array_equal(d, depths[i])
    np.testing.assert_allclose(seq.ground_truth.joints_mm, joints, atol=1e-5)
    assert seq.frame_names[1] == "000001_depth.bin"


def test_msra_bin_layout_and_tight_box(tmp_path):
    depth = np.zeros((240, 320), np.float32)
    depth[7, 11] = 400.0
    depth[9, 15] = 500.0
    write_msra_frame(tmp_path / "000000_depth.bin", depth)
    data = (tmp_path / "000000_depth.bin").read_bytes()
    header = np.frombuffer(data, "<i4", 6)
    assert header.tolist() == [320, 240, 11, 7, 16, 10]  # w, h, left, top, right, bottom
    box = np.frombuffer(data, "<f4", offset=24).reshape(3, 5)
    assert box[0, 0] == 400.0 and box[2, 4] == 500.0 and box.sum() == 900.0


def test_msra_all_zero_frame_writes_1x1_box(tmp_path):
    write_msra_frame(tmp_path / "000000_depth.bin", np.zeros((240, 320)))
    data = (tmp_path / "000000_depth.bin").read_bytes()
    assert len(data) == 28
    assert np.frombuffer(data, "<i4", 6).tolist() == [320, 240, 0, 0, 1, 1]
    seq = MSRASequence(tmp_path)
    assert not seq.depth(0).any()
    assert seq.ground_truth is None


def test_msra_joint_convention_in_file(tmp_path):
    """File: y up, z negative; reader: OpenCV (x, -y, -z); writer converts back."""
    write_msra_frame(tmp_path / "000000_depth.bin", np.ones((240, 320)))
    values = np.zeros(63)
    values[:3] = [10.0, 20.0, -300.0]
    (tmp_path / "joint.txt").write_text("1\n" + " ".join(map(str, values)) + "\n")
    gt = MSRASequence(tmp_path).ground_truth.joints_mm
    np.testing.assert_allclose(gt[0, 0], [10.0, -20.0, 300.0])
    write_msra_joints(tmp_path / "joint2.txt", gt)
    line = (tmp_path / "joint2.txt").read_text().splitlines()[1].split()
    np.testing.assert_allclose([float(v) for v in line[:3]], [10.0, 20.0, -300.0])


def test_msra_joint_projects_onto_its_pixel(tmp_path):
    """A joint at depth d seen at pixel (u, v) must project back there after conversion."""
    u, v, d = 200.0, 60.0, 420.0
    xyz = MSRA_CAMERA.backproject(np.array([u, v]), np.array(d))  # OpenCV frame
    joints = np.tile(xyz, (1, 21, 1))
    write_msra_frame(tmp_path / "000000_depth.bin", np.ones((240, 320)))
    write_msra_joints(tmp_path / "joint.txt", joints)
    raw = np.array((tmp_path / "joint.txt").read_text().split()[1:4], float)
    assert raw[1] > 0 and raw[2] < 0  # below the centre row -> y up is positive; z negative
    gt = MSRASequence(tmp_path).ground_truth.joints_mm
    np.testing.assert_allclose(MSRA_CAMERA.project(gt[0, 0]), [u, v], atol=1e-4)


def test_msra_gesture_folders_are_one_sequence_with_breaks(tmp_path):
    rng = np.random.default_rng(1)
    parts = {}
    for name, n in [("P0/2", 2), ("P0/10", 3), ("P1/1", 4)]:
        parts[name] = _write_gesture(tmp_path / name, rng, n=n)
    seq = open_sequence(tmp_path)
    assert len(seq) == 9
    assert seq.sequence_breaks == [2, 5]  # natural order: P0/2, P0/10, P1/1
    assert seq.frame_names[2] == "P0/10/000000_depth.bin"
    np.testing.assert_array_equal(seq.depth(5), parts["P1/1"][0][0])
    gt = seq.ground_truth.joints_mm
    np.testing.assert_allclose(gt[2:5], parts["P0/10"][1], atol=1e-5)
    # flat gesture folders 1/, 2/ work too, and a single gesture folder opens alone
    assert open_sequence(tmp_path / "P0").sequence_breaks == [2]
    assert len(open_sequence(tmp_path / "P1" / "1")) == 4


def test_msra_camera_json(tmp_path):
    rng = np.random.default_rng(2)
    d = _hand_depth(rng, (30, 40), box=(5, 10, 5, 12))
    write_msra_frame(tmp_path / "000000_depth.bin", d)
    SMALL.to_json(tmp_path / "camera.json")
    seq = open_sequence(tmp_path)
    assert seq.camera == SMALL
    np.testing.assert_array_equal(seq.depth(0), d)
    # a frame whose header size differs from the camera is reported
    write_msra_frame(tmp_path / "000001_depth.bin", np.ones((240, 320)))
    with pytest.raises(FrameError, match=r"000001_depth.bin \(frame 1\).*320x240.*40x30"):
        MSRASequence(tmp_path).depth(1)


def test_msra_open_is_lazy(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    _write_gesture(tmp_path / "1", rng, n=3)
    _write_gesture(tmp_path / "2", rng, n=3)
    opened: list[str] = []
    real_open = builtins.open

    def spy(file, *args, **kwargs):
        opened.append(str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", spy)
    seq = open_sequence(tmp_path)
    assert len(seq) == 6
    assert not [f for f in opened if f.endswith((".bin", "joint.txt"))]
    seq.depth(4)
    assert [f for f in opened if f.endswith(".bin")] == [str(tmp_path / "2" / "000001_depth.bin")]
    assert not [f for f in opened if f.endswith("joint.txt")]
    assert seq.ground_truth.joints_mm.shape == (6, 21, 3)
    assert len([f for f in opened if f.endswith("joint.txt")]) == 2
    _ = seq.ground_truth  # cached: not parsed again
    assert len([f for f in opened if f.endswith("joint.txt")]) == 2


def _bin(tmp_path, header, payload_floats=None, raw=None) -> Path:
    path = tmp_path / "000000_depth.bin"
    data = np.asarray(header, "<i4").tobytes()
    if payload_floats is not None:
        data += np.asarray(payload_floats, "<f4").tobytes()
    if raw is not None:
        data += raw
    path.write_bytes(data)
    return path


@pytest.mark.parametrize(
    ("header", "payload", "message"),
    [
        ([320, 240, 0, 0, 2, 2], [1.0, 2.0, 3.0], r"wrong size.*truncated"),
        ([320, 240, 0, 0, 2, 2], [1.0] * 5, r"wrong size.*trailing"),
        ([320, 240, 300, 0, 330, 1], [1.0] * 30, r"outside the 320x240 image"),
        ([320, 240, 5, 0, 5, 1], [], r"empty or outside"),
        ([320, 240, -1, 0, 1, 1], [1.0, 1.0], r"outside"),
        ([640, 480, 0, 0, 1, 1], [1.0], r"header image size 640x480"),
        ([320, 240, 0, 0, 2, 1], [np.nan, 1.0], r"NaN/inf"),
        ([320, 240, 0, 0, 2, 1], [np.inf, 1.0], r"NaN/inf"),
        ([320, 240, 0, 0, 2, 1], [-5.0, 1.0], r"negative"),
    ],
)
def test_msra_bad_frames(tmp_path, header, payload, message):
    path = _bin(tmp_path, header, payload)
    with pytest.raises(FrameError, match=message) as info:
        MSRASequence(tmp_path).depth(0)
    assert info.value.path == str(path) and info.value.frame == 0
    assert "000000_depth.bin (frame 0)" in str(info.value)


def test_msra_short_header_and_missing_file(tmp_path):
    _bin(tmp_path, [320, 240, 0])
    seq = MSRASequence(tmp_path)
    with pytest.raises(FrameError, match=r"truncated: 12 bytes"):
        seq.depth(0)
    (tmp_path / "000000_depth.bin").unlink()
    with pytest.raises(FrameError, match=r"000000_depth.bin \(frame 0\): cannot read file"):
        seq.depth(0)


def test_msra_iter_depth_report_skips_bad_frames(tmp_path):
    rng = np.random.default_rng(4)
    _write_gesture(tmp_path, rng, n=5)
    (tmp_path / "000001_depth.bin").write_bytes(b"\x00" * 10)
    path3 = tmp_path / "000003_depth.bin"
    path3.write_bytes(path3.read_bytes()[:-4])
    seq = MSRASequence(tmp_path)
    report = BadFrameReport()
    got = [i for i, _ in seq.iter_depth(report=report)]
    assert got == [0, 2, 4]
    assert report.frames == [1, 3]
    assert "000003_depth.bin" in report.summary()
    with pytest.raises(FrameError):
        list(seq.iter_depth())


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("2\n" + " ".join(["1"] * 63) + "\n", r"line 1 says N=2 .* 1 depth frames"),
        ("1\n" + " ".join(["1"] * 62) + "\n", r"line 2 \(frame 0\): 62 values, expected 63"),
        ("1\n" + " ".join(["1"] * 62) + " x\n", r"line 2 \(frame 0\): non-numeric"),
        ("1\n" + " ".join(["1"] * 62) + " nan\n", r"line 2 \(frame 0\): NaN/inf"),
        ("one\n" + " ".join(["1"] * 63) + "\n", r"line 1 must be the frame count"),
        ("1\n", r"N=1 frames but 0 joint lines"),
    ],
)
def test_msra_bad_joint_file(tmp_path, text, message):
    write_msra_frame(tmp_path / "000000_depth.bin", np.ones((240, 320)))
    (tmp_path / "joint.txt").write_text(text)
    seq = MSRASequence(tmp_path)  # opening does not parse joint.txt
    with pytest.raises(DatasetError, match=message) as info:
        _ = seq.ground_truth
    assert "joint.txt" in str(info.value)


def test_msra_joint_file_wrong_line_in_the_middle(tmp_path):
    rng = np.random.default_rng(5)
    _write_gesture(tmp_path, rng, n=3)
    lines = (tmp_path / "joint.txt").read_text().splitlines()
    lines[2] = " ".join(lines[2].split()[:60])
    (tmp_path / "joint.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"line 3 \(frame 1\): 60 values"):
        _ = MSRASequence(tmp_path).ground_truth


def test_msra_joint_file_missing_in_one_gesture(tmp_path):
    rng = np.random.default_rng(6)
    _write_gesture(tmp_path / "1", rng, n=2)
    _write_gesture(tmp_path / "2", rng, n=2)
    (tmp_path / "2" / "joint.txt").unlink()
    with pytest.raises(DatasetError, match=r"lack joint.txt"):
        _ = open_sequence(tmp_path).ground_truth


def test_msra_writers_reject_bad_input(tmp_path):
    with pytest.raises(ValueError):
        write_msra_frame(tmp_path / "a.bin", np.full((4, 4), np.nan))
    with pytest.raises(ValueError):
        write_msra_frame(tmp_path / "a.bin", np.zeros((4, 4, 2)))
    with pytest.raises(ValueError):
        write_msra_joints(tmp_path / "j.txt", np.zeros((2, 20, 3)))


def test_msra_empty_folder(tmp_path):
    with pytest.raises(DatasetError, match=str(tmp_path)):
        MSRASequence(tmp_path)


# ---------------------------------------------------------------------------- Blender
def _blender_fixture(tmp_path, rng, ids=(2, 10, 1), channels=False, cam=BLENDER_CAMERA):
    h, w = cam.height, cam.width
    truth = {}
    for k in ids:
        metres = np.full((h, w), 1e10)  # background
        metres[100:120, 200:230] = rng.uniform(0.3, 0.6, (20, 30))
        metres[0, 0] = 0.0
        metres[0, 1] = -1.0
        metres[0, 2] = np.inf
        xyz = _joints(rng, 1, 24)[0]
        uvz = np.concatenate([cam.project(xyz), xyz[:, 2:] / 1000.0], axis=1)
        arr = np.stack([metres] * 3, -1) if channels else metres
        np.save(tmp_path / f"c00_{k:08d}_depth_0002.npy", arr.astype(np.float32))
        np.savetxt(tmp_path / f"c00_{k:08d}_anno_blender.txt", uvz.reshape(1, -1), fmt="%.10f")
        truth[k] = (metres, xyz)
    return truth


@pytest.mark.parametrize("channels", [False, True])
def test_blender_depth_and_ground_truth(tmp_path, channels):
    rng = np.random.default_rng(10)
    truth = _blender_fixture(tmp_path, rng, channels=channels)
    seq = open_sequence(tmp_path)
    assert isinstance(seq, BlenderSequence) and seq.skeleton.name == "blender24"
    assert seq.camera == BLENDER_CAMERA
    assert seq.frame_names == [
        "c00_00000001_depth_0002.npy",
        "c00_00000002_depth_0002.npy",
        "c00_00000010_depth_0002.npy",
    ]
    d = seq.depth(2)
    metres = truth[10][0]
    np.testing.assert_allclose(d[100:120, 200:230], metres[100:120, 200:230] * 1000, rtol=1e-6)
    assert d[0, 0] == 0 and d[0, 1] == 0 and d[0, 2] == 0 and d[50, 50] == 0
    assert d.dtype == np.float32
    gt = seq.ground_truth.joints_mm
    assert gt.shape == (3, 24, 3)
    np.testing.assert_allclose(gt[0], truth[1][1], atol=1e-4)
    np.testing.assert_allclose(gt[2], truth[10][1], atol=1e-4)


def test_blender_bad_input(tmp_path):
    rng = np.random.default_rng(11)
    _blender_fixture(tmp_path, rng, ids=(1, 2, 3, 4))
    (tmp_path / "c00_00000001_depth_0002.npy").write_bytes(b"not a numpy file")
    bad = np.zeros((480, 640), np.float32)
    bad[5, 5] = np.nan
    np.save(tmp_path / "c00_00000002_depth_0002.npy", bad)
    np.save(tmp_path / "c00_00000003_depth_0002.npy", np.zeros((240, 320), np.float32))
    seq = BlenderSequence(tmp_path)
    with pytest.raises(FrameError, match=r"c00_00000001_depth_0002.npy \(frame 0\): cannot read"):
        seq.depth(0)
    with pytest.raises(FrameError, match=r"\(frame 1\): 1 NaN"):
        seq.depth(1)
    with pytest.raises(FrameError, match=r"\(frame 2\): depth has shape \(240, 320\)"):
        seq.depth(2)
    report = BadFrameReport()
    assert [i for i, _ in seq.iter_depth(report=report)] == [3]
    assert report.frames == [0, 1, 2]
    (tmp_path / "c00_00000004_anno_blender.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match=r"c00_00000004_anno_blender.txt \(frame 3\): 3 values"):
        _ = seq.ground_truth
    (tmp_path / "c00_00000004_anno_blender.txt").unlink()
    with pytest.raises(DatasetError, match=r"no \*anno_blender.txt"):
        _ = BlenderSequence(tmp_path).ground_truth


# ---------------------------------------------------------------------------- NYU
def _nyu_fixture(folder: Path, rng, n=3, cameras=3):
    folder.mkdir(parents=True, exist_ok=True)
    depths = []
    for cam in range(1, cameras + 1):
        for i in range(1, n + 1):
            d = np.zeros((480, 640), np.float32)
            d[200:240, 300:350] = rng.integers(400, 3000, (40, 50))
            d[0, 0] = 65535
            cv2.imwrite(str(folder / f"depth_{cam}_{i:07d}.png"), encode_nyu_png(d))
            if cam == 1:
                depths.append(d)
    xyz = rng.normal(0, 50, (cameras, n, 36, 3))
    xyz[..., 2] += 700
    scipy.io.savemat(folder / "joint_data.mat", {"joint_xyz": xyz, "joint_uvd": xyz})
    return np.stack(depths), xyz


def test_nyu_depth_and_ground_truth(tmp_path):
    rng = np.random.default_rng(20)
    depths, xyz = _nyu_fixture(tmp_path / "train", rng)
    seq = open_sequence(tmp_path)  # parent of train/ is accepted
    assert isinstance(seq, NYUSequence) and seq.path == tmp_path / "train"
    assert len(seq) == 3 and seq.camera == NYU_CAMERA and seq.skeleton.name == "nyu14"
    for i in range(3):
        np.testing.assert_array_equal(seq.depth(i), depths[i])
    gt = seq.ground_truth.joints_mm
    assert gt.shape == (3, 14, 3)
    expected = xyz[0][:, NYU_JOINTS] * np.array([1.0, -1.0, 1.0])
    np.testing.assert_allclose(gt, expected)
    cam2 = NYUSequence(tmp_path / "train", camera_index=2)
    np.testing.assert_allclose(cam2.ground_truth.joints_mm[:, :, 0], xyz[1][:, NYU_JOINTS, 0])


def test_nyu_png_channel_packing(tmp_path):
    """Depth 0x0102 = 258 mm is B=0x02, G=0x01 in OpenCV's BGR order."""
    img = np.zeros((480, 640, 3), np.uint8)
    img[10, 20] = (0x02, 0x01, 0x77)  # B, G, R (R ignored)
    cv2.imwrite(str(tmp_path / "depth_1_0000001.png"), img)
    d = NYUSequence(tmp_path).depth(0)
    assert d[10, 20] == 258.0 and d.sum() == 258.0
    assert NYUSequence(tmp_path).ground_truth is None


def test_nyu_bad_input(tmp_path):
    rng = np.random.default_rng(21)
    _nyu_fixture(tmp_path, rng, n=3, cameras=1)
    (tmp_path / "depth_1_0000001.png").write_bytes(b"\x89PNG garbage")
    cv2.imwrite(str(tmp_path / "depth_1_0000002.png"), np.zeros((480, 640), np.uint16))
    seq = NYUSequence(tmp_path)
    with pytest.raises(FrameError, match=r"depth_1_0000001.png \(frame 0\): unreadable PNG"):
        seq.depth(0)
    with pytest.raises(FrameError, match=r"\(frame 1\): expected 8-bit 3-channel"):
        seq.depth(1)
    (tmp_path / "depth_1_0000003.png").unlink()
    with pytest.raises(FrameError, match=r"\(frame 2\): file missing"):
        seq.depth(2)
    scipy.io.savemat(tmp_path / "joint_data.mat", {"joint_xyz": np.zeros((1, 2, 36, 3))})
    with pytest.raises(DatasetError, match=r"joint_data.mat: has 2 frames"):
        _ = seq.ground_truth


# ---------------------------------------------------------------------------- ICVL
def _icvl_fixture(root: Path, rng, n=3, label_name="labels.txt"):
    (root / "Depth" / "seq1").mkdir(parents=True, exist_ok=True)
    depths, joints, lines = [], [], []
    for i in range(n):
        d = np.zeros((240, 320), np.uint16)
        d[60:100, 100:150] = rng.integers(200, 800, (40, 50))
        name = f"seq1/image_{i:04d}.png"
        cv2.imwrite(str(root / "Depth" / name), d)
        xyz = _joints(rng, 1, 16)[0]
        uvd = np.concatenate([ICVL_CAMERA.project(xyz), xyz[:, 2:]], axis=1)
        lines.append(name + " " + " ".join(f"{v:.8f}" for v in uvd.ravel()))
        depths.append(d.astype(np.float32))
        joints.append(xyz)
    (root / label_name).write_text("\n".join(lines) + "\n")
    return np.stack(depths), np.stack(joints)


def test_icvl_depth_and_ground_truth(tmp_path):
    rng = np.random.default_rng(30)
    depths, joints = _icvl_fixture(tmp_path, rng)
    seq = open_sequence(tmp_path)
    assert isinstance(seq, ICVLSequence) and seq.skeleton.name == "icvl16"
    assert seq.camera == ICVL_CAMERA and len(seq) == 3
    np.testing.assert_array_equal(seq.depth(1), depths[1])
    np.testing.assert_allclose(seq.ground_truth.joints_mm, joints, atol=1e-5)
    # the label file itself can be given; depth_scale_mm applies
    seq2 = open_sequence(tmp_path / "labels.txt", depth_scale_mm=0.5)
    np.testing.assert_allclose(seq2.depth(0), depths[0] * 0.5)


def test_icvl_bad_input(tmp_path):
    rng = np.random.default_rng(31)
    _icvl_fixture(tmp_path, rng)
    cv2.imwrite(str(tmp_path / "Depth/seq1/image_0001.png"), np.zeros((240, 320), np.uint8))
    (tmp_path / "Depth/seq1/image_0002.png").unlink()
    seq = ICVLSequence(tmp_path)
    with pytest.raises(
        FrameError, match=r"image_0001.png \(frame 1\): expected a single-channel 16-bit"
    ):
        seq.depth(1)
    with pytest.raises(FrameError, match=r"image_0002.png \(frame 2\): file missing"):
        seq.depth(2)
    text = (tmp_path / "labels.txt").read_text().splitlines()
    (tmp_path / "bad.txt").write_text(text[0] + "\n" + " ".join(text[1].split()[:-1]) + "\n")
    with pytest.raises(DatasetError, match=r"bad.txt: line 2: 47 values"):
        ICVLSequence(tmp_path / "bad.txt")


# ---------------------------------------------------------------------------- folder
def test_folder_png_with_intrinsics_json(tmp_path):
    rng = np.random.default_rng(40)
    raw = {}
    for k in (10, 2, 1):
        img = rng.integers(0, 4000, (30, 40)).astype(np.uint16)
        cv2.imwrite(str(tmp_path / f"frame_{k}.png"), img)
        raw[k] = img
    meta = SMALL.model_dump() | {"depth_scale_mm": 0.125}
    (tmp_path / "intrinsics.json").write_text(json.dumps(meta))
    seq = open_sequence(tmp_path)
    assert isinstance(seq, FolderSequence) and seq.camera == SMALL
    assert seq.frame_names == ["frame_1.png", "frame_2.png", "frame_10.png"]
    np.testing.assert_allclose(seq.depth(2), raw[10] * 0.125)
    assert seq.ground_truth is None and seq.skeleton.name == "msra21"
    # argument beats the JSON key
    np.testing.assert_allclose(open_sequence(tmp_path, depth_scale_mm=1.0).depth(0), raw[1])


def test_folder_npy_with_joints(tmp_path):
    rng = np.random.default_rng(41)
    frames = [rng.uniform(0, 900, (30, 40)).astype(np.float32) for _ in range(3)]
    for i, f in enumerate(frames):
        np.save(tmp_path / f"{i}.npy", f)
    joints = _joints(rng, 3, 16)
    np.save(tmp_path / "joints.npy", joints)
    seq = open_sequence(tmp_path, format="folder", intrinsics=SMALL)
    assert len(seq) == 3 and seq.skeleton.name == "icvl16"
    np.testing.assert_array_equal(seq.depth(1), frames[1])
    np.testing.assert_allclose(seq.ground_truth.joints_mm, joints)
    np.save(tmp_path / "joints.npy", joints[:2])
    with pytest.raises(DatasetError, match=r"joints.npy: 2 poses but the folder has 3"):
        FolderSequence(tmp_path, intrinsics=SMALL)


def test_folder_bad_input(tmp_path):
    np.save(tmp_path / "0.npy", np.full((30, 40), -1.0))
    np.save(tmp_path / "1.npy", np.zeros((30, 41)))
    (tmp_path / "2.npy").write_bytes(b"junk")
    np.save(tmp_path / "3.npy", np.zeros((30, 40)))
    with pytest.raises(DatasetError, match=rf"{tmp_path}: no camera intrinsics"):
        FolderSequence(tmp_path)
    seq = FolderSequence(tmp_path, intrinsics=SMALL)
    with pytest.raises(FrameError, match=r"0.npy \(frame 0\): 1200 negative"):
        seq.depth(0)
    with pytest.raises(FrameError, match=r"1.npy \(frame 1\): depth has shape \(30, 41\)"):
        seq.depth(1)
    with pytest.raises(FrameError, match=r"2.npy \(frame 2\): cannot read"):
        seq.depth(2)
    report = BadFrameReport()
    assert [i for i, _ in seq.iter_depth(report=report)] == [3]
    assert report.frames == [0, 1, 2]
    with pytest.raises(DatasetError, match="depth_scale_mm"):
        FolderSequence(tmp_path, intrinsics=SMALL, depth_scale_mm=-1)


def test_folder_unreadable_png(tmp_path):
    (tmp_path / "0.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    seq = FolderSequence(tmp_path, intrinsics=SMALL)
    with pytest.raises(FrameError, match=r"0.png \(frame 0\): unreadable"):
        seq.depth(0)


REAL = Path("/work/shared/data/real-sr305/20210326-230536")


@pytest.mark.skipif(not REAL.is_dir(), reason="real SR305 frames not present")
def test_folder_opens_real_sr305_frames():
    seq = open_sequence(REAL, intrinsics=SR305_CAMERA, depth_scale_mm=0.125)
    assert seq.format == "folder" and len(seq) == 8
    assert seq.frame_names[0] == "30.png" and seq.frame_names[-1] == "170.png"
    d = seq.depth(0)
    valid = d[d > 0]
    assert d.shape == (480, 640) and valid.size > 10_000
    assert 300 < np.median(valid) < 2000  # hand and body at roughly 0.5-1.5 m


# ---------------------------------------------------------------------------- open_sequence
def test_open_sequence_detection_and_errors(tmp_path):
    rng = np.random.default_rng(50)
    _write_gesture(tmp_path / "msra", rng, n=1)
    (tmp_path / "blender").mkdir()
    _blender_fixture(tmp_path / "blender", rng, ids=(1,))
    _nyu_fixture(tmp_path / "nyu", rng, n=1, cameras=1)
    _icvl_fixture(tmp_path / "icvl", rng, n=1)
    (tmp_path / "folder").mkdir()
    np.save(tmp_path / "folder" / "0.npy", np.zeros((30, 40)))
    for name in FORMATS:
        assert detect_format(tmp_path / name) == name
    assert open_sequence(tmp_path / "folder", intrinsics=SMALL).format == "folder"
    assert detect_format(tmp_path / "nyu" / "joint_data.mat") == "nyu"
    # format= overrides detection: an MSRA folder read as ... MSRA explicitly, and a wrong one fails
    assert open_sequence(tmp_path / "msra", format="MSRA").format == "msra"
    with pytest.raises(DatasetError, match="no \\*depth\\*.npy"):
        open_sequence(tmp_path / "msra", format="blender")
    (tmp_path / "empty").mkdir()
    with pytest.raises(
        DatasetError, match=r"empty: cannot detect .*msra, blender, nyu, icvl, folder"
    ):
        open_sequence(tmp_path / "empty")
    with pytest.raises(DatasetError, match=r"unknown format 'kinect' .*msra, blender"):
        open_sequence(tmp_path / "msra", format="kinect")
    with pytest.raises(DatasetError, match=r"missing: no such file"):
        open_sequence(tmp_path / "missing")
    with pytest.raises(DatasetError, match="depth_scale_mm"):
        open_sequence(tmp_path / "msra", depth_scale_mm=0.125)


def test_opening_reads_no_frame(tmp_path, monkeypatch):
    """No reader decodes a depth file while opening: imread / np.load / .bin reads are refused."""
    rng = np.random.default_rng(60)
    (tmp_path / "blender").mkdir()
    _blender_fixture(tmp_path / "blender", rng, ids=(1, 2))
    _nyu_fixture(tmp_path / "nyu", rng, n=2, cameras=1)
    _icvl_fixture(tmp_path / "icvl", rng, n=2)
    _write_gesture(tmp_path / "msra", rng, n=2)
    (tmp_path / "folder").mkdir()
    cv2.imwrite(str(tmp_path / "folder" / "0.png"), np.zeros((30, 40), np.uint16))

    def refuse(*args, **kwargs):
        raise AssertionError("a frame was read while opening")

    with monkeypatch.context() as m:
        m.setattr(cv2, "imread", refuse)
        m.setattr(np, "load", refuse)
        m.setattr(msra_module, "read_msra_frame", refuse)
        m.setattr(scipy.io, "loadmat", refuse)
        seqs = {
            name: open_sequence(tmp_path / name, intrinsics=SMALL if name == "folder" else None)
            for name in FORMATS
        }
    for name, seq in seqs.items():
        assert seq.format == name and len(seq) >= 1
        assert seq.depth(0).dtype == np.float32
