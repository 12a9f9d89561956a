"""A large session made cheaply, for the app at scale (tests/e2e/test_large_session.py,
benchmarks/bench_app_scale.py): one short synthetic sequence is rendered once, and its frames are
reused as ``copies`` gesture folders of an MSRA-layout dataset (symbolic links, no rendering); the
session's crop cache, selection, annotations and ``results.npz`` are the base's, tiled to N frames.
The results are ground truth plus noise of a size drawn per frame (so the review ranking has a
spread), not a pipeline run: what is exercised is the app on arrays of N frames.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from handanno_core.datasets.msra import CAMERA_FILE, FRAME_SUFFIX, JOINT_FILE


def tiled_dataset(base: Path, out: Path, copies: int) -> Path:
    """An MSRA-layout dataset ``out`` of ``copies`` gesture folders ``g00000``..., each holding
    symbolic links to the frames and ``joint.txt`` of the one-folder sequence ``base``."""
    base = Path(base).resolve()
    frames = sorted(p.name for p in base.iterdir() if p.name.endswith(FRAME_SUFFIX))
    out.mkdir(parents=True, exist_ok=True)
    if (base / CAMERA_FILE).exists():
        os.symlink(base / CAMERA_FILE, out / CAMERA_FILE)
    for k in range(copies):
        folder = out / f"g{k:05d}"
        folder.mkdir()
        os.symlink(base / JOINT_FILE, folder / JOINT_FILE)
        for name in frames:
            os.symlink(base / name, folder / name)
    return out


def build_large_session(
    folder: Path,
    base: Path,
    copies: int,
    *,
    ref_step: int = 20,
    crop_size: int | None = None,
    seed: int = 0,
) -> Path:
    """A session in ``folder`` over ``copies`` copies of the MSRA-layout sequence ``base`` (its
    dataset in ``folder.parent / (folder.name + "-data")``); returns ``folder``.

    References every ``ref_step``-th frame of each copy, annotated by the simulated annotator (on
    the base, copied); every other frame's parent is its predecessor. Crops (``crop_size``: the
    session's crop size, default the standard one) cut once from the base and tiled. Results:
    ``lifted_mm`` = ground truth at references; ``init_mm`` = ground truth plus Gaussian noise whose
    sigma is drawn per frame (exponential, mean 4 mm); ``final_mm`` = ``init_mm`` plus a tenth of
    that; ``confidence`` uniform in [0.3, 1].
    """
    from handanno_core.fileio import atomic_save_npz
    from handanno_core.pipeline import crops_fingerprint, ensure_crops, new_session
    from handanno_core.session import CROPS_FILE, CROPS_META_FILE, Session
    from handanno_core.synth import simulate_annotations

    folder = Path(folder)
    work = folder.parent / f"{folder.name}-base"
    small = new_session(work, base, format="msra", overwrite=True)
    if crop_size is not None:
        small.model.settings.crop_size = int(crop_size)
        small.save()
    crops, centres, boxes = ensure_crops(small, quiet=True)
    f = small.num_frames
    settings = small.model.settings.model_copy()
    seq = small.open_sequence()
    gt_base = seq.ground_truth.joints_mm
    base_refs = np.arange(0, f, ref_step)
    base_ann = {int(r): a.to_json() for r, a in simulate_annotations(seq, base_refs).items()}
    small.close()

    data = tiled_dataset(base, folder.parent / f"{folder.name}-data", copies)
    session = new_session(folder, data, format="msra", overwrite=True)
    n = session.num_frames
    session.model.settings = settings
    out = np.lib.format.open_memmap(
        folder / CROPS_FILE, mode="w+", dtype=crops.dtype, shape=(n, *crops.shape[1:])
    )
    for k in range(copies):
        out[k * f : (k + 1) * f] = crops
    out.flush()
    del out
    atomic_save_npz(
        folder / CROPS_META_FILE,
        {
            "frames": np.asarray(n),
            "cube_mm": np.asarray(settings.cube_mm),
            "size": np.asarray(settings.crop_size),
            "centres_mm": np.tile(centres, (copies, 1)),
            "boxes": np.tile(boxes, (copies, 1)),
            "crops_fingerprint": np.asarray(crops_fingerprint(folder / CROPS_FILE)),
        },
    )
    offsets = np.arange(copies)[:, None] * f
    refs = (offsets + base_refs[None, :]).ravel()
    parent = np.arange(n) - 1
    parent[refs] = -1
    session.set_selection(
        {"strategy": "uniform", "reference_frames": refs.tolist(), "parent": parent.tolist()}
    )
    session.model.annotations = {str(int(r)): base_ann[int(r) % f] for r in refs}
    gt = np.tile(gt_base, (copies, 1, 1))
    session.set_bone_lengths(session.skeleton.estimate_bone_lengths(gt_base))
    rng = np.random.default_rng(seed)
    sigma = rng.exponential(4.0, n)
    init = gt + rng.normal(0.0, 1.0, gt.shape) * sigma[:, None, None]
    final = init + rng.normal(0.0, 1.0, gt.shape) * (0.1 * sigma)[:, None, None]
    lifted = np.full_like(gt, np.nan)
    lifted[refs] = gt[refs]
    init[refs] = final[refs] = gt[refs]
    conf = rng.uniform(0.3, 1.0, gt.shape[:2])
    conf[refs] = 1.0
    session.save_results(lifted_mm=lifted, init_mm=init, final_mm=final, confidence=conf)
    session.save()
    session.close()
    Session.open(folder).close()  # it opens (and has no journal to replay)
    return folder
