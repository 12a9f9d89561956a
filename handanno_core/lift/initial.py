"""The starting pose of a lift and the starting bone lengths: observed depth under the 2D
annotation, inconsistent readings dropped, back-projection with the template's directions for
joints without 2D.
"""

from __future__ import annotations

import numpy as np

from ..annotation import FrameAnnotation
from ..camera import CameraIntrinsics
from ..rigid import kabsch
from ..sampling import depth_at
from ..skeleton import Skeleton
from ..synth import template_hand


# ---------------------------------------------------------------------------------------- depth
def observed_depth(
    depth_mm: np.ndarray,
    uv_px: np.ndarray,
    window: int = 3,
    near_px: int = 1,
    front_band_mm: float | None = None,
) -> np.ndarray:
    """Observed depth ``(J,)`` mm under 2D points ``(J, 2)``: :func:`handanno_core.sampling.depth_at`
    (closest surface in the 3x3 block, or with ``front_band_mm`` the median of the block's front
    surface; else the nearest valid pixel within ``window`` px)."""
    return depth_at(depth_mm, uv_px, window=window, near_px=near_px, front_band_mm=front_band_mm)


def _drop_inconsistent_depths(
    d_obs: np.ndarray,
    visible: np.ndarray,
    offsets: np.ndarray,
    skeleton: Skeleton,
    lengths: np.ndarray,
    slack_mm: float,
) -> np.ndarray:
    """``d_obs`` ``(J,)`` with the wrong-looking readings of impossible visible bones set to NaN
    (rules in :func:`initial_pose`). Loops over the (few) inconsistent bones only."""
    z = d_obs + offsets
    p, c = skeleton.bones[:, 0], skeleton.bones[:, 1]
    ok = visible[p] & visible[c] & np.isfinite(z[p]) & np.isfinite(z[c])
    gap = np.where(ok, z[c] - z[p], 0.0)
    bad = np.abs(gap) > lengths + slack_mm
    if not np.any(bad):
        return d_obs
    # a reading that agrees with another visible neighbour is trusted; with no such support on
    # either side both readings are dropped; with support on both, the farther one goes
    fine = ok & ~bad
    support = np.bincount(p[fine], minlength=len(z)) + np.bincount(c[fine], minlength=len(z))
    out = d_obs.copy()
    for pp, cc, g in zip(p[bad], c[bad], gap[bad], strict=True):
        sp, sc = support[pp] > 0, support[cc] > 0
        if sp and not sc:
            out[cc] = np.nan
        elif sc and not sp:
            out[pp] = np.nan
        elif sp and sc:
            out[cc if g > 0 else pp] = np.nan
        else:
            out[[pp, cc]] = np.nan
    return out


def _template_direction(skeleton: Skeleton, joint: int, pose: np.ndarray) -> np.ndarray:
    p = skeleton.parent_array[joint]
    pp = skeleton.parent_array[p] if p >= 0 else -1
    if pp >= 0:
        d = pose[p] - pose[pp]
    else:
        d = np.nanmean(pose, axis=0) - pose[p] if np.isfinite(pose).any() else np.zeros(3)
        if not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-6:
            d = np.array([0.0, -1.0, 0.0])
    n = np.linalg.norm(d)
    return d / n if n > 1e-9 else np.array([0.0, -1.0, 0.0])


def _template_placed(skeleton: Skeleton, pose: np.ndarray, placed: np.ndarray):
    """The skeleton's template hand (:func:`handanno_core.synth.template_hand`) moved rigidly
    onto the ``placed`` joints of ``pose`` (J, 3) mm (Kabsch), or None: every joint placed, no
    template, fewer than 3 placed joints or nearly collinear ones."""
    if placed.all():
        return None
    tmpl = template_hand(skeleton, np.zeros(3))
    fit = None if tmpl is None else kabsch(tmpl[placed], pose[placed])
    if fit is None:
        return None
    rot, ca, cb = fit
    return (tmpl - ca) @ rot.T + cb


#: bone length (mm) of a skeleton without template lengths, when none are given
_FALLBACK_BONE_MM = 40.0
#: start depth (mm) of a frame without a single valid depth pixel
_FALLBACK_DEPTH_MM = 400.0


