"""How far a finger could be from where a skeleton shows it without the depth saying otherwise:
:func:`finger_ambiguity`, a term of the review ranking (:func:`handanno_core.review.review_evidence`).

A frame's worst errors are often invisible to every residual: a finger hidden behind the palm or
pointing along the camera's rays is explained by the depth equally well curled or extended, so
the propagated pose keeps whatever its reference had, and the model fit, the depth residuals and
the flow consistency all look fine. What the frame does show is that it cannot tell: setting
that finger to other flexions (:func:`handanno_core.handmodel.finger_hypotheses`, the grid of
:data:`handanno_core.handmodel.FINGER_FLEXIONS`) barely changes the personalized hand model's
energy on the frame's own depth (:func:`handanno_core.handmodel.candidate_energies`, no priors).

The energy leaves out the model's pose prior (learned from real hands,
:mod:`handanno_core.pose_prior`) and keeps what the depth and anatomy say (points, free space,
joint limits, fingers not inside each other). The prior is what decided a hidden finger in the
first place: a ring finger curled behind the palm while the middle finger is straight costs the
prior far more than the depth, so with the prior the curled hypothesis scored as excluded and
the frame looked certain exactly where its finger was far off (README, stop 53).

Per frame the term is the largest joint displacement (mm) of any one-finger hypothesis, each
weighted by ``exp(-max(dE, 0) / (tolerance * level))`` where ``dE`` is the hypothesis' energy
above the shown pose's and ``level`` the references' (:func:`handanno_core.handmodel.reference_level`):
a finger the depth pins down scores near 0, a finger that could be 80 mm elsewhere at no cost
scores 80. It is the spread of what the evidence allows, not an error: a frame scores high where
the annotator's look is worth most. The weighting is soft so that a hypothesis just above the
tolerance does not flip the term (a hard threshold was noisier on the suite's tune part).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import handmodel as hm
from .camera import CameraIntrinsics

__all__ = ["AMBIGUITY_TOLERANCE", "finger_ambiguity"]

#: energy rise (in units of the references' level) at which a hypothesis' displacement counts
#: ``1/e``: chosen on the suite's tune part (recall@10 % of the review ranking;
#: benchmarks/HISTORY.md, stop 48)
AMBIGUITY_TOLERANCE = 0.15


def finger_ambiguity(
    model: hm.HandModel,
    joints_mm: np.ndarray,
    obs: hm.FrameObservations,
    camera: CameraIntrinsics,
    reference_level: float,
    *,
    tolerance: float = AMBIGUITY_TOLERANCE,
    flexions=hm.FINGER_FLEXIONS,
    points: int | None = hm.RANKING_POINTS,
    weights: hm.FitWeights | None = None,
) -> np.ndarray:
    """``(n,)`` mm: how far one finger of each of ``n`` poses ``joints_mm`` (n, J, 3) mm could move
    at little cost on its frame's depth (``obs``, :func:`handmodel.observe` of those ``n`` frames;
    scored on about ``points`` of its points, None: all). See the module docstring; ``tolerance``
    in units of ``reference_level`` (> 0), ``flexions`` as :func:`handmodel.grid_flexions` takes
    them. A pose with NaN joints gets NaN."""
    x = np.asarray(joints_mm, dtype=np.float64)
    n = len(x)
    out = np.full(n, np.nan)
    ok = np.flatnonzero(np.all(np.isfinite(x), axis=(1, 2)))
    if len(ok) == 0 or not np.isfinite(reference_level) or reference_level <= 0:
        return out
    skeleton = model.skeleton
    if not hm.finger_chains(skeleton):
        return out
    # the depth's say only: the pose prior is a belief, not evidence (module docstring)
    w = replace(weights or hm.FitWeights(), prior=0.0)
    kin = hm.Kinematics(skeleton, model.bone_lengths_mm)
    root, u = kin.fit(x[ok])
    shown = kin.joints(root, u)
    seen = obs.take(ok)
    seen = seen if points is None else seen.thinned(points)
    m = len(ok)
    hyp = hm.finger_hypotheses(skeleton, kin, root, u, hm.grid_flexions(skeleton, flexions))
    f, k = hyp.shape[1:3]
    flat = hyp.reshape((-1,) + hyp.shape[3:])
    owner = np.repeat(np.arange(m), f * k)
    # the shown poses first, then every hypothesis, scored in one pass
    energy = hm.candidate_energies(
        model, kin, np.concatenate([root, root[owner]]), np.concatenate([u, flat]), seen,
        np.concatenate([np.arange(m), owner]), camera, w,
    )  # fmt: skip
    moved = kin.joints(root[owner], flat).reshape((m, f * k) + shown.shape[1:])
    disp = np.linalg.norm(moved - shown[:, None], axis=-1).max(axis=-1)  # (m, F*K)
    rise = np.maximum(energy[m:].reshape(m, f * k) - energy[:m, None], 0.0)
    out[ok] = np.max(disp * np.exp(-rise / (tolerance * reference_level)), axis=1)
    return out
