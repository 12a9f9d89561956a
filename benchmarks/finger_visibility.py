"""Are the badly placed joints of a finished bench session observable in their frames' depth?

For every joint more than ``--threshold`` mm (default 30) from the ground truth in the session's
final result (evaluation only: ground truth never feeds the pipeline), at its frame:

- *own points*: observed hand points (``handmodel.observe``, 512 per crop) within 6 mm of the
  surface of the joint's bone capsule at the true pose and nearest to that capsule; the joint
  counts as *visible* with >= 8 of them, *unexplained* when >= 5 of those are more than 6 mm
  from every capsule of the final pose;
- *hidden*: the true joint lies more than 15 mm behind the observed depth at its pixel, or off
  the hand's silhouette;
- the model's data + free-space level (relative to the references', as propagation's guard) at
  the true pose and at the final pose: a finger search can only help where the truth scores
  lower.

    .venv/bin/python benchmarks/finger_visibility.py SESSION_FOLDER [...] [--threshold 30]

(``SESSION_FOLDER``: e.g. ``handanno bench --work-dir W`` leaves ``W/<sequence>/uniform-0.05``.)
"""

from __future__ import annotations

import argparse

import numpy as np

from handanno_core import handmodel as hm
from handanno_core.crops import image_to_crop
from handanno_core.hands import BoneTable
from handanno_core.pipeline import _reference_joints, ensure_crops
from handanno_core.propagate import PropagationSettings, _hand_models
from handanno_core.session import Session


def visibility(folder: str, threshold: float = 30.0) -> dict:
    """Counts for one session folder (see the module docstring)."""
    s = Session.open(folder)
    seq = s.open_sequence()
    cam = seq.camera
    gt = seq.ground_truth.joints_mm
    res = s.load_results()
    crops, centres, boxes = ensure_crops(s, quiet=True)
    refj = _reference_joints(s, res)
    known = {f: (x, None, None) for f, x in refj.items()}
    bl = np.asarray(s.frame_bone_lengths())
    bones = BoneTable(np.atleast_2d(np.median(bl, 0) if bl.ndim == 2 else bl), None)
    st = PropagationSettings.from_session(s.model.settings)
    models, levels = _hand_models(
        True, known, refj, crops, boxes, centres, cam, seq.skeleton, bones, st
    )
    model, level = models[0], levels[0]
    kin = hm.Kinematics(model.skeleton, model.bone_lengths_mm)
    err = np.linalg.norm(res["final_mm"] - gt, axis=2)
    bad = np.flatnonzero(err.max(1) > threshold)
    out = {"frames": len(bad), "joints": 0, "visible": 0, "unexplained": 0, "hidden": 0}
    if len(bad) == 0:
        return out
    obs = hm.observe(
        np.asarray(crops[bad], np.float32), boxes[bad], centres[bad], cam, cube_mm=st.cube_mm
    )

    def lv(x):
        _, t, _, _ = hm.frame_energy(
            model, kin, *kin.fit(x), obs, cam, hm.FitWeights(), diagnostics=False
        )
        return (t["data"] + t["free_space"]) / level

    l_gt, l_fin = lv(gt[bad]), lv(res["final_mm"][bad])
    a_gt, b_gt = model.capsules(gt[bad])
    a_fin, b_fin = model.capsules(res["final_mm"][bad])
    c_gt, _, _, sd_gt = hm._nearest_capsule(obs.points, a_gt, b_gt, model.radii)
    _, _, _, sd_fin = hm._nearest_capsule(obs.points, a_fin, b_fin, model.radii)
    s_px = obs.depth.shape[-1]
    for i, f in enumerate(bad):
        for j in np.flatnonzero(err[f] > threshold):
            caps = np.flatnonzero(model.pairs[:, 1] == j)
            own = obs.valid[i] & np.isin(c_gt[i], caps) & (np.abs(sd_gt[i]) < 6.0)
            xy = np.rint(image_to_crop(cam.project(gt[f, j][None]), boxes[f])[0]).astype(int)
            inside = np.all((xy >= 0) & (xy < s_px))
            d_obs = obs.depth[i][xy[1], xy[0]] if inside else np.nan
            out["joints"] += 1
            out["visible"] += int(own.sum() >= 8)
            out["unexplained"] += int(
                own.sum() >= 8 and (own & (np.abs(sd_fin[i]) > 6.0)).sum() >= 5
            )
            out["hidden"] += int(not gt[f, j, 2] - d_obs < 15.0)
    out["level_gt_median"] = float(np.median(l_gt))
    out["level_final_median"] = float(np.median(l_fin))
    out["frames_gt_lower"] = int(np.sum(l_gt < l_fin))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--threshold", type=float, default=30.0)
    args = ap.parse_args()
    for folder in args.folders:
        v = visibility(folder, args.threshold)
        print(folder, {k: round(x, 2) if isinstance(x, float) else x for k, x in v.items()})


if __name__ == "__main__":
    main()