def _on_ray(
    camera: CameraIntrinsics,
    uv: np.ndarray,
    parent_mm: np.ndarray,
    length: float,
    order: int,
    z_target: float,
) -> np.ndarray | None:
    """The point ``(3,)`` mm on the viewing ray of pixel ``uv`` at ``length`` from the parent:
    of the two intersections, the one that honours the depth ``order`` (+1 farther, -1 nearer than
    the parent, 0 any) nearest ``z_target``; the ray's closest point when the sphere misses it.
    None if that point is not in front of the camera (z <= 1 mm)."""
    ray = np.array([(uv[0] - camera.cx) / camera.fx, (uv[1] - camera.cy) / camera.fy, 1.0])
    ray /= np.linalg.norm(ray)
    rp = float(ray @ parent_mm)
    disc = rp**2 - float(parent_mm @ parent_mm) + length**2
    if disc < 0:
        t = rp
    else:
        cands = np.array([rp - np.sqrt(disc), rp + np.sqrt(disc)])
        zc = cands * ray[2]
        ok = np.ones(2, dtype=bool)
        if order != 0:
            ok = order * (zc - parent_mm[2]) > 0
            if not ok.any():
                ok[:] = True
        cost = np.where(ok, np.abs(zc - z_target), np.inf)
        t = float(cands[np.argmin(cost)])
    return t * ray if t * ray[2] > 1.0 else None


