"""Real depth frames from ``../shared/data`` (outside the repository) for localization tests and
benchmarks: the 19 SR305 frames, the HANDS 2017 SR300 frame and the MSRA 2015 frame (formats and
intrinsics: the READMEs there). ``DATA`` is None when the folder is absent (tests skip)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from handanno_core.camera import SR305_CAMERA, CameraIntrinsics

_CANDIDATES = (
    Path(__file__).resolve().parents[2]
    / "shared"
    / "data",  # /work/wt/<name>/tests -> /work/shared
    Path(__file__).resolve().parents[1] / ".." / "shared" / "data",
    Path("/work/shared/data"),
)
DATA: Path | None = next((p.resolve() for p in _CANDIDATES if (p / "real-sr305").is_dir()), None)

HANDS2017_CAMERA = CameraIntrinsics(
    fx=475.065948, fy=475.065857, cx=315.944855, cy=245.287079, width=640, height=480
)
MSRA15_CAMERA = CameraIntrinsics(fx=241.42, fy=241.42, cx=160.0, cy=120.0, width=320, height=240)


def load_frame(name: str) -> tuple[np.ndarray, CameraIntrinsics]:
    """Depth ``(H, W)`` float32 mm (0 = none) and camera of a frame named as in :func:`frame_names`."""
    if DATA is None:
        raise FileNotFoundError("../shared/data is not available")
    if name.startswith("real-sr305/"):
        raw = cv2.imread(str(DATA / name), cv2.IMREAD_UNCHANGED)
        return raw.astype(np.float32) * 0.125, SR305_CAMERA
    if name.endswith(".png"):
        raw = cv2.imread(str(DATA / name), cv2.IMREAD_UNCHANGED)
        return raw.astype(np.float32), HANDS2017_CAMERA
    raw = np.loadtxt(DATA / name, dtype=np.float32)
    return np.where(raw >= 1000, 0, raw).astype(np.float32), MSRA15_CAMERA  # 1000 = background


def frame_names() -> list[str]:
    """Every real frame, as paths relative to ``DATA`` (empty without the data)."""
    if DATA is None:
        return []
    sr = sorted(str(p.relative_to(DATA)) for p in (DATA / "real-sr305").glob("*/*.png"))
    return sr + ["real-frames/hands2017_image_D00000030.png", "real-frames/msra15_frame.txt"]


# Hand (palm + fingers, not forearm) bounding boxes (u0, v0, u1, v1) px, read off the frames by
# eye with a 50 px grid drawn on them (benchmarks/bench_crops.py writes an annotated montage).
# Each excludes the head, the torso and the forearm below the wrist.
HAND_BOXES = {
    "real-sr305/20210326-230536/110.png": (195, 155, 385, 315),
    "real-sr305/20210326-230536/130.png": (190, 140, 370, 310),
    "real-sr305/20210326-230536/150.png": (210, 130, 385, 340),
    "real-sr305/20210326-230536/170.png": (185, 180, 330, 330),
    "real-sr305/20210326-230536/30.png": (200, 255, 350, 390),
    "real-sr305/20210326-230536/50.png": (190, 205, 350, 350),
    "real-sr305/20210326-230536/70.png": (210, 175, 350, 345),
    "real-sr305/20210326-230536/90.png": (260, 130, 385, 330),
    "real-sr305/20210326-231615/0.png": (205, 195, 335, 360),
    "real-sr305/20210326-231615/100.png": (260, 195, 390, 360),
    "real-sr305/20210326-231615/140.png": (255, 190, 375, 370),
    "real-sr305/20210326-231615/160.png": (270, 190, 410, 375),
    "real-sr305/20210326-231615/180.png": (265, 190, 415, 360),
    "real-sr305/20210326-231615/20.png": (270, 205, 400, 365),
    "real-sr305/20210326-231615/200.png": (280, 175, 415, 365),
    "real-sr305/20210326-231615/220.png": (295, 185, 415, 375),
    "real-sr305/20210326-231615/40.png": (245, 215, 385, 365),
    "real-sr305/20210326-231615/60.png": (255, 195, 395, 355),
    "real-sr305/20210326-231615/80.png": (250, 195, 390, 355),
    "real-frames/hands2017_image_D00000030.png": (265, 100, 350, 260),
    "real-frames/msra15_frame.txt": (130, 55, 205, 195),
}