def initial_pose(
    annotation: FrameAnnotation,
    depth_mm: np.ndarray,
    camera: CameraIntrinsics,
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray | None = None,
    depth_near_px: int = 1,
    depth_check_mm: float | None = 15.0,
    front_band_mm: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Initial joints ``(J, 3)`` mm and observed depths ``(J,)`` mm for a frame.

    Observed depths that no pose with these bone lengths can meet are dropped (NaN): for a bone
    whose both joints are visible, ``|(D_c + o_c) - (D_p + o_p)| > d_b + depth_check_mm`` means one
    reading is wrong (synthetic sequence, 2 px noise: a thumb tip reading the palm 90 mm behind, an
    index DIP reading a finger 100 mm in front). A reading backed by another consistent visible
    bone is kept and the other dropped; with no backing on either side both are dropped; with
    backing on both, the farther one. A joint placed in 3D loses a reading more than
    ``depth_check_mm`` behind its placed depth (its pixel sees past it: a review correction's
    seeded joint just off a thin finger's edge read the background 29 mm behind and was pushed
    there, HISTORY.md stop 39). ``depth_check_mm=None`` disables both checks.

    Joints with 2D are back-projected at the observed depth plus their surface offset (the median
    of the other joints' depths where there is no valid depth); joints placed in 3D start there;
    unannotated joints (a joint off the image has no 2D) are hung off their parent along the
    template hand's bone, the template moved rigidly onto the placed joints (which also places an
    unannotated root; :func:`_template_placed`), else along the parent bone's direction.
    """
    ann = annotation
    j = skeleton.num_joints
    offsets = np.asarray(skeleton.surface_offsets_mm, dtype=np.float64)
    d_obs = observed_depth(depth_mm, ann.uv_px, near_px=depth_near_px, front_band_mm=front_band_mm)
    has2d = ann.has_2d
    has3d = ann.has_3d
    lengths = (
        np.asarray(bone_lengths_mm, dtype=np.float64)
        if bone_lengths_mm is not None
        else np.asarray(
            skeleton.template_bone_lengths_mm or [_FALLBACK_BONE_MM] * (j - 1), dtype=np.float64
        )
    )
    if depth_check_mm is not None:
        d_obs = _drop_inconsistent_depths(
            d_obs, ann.visible & has2d, offsets, skeleton, lengths, depth_check_mm
        )
        # a joint placed in 3D whose pixel reads a surface behind it (the edge of a thin finger,
        # the background) sees past the joint: the reading is not its surface
        with np.errstate(invalid="ignore"):
            past = has3d & (d_obs + offsets > ann.xyz_mm[:, 2] + depth_check_mm)
        d_obs = np.where(past, np.nan, d_obs)
    z = d_obs + offsets
    known = np.isfinite(z) & has2d
    ref_depths = np.concatenate([z[known], ann.xyz_mm[has3d, 2]])
    if len(ref_depths) == 0:
        valid = depth_mm[(depth_mm > 0) & np.isfinite(depth_mm)]
        ref_depths = np.array([np.median(valid)]) if valid.size else np.array([_FALLBACK_DEPTH_MM])
    zmed = float(np.median(ref_depths))
    z = np.where(np.isfinite(z), z, zmed)
    # occluded joints: behind the occluder, at least near the hand's median depth
    z = np.where(has2d & ~ann.visible, np.maximum(z, zmed), z)
    pose = np.full((j, 3), np.nan)
    pose[has2d] = camera.backproject(ann.uv_px[has2d], z[has2d])
    pose[has3d] = ann.xyz_mm[has3d]
    bone_of_child = np.full(j, -1)
    bone_of_child[skeleton.bones[:, 1]] = np.arange(len(skeleton.bones))
    order = skeleton.topological_order
    root = skeleton.root
    template = _template_placed(skeleton, pose, has2d | has3d)
    if template is not None and not (has2d[root] or has3d[root]):
        pose[root] = template[root]
    if not np.all(np.isfinite(pose[root])):
        pose[root] = (
            np.nanmean(pose, axis=0)
            if np.isfinite(pose).any()
            else camera.backproject(np.array([camera.cx, camera.cy]), np.array(zmed))
        )
    par = skeleton.parent_array
    for k in order:
        if k == root:
            continue
        p = par[k]
        length = lengths[bone_of_child[k]]
        if has3d[k]:
            continue
        if not has2d[k]:
            if template is not None:
                d = template[k] - template[p]
                pose[k] = pose[p] + length * d / max(np.linalg.norm(d), 1e-9)
            else:
                pose[k] = pose[p] + length * _template_direction(skeleton, k, pose)
            continue
        # on the joint's viewing ray at bone length from the (already placed) parent
        zt = z[k]
        if not ann.visible[k]:
            # hidden joint: its observed depth is only a lower bound (the occluder). Of the
            # two ray intersections take the one nearer the parent's depth (behind the
            # occluder): avoids fingers folded towards the camera behind a palm
            zt = max(pose[p, 2], d_obs[k] + offsets[k] if np.isfinite(d_obs[k]) else -np.inf)
        placed = _on_ray(camera, ann.uv_px[k], pose[p], length, int(ann.depth_order[k]), zt)
        if placed is not None:
            pose[k] = placed
    return pose, d_obs


def initial_bone_lengths(
    annotations: dict[int, FrameAnnotation],
    depths: dict[int, np.ndarray],
    camera: CameraIntrinsics,
    skeleton: Skeleton,
) -> np.ndarray:
    """Template bone lengths ``(B,)`` scaled to the annotated frames.

    The scale is the median over frames and bones (both joints visible with valid depth) of the
    back-projected 2D length divided by the template length, corrected upwards because a
    projected length is never longer than the bone (we take the 75th percentile of the ratios).
    """
    if skeleton.template_bone_lengths_mm is None:
        raise ValueError(
            f"skeleton {skeleton.name} has no template bone lengths; pass bone_lengths_mm"
        )
    tmpl = np.asarray(skeleton.template_bone_lengths_mm, dtype=np.float64)
    ratios = []
    offsets = np.asarray(skeleton.surface_offsets_mm)
    p, c = skeleton.bones[:, 0], skeleton.bones[:, 1]
    for f, ann in annotations.items():
        d_obs = observed_depth(depths[f], ann.uv_px)
        ok = ann.has_2d & ann.visible & np.isfinite(d_obs)
        z = np.where(ok, d_obs + offsets, np.nan)
        X = camera.backproject(np.where(ann.has_2d[:, None], ann.uv_px, 0.0), np.nan_to_num(z))
        good = ok[p] & ok[c]
        # planar (projected) length at the mean depth of the two joints
        zm = 0.5 * (z[p] + z[c])
        planar = (
            np.linalg.norm(
                (X[c, :2] / np.maximum(z[c, None], 1) - X[p, :2] / np.maximum(z[p, None], 1)),
                axis=1,
            )
            * zm
        )
        ratios.append((planar / tmpl)[good])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    r = r[np.isfinite(r) & (r > 0)]
    scale = float(np.percentile(r, 75)) if len(r) >= 5 else 1.0
    return tmpl * float(np.clip(scale, 0.5, 2.0))
